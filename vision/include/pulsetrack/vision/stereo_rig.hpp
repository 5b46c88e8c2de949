#pragma once
// A calibrated stereo pair: two CameraModels and the rigid transform (R, T) that maps
// left-camera coordinates to right-camera coordinates, x_r = R x_l + T (OpenCV's
// stereoCalibrate convention). The left camera frame is the rig's frame {C}; lengths are in the
// calibration's unit (mm for every rig pulsetrack ships).
//
// Files: OpenCV FileStorage YAML with the keys of OpenCV's stereo_calib sample
// (M1 D1 M2 D2 R T) plus image_size and rms, so OpenCV and ROS tools read it unchanged.

#include <filesystem>
#include <opencv2/core/matx.hpp>
#include <string>

#include "pulsetrack/vision/camera_model.hpp"
#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::vision {

struct StereoRig {
  CameraModel left;
  CameraModel right;
  cv::Matx33d r = cv::Matx33d::eye();  // left -> right rotation
  cv::Vec3d t;                         // left -> right translation
  double rms = 0.0;                    // stereo reprojection RMS of the calibration, px
  // False: the file gave no distortion (neither D1 nor D2): the images are taken as free of it
  // (rectified or undistorted video). The tools say so (rigNotes()).
  bool distortion_given = true;

  [[nodiscard]] double baseline() const noexcept { return cv::norm(t); }
  // The right camera's centre in the left frame: -R^T T.
  [[nodiscard]] cv::Vec3d rightCentre() const noexcept { return -(r.t() * t); }

  // Eq. (2) for each camera, both rays expressed in the left frame {C}.
  [[nodiscard]] Ray backProjectLeft(const cv::Vec2d& pixel) const noexcept {
    return left.backProject(pixel);
  }
  [[nodiscard]] Ray backProjectRight(const cv::Vec2d& pixel) const noexcept;

  // A point in the left frame {C} -> pixel in each camera.
  [[nodiscard]] cv::Vec2d projectLeft(const cv::Vec3d& p) const noexcept { return left.project(p); }
  [[nodiscard]] cv::Vec2d projectRight(const cv::Vec3d& p) const noexcept {
    return right.project(r * p + t);
  }

  // E = [T]x R and F = K2^-T E K1^-1, for undistorted pixel coordinates (cv::undistortPoints
  // with P = K), as stereoCalibrate returns them.
  [[nodiscard]] cv::Matx33d essential() const noexcept;
  [[nodiscard]] cv::Matx33d fundamental() const noexcept;

  // Distance in px of the right pixel from the epipolar line of the left pixel and the reverse,
  // both on undistorted pixel coordinates; returns {left->right line distance, right->left}.
  [[nodiscard]] cv::Vec2d epipolarDistances(const cv::Vec2d& left_px,
                                            const cv::Vec2d& right_px) const noexcept;
  // The first of those, signed: positive on the side of the line its normal points to, the
  // normal's larger component taken positive (the same side for neighbouring pixels).
  [[nodiscard]] double epipolarOffset(const cv::Vec2d& left_px,
                                      const cv::Vec2d& right_px) const noexcept;
};

// Eq. (3): the point midway along the shortest segment between two rays, solved in closed form.
// Returns NaN when the rays are parallel.
[[nodiscard]] cv::Vec3d midpoint(const Ray& a, const Ray& b) noexcept;

// The bounds of a real rig. A file past them is corrupt or hostile: every size the tracker
// allocates follows from these values, so they are refused with the key that broke them.
inline constexpr int kMaxImageSide = 16384;          // px, each side
inline constexpr double kMaxFocalPx = 1e5;           // px
inline constexpr double kMaxBaselineMm = 10000.0;    // calibration units (mm): 10 m
inline constexpr size_t kMaxRigFileBytes = 1 << 20;  // a rig file is ~2 KB

// Checks what a loaded or computed rig must satisfy: positive focal lengths up to kMaxFocalPx,
// zero skew, the principal point inside the image, finite values, a distortion that maps the
// image one to one, R a rotation (|R^T R - I| < 1e-6, det +1), a baseline above zero and up to
// kMaxBaselineMm, an image of 1 to kMaxImageSide px a side.
// `where` names the source in messages (a file path, or "calibration").
[[nodiscard]] Result<void> validateRig(const StereoRig& rig, const std::string& where);

// Reads a rig file (the YAML OpenCV writes, read with yaml-cpp: OpenCV's own parser overflowed
// its stack at 100 000 levels of nesting, allocated 48 GB for `cols: NaN`, looped forever on
// some 24-byte files and threw std::length_error on others; docs/fuzzing.md). yaml-cpp bounds the
// nesting itself (its depth guard); the file's size is bounded here (kMaxRigFileBytes), each
// matrix's rows and cols as it is read, and every value after (validateRig); each error names
// the file, and the key or line.
// Files as calibration tools write them: matrices float or double, T 3x1 or 1x3, `rms`
// optional (0 when absent), `image_size` optional when `data_size` (the images' size, named
// `data_name` in messages) is given; when both are, they must agree (a named error).
[[nodiscard]] Result<StereoRig> loadRig(const std::filesystem::path& path, cv::Size data_size = {},
                                        const std::string& data_name = {});
// What a loaded calibration took for granted, for the tools to say ("" when nothing): a file
// without D1/D2 is read as images free of lens distortion.
[[nodiscard]] std::string rigNotes(const StereoRig& rig, const std::string& where);
// A rectified pair known only by its focal length and principal point (px, both views) and
// baseline (mm), for `size` images; `where` names the source in messages.
[[nodiscard]] Result<StereoRig> rectifiedRig(double focal_px, cv::Point2d principal,
                                             double baseline_mm, cv::Size size,
                                             const std::string& where);
// The same from "f,cx,cy,baseline_mm" (the --rectified option).
[[nodiscard]] Result<StereoRig> parseRectified(const std::string& text, cv::Size size);
// Two ROS camera_info YAML files (camera_calibration_parsers' layout: image_width,
// image_height, camera_matrix, distortion_model, distortion_coefficients, rectification_matrix,
// projection_matrix) of a stereo pair: the raw cameras from K and D, the extrinsics from the
// rectification rotations and the right P's Tx = -fx * baseline (metres, REP 103).
[[nodiscard]] Result<StereoRig> loadCameraInfoPair(const std::filesystem::path& left,
                                                   const std::filesystem::path& right,
                                                   cv::Size data_size = {},
                                                   const std::string& data_name = {});
[[nodiscard]] Result<void> saveRig(const StereoRig& rig, const std::filesystem::path& path);

}  // namespace pulsetrack::vision
