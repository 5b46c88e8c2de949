// Stereo video as a lab has it, through the CLI: videos made here with OpenCV's VideoWriter
// (two files, side by side, top-bottom; lossless FFV1 and lossy Motion JPEG), a frame dropped
// from one with the ffmpeg program as a camera or an encoder drops one (the time stamps keep
// the gap), tracked with `pulsetrack track`, analysed with `pulsetrack analyze`; a recording
// exported with `pulsetrack export` and read back with OpenCV's VideoCapture and imread (nothing
// of the exporter's code): bit-exact; the overlay video read back.

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <regex>
#include <sstream>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

const std::string kRois = " --roi-left 483,339,400,340 --roi-right 476,344,400,340 --depth 20 ";
std::string scenes() { return test::sourceDir() + "/config/scenes"; }

// A simulated recording of `frames` pairs (10 fps).
void simulate(const test::TempDir& dir, int frames) {
  ASSERT_EQ(
      test::run(test::cli() + " simulate -q --scene " + scenes() + "/cortex-60s.toml --frames " +
                std::to_string(frames) + " --out " + (dir / "rec"))
          .exit_code,
      0);
}

struct Pairs {
  std::vector<cv::Mat> left, right;
};
Pairs readRecording(const std::filesystem::path& rec) {
  Pairs p;
  auto r = record::Reader::open(rec);
  EXPECT_TRUE(r) << r.error().message;
  if (!r) return p;
  for (size_t i = 0; i < r->size(); ++i) {
    cv::Mat l, rr;
    EXPECT_TRUE(r->read(i, l, rr));
    p.left.push_back(l.clone());
    p.right.push_back(rr.clone());
  }
  return p;
}

// Every frame of a video in grey, as OpenCV decodes it.
std::vector<cv::Mat> decode(const std::string& path, std::vector<double>* t_ms = nullptr) {
  cv::VideoCapture c(path, cv::CAP_FFMPEG);
  EXPECT_TRUE(c.isOpened()) << path;
  std::vector<cv::Mat> out;
  cv::Mat f;
  while (c.read(f)) {
    cv::Mat g;
    cv::cvtColor(f, g, cv::COLOR_BGR2GRAY);
    out.push_back(g);
    if (t_ms != nullptr) t_ms->push_back(c.get(cv::CAP_PROP_POS_MSEC));
  }
  return out;
}

void write(const std::string& path, int fourcc, const std::vector<cv::Mat>& frames) {
  cv::VideoWriter w(path, cv::CAP_FFMPEG, fourcc, 10.0, frames.front().size(), false);
  ASSERT_TRUE(w.isOpened()) << path;
  for (const cv::Mat& f : frames) w.write(f);
}

std::map<long, std::vector<record::TrackRow>> byFrame(const std::filesystem::path& csv) {
  std::map<long, std::vector<record::TrackRow>> m;
  auto rows = record::readTrackCsv(csv);
  EXPECT_TRUE(rows) << rows.error().message;
  if (rows)
    for (const auto& r : *rows) m[r.frame].push_back(r);
  return m;
}

TEST(VideoFiles, TrackReadsTwoFilesSideBySideAndTopBottomAndSeesADroppedFrame) {
  test::TempDir dir;
  simulate(dir, 20);  // analyze wants 16 frames at least
  const Pairs p = readRecording(dir.path() / "rec");
  const size_t n = p.left.size();  // the scene drops a trigger now and then: not 20
  ASSERT_GE(n, 17U);
  const int ffv1 = cv::VideoWriter::fourcc('F', 'F', 'V', '1');
  write(dir / "left.mkv", ffv1, p.left);
  write(dir / "right.mkv", ffv1, p.right);
  std::vector<cv::Mat> sbs, tb;
  for (size_t i = 0; i < p.left.size(); ++i) {
    cv::Mat h, v;
    cv::hconcat(p.left[i], p.right[i], h);
    cv::vconcat(p.left[i], p.right[i], v);
    sbs.push_back(h);
    tb.push_back(v);
  }
  write(dir / "sbs.mkv", ffv1, sbs);
  write(dir / "tb.mkv", ffv1, tb);
  write(dir / "sbs-mjpeg.avi", cv::VideoWriter::fourcc('M', 'J', 'P', 'G'), sbs);
  // The left camera drops frame 5 (and the side-by-side file too): the time stamps keep the gap.
  for (const std::string f : {"left", "sbs"}) {
    const auto r = test::run(fmt::format(
        "ffmpeg -v error -y -i {} -vf \"select='not(eq(n\\,5))'\" -fps_mode passthrough -c:v "
        "ffv1 {}",
        (dir / (f + ".mkv")), (dir / (f + "-drop.mkv"))));
    ASSERT_EQ(r.exit_code, 0) << r.output;
  }
  const std::string rig = " --rig " + (dir / "rec/rig.yaml");
  auto r = test::run(test::cli() + " track -q --input " + (dir / "rec") + kRois + "--out " +
                     (dir / "rec.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  // The recording's track by pair index: the videos hold its pairs one after the other (video
  // frame k is the recording's k-th pair, whatever the recording's own gaps).
  std::map<long, std::vector<record::TrackRow>> want;
  {
    auto rec = record::Reader::open(dir.path() / "rec");
    ASSERT_TRUE(rec);
    const auto by_rec = byFrame(dir / "rec.csv");
    for (size_t k = 0; k < rec->size(); ++k)
      want[static_cast<long>(k)] = by_rec.at(static_cast<long>(rec->meta(k).frame));
  }
  // Lossless video: the same pixels, so the same track as the recording's, row for row.
  for (const auto& [name, input] : std::map<std::string, std::string>{
           {"two", " --left-video " + (dir / "left.mkv") + " --right-video " + (dir / "right.mkv")},
           {"sbs", " --video " + (dir / "sbs.mkv")},
           {"tb", " --video " + (dir / "tb.mkv") + " --layout tb"}}) {
    r = test::run(fmt::format("{} track -q{}{}{}--out {}", test::cli(), rig, input, kRois,
                              (dir / (name + ".csv"))));
    ASSERT_EQ(r.exit_code, 0) << name << ": " << r.output;
    EXPECT_NE(r.output.find(fmt::format("{} pairs at 10.000 frames/s, 0 missing, 0 unpaired", n)),
              std::string::npos)
        << r.output;
    const auto got = byFrame(dir / (name + ".csv"));
    ASSERT_EQ(got.size(), want.size()) << name;
    for (const auto& [frame, rows] : want) {
      ASSERT_TRUE(got.count(frame)) << name << " frame " << frame;
      const auto& g = got.at(frame);
      ASSERT_EQ(g.size(), rows.size()) << name << " frame " << frame;
      for (size_t k = 0; k < rows.size(); ++k) {
        EXPECT_EQ(g[k].id, rows[k].id);
        EXPECT_EQ(g[k].status, rows[k].status);
        EXPECT_DOUBLE_EQ(g[k].x, rows[k].x);
        EXPECT_DOUBLE_EQ(g[k].z, rows[k].z);
      }
      EXPECT_NEAR(g.front().t, static_cast<double>(frame) * 0.1, 0.0011)
          << "the container's time stamps, 10 fps";
    }
  }
  // The dropped frame: said, numbered around, the pairs of the other file's frame 5 unpaired.
  r = test::run(test::cli() + " track -q" + rig + " --left-video " + (dir / "left-drop.mkv") +
                " --right-video " + (dir / "right.mkv") + kRois + "--out " + (dir / "drop.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("1 frame(s) missing after frame 4"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find(fmt::format("{} pairs at 10.000 frames/s, 1 missing, 1 unpaired", n - 1)),
            std::string::npos)
      << r.output;
  auto dropped = byFrame(dir / "drop.csv");
  EXPECT_EQ(dropped.count(5), 0U);
  EXPECT_EQ(dropped.count(6), 1U);
  EXPECT_EQ(dropped.size(), n - 1);
  for (long f = 0; f < 5; ++f) {  // before the drop: the recording's track
    ASSERT_EQ(dropped[f].size(), want.at(f).size());
    for (size_t k = 0; k < dropped[f].size(); ++k)
      EXPECT_DOUBLE_EQ(dropped[f][k].x, want.at(f)[k].x);
  }
  r = test::run(test::cli() + " track -q" + rig + " --video " + (dir / "sbs-drop.mkv") + kRois +
                "--out " + (dir / "sbs-drop.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find(fmt::format("{} pairs at 10.000 frames/s, 1 missing, 0 unpaired", n - 1)),
            std::string::npos)
      << r.output;
  // The analysis of what track made of the video: the missing frame filled.
  r = test::run(test::cli() + " analyze " + (dir / "drop-deformation.csv") + " --out " +
                (dir / "report"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find(fmt::format("{} frames ({} measured, 1 missing filled)", n, n - 1)),
            std::string::npos)
      << r.output;
  // A lossy codec (Motion JPEG): tracked, most features ok.
  r = test::run(test::cli() + " track -q" + rig + " --video " + (dir / "sbs-mjpeg.avi") + kRois +
                "--out " + (dir / "mjpeg.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto mj = byFrame(dir / "mjpeg.csv");
  ASSERT_EQ(mj.size(), n);
  int ok = 0;
  for (const auto& row : mj.rbegin()->second) ok += row.ok() ? 1 : 0;
  EXPECT_GT(ok, 20) << "ok features in the last Motion JPEG pair";
}

TEST(VideoFiles, ExportIsBitExactAndTheOverlayShowsTheFeatures) {
  test::TempDir dir;
  simulate(dir, 8);
  const Pairs p = readRecording(dir.path() / "rec");
  auto r = test::run(test::cli() + " export -q " + (dir / "rec") + " --video " +
                     (dir / "case.mkv") + " --images " + (dir / "images"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  // FFV1 in Matroska, read back with OpenCV: every pixel as recorded.
  const auto l = decode(dir / "case-left.mkv");
  const auto rr = decode(dir / "case-right.mkv");
  ASSERT_EQ(l.size(), p.left.size());
  ASSERT_EQ(rr.size(), p.right.size());
  for (size_t i = 0; i < l.size(); ++i) {
    EXPECT_EQ(cv::norm(l[i], p.left[i], cv::NORM_INF), 0.0) << "left " << i;
    EXPECT_EQ(cv::norm(rr[i], p.right[i], cv::NORM_INF), 0.0) << "right " << i;
  }
  // The frames' numbers and exposure times kept beside the video.
  auto rec = record::Reader::open(dir.path() / "rec");
  ASSERT_TRUE(rec);
  std::ifstream csv(dir / "case-frames.csv");
  std::string line;
  std::getline(csv, line);
  EXPECT_EQ(line, "video_frame,frame,trigger_seq,t_left_ns,t_right_ns");
  for (size_t i = 0; i < rec->size(); ++i) {
    ASSERT_TRUE(std::getline(csv, line));
    const auto& m = rec->meta(i);
    EXPECT_EQ(line,
              fmt::format("{},{},{},{},{}", i, m.frame, m.trigger_seq, m.t_left_ns, m.t_right_ns));
  }
  // Side by side: the same pixels in one file.
  r = test::run(test::cli() + " export -q " + (dir / "rec") + " --video " + (dir / "sbs.mkv") +
                " --layout sbs");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto s = decode(dir / "sbs.mkv");
  ASSERT_EQ(s.size(), p.left.size());
  for (size_t i = 0; i < s.size(); ++i) {
    cv::Mat both;
    cv::hconcat(p.left[i], p.right[i], both);
    EXPECT_EQ(cv::norm(s[i], both, cv::NORM_INF), 0.0) << i;
  }
  // The image folder (PNG, lossless), tracked by name as any image sequence.
  for (size_t i = 0; i < rec->size(); ++i) {
    const cv::Mat img = cv::imread(
        (dir / fmt::format("images/left_{:06d}.png", rec->meta(i).frame)), cv::IMREAD_UNCHANGED);
    ASSERT_FALSE(img.empty());
    EXPECT_EQ(cv::norm(img, p.left[i], cv::NORM_INF), 0.0);
  }
  // The overlay (FFV1 here, to look at its pixels): the left view, each ok feature's ring in
  // green where the track says it is, the plot strip below.
  r = test::run(test::cli() + " track -q --input " + (dir / "rec") + kRois + "--out " +
                (dir / "t.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run(test::cli() + " export -q " + (dir / "rec") + " --overlay " +
                (dir / "overlay.mkv") + " --track " + (dir / "t.csv") +
                " --roi-left 483,339,400,340");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  cv::VideoCapture c((dir / "overlay.mkv"), cv::CAP_FFMPEG);
  ASSERT_TRUE(c.isOpened());
  cv::Mat frame;
  std::vector<cv::Mat> frames;
  while (c.read(frame)) frames.push_back(frame.clone());
  ASSERT_EQ(frames.size(), p.left.size());
  EXPECT_EQ(frames[0].cols, p.left[0].cols);
  EXPECT_EQ(frames[0].rows, p.left[0].rows + 220);
  const auto rows = byFrame(dir / "t.csv");
  int green = 0, checked = 0;
  const long last = static_cast<long>(rec->meta(rec->size() - 1).frame);
  for (const auto& row : rows.at(last)) {
    if (!row.ok()) continue;
    const cv::Vec3b px = frames.back().at<cv::Vec3b>(static_cast<int>(std::lround(row.yl)),
                                                     static_cast<int>(std::lround(row.xl)) + 5);
    ++checked;
    green += px[1] > 150 && px[0] < 100 && px[2] < 100 ? 1 : 0;
  }
  EXPECT_GT(checked, 10);
  EXPECT_GE(green, checked * 9 / 10) << green << " of " << checked;
  // The plot strip is drawn (not the black of an empty canvas).
  EXPECT_GT(cv::mean(frames.back()(cv::Rect(0, p.left[0].rows, 200, 220)))[0], 200.0);
  // H.264 for talks (.mp4): it opens and has every frame.
  r = test::run(test::cli() + " export -q " + (dir / "rec") + " --overlay " +
                (dir / "overlay.mp4") + " --track " + (dir / "t.csv"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(decode(dir / "overlay.mp4").size(), p.left.size());
}

TEST(VideoFiles, BadVideoInputIsAClearError) {
  test::TempDir dir;
  simulate(dir, 2);
  const std::string rig = " --rig " + (dir / "rec/rig.yaml");
  std::ofstream(dir / "notes.mkv") << "not a video\n";
  auto r = test::run(test::cli() + " track" + rig + " --video " + (dir / "notes.mkv") + kRois +
                     "--out " + (dir / "x.csv"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("notes.mkv: cannot open as video"), std::string::npos) << r.output;
  r = test::run(test::cli() + " track" + rig + " --video " + (dir / "none.mkv") + kRois + "--out " +
                (dir / "x.csv"));
  EXPECT_NE(r.output.find("none.mkv: no such file"), std::string::npos) << r.output;
  // A video whose views are not the rig's size; two files of different sizes.
  const int ffv1 = cv::VideoWriter::fourcc('F', 'F', 'V', '1');
  write(dir / "small.mkv", ffv1, {cv::Mat(64, 128, CV_8UC1, cv::Scalar(7))});
  write(dir / "other.mkv", ffv1, {cv::Mat(64, 96, CV_8UC1, cv::Scalar(7))});
  r = test::run(test::cli() + " track" + rig + " --video " + (dir / "small.mkv") + kRois +
                "--out " + (dir / "x.csv"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("the calibration is for 1360x1024 images, each view of "),
            std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("small.mkv (side by side) is 64x64"), std::string::npos) << r.output;
  r = test::run(test::cli() + " track" + rig + " --left-video " + (dir / "small.mkv") +
                " --right-video " + (dir / "other.mkv") + kRois + "--out " + (dir / "x.csv"));
  EXPECT_NE(r.output.find("the views must be the same size"), std::string::npos) << r.output;
  r = test::run(test::cli() + " track" + rig + " --left-video " + (dir / "small.mkv") + kRois +
                "--out " + (dir / "x.csv"));
  EXPECT_NE(r.output.find("give both --left-video and --right-video"), std::string::npos)
      << r.output;
  r = test::run(test::cli() + " track --input " + (dir / "rec") + " --video " +
                (dir / "small.mkv") + kRois + "--out " + (dir / "x.csv"));
  EXPECT_NE(r.output.find("give one input"), std::string::npos) << r.output;
  r = test::run(test::cli() + " export " + (dir / "rec"));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("nothing to do"), std::string::npos) << r.output;
  r = test::run(test::cli() + " export " + (dir / "rec") + " --overlay " + (dir / "o.webm") +
                " --track " + (dir / "x.csv"));
  EXPECT_NE(r.output.find("x.csv"), std::string::npos) << r.output;
}

}  // namespace
}  // namespace pulsetrack
