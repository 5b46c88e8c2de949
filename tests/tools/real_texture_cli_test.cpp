// Truth on real texture (issue 32): the simulator's surface wearing the Hamlyn heart's own
// in-vivo frame (config/scenes/real-texture*.toml), through the CLI as a research team would run
// it: simulate, track with a left ROI only, evaluate against the exact truth. At the paper's
// 1360x1024, at half resolution through JPEG, and with cortex-hard's glints, gains and
// instrument added. The texture is read from ../shared/data; the test says so when it is absent.

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <regex>
#include <sstream>
#include <string>

#include "pulsetrack/record/track_csv.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

struct Figures {
  int features = 0;
  double rms_mm = 0.0;
  double held_50 = 0.0;  // fraction of pairs with >= 50 ok
  int median_ok = 0;
};

// `pulsetrack evaluate`'s feature count and 3D RMS, as it prints them.
void readEvaluation(const std::string& output, int& features, double& rms_mm) {
  std::smatch m;
  if (std::regex_search(output, m, std::regex("features +([0-9]+)"))) features = std::stoi(m[1]);
  if (std::regex_search(output, m, std::regex("3D error +RMS ([0-9.]+) mm")))
    rms_mm = std::stod(m[1]);
  // Its error parts (bias, slow change, pair-to-pair noise): their squares add up to the RMS's.
  const std::regex parts(
      "per-feature bias ([0-9.]+) mm, slow change ([0-9.]+), pair-to-pair noise ([0-9.]+)");
  EXPECT_TRUE(std::regex_search(output, m, parts)) << output;
  if (m.size() == 4) {
    const double b = std::stod(m[1]), s = std::stod(m[2]), n = std::stod(m[3]);
    EXPECT_NEAR(std::sqrt(b * b + s * s + n * n), rms_mm, 0.0003) << output;
  }
}

// Simulates the scene (unless done) and tracks it, with a left ROI or none (roi empty).
Figures run(const test::TempDir& dir, const std::string& scene, const std::string& roi) {
  Figures f;
  const std::string rec = dir / scene;
  test::CommandResult r;
  if (!std::filesystem::exists(rec)) {
    r = test::run(test::cli() + " simulate -q --scene " + test::sourceDir() + "/config/scenes/" +
                  scene + ".toml --out " + rec);
    EXPECT_EQ(r.exit_code, 0) << r.output;
  }
  // The recording carries its texture (evaluate reads the scene from it).
  EXPECT_TRUE(std::filesystem::exists(std::filesystem::path(rec) / "texture.png")) << scene;
  r = test::run(test::cli() + " track -q --input " + rec +
                (roi.empty() ? std::string() : " --roi-left " + roi) + " --out " + rec + ".csv");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  r = test::run(test::cli() + " evaluate --recording " + rec + " --track " + rec + ".csv");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  readEvaluation(r.output, f.features, f.rms_mm);
  auto rows = record::readTrackCsv(rec + ".csv");
  EXPECT_TRUE(rows) << rows.error().message;
  if (!rows) return f;
  std::map<long, int> ok;
  for (const auto& row : *rows) ok[row.frame] += row.status == "ok" ? 1 : 0;
  std::vector<int> counts;
  int held = 0;
  for (const auto& [frame, n] : ok) {
    counts.push_back(n);
    held += n >= 50 ? 1 : 0;
  }
  if (!counts.empty()) {
    std::sort(counts.begin(), counts.end());
    f.median_ok = counts[counts.size() / 2];
    f.held_50 = static_cast<double>(held) / static_cast<double>(counts.size());
  }
  std::cout << scene << (roi.empty() ? " (no ROI)" : "") << ": " << f.features
            << " features, 3D RMS " << f.rms_mm << " mm, ok per pair median " << f.median_ok
            << ", >= 50 ok in " << 100.0 * f.held_50 << " % of the pairs\n";
  return f;
}

TEST(RealTexture, TrackedAgainstExactTruthAtEachResolution) {
  PULSETRACK_SKIP_WITHOUT_DATA(data::shared("hamlyn-invivo-tpsnet"));
  test::TempDir dir;
  // 1360x1024: within 1.5x of cortex-60s's 0.028 mm (the acceptance). Measured 0.035.
  const Figures full = run(dir, "real-texture", "483,339,400,340");
  EXPECT_GE(full.features, 90);
  EXPECT_GE(full.held_50, 0.95);
  EXPECT_LE(full.rms_mm, 1.5 * 0.028);
  // The same recording with no ROI at all (the region found in the first pair): measured 0.034.
  const Figures found = run(dir, "real-texture", "");
  EXPECT_GE(found.features, 90);
  EXPECT_LE(found.rms_mm, 1.5 * 0.028);
  // Half resolution through JPEG 60, and with the hard scene's troubles: NOT at the issue's
  // acceptance (<= 0.04 mm; >= 50 held in 80 % of the pairs, <= 0.06 mm). These bounds only
  // keep what there is from getting worse (measured 51 features at 0.136 mm, 0.142 before the
  // stereo refresh matched beside glints with their pixels left out; 30 at 0.236 mm, 0.354
  // before the stereo confirmation retired the 7 whose next pairs' stereo NCC did not bear their
  // first match out, TrackerConfig::min_stereo_confirmed, and 0.254 before the refresh's
  // consensus re-seated first matches that its next pairs agree are off and its glint masking).
  const Figures sd = run(dir, "real-texture-sd", "241,169,200,170");
  EXPECT_GE(sd.features, 40);
  EXPECT_LE(sd.rms_mm, 0.145);
  const Figures hard = run(dir, "real-texture-hard", "241,169,200,170");
  EXPECT_GE(hard.features, 20);
  EXPECT_LE(hard.rms_mm, 0.27);
}

// The lateral error of the measured motion: each feature's error less its own mean (its constant
// bias, which the depth dominates at this resolution), RMS over the ok rows of features seen in
// at least 5, from evaluate's per-row errors (frame,id,error_mm,ex,ey,ez).
double lateralMotionError(const std::string& errors_csv) {
  std::ifstream in(errors_csv);
  std::string line;
  std::getline(in, line);
  std::map<long, std::vector<std::array<double, 2>>> by_id;
  while (std::getline(in, line)) {
    std::array<std::string, 6> f;
    std::istringstream cells(line);
    for (auto& c : f) std::getline(cells, c, ',');
    if (f[2] == "nan" || f[2].empty()) continue;
    by_id[std::stol(f[1])].push_back({std::stod(f[3]), std::stod(f[4])});
  }
  double ss = 0.0;
  long n = 0;
  for (const auto& [id, e] : by_id) {
    if (e.size() < 5) continue;
    std::array<double, 2> mean{};
    for (const auto& v : e) {
      mean[0] += v[0] / static_cast<double>(e.size());
      mean[1] += v[1] / static_cast<double>(e.size());
    }
    for (const auto& v : e) {
      ss += (v[0] - mean[0]) * (v[0] - mean[0]) + (v[1] - mean[1]) * (v[1] - mean[1]);
      ++n;
    }
  }
  return n > 0 ? std::sqrt(ss / static_cast<double>(n)) : 0.0;
}

// Interlaced SD video (config/scenes/real-texture-interlaced.toml: the heart's texture beating at
// 1.2 Hz, each frame's odd rows 20 ms after its even rows, JPEG 60), tracked both ways against
// the exact truth: as frames (every template straddles two instants) and as fields (`--fields
// tff`, twice the pairs, each at its own instant). Measured: frames 53 features, lateral motion
// error 0.087 mm, 3D RMS 0.342 mm; fields 66 features, 0.048 mm, 0.321 mm.
TEST(RealTexture, InterlacedVideoIsMeasuredByItsFields) {
  PULSETRACK_SKIP_WITHOUT_DATA(data::shared("hamlyn-invivo-tpsnet"));
  test::TempDir dir;
  const std::string rec = dir / "interlaced";
  auto r = test::run(test::cli() + " simulate -q --scene " + test::sourceDir() +
                     "/config/scenes/real-texture-interlaced.toml --out " + rec);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  struct Way {
    std::string track_flag, evaluate_flag, name;
    int features = 0;
    double rms_mm = 0.0, lateral_mm = 0.0;
    size_t pairs = 0;
  };
  std::array<Way, 2> ways{Way{"", "", "frames"}, Way{" --fields tff", " --fields", "fields"}};
  for (Way& w : ways) {
    const std::string csv = fmt::format("{}-{}.csv", rec, w.name);
    r = test::run(fmt::format("{} track -q --input {} --roi-left 241,169,200,170{} --out {}",
                              test::cli(), rec, w.track_flag, csv));
    ASSERT_EQ(r.exit_code, 0) << r.output;
    r = test::run(fmt::format("{} evaluate --recording {} --track {}{} --out {}-errors.csv",
                              test::cli(), rec, csv, w.evaluate_flag, csv));
    ASSERT_EQ(r.exit_code, 0) << r.output;
    readEvaluation(r.output, w.features, w.rms_mm);
    w.lateral_mm = lateralMotionError(csv + "-errors.csv");
    auto rows = record::readTrackCsv(csv);
    ASSERT_TRUE(rows) << rows.error().message;
    std::map<long, int> frames;
    for (const auto& row : *rows) frames[row.frame] += 1;
    w.pairs = frames.size();
    std::cout << "interlaced, as " << w.name << ": " << w.pairs << " pairs, " << w.features
              << " features, lateral motion error " << w.lateral_mm << " mm, 3D RMS " << w.rms_mm
              << " mm\n";
  }
  const Way& frames = ways[0];
  const Way& fields = ways[1];
  EXPECT_EQ(frames.pairs, 75U);
  EXPECT_EQ(fields.pairs, 150U);  // two fields a frame
  EXPECT_GE(fields.features, frames.features);
  EXPECT_GT(frames.lateral_mm, 0.0);
  EXPECT_LE(fields.lateral_mm, 0.75 * frames.lateral_mm);
  EXPECT_LE(fields.rms_mm, frames.rms_mm);
  // A track from fields is scored as such: without --fields its frames are out of the scene.
  r = test::run(test::cli() + " evaluate --recording " + rec + " --track " + rec + "-fields.csv");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("track row for frame 75 but the scene has frames 0..74"),
            std::string::npos)
      << r.output;
}

}  // namespace
}  // namespace pulsetrack
