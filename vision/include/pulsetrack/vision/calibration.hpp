#pragma once
// Stereo calibration (section 2.A of the paper): a planar target seen in N stereo pairs ->
// per-camera intrinsics, then the stereo transform, then a joint refinement of everything.
// Views whose reprojection error stands out are rejected and reported, never silently.
//
// Two targets: OpenCV's chessboard (inner corners, sub-pixel by findChessboardCornersSB with
// CALIB_CB_ACCURACY) and ChArUco, the coded board that plays the role of the paper's CALTag:
// every corner carries its identity, so rotated, partial and occluded views still calibrate.

#include <functional>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

namespace cv::aruco {
class CharucoBoard;
}

namespace pulsetrack::vision {

enum class PatternKind { kChessboard, kCharuco };

struct PatternSpec {
  PatternKind kind = PatternKind::kChessboard;
  int cols = 9;         // chessboard: inner corners per row; ChArUco: squares per row
  int rows = 6;         // chessboard: inner corners per column; ChArUco: squares per column
  double square = 1.0;  // side of one square, in the rig's length unit (mm)
  double marker = 0.0;  // ChArUco marker side (< square)
  std::string dictionary = "DICT_5X5_100";  // ChArUco: any cv::aruco::PREDEFINED_DICTIONARY_NAME
};

// Corners found in one image: ids index CalibrationTarget::objectPoints().
struct Detection {
  std::vector<int> ids;
  std::vector<cv::Point2f> corners;
  [[nodiscard]] bool empty() const { return ids.empty(); }
};

class CalibrationTarget {
 public:
  // Fails on nonsense geometry (too few corners, marker >= square, unknown dictionary).
  static Result<CalibrationTarget> create(const PatternSpec& spec);

  // Finds the target in a grey 8-bit image. An empty Detection when it is not there.
  [[nodiscard]] Detection detect(const cv::Mat& grey) const;

  // Board coordinates of every corner id (z = 0), in the spec's unit.
  [[nodiscard]] const std::vector<cv::Point3f>& objectPoints() const { return object_points_; }
  [[nodiscard]] const PatternSpec& spec() const { return spec_; }

  // A flat image of the board for printing or rendering, `px_per_square` pixels per square and
  // `margin_px` of white around it. `texture_from_board` maps board coordinates (x, y, 1) to
  // pixel coordinates of the image (OpenCV's pixel-centre convention).
  [[nodiscard]] cv::Mat draw(int px_per_square, int margin_px,
                             cv::Matx33d& texture_from_board) const;

 private:
  PatternSpec spec_;
  std::vector<cv::Point3f> object_points_;
  cv::Ptr<cv::aruco::CharucoBoard> board_;  // ChArUco only
};

struct CalibrationOptions {
  int min_views = 5;            // stereo pairs needed after rejection
  int min_corners = 8;          // corners a view needs in each camera to count
  double reject_mad = 4.0;      // reject views above median + reject_mad * 1.4826 * MAD ...
  double reject_ratio = 2.5;    // ... and above reject_ratio * median (both must hold)
  bool rational_model = false;  // k4 k5 k6 as well (8 coefficients)
};

struct ViewInput {
  std::string left_name;
  std::string right_name;
  Detection left;
  Detection right;
};

struct ViewReport {
  std::string left_name;
  std::string right_name;
  int left_corners = 0;
  int right_corners = 0;
  int common_corners = 0;
  double left_rms = -1.0;  // px, in the final joint calibration; -1 when not evaluated
  double right_rms = -1.0;
  bool used = false;
  std::string rejected_because;  // empty when used
};

struct CalibrationResult {
  StereoRig rig;
  double left_rms = 0.0;  // per-camera calibration RMS, px
  double right_rms = 0.0;
  double stereo_rms = 0.0;  // joint stereo RMS, px
  // Mean epipolar error as OpenCV's stereo_calib sample defines it (sum of the two point-to-
  // epiline distances per corner, averaged over corners), and the plain one-way mean.
  double epipolar_sample_px = 0.0;
  double epipolar_mean_px = 0.0;
  int views_used = 0;
  std::vector<ViewReport> views;
};

// Called once per image pair while detecting: index (0-based), total, the pair's names and
// how many corners were found on each side.
using DetectProgress = std::function<void(size_t index, size_t total, const ViewInput& view)>;

// Reads each pair of image files (any format OpenCV decodes; colour is converted to grey) and
// detects the target. Fails naming the file on an unreadable image or one whose size differs
// from the first image's.
Result<std::vector<ViewInput>> detectViews(
    const std::vector<std::pair<std::string, std::string>>& pairs, const CalibrationTarget& target,
    cv::Size& image_size, const DetectProgress& progress = {});

// Calibrates the rig. Fails when fewer than options.min_views pairs show the target (naming how
// many did) or the calibration does not converge.
Result<CalibrationResult> calibrateStereo(const std::vector<ViewInput>& views,
                                          const CalibrationTarget& target, cv::Size image_size,
                                          const CalibrationOptions& options = {});

// A figure for a person: per-view reprojection errors (left, right; rejected views marked) and
// the coverage of each image by the detected corners.
cv::Mat renderCalibrationReport(const CalibrationResult& result,
                                const std::vector<ViewInput>& views, cv::Size image_size);

}  // namespace pulsetrack::vision
