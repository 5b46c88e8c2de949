#include "pulsetrack/vision/camera_model.hpp"

#include <cmath>
#include <limits>

namespace pulsetrack::vision {

CameraModel::CameraModel(const cv::Matx33d& k, const double* dist, int num_dist,
                         cv::Size image_size) noexcept
    : k_(k), num_dist_(num_dist), image_size_(image_size) {
  for (int i = 0; i < num_dist && i < kMaxDistortion; ++i) dist_[static_cast<size_t>(i)] = dist[i];
}

cv::Vec2d CameraModel::distortNormalized(const cv::Vec2d& xy) const noexcept {
  cv::Matx22d unused;
  return distortNormalized(xy, unused);
}

// OpenCV's model (cv::projectPoints):
//   r2 = x^2 + y^2, radial = (1 + k1 r2 + k2 r4 + k3 r6) / (1 + k4 r2 + k5 r4 + k6 r6)
//   x'' = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
//   y'' = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
cv::Vec2d CameraModel::distortNormalized(const cv::Vec2d& xy,
                                         cv::Matx22d& jacobian) const noexcept {
  const double x = xy[0];
  const double y = xy[1];
  const double k1 = dist_[0], k2 = dist_[1], p1 = dist_[2], p2 = dist_[3], k3 = dist_[4];
  const double k4 = dist_[5], k5 = dist_[6], k6 = dist_[7];
  const double r2 = x * x + y * y;
  const double r4 = r2 * r2;
  const double r6 = r4 * r2;
  const double num = 1.0 + k1 * r2 + k2 * r4 + k3 * r6;
  const double den = 1.0 + k4 * r2 + k5 * r4 + k6 * r6;
  const double radial = num / den;
  // d(radial)/d(r2)
  const double dnum = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4;
  const double dden = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4;
  const double dradial = (dnum * den - num * dden) / (den * den);

  const double xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
  const double yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;

  // dr2/dx = 2x, dr2/dy = 2y
  jacobian(0, 0) = radial + x * dradial * 2.0 * x + 2.0 * p1 * y + p2 * 6.0 * x;
  jacobian(0, 1) = x * dradial * 2.0 * y + 2.0 * p1 * x + p2 * 2.0 * y;
  jacobian(1, 0) = y * dradial * 2.0 * x + p1 * 2.0 * x + 2.0 * p2 * y;
  jacobian(1, 1) = radial + y * dradial * 2.0 * y + p1 * 6.0 * y + 2.0 * p2 * x;
  return {xd, yd};
}

cv::Vec2d CameraModel::project(const cv::Vec3d& point) const noexcept {
  if (!(point[2] > 0.0)) {
    const double nan = std::numeric_limits<double>::quiet_NaN();
    return {nan, nan};
  }
  const double inv_z = 1.0 / point[2];
  const cv::Vec2d d = distortNormalized({point[0] * inv_z, point[1] * inv_z});
  return {k_(0, 0) * d[0] + k_(0, 1) * d[1] + k_(0, 2), k_(1, 1) * d[1] + k_(1, 2)};
}

cv::Vec2d CameraModel::undistortToNormalized(const cv::Vec2d& pixel) const noexcept {
  // Distorted normalized coordinates (inverse of K, which may carry a skew term).
  const double yd = (pixel[1] - k_(1, 2)) / k_(1, 1);
  const double xd = (pixel[0] - k_(0, 2) - k_(0, 1) * yd) / k_(0, 0);
  const cv::Vec2d target{xd, yd};
  // Gauss-Newton on distort(xy) = target, from the distorted point. Converges in a handful of
  // iterations for any physical lens; 20 is a hard ceiling.
  cv::Vec2d xy = target;
  for (int iter = 0; iter < 20; ++iter) {
    cv::Matx22d j;
    const cv::Vec2d residual = distortNormalized(xy, j) - target;
    const double det = j(0, 0) * j(1, 1) - j(0, 1) * j(1, 0);
    if (std::abs(det) < 1e-12) break;
    const cv::Vec2d step{(j(1, 1) * residual[0] - j(0, 1) * residual[1]) / det,
                         (-j(1, 0) * residual[0] + j(0, 0) * residual[1]) / det};
    xy -= step;
    if (std::abs(step[0]) + std::abs(step[1]) < 1e-16) break;
  }
  return xy;
}

cv::Vec2d CameraModel::undistortPixel(const cv::Vec2d& pixel) const noexcept {
  const cv::Vec2d n = undistortToNormalized(pixel);
  return {k_(0, 0) * n[0] + k_(0, 1) * n[1] + k_(0, 2), k_(1, 1) * n[1] + k_(1, 2)};
}

Ray CameraModel::backProject(const cv::Vec2d& pixel) const noexcept {
  const cv::Vec2d n = undistortToNormalized(pixel);
  return {cv::Vec3d(0, 0, 0), cv::normalize(cv::Vec3d(n[0], n[1], 1.0))};
}

}  // namespace pulsetrack::vision
