#pragma once
// The pinhole camera with OpenCV's lens distortion model (k1 k2 p1 p2 [k3 [k4 k5 k6]]), exactly
// as cv::projectPoints and cv::undistortPoints define it, so OpenCV and ROS tools read our
// calibrations and we read theirs. Everything here is noexcept and allocation-free: it is called
// per feature and frame by the tracker.

#include <array>
#include <opencv2/core/matx.hpp>
#include <opencv2/core/types.hpp>

namespace pulsetrack::vision {

// A ray L = p + lambda g with |g| = 1 (eq. 2 of the paper).
struct Ray {
  cv::Vec3d origin;
  cv::Vec3d direction;
};

class CameraModel {
 public:
  static constexpr int kMaxDistortion = 8;

  CameraModel() = default;
  // dist holds 4, 5 or 8 coefficients in OpenCV's order; missing ones are zero.
  CameraModel(const cv::Matx33d& k, const double* dist, int num_dist, cv::Size image_size) noexcept;

  [[nodiscard]] const cv::Matx33d& k() const noexcept { return k_; }
  [[nodiscard]] double fx() const noexcept { return k_(0, 0); }
  [[nodiscard]] double fy() const noexcept { return k_(1, 1); }
  [[nodiscard]] double cx() const noexcept { return k_(0, 2); }
  [[nodiscard]] double cy() const noexcept { return k_(1, 2); }
  [[nodiscard]] const std::array<double, kMaxDistortion>& dist() const noexcept { return dist_; }
  // How many coefficients the calibration carries (4, 5 or 8); written back as such.
  [[nodiscard]] int numDistortion() const noexcept { return num_dist_; }
  [[nodiscard]] cv::Size imageSize() const noexcept { return image_size_; }

  // Normalized undistorted (x, y) -> normalized distorted (x'', y'').
  [[nodiscard]] cv::Vec2d distortNormalized(const cv::Vec2d& xy) const noexcept;
  // The same with its 2x2 Jacobian d(distorted)/d(xy).
  [[nodiscard]] cv::Vec2d distortNormalized(const cv::Vec2d& xy,
                                            cv::Matx22d& jacobian) const noexcept;

  // A point in this camera's frame -> pixel. Undefined for points with z <= 0 (returns NaN).
  [[nodiscard]] cv::Vec2d project(const cv::Vec3d& point) const noexcept;

  // Pixel -> normalized undistorted coordinates, solved by Gauss-Newton to machine precision
  // (OpenCV's cv::undistortPoints stops after 5 fixed-point iterations by default, which leaves
  // errors of 1e-3 px and more near the corners of a strongly distorted lens).
  [[nodiscard]] cv::Vec2d undistortToNormalized(const cv::Vec2d& pixel) const noexcept;
  // Pixel -> undistorted pixel of the ideal pinhole camera K (cv::undistortPoints with P = K).
  [[nodiscard]] cv::Vec2d undistortPixel(const cv::Vec2d& pixel) const noexcept;

  // Eq. (2) of the paper in this camera's frame: the ray through the pixel, origin at the
  // camera centre, unit direction.
  [[nodiscard]] Ray backProject(const cv::Vec2d& pixel) const noexcept;

 private:
  cv::Matx33d k_ = cv::Matx33d::eye();
  std::array<double, kMaxDistortion> dist_{};
  int num_dist_ = 5;
  cv::Size image_size_;
};

}  // namespace pulsetrack::vision
