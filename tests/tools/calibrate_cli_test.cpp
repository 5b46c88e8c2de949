// `pulsetrack calibrate` as a user runs it: the real binary, real files.

#include <gtest/gtest.h>

#include <fstream>
#include <opencv2/imgcodecs.hpp>

#include "pulsetrack/vision/stereo_rig.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

// OpenCV's 13 stereo chessboard pairs (Debian's opencv-doc; the folder holds other samples too,
// left.jpg among them: the globs name the numbered pairs).
std::string sampleDir() { return data::opencvSamples().string(); }

std::string calibrate(const std::string& left, const std::string& right, const std::string& out,
                      const std::string& extra = "") {
  return test::cli() + " calibrate --pattern chessboard --cols 9 --rows 6 --square 1.0 --left '" +
         left + "' --right '" + right + "' --out '" + out + "' " + extra;
}

TEST(CalibrateCli, HelpDescribesEveryOption) {
  const auto r = test::run(test::cli() + " calibrate --help");
  EXPECT_EQ(r.exit_code, 0);
  for (const char* opt : {"--pattern", "--cols", "--rows", "--square", "--marker", "--dictionary",
                          "--left", "--right", "--out", "--report", "--min-views", "--rational"}) {
    EXPECT_NE(r.output.find(opt), std::string::npos) << opt;
  }
  const auto top = test::run(test::cli() + " --help");
  EXPECT_EQ(top.exit_code, 0);
  EXPECT_NE(top.output.find("calibrate"), std::string::npos);
}

TEST(CalibrateCli, SamplePairsWithReport) {
  PULSETRACK_SKIP_WITHOUT_DATA(data::opencvSamples());
  test::TempDir dir;
  const std::string out = dir / "rig.yaml";
  const auto r =
      test::run(calibrate(sampleDir() + "/left[0-9][0-9].jpg", sampleDir() + "/right[0-9][0-9].jpg",
                          out, "--report '" + (dir / "report") + "'"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("[ 13/13] left14.jpg + right14.jpg: 54/54 and 54/54 corners"),
            std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("RMS stereo"), std::string::npos);
  EXPECT_NE(r.output.find("epipolar error"), std::string::npos);
  EXPECT_NE(r.output.find("baseline"), std::string::npos);
  auto rig = vision::loadRig(out);
  ASSERT_TRUE(rig) << rig.error().message;
  EXPECT_LE(rig->rms, 0.30);
  const cv::Mat png = cv::imread(dir / "report/calibration_report.png");
  ASSERT_FALSE(png.empty());
  EXPECT_EQ(png.cols, 1400);
  EXPECT_GT(png.rows, 800);
  std::ifstream csv(dir / "report/views.csv");
  std::string header;
  std::getline(csv, header);
  EXPECT_EQ(header.rfind("view,left,right,", 0), 0U);
  int rows = 0;
  for (std::string line; std::getline(csv, line);) ++rows;
  EXPECT_EQ(rows, 13);
}

TEST(CalibrateCli, ClearErrors) {
  PULSETRACK_SKIP_WITHOUT_DATA(data::opencvSamples());
  test::TempDir dir;
  const std::string out = dir / "rig.yaml";
  // No image matches a glob.
  auto r = test::run(calibrate(dir / "nothing*.jpg", sampleDir() + "/right[0-9][0-9].jpg", out));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("error: --left '" + (dir / "nothing*.jpg") + "': no file matches"),
            std::string::npos)
      << r.output;
  // Unpaired images.
  r = test::run(calibrate(sampleDir() + "/left0*.jpg", sampleDir() + "/right[0-9][0-9].jpg", out));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("right11.jpg has no left image"), std::string::npos) << r.output;
  // Unreadable image and different sizes.
  std::filesystem::create_directories(dir / "imgs");
  for (const char* n : {"01", "02", "03", "04", "05", "06"}) {
    std::filesystem::copy_file(sampleDir() + "/left" + n + ".jpg",
                               dir / ("imgs/left" + std::string(n) + ".jpg"));
    std::filesystem::copy_file(sampleDir() + "/right" + n + ".jpg",
                               dir / ("imgs/right" + std::string(n) + ".jpg"));
  }
  std::ofstream(dir / "imgs/right03.jpg", std::ios::trunc) << "garbage";
  r = test::run(calibrate(dir / "imgs/left*.jpg", dir / "imgs/right*.jpg", out));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("right03.jpg: unreadable image"), std::string::npos) << r.output;
  cv::imwrite(dir / "imgs/right03.jpg", cv::Mat(100, 200, CV_8UC1, cv::Scalar(0)));
  r = test::run(calibrate(dir / "imgs/left*.jpg", dir / "imgs/right*.jpg", out));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("right03.jpg: image is 200x100 but"), std::string::npos) << r.output;
  // Pattern found in too few views (the 200x100 image is back to a real one, two are blank).
  std::filesystem::copy_file(sampleDir() + "/right03.jpg", dir / "imgs/right03.jpg",
                             std::filesystem::copy_options::overwrite_existing);
  for (const char* n : {"04", "05"}) {
    cv::imwrite(dir / ("imgs/left" + std::string(n) + ".jpg"),
                cv::Mat(480, 640, CV_8UC1, cv::Scalar(128)));
  }
  r = test::run(calibrate(dir / "imgs/left*.jpg", dir / "imgs/right*.jpg", out));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("pattern found in both images of only 4 of 6 pairs (need at least 5)"),
            std::string::npos)
      << r.output;
  EXPECT_FALSE(std::filesystem::exists(out));
  // Bad option values are refused by the parser.
  r = test::run(test::cli() + " calibrate --pattern circles --left a --right b --out c");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("--pattern"), std::string::npos) << r.output;
}

}  // namespace
}  // namespace pulsetrack
