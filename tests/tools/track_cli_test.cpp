// `pulsetrack track` and `pulsetrack match` as a user runs them: a simulated recording tracked,
// scored by `pulsetrack evaluate`; an image folder; clear errors.

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <opencv2/core/persistence.hpp>
#include <opencv2/imgcodecs.hpp>
#include <regex>
#include <set>
#include <sstream>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

const std::string kRois = " --roi-left 483,339,400,340 --roi-right 476,344,400,340 --depth 20 ";

std::string scenes() { return test::sourceDir() + "/config/scenes"; }

TEST(TrackCli, RecordingTrackedAndScored) {
  test::TempDir dir;
  ASSERT_EQ(test::run(test::cli() + " simulate -q --scene " + scenes() +
                      "/cortex-60s.toml --frames 12 --out " + (dir / "rec"))
                .exit_code,
            0);
  auto r = test::run(test::cli() + " track -q --input " + (dir / "rec") + kRois + "--out " +
                     (dir / "track.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("per-frame step    p50"), std::string::npos) << r.output;
  auto rows = record::readTrackCsv(dir / "track.csv");
  ASSERT_TRUE(rows) << rows.error().message;
  ASSERT_FALSE(rows->empty());
  // Frame numbers are the recording's (dropped frames leave gaps), times its timestamps.
  auto rec = record::Reader::open(dir.path() / "rec");
  ASSERT_TRUE(rec);
  EXPECT_EQ(rows->back().frame, static_cast<long>(rec->meta(rec->size() - 1).frame));
  r = test::run(test::cli() + " evaluate --recording " + (dir / "rec") + " --track " +
                (dir / "track.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  std::smatch m;
  ASSERT_TRUE(std::regex_search(r.output, m, std::regex("3D error +RMS ([0-9.]+) mm"))) << r.output;
  EXPECT_LT(std::stod(m[1]), 0.08) << r.output;
  EXPECT_NE(r.output.find("outliers > 0.50 mm    0 "), std::string::npos) << r.output;

  // The dense field and the targets: the first pair's ok features as targets (as a robot would
  // pick points on the surface), one point far off the surface; a broken points file.
  std::ofstream pts(dir / "points.csv");
  pts << "x,y,z\n";
  std::map<int, cv::Vec3d> first;
  for (const record::TrackRow& row : *rows) {
    if (row.frame != rows->front().frame || row.status != "ok" || first.size() >= 5) continue;
    first[row.id] = {row.x, row.y, row.z};
    pts << fmt::format("{:.6f},{:.6f},{:.6f}\n", row.x, row.y, row.z);
  }
  pts << "0,0,1450\n";
  pts.close();
  ASSERT_EQ(first.size(), 5U);
  r = test::run(test::cli() + " track -q --input " + (dir / "rec") + kRois + "--out " +
                (dir / "track2.csv") + " --field " + (dir / "field.csv") +
                " --field-every 5 --targets " + (dir / "points.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("targets           " + (dir / "track2-targets.csv") + " (6 targets"),
            std::string::npos)
      << r.output;
  // The targets follow their features: each answer's displacement within 0.1 mm of the feature's
  // own, the far point has no confidence.
  std::ifstream tin(dir / "track2-targets.csv");
  std::string header;
  std::getline(tin, header);
  EXPECT_EQ(header, "frame,t,target,x,y,z,dx,dy,dz,confidence");
  std::map<std::pair<long, int>, cv::Vec3d> feature_at;
  for (const record::TrackRow& row : *rows)
    if (row.status == "ok") feature_at[{row.frame, row.id}] = {row.x, row.y, row.z};
  std::vector<int> ids;
  ids.reserve(first.size());
  for (const auto& [id, p] : first) ids.push_back(id);
  int compared = 0, far = 0;
  double worst = 0, moved = 0;
  for (std::string line; std::getline(tin, line);) {
    std::vector<std::string> c;
    std::stringstream ss(line);
    for (std::string v; std::getline(ss, v, ',');) c.push_back(v);
    ASSERT_EQ(c.size(), 10U) << line;
    const int k = std::stoi(c[2]);
    if (k == 5) {
      EXPECT_EQ(std::stod(c[9]), 0.0) << line;
      ++far;
      continue;
    }
    const auto f = feature_at.find({std::stol(c[0]), ids[static_cast<size_t>(k)]});
    if (f == feature_at.end()) continue;
    // Its displacement against the feature's own (its track's position less its first); the
    // absolute positions also differ by the stereo refresh's correction of the first pair.
    const cv::Vec3d feature_d = f->second - first[ids[static_cast<size_t>(k)]];
    worst = std::max(
        worst, cv::norm(cv::Vec3d(std::stod(c[6]), std::stod(c[7]), std::stod(c[8])) - feature_d));
    moved = std::max(moved, cv::norm(feature_d));
    EXPECT_GT(std::stod(c[9]), 0.9) << line;
    ++compared;
  }
  std::cout << compared << " target answers against their features' tracks: displacement within "
            << worst << " mm of theirs, which moved up to " << moved << " mm\n";
  EXPECT_GT(compared, 40);
  EXPECT_GT(far, 10);
  // A feature's own track carries its noise (3D error RMS 0.028 mm: docs/results.md), the field's
  // answer the spline's average of its neighbours.
  EXPECT_LT(worst, 0.1);
  EXPECT_GT(moved, 3 * worst);
  // The field file: the grid every 5th pair, with its figures.
  std::ifstream fin(dir / "field.csv");
  std::getline(fin, header);
  EXPECT_EQ(header, "frame,t,signal,row,col,x,y,z,dx,dy,dz,confidence");
  std::set<std::string> frames;
  long field_rows = 0, beyond = 0;
  for (std::string line; std::getline(fin, line); ++field_rows) {
    frames.insert(line.substr(0, line.find(',')));
    beyond += line.ends_with(",,,,,,,0") ? 1 : 0;
  }
  EXPECT_GE(frames.size(), 2U);
  EXPECT_EQ(field_rows % static_cast<long>(frames.size()), 0);
  EXPECT_GT(field_rows / static_cast<long>(frames.size()), 300);
  EXPECT_LT(beyond, field_rows / 2);
  for (const char* png : {"field-map.png", "field-points.png"}) {
    const cv::Mat img = cv::imread(dir / png);
    EXPECT_FALSE(img.empty()) << png;
    EXPECT_GT(img.cols, 400) << png;
  }
  pts.open(dir / "bad.csv");
  pts << "1,2,3\n4,5\n";
  pts.close();
  r = test::run(test::cli() + " track -q --input " + (dir / "rec") + kRois + "--out " +
                (dir / "track3.csv") + " --targets " + (dir / "bad.csv"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("bad.csv:2: '4,5': expected x,y,z in mm"), std::string::npos) << r.output;
}

TEST(TrackCli, ImageFolderAndMatch) {
  test::TempDir dir;
  ASSERT_EQ(test::run(test::cli() + " simulate -q --scene " + scenes() +
                      "/cortex-60s.toml --frames 3 --out " + (dir / "rec"))
                .exit_code,
            0);
  auto rec = record::Reader::open(dir.path() / "rec");
  ASSERT_TRUE(rec);
  cv::Mat l, r;
  for (size_t i = 0; i < rec->size(); ++i) {
    ASSERT_TRUE(rec->read(i, l, r));
    cv::imwrite(dir / ("left_" + std::to_string(i) + ".png"), l);
    cv::imwrite(dir / ("right_" + std::to_string(i) + ".png"), r);
  }
  auto out = test::run(test::cli() + " track -q --rig " + (dir / "rec/rig.yaml") + " --left '" +
                       (dir / "left_*.png") + "' --right '" + (dir / "right_*.png") + "' --fps 10" +
                       kRois + "--out " + (dir / "t.csv"));
  ASSERT_EQ(out.exit_code, 0) << out.output;
  auto rows = record::readTrackCsv(dir / "t.csv");
  ASSERT_TRUE(rows);
  EXPECT_NEAR(rows->back().t, 0.1 * static_cast<double>(rec->size() - 1), 1e-9)
      << test::run("head -3 " + (dir / "t.csv") + "; ls " + dir.path().string()).output;
  out = test::run(test::cli() + " match --rig " + (dir / "rec/rig.yaml") + " --left " +
                  (dir / "left_0.png") + " --right " + (dir / "right_0.png") + kRois + "--out " +
                  (dir / "m.csv"));
  ASSERT_EQ(out.exit_code, 0) << out.output;
  std::ifstream csv(dir / "m.csv");
  std::string header;
  std::getline(csv, header);
  EXPECT_EQ(header, "id,xl,yl,xr,yr,ncc,nmi,epipolar_px,x,y,z,status");
  int ok = 0, n = 0, named = 0;
  for (std::string line; std::getline(csv, line); ++n) {
    ok += line.ends_with(",ok") ? 1 : 0;
    // A rejected candidate names the gate: "occluded:stereo_ncc", "lost:no_peak", ...
    const std::string status = line.substr(line.rfind(',') + 1);
    named += status != "ok" && status.find(':') != std::string::npos ? 1 : 0;
  }
  EXPECT_GT(ok, 40);
  EXPECT_EQ(named, n - ok) << "every rejected candidate names its gate";
  // The file holds what the command said it found.
  EXPECT_NE(out.output.find(std::to_string(n) + " candidates, " + std::to_string(ok) + " ok"),
            std::string::npos)
      << out.output << " (file: " << n << " rows, " << ok << " ok)";
  // The same rig written by OpenCV without D1/D2 (a calibration of rectified or undistorted
  // images, as some tools write it): taken, and the command says what it assumed.
  {
    cv::FileStorage in(dir / "rec/rig.yaml", cv::FileStorage::READ);
    cv::FileStorage nd(dir / "no-d.yml", cv::FileStorage::WRITE);
    for (const char* key : {"M1", "M2", "R", "T"}) nd << key << in[key].mat();
  }
  out = test::run(test::cli() + " match --rig " + (dir / "no-d.yml") + " --left " +
                  (dir / "left_0.png") + " --right " + (dir / "right_0.png") + kRois + "--out " +
                  (dir / "m2.csv"));
  ASSERT_EQ(out.exit_code, 0) << out.output;
  EXPECT_NE(out.output.find("note: " + (dir / "no-d.yml") +
                            ": no D1/D2 (lens distortion): the images are taken as free of it"),
            std::string::npos)
      << out.output;
}

TEST(TrackCli, ClearErrors) {
  test::TempDir dir;
  auto r = test::run(test::cli() + " track --input " + (dir / "nope") + kRois + "--out x.csv");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("not a recording folder"), std::string::npos) << r.output;
  r = test::run(test::cli() +
                " track --left 'a*' --right 'b*' --roi-left 1,2,3 --roi-right 1,2,3,4 --out x.csv");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("--roi-left '1,2,3': expected x,y,w,h"), std::string::npos) << r.output;
  r = test::run(test::cli() + " track --left '" + (dir / "a*") + "' --right 'b*'" + kRois +
                "--out x.csv");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("no file matches"), std::string::npos) << r.output;
  ASSERT_EQ(test::run(test::cli() + " simulate -q --scene " + scenes() +
                      "/cortex-60s.toml --frames 1 --out " + (dir / "rec"))
                .exit_code,
            0);
  r = test::run(test::cli() + " track --input " + (dir / "rec") +
                " --roi-left 1300,1000,200,200 --roi-right 1,1,200,200 --out " + (dir / "x.csv"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("left ROI 1300,1000 200x200: not inside the 1360x1024 image"),
            std::string::npos)
      << r.output;
  // The cameras given twice, a depth range that is not one, a --rectified that is not four numbers.
  r = test::run(test::cli() + " track --input " + (dir / "rec") + " --rig " +
                (dir / "rec/rig.yaml") +
                " --rectified 1000,680,512,60 --roi-left 400,300,500,400 "
                "--out " +
                (dir / "x.csv"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("give one of --rig, --rectified and --camera-info"), std::string::npos)
      << r.output;
  r = test::run(test::cli() + " track --input " + (dir / "rec") +
                " --roi-left 400,300,500,400 --depth-range 500,20 --out " + (dir / "x.csv"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("--depth-range 500,20: expected near,far in mm"), std::string::npos)
      << r.output;
  r = test::run(test::cli() + " track --input " + (dir / "rec") +
                " --rectified 1000,680 --roi-left 400,300,500,400 --out " + (dir / "x.csv"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("--rectified 1000,680: expected four numbers f,cx,cy,baseline_mm"),
            std::string::npos)
      << r.output;
  // A recording with no frame (its frames.ptv cut to the header) is an error, not "0 features"
  // and exit 0 (found by fuzzing, issue 15).
  std::filesystem::resize_file(dir / "rec/frames.ptv", 32);
  r = test::run(test::cli() + " track --input " + (dir / "rec") + kRois + "--out " +
                (dir / "x.csv"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("rec: the recording holds no complete frame"), std::string::npos)
      << r.output;
}

}  // namespace
}  // namespace pulsetrack
