// `pulsetrack simulate` and `pulsetrack evaluate` as a user runs them, and the evaluator's
// numbers against errors injected into a track made from the ground truth.

#include <gtest/gtest.h>

#include <fstream>
#include <random>
#include <regex>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "pulsetrack/sim/evaluate.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

std::string scenes() { return test::sourceDir() + "/config/scenes"; }

TEST(SimulateCli, CortexRecordingWithTruth) {
  test::TempDir dir;
  const std::string out = dir / "rec";
  const auto r = test::run(test::cli() + " simulate --scene " + scenes() +
                           "/cortex-60s.toml --frames 40 --supersample 1 --out " + out);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("frame 40/40 (100%)"), std::string::npos) << r.output;
  auto rec = record::Reader::open(out);
  ASSERT_TRUE(rec) << rec.error().message;
  EXPECT_EQ(rec->manifest().source, "sim:cortex-60s");
  EXPECT_EQ(rec->manifest().width, 1360);
  // The scene drops ~2 % of frames: recorded frames + dropped = 40, gaps visible in the index.
  std::ifstream truth(dir / "rec/truth/cortex.csv");
  std::string line;
  std::getline(truth, line);
  EXPECT_EQ(line, "frame,t_ns,recorded,com_x,com_y,com_z");
  int rows = 0, recorded = 0;
  while (std::getline(truth, line)) {
    ++rows;
    recorded += line.find(",1,") != std::string::npos ? 1 : 0;
  }
  EXPECT_EQ(rows, 40);
  EXPECT_EQ(static_cast<int>(rec->size()), recorded);
  for (size_t i = 1; i < rec->size(); ++i) {
    const auto& a = rec->meta(i - 1);
    const auto& b = rec->meta(i);
    EXPECT_EQ(b.t_left_ns - a.t_left_ns, static_cast<int64_t>(b.frame - a.frame) * 100'000'000);
  }
  cv::Mat l, rr;
  ASSERT_TRUE(rec->read(0, l, rr));
  cv::Scalar mean, stddev;
  cv::meanStdDev(l, mean, stddev);
  EXPECT_GT(stddev[0], 20.0);  // a textured image, not a blank one
}

// The shipped hard scene as a user renders it: the right camera's own [camera.right] gain and
// drift reach the recorded images (at 3 s the right gain is 0.8 x (1 - 0.26), the left 1.0).
TEST(SimulateCli, HardSceneRendersTheRightCamerasOwnGain) {
  test::TempDir dir;
  const std::string out = dir / "rec";
  const auto r = test::run(test::cli() + " simulate -q --scene " + scenes() +
                           "/cortex-hard.toml --frames 31 --supersample 1 --out " + out);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  auto rec = record::Reader::open(out);
  ASSERT_TRUE(rec) << rec.error().message;
  EXPECT_EQ(rec->manifest().source, "sim:cortex-hard");
  ASSERT_EQ(rec->size(), 31U);  // this scene drops no frames
  const auto ratio = [&](size_t i) {
    cv::Mat l, rr;
    EXPECT_TRUE(rec->read(i, l, rr));
    return cv::mean(rr)[0] / cv::mean(l)[0];
  };
  const double at0 = ratio(0), at3s = ratio(30);
  // Gains right/left: 1.008 at 0 s, 0.592 at 3 s (the vignetting's part is the same in both).
  EXPECT_NEAR(at3s / at0, 0.592 / 1.008, 0.05) << at0 << " " << at3s;
}

// The hours-long scenes as a user renders them: the CLI reads their new keys (the sag's turn,
// repeated instruments) and the recording's copy of the scene reads back with them.
TEST(SimulateCli, LongScenesRenderAndTheirCopyReadsBack) {
  for (const std::string name : {"cortex-1h", "cortex-1h-compressed"}) {
    test::TempDir dir;
    const std::string out = dir / "rec";
    std::string cmd = test::cli() + " simulate -q --scene " + scenes();
    cmd += "/";
    cmd += name;
    cmd += ".toml --frames 3 --out ";
    cmd += out;
    const auto r = test::run(cmd);
    ASSERT_EQ(r.exit_code, 0) << name << ": " << r.output;
    auto rec = record::Reader::open(out);
    ASSERT_TRUE(rec) << rec.error().message;
    EXPECT_EQ(rec->manifest().source, "sim:" + name);
    EXPECT_EQ(rec->size(), 3U) << name;
    auto copy = sim::loadScene(dir.path() / "rec/scene.toml");
    ASSERT_TRUE(copy) << copy.error().message;
    auto shipped = sim::loadScene(scenes() + "/" + name + ".toml");
    ASSERT_TRUE(shipped) << shipped.error().message;
    EXPECT_EQ(copy->cortex.sag.rotation_deg, shipped->cortex.sag.rotation_deg) << name;
    EXPECT_GT(copy->cortex.sag.rotation_deg, 0.0) << name;
    EXPECT_EQ(copy->cortex.instrument.period_s, shipped->cortex.instrument.period_s) << name;
    EXPECT_GT(copy->cortex.instrument.period_s, 0.0) << name;  // crossings again and again
    cv::Mat l, rr;
    ASSERT_TRUE(rec->read(2, l, rr));
    cv::Scalar mean, stddev;
    cv::meanStdDev(l, mean, stddev);
    EXPECT_GT(stddev[0], 20.0) << name;  // rendered cortex, not a blank image
  }
}

TEST(SimulateCli, PlateRecordingHasTrackerFiles) {
  test::TempDir dir;
  const auto r = test::run(test::cli() + " simulate -q --scene " + scenes() +
                           "/plate-static.toml --frames 3 --out " + (dir / "rec"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  for (const char* f :
       {"truth/plate.csv", "truth/transforms.csv", "truth/tracker_markers.csv",
        "tracker/markers.csv", "tracker/divots.csv", "tracker/digitization_markers.csv",
        "scene.toml", "rig.yaml", "manifest.toml"}) {
    EXPECT_TRUE(std::filesystem::exists(dir.path() / "rec" / f)) << f;
  }
}

TEST(SimulateCli, ClearErrors) {
  test::TempDir dir;
  std::ofstream(dir / "bad.toml") << "kind = \"cortex\"\nrig = \"x.yaml\"\ntilt = 3\n";
  auto r =
      test::run(test::cli() + " simulate --scene " + (dir / "bad.toml") + " --out " + (dir / "o"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("bad.toml:3: unknown key 'tilt'"), std::string::npos) << r.output;
  std::ofstream(dir / "norig.toml") << "kind = \"cortex\"\nrig = \"missing.yaml\"\n";
  r = test::run(test::cli() + " simulate --scene " + (dir / "norig.toml") + " --out " +
                (dir / "o"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("missing.yaml: rig file not found"), std::string::npos) << r.output;
  std::filesystem::create_directories(dir.path() / "full");
  std::ofstream(dir / "full/x") << "x";
  r = test::run(test::cli() + " simulate --scene " + scenes() +
                "/cortex-60s.toml --frames 1 --out " + (dir / "full"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("never overwritten"), std::string::npos) << r.output;
}

// A track built from the truth: material points projected into both images, their true 3D
// positions plus a known error; the evaluator must report that error.
TEST(Evaluate, ReportsTheErrorInjectedIntoATrack) {
  test::TempDir dir;
  const std::string out = dir / "rec";
  ASSERT_EQ(test::run(test::cli() + " simulate -q --scene " + scenes() +
                      "/cortex-60s.toml --frames 30 --supersample 1 --out " + out)
                .exit_code,
            0);
  auto spec = sim::loadScene(dir.path() / "rec/scene.toml");
  ASSERT_TRUE(spec) << spec.error().message;
  auto rec = record::Reader::open(out);
  ASSERT_TRUE(rec);
  sim::StereoSimulator simulator(*spec, rec->rig());
  const sim::CortexScene& scene = *simulator.cortex();
  std::mt19937 rng(1);
  std::normal_distribution<double> noise(0.0, 0.05);
  std::vector<record::TrackRow> rows;
  int id = 0;
  for (double v = -20; v <= 20; v += 10) {
    for (double u = -20; u <= 20; u += 10) {
      for (int f = 0; f < 30; ++f) {
        const double t = f / 10.0;
        const cv::Vec3d p = scene.position(u, v, t);
        const cv::Vec2d l = rec->rig().projectLeft(p);
        const cv::Vec2d r = rec->rig().projectRight(p);
        record::TrackRow row{f,
                             t,
                             id,
                             l[0],
                             l[1],
                             r[0],
                             r[1],
                             p[0] + noise(rng),
                             p[1] + noise(rng),
                             p[2] + noise(rng),
                             0.95,
                             0.8,
                             "ok"};
        if (f == 0) row.x = p[0], row.y = p[1], row.z = p[2];  // exact where identity is taken
        if (id == 3 && f == 12) row.z += 1.0;                  // one outlier
        if (id == 5 && f >= 20) row.status = "occluded";
        rows.push_back(row);
      }
      ++id;
    }
  }
  auto ev = sim::evaluateTrack(simulator, rows, 0.5);
  ASSERT_TRUE(ev) << ev.error().message;
  EXPECT_EQ(ev->features, 25);
  EXPECT_EQ(ev->unmatched, 0);
  EXPECT_EQ(ev->rows_ok, 25 * 30 - 10);
  EXPECT_EQ(ev->outliers, 1);
  EXPECT_EQ(ev->not_ok.at("occluded"), 10);
  EXPECT_NEAR(ev->max_mm, 1.0, 0.2);
  // RMS of 3-D Gaussian error with sigma 0.05 per axis: 0.0866 mm (plus the outlier).
  EXPECT_NEAR(ev->median_mm, 0.05 * 1.538, 0.01);
  // And through the CLI.
  ASSERT_TRUE(record::writeTrackCsv(dir / "track.csv", rows));
  const auto r = test::run(test::cli() + " evaluate --recording " + out + " --track " +
                           (dir / "track.csv") + " --out " + (dir / "errors.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("features              25 (0 without ground truth)"), std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("outliers > 0.50 mm    1"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("rows not ok           10 (occluded 10)"), std::string::npos) << r.output;
  EXPECT_TRUE(std::filesystem::exists(dir.path() / "errors.csv"));
  // A bad track file is named with its line.
  std::ofstream(dir / "bad.csv") << record::kTrackCsvHeader
                                 << "\n0,0.0,1,2,3,4,5,6,7,x,0.9,0.8,ok\n";
  const auto bad =
      test::run(test::cli() + " evaluate --recording " + out + " --track " + (dir / "bad.csv"));
  EXPECT_EQ(bad.exit_code, 1);
  EXPECT_NE(bad.output.find("bad.csv:2: field 'z' is not a number: 'x'"), std::string::npos)
      << bad.output;
}

}  // namespace
}  // namespace pulsetrack
