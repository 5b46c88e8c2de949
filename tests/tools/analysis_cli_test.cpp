// `pulsetrack validate` and `pulsetrack analyze` end to end on the simulator's recordings, against
// their ground truth: the registration O_T_C (truth/transforms.csv), the report files (real
// PNG images of the expected size, the HTML page), the dynamic session with an earlier
// registration, and the 60 s cortex case's breathing and cardiac peaks. Release build only
// (rendering 600 frames takes a minute there).

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <sstream>

#include "pulsetrack/analysis/motion.hpp"
#include "pulsetrack/analysis/reference.hpp"
#include "pulsetrack/analysis/report.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

const std::string kCli = PULSETRACK_CLI;
const std::string kScenes = std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/";

std::string slurp(const std::filesystem::path& p) {
  std::ifstream f(p);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

// A scene file with some keys replaced, written next to the shipped ones' rig (a scene names its
// rig relative to itself).
std::string sceneVariant(const test::TempDir& dir, const std::string& base,
                         const std::map<std::string, std::string>& keys) {
  std::string text = slurp(kScenes + base);
  for (const auto& [key, value] : keys) {
    const auto at = text.find("\n" + key + " = ");
    EXPECT_NE(at, std::string::npos) << key;
    const auto end = text.find('\n', at + 1);
    text.replace(at + 1, end - at - 1, key + " = ");
    text.insert(at + 1 + key.size() + 3, value);
  }
  const auto rig = std::string(PULSETRACK_SOURCE_DIR) + "/config/rigs/paper-rig.yaml";
  const auto r = text.find("rig = \"../rigs/paper-rig.yaml\"");
  EXPECT_NE(r, std::string::npos);
  text.replace(r, std::string("rig = \"../rigs/paper-rig.yaml\"").size(), "rig = \"" + rig + "\"");
  std::string path = dir / ("variant-" + base);
  std::ofstream(path) << text;
  return path;
}

struct RegistrationError {
  double workspace_rms_mm = 0, rotation_deg = 0;
};

// The estimated O_T_C against the truth: the angle between them and the RMS of the difference
// over the plate's true positions (the registration's error where it is used).
RegistrationError registrationError(const std::filesystem::path& recording,
                                    const std::filesystem::path& report) {
  auto est = analysis::readRegistration(report / "registration.csv");
  EXPECT_TRUE(est) << (est ? "" : est.error().message);
  auto truth = analysis::readCsv(recording / "truth/transforms.csv");
  EXPECT_TRUE(truth);
  analysis::Pose t = analysis::Pose::Identity();
  for (size_t i = 0; i < truth->rows.size(); ++i) {
    if (truth->rows[i][0] != "O_T_C") continue;
    std::array<double, 7> v{};
    for (int k = 0; k < 7; ++k) v[static_cast<size_t>(k)] = *truth->number(i, k + 1);
    t.linear() = Eigen::Quaterniond(v[3], v[4], v[5], v[6]).normalized().toRotationMatrix();
    t.translation() = analysis::Vec3(v[0], v[1], v[2]);
  }
  auto plate = analysis::readCsv(recording / "truth/plate.csv");
  EXPECT_TRUE(plate);
  const int cx = plate->column({"tx"});
  double ss = 0;
  for (size_t i = 0; i < plate->rows.size(); ++i) {
    const analysis::Vec3 p(*plate->number(i, cx), *plate->number(i, cx + 1),
                           *plate->number(i, cx + 2));
    ss += (*est * p - t * p).squaredNorm();
  }
  return {std::sqrt(ss / static_cast<double>(plate->rows.size())),
          Eigen::AngleAxisd(est->linear().transpose() * t.linear()).angle() * 180.0 / M_PI};
}

void expectPng(const std::filesystem::path& p, int width, int height) {
  const cv::Mat img = cv::imread(p.string(), cv::IMREAD_UNCHANGED);
  ASSERT_FALSE(img.empty()) << p << " is not a readable image";
  EXPECT_EQ(img.cols, width) << p;
  EXPECT_EQ(img.rows, height) << p;
  EXPECT_EQ(img.channels(), 3) << p;
  cv::Scalar mean, sd;
  cv::meanStdDev(img, mean, sd);
  EXPECT_GT(sd[0], 10.0) << p << " is blank";  // something was drawn
}

TEST(ValidateCli, StaticProtocolRegistrationTableIIStatisticsAndReport) {
  test::TempDir dir;
  const std::string rec = dir / "static", out = dir / "report";
  auto sim = test::run(kCli + " simulate --scene " + kScenes + "plate-static.toml --out " + rec +
                       " --quiet");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  auto v = test::run(kCli + " validate --recording " + rec + " --out " + out + " --quiet");
  ASSERT_EQ(v.exit_code, 0) << v.output;
  std::cout << v.output;
  EXPECT_NE(v.output.find("frames measured: 50 (0 not"), std::string::npos);
  EXPECT_NE(v.output.find("Table II, registration residuals (10 acquisitions)"), std::string::npos);
  EXPECT_NE(v.output.find("static: translation error (mm) by set"), std::string::npos);
  EXPECT_NE(v.output.find("Kruskal-Wallis H = "), std::string::npos);
  const RegistrationError e = registrationError(rec, out);
  std::cout << "O_T_C, reference tracker 0.1 mm RMS: " << e.workspace_rms_mm
            << " mm RMS over the workspace, " << e.rotation_deg << " deg\n";
  // The reference's own noise (0.1 mm on each divot, the divots digitized once) limits a
  // ten-acquisition registration: across seeds 0.05-0.15 mm.
  EXPECT_LT(e.workspace_rms_mm, 0.1);
  EXPECT_LT(e.rotation_deg, 0.1);
  expectPng(std::filesystem::path(out) / "fig7_static.png", 1100, 480);
  const std::string html = slurp(std::filesystem::path(out) / "report.html");
  EXPECT_NE(html.find("<img src=\"fig7_static.png\""), std::string::npos);
  EXPECT_NE(html.find("Table II"), std::string::npos);
  const std::string stats = slurp(std::filesystem::path(out) / "statistics.csv");
  EXPECT_NE(stats.find("static: rotation error (deg) by set,"), std::string::npos);
  EXPECT_NE(slurp(std::filesystem::path(out) / "table2.csv").find("alpha (deg),"),
            std::string::npos);

  // The dynamic session: same cameras and tracker, the registration from the static one.
  const std::string dyn = dir / "dynamic", dout = dir / "dreport";
  const std::string scene = sceneVariant(
      dir, "plate-dynamic.toml", {{"acquisitions_per_set", "3"}, {"frames_per_acquisition", "20"}});
  sim =
      test::run(kCli + " simulate --scene " + scene + " --out " + dyn + " --quiet --supersample 1");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  auto none = test::run(kCli + " validate --recording " + dyn + " --out " + dout + " --quiet");
  EXPECT_EQ(none.exit_code, 1);
  EXPECT_NE(none.output.find("no measured acquisition in set 0 and no registration was given"),
            std::string::npos)
      << none.output;
  v = test::run(kCli + " validate --recording " + dyn + " --registration " + out +
                "/registration.csv --out " + dout + " --quiet");
  ASSERT_EQ(v.exit_code, 0) << v.output;
  std::cout << v.output;
  EXPECT_NE(v.output.find("frames measured: 240 (0 not"), std::string::npos);
  EXPECT_NE(v.output.find("dynamic: translation error (mm) by linear speed"), std::string::npos);
  EXPECT_NE(v.output.find("dynamic: rotation error (deg) by angular speed"), std::string::npos);
  expectPng(std::filesystem::path(dout) / "fig8_dynamic.png", 1100, 480);
  // Every moving frame within the paper's static bound (0.6 mm, 1.6 deg).
  auto frames = analysis::readCsv(std::filesystem::path(dout) / "frames.csv");
  ASSERT_TRUE(frames);
  const int ct = frames->column({"e_t_mm"}), cr = frames->column({"e_r_deg"});
  for (size_t i = 0; i < frames->rows.size(); ++i) {
    EXPECT_LT(*frames->number(i, ct), 0.6);
    EXPECT_LT(*frames->number(i, cr), 1.6);
  }
}

TEST(ValidateCli, ExactReferenceRecoversOTCWithin005mmAnd005deg) {
  test::TempDir dir;
  // Straight from a scene: validate renders it into OUT/recording first.
  const std::string out = dir / "report", rec = out + "/recording";
  const std::string scene = sceneVariant(dir, "plate-static.toml", {{"tracker_noise_mm", "0.0"}});
  auto v = test::run(kCli + " validate --scene " + scene + " --out " + out + " --quiet");
  ASSERT_EQ(v.exit_code, 0) << v.output;
  EXPECT_NE(
      slurp(std::filesystem::path(out) / "report.html").find("Validation of variant-plate-static"),
      std::string::npos);
  const RegistrationError e = registrationError(rec, out);
  std::cout << "O_T_C, exact reference: " << e.workspace_rms_mm << " mm RMS over the workspace, "
            << e.rotation_deg << " deg\n";
  EXPECT_LT(e.workspace_rms_mm, 0.05);
  EXPECT_LT(e.rotation_deg, 0.05);
  // Bad input is named: a protocol file that is not there, a broken markers row.
  auto missing = test::run(kCli + " validate --recording " + rec + " --protocol " +
                           (dir / "nope.csv") + " --out " + out);
  EXPECT_EQ(missing.exit_code, 1);
  EXPECT_NE(missing.output.find("nope.csv: cannot open"), std::string::npos) << missing.output;
  std::string markers = slurp(std::filesystem::path(rec) / "tracker/markers.csv");
  markers.replace(markers.find('\n', markers.find('\n') + 1) + 1, 1, "x");  // line 3's first cell
  std::ofstream(dir / "bad-markers.csv") << markers;
  auto bad = test::run(kCli + " validate --recording " + rec + " --markers " +
                       (dir / "bad-markers.csv") + " --out " + out);
  EXPECT_EQ(bad.exit_code, 1);
  EXPECT_NE(bad.output.find("bad-markers.csv:3: column 'frame'"), std::string::npos) << bad.output;
}

TEST(AnalyzeCli, CortexCaseBreathingAndCardiacAgainstTheTruth) {
  test::TempDir dir;
  const std::string rec = dir / "cortex", track = dir / "track.csv", out = dir / "motion";
  auto sim = test::run(kCli + " simulate --scene " + kScenes + "cortex-60s.toml --out " + rec +
                       " --quiet --supersample 1");
  ASSERT_EQ(sim.exit_code, 0) << sim.output;
  auto tr = test::run(kCli + " track --input " + rec +
                      " --roi-left 483,339,400,340 --roi-right 476,344,400,340 --depth 20 --out " +
                      track);
  ASSERT_EQ(tr.exit_code, 0) << tr.output;
  auto an = test::run(kCli + " analyze " + track + " --out " + out);
  ASSERT_EQ(an.exit_code, 0) << an.output;
  std::cout << an.output;
  EXPECT_NE(an.output.find("(580 measured, 20 missing filled)"), std::string::npos);
  // The truth: the same features' true positions (the track minus evaluate's error vectors),
  // through the same analysis (exact data: its joint fit recovers amplitudes to 0.3 %).
  const std::string errors = dir / "errors.csv";
  auto ev =
      test::run(kCli + " evaluate --recording " + rec + " --track " + track + " --out " + errors);
  ASSERT_EQ(ev.exit_code, 0) << ev.output;
  auto rows = record::readTrackCsv(track);
  ASSERT_TRUE(rows);
  auto err = analysis::readCsv(errors);
  ASSERT_TRUE(err);
  std::map<std::pair<long, int>, analysis::Vec3> e;
  for (size_t i = 0; i < err->rows.size(); ++i)
    e[{static_cast<long>(*err->number(i, 0)), static_cast<int>(*err->number(i, 1))}] =
        analysis::Vec3(*err->number(i, 3), *err->number(i, 4), *err->number(i, 5));
  std::vector<record::TrackRow> truth;
  for (record::TrackRow r : *rows) {
    const auto it = e.find({r.frame, r.id});
    if (!r.ok() || it == e.end()) continue;
    r.x -= it->second.x();
    r.y -= it->second.y();
    r.z -= it->second.z();
    truth.push_back(r);
  }
  auto measured = analysis::analyzeMotion(*rows);
  auto exact = analysis::analyzeMotion(truth);
  ASSERT_TRUE(measured && exact);
  const auto peak = [](const analysis::MotionAnalysis& m, const std::string& name) {
    for (const auto& p : m.peaks) {
      if (p.name == name) return p;
    }
    return analysis::SpectralPeak{};
  };
  for (const auto& [name, f] :
       std::vector<std::pair<std::string, double>>{{"breathing", 0.2}, {"cardiac", 1.0}}) {
    const auto m = peak(*measured, name), t = peak(*exact, name);
    std::cout << name << ": measured " << m.frequency_hz << " Hz " << m.amplitude_mm
              << " mm, truth " << f << " Hz " << t.amplitude_mm << " mm\n";
    EXPECT_NEAR(m.frequency_hz, f, 0.02) << name;
    EXPECT_NEAR(m.amplitude_mm, t.amplitude_mm, 0.05 * t.amplitude_mm) << name;
  }
  expectPng(std::filesystem::path(out) / "fig9_motion.png", 1200, 330);
  EXPECT_NE(slurp(std::filesystem::path(out) / "peaks.csv").find(",breathing\n"),
            std::string::npos);
  // The same analysis of the TrackingSession's deformation (the signal pulsetrackd publishes),
  // which `track` wrote beside the track: the same peaks, against the same truth.
  const std::string def = dir / "track-deformation.csv", out2 = dir / "motion-session";
  auto an2 = test::run(kCli + " analyze " + def + " --out " + out2);
  ASSERT_EQ(an2.exit_code, 0) << an2.output;
  auto def_rows = record::readDeformationCsv(def);
  ASSERT_TRUE(def_rows) << def_rows.error().message;
  auto session = analysis::analyzeMotion(*def_rows);
  ASSERT_TRUE(session) << session.error().message;
  for (const auto& [name, f] :
       std::vector<std::pair<std::string, double>>{{"breathing", 0.2}, {"cardiac", 1.0}}) {
    const auto m = peak(*session, name), t = peak(*exact, name);
    std::cout << name << " (session's deformation): " << m.frequency_hz << " Hz " << m.amplitude_mm
              << " mm, truth " << t.amplitude_mm << " mm\n";
    EXPECT_NEAR(m.frequency_hz, f, 0.02) << name;
    EXPECT_NEAR(m.amplitude_mm, t.amplitude_mm, 0.05 * t.amplitude_mm) << name;
  }
  expectPng(std::filesystem::path(out2) / "fig9_motion.png", 1200, 330);
  // A broken track is named with its line.
  std::ofstream(dir / "bad.csv") << record::kTrackCsvHeader << "\n0,0.0,1,1,1,1,1,x,1,1,1,1,ok\n";
  auto bad = test::run(kCli + " analyze " + (dir / "bad.csv") + " --out " + out);
  EXPECT_EQ(bad.exit_code, 1);
  EXPECT_NE(bad.output.find("bad.csv:2"), std::string::npos) << bad.output;
}

}  // namespace
}  // namespace pulsetrack
