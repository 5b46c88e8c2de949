// pulsetrack calibrate: stereo calibration from image pairs of a chessboard or ChArUco board.

#include <fmt/format.h>
#include <fmt/ostream.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <opencv2/imgcodecs.hpp>

#include "pulsetrack/tools/commands.hpp"
#include "pulsetrack/tools/image_pairs.hpp"
#include "pulsetrack/vision/calibration.hpp"

namespace pulsetrack::tools {

namespace {

struct CalibrateArgs {
  std::string pattern = "chessboard";
  int cols = 9;
  int rows = 6;
  double square = 1.0;
  double marker = 0.0;
  std::string dictionary = "DICT_5X5_100";
  std::string left;
  std::string right;
  std::string out;
  std::string report;
  int min_views = 5;
  bool rational = false;
  bool quiet = false;
};

std::string baseName(const std::string& p) { return std::filesystem::path(p).filename().string(); }

int error(const std::string& message) {
  fmt::print(stderr, "pulsetrack calibrate: error: {}\n", message);
  return 1;
}

vision::Result<void> writeViewsCsv(const vision::CalibrationResult& result,
                                   const std::filesystem::path& path) {
  std::ofstream f(path);
  if (!f) return vision::fail(fmt::format("{}: cannot open for writing", path.string()));
  f << "view,left,right,left_corners,right_corners,common_corners,left_rms_px,right_rms_px,used,"
       "rejected_because\n";
  for (size_t i = 0; i < result.views.size(); ++i) {
    const auto& v = result.views[i];
    fmt::print(f, "{},{},{},{},{},{},{:.5f},{:.5f},{},\"{}\"\n", i + 1, v.left_name, v.right_name,
               v.left_corners, v.right_corners, v.common_corners, v.left_rms, v.right_rms,
               v.used ? 1 : 0, v.rejected_because);
  }
  if (!f) return vision::fail(fmt::format("{}: write failed", path.string()));
  return {};
}

int runCalibrate(const CalibrateArgs& a) {
  vision::PatternSpec spec;
  spec.kind =
      a.pattern == "charuco" ? vision::PatternKind::kCharuco : vision::PatternKind::kChessboard;
  spec.cols = a.cols;
  spec.rows = a.rows;
  spec.square = a.square;
  spec.marker = a.marker > 0 ? a.marker : a.square * 0.7;
  spec.dictionary = a.dictionary;
  auto target = vision::CalibrationTarget::create(spec);
  if (!target) return error(target.error().message);

  auto pairs = pairImages(a.left, a.right);
  if (!pairs) return error(pairs.error().message);
  if (!a.quiet)
    fmt::print(stderr, "detecting the {} in {} image pairs\n", a.pattern, pairs->size());

  cv::Size size;
  const size_t expected = target->objectPoints().size();
  auto views = vision::detectViews(
      *pairs, *target, size, [&](size_t i, size_t n, const vision::ViewInput& v) {
        if (a.quiet) return;
        fmt::print(stderr, "[{:>3}/{}] {} + {}: {}/{} and {}/{} corners\n", i + 1, n,
                   baseName(v.left_name), baseName(v.right_name), v.left.ids.size(), expected,
                   v.right.ids.size(), expected);
      });
  if (!views) return error(views.error().message);

  vision::CalibrationOptions options;
  options.min_views = a.min_views;
  options.rational_model = a.rational;
  if (!a.quiet) fmt::print(stderr, "calibrating ({}x{} images)\n", size.width, size.height);
  auto result = vision::calibrateStereo(*views, *target, size, options);
  if (!result) return error(result.error().message);

  for (size_t i = 0; i < result->views.size(); ++i) {
    const auto& v = result->views[i];
    if (!v.used) {
      fmt::print(stderr, "view {} ({} + {}) not used: {}\n", i + 1, baseName(v.left_name),
                 baseName(v.right_name), v.rejected_because);
    }
  }

  if (auto ok = vision::saveRig(result->rig, a.out); !ok) return error(ok.error().message);

  const auto& rig = result->rig;
  fmt::print(
      "views used          {} of {}\n"
      "RMS left camera     {:.4f} px\n"
      "RMS right camera    {:.4f} px\n"
      "RMS stereo          {:.4f} px\n"
      "epipolar error      {:.4f} px mean per image ({:.4f} px as OpenCV's stereo_calib sums "
      "both)\n"
      "baseline            {:.4f} (units of --square)\n"
      "focal length        left {:.2f} x {:.2f} px, right {:.2f} x {:.2f} px\n"
      "rig written to      {}\n",
      result->views_used, result->views.size(), result->left_rms, result->right_rms,
      result->stereo_rms, result->epipolar_mean_px, result->epipolar_sample_px, rig.baseline(),
      rig.left.fx(), rig.left.fy(), rig.right.fx(), rig.right.fy(), a.out);

  if (!a.report.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(a.report, ec);
    if (ec)
      return error(fmt::format("{}: cannot create report folder: {}", a.report, ec.message()));
    const std::filesystem::path png = std::filesystem::path(a.report) / "calibration_report.png";
    const cv::Mat fig = vision::renderCalibrationReport(*result, *views, size);
    bool written = false;
    try {
      written = cv::imwrite(png.string(), fig);
    } catch (const cv::Exception& e) {
      return error(fmt::format("{}: cannot write: {}", png.string(), e.err));
    }
    if (!written) return error(fmt::format("{}: cannot write", png.string()));
    const auto csv = std::filesystem::path(a.report) / "views.csv";
    if (auto ok = writeViewsCsv(*result, csv); !ok) return error(ok.error().message);
    fmt::print("report written to   {} and {}\n", png.string(), csv.string());
  }
  return 0;
}

}  // namespace

CommandRunner addCalibrateCommand(CLI::App& app) {
  auto args = std::make_shared<CalibrateArgs>();
  CLI::App* cmd = app.add_subcommand(
      "calibrate",
      "Stereo calibration from image pairs of a chessboard or ChArUco board: per-camera then "
      "stereo calibration, outlier views rejected and reported, rig YAML written (OpenCV keys).");
  cmd->add_option("--pattern", args->pattern, "Target: chessboard or charuco")
      ->check(CLI::IsMember({"chessboard", "charuco"}))
      ->capture_default_str();
  cmd->add_option("--cols", args->cols,
                  "chessboard: inner corners per row; charuco: squares per row")
      ->check(CLI::Range(3, 100))
      ->capture_default_str();
  cmd->add_option("--rows", args->rows,
                  "chessboard: inner corners per column; charuco: squares per column")
      ->check(CLI::Range(3, 100))
      ->capture_default_str();
  cmd->add_option("--square", args->square, "Square side, in the rig's length unit (mm)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--marker", args->marker, "charuco: marker side (default 0.7 x square)")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--dictionary", args->dictionary, "charuco: ArUco dictionary")
      ->capture_default_str();
  cmd->add_option("--left", args->left, "Left images, a quoted glob such as 'DIR/left*.jpg'")
      ->required();
  cmd->add_option("--right", args->right, "Right images, a quoted glob such as 'DIR/right*.jpg'")
      ->required();
  cmd->add_option("--out", args->out, "Rig YAML to write")->required();
  cmd->add_option("--report", args->report,
                  "Folder for calibration_report.png (per-view errors, corner coverage) and "
                  "views.csv");
  cmd->add_option("--min-views", args->min_views, "Stereo pairs needed after rejection")
      ->check(CLI::Range(3, 1000))
      ->capture_default_str();
  cmd->add_flag("--rational", args->rational, "Rational distortion model (k4 k5 k6 as well)");
  cmd->add_flag("-q,--quiet", args->quiet, "No progress lines");
  return [args] { return runCalibrate(*args); };
}

}  // namespace pulsetrack::tools
