// Truth on real texture (issue 32): the simulator's surface wearing the Hamlyn heart's own
// in-vivo frame (config/scenes/real-texture*.toml), through the CLI as a research team would run
// it: simulate, track with a left ROI only, evaluate against the exact truth. At the paper's
// 1360x1024, at half resolution through JPEG, and with cortex-hard's glints, gains and
// instrument added. The texture is read from ../shared/data; the test says so when it is absent.

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <regex>
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
  std::smatch m;
  if (std::regex_search(r.output, m, std::regex("features +([0-9]+)")))
    f.features = std::stoi(m[1]);
  if (std::regex_search(r.output, m, std::regex("3D error +RMS ([0-9.]+) mm")))
    f.rms_mm = std::stod(m[1]);
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
  // keep what there is from getting worse (measured 37 features at 0.137 mm; 17 at 0.337 mm: the
  // translation-refined stereo matches add features and some of the foreshortening's bias).
  const Figures sd = run(dir, "real-texture-sd", "241,169,200,170");
  EXPECT_GE(sd.features, 25);
  EXPECT_LE(sd.rms_mm, 0.16);
  const Figures hard = run(dir, "real-texture-hard", "241,169,200,170");
  EXPECT_GE(hard.features, 8);
  EXPECT_LE(hard.rms_mm, 0.4);
}

}  // namespace
}  // namespace pulsetrack
