#pragma once
// A feature's motion from its neighbours': their motions as an affine function of where they
// are, evaluated where the feature is. A sag's bowl or a turn moves the tissue by more on one
// side of a feature than on the other; the neighbours' mean would blame the difference on the
// feature (the tracker's motion gate, re-acquisition) or put it into a hidden feature's
// displacement (the session), more and more as the shift grows (issue 34). Where the neighbours
// surround the feature too thinly the affine model would extrapolate and amplify their own
// noise: their mean then. Header only, noexcept, no allocation: called per feature and pair.

#include <algorithm>
#include <cmath>
#include <opencv2/core/matx.hpp>

namespace pulsetrack::vision {

template <int D>
struct NeighbourMotion {
  cv::Vec2d centroid{0, 0};       // the neighbours' mean position
  cv::Vec<double, D> mean{};      // their mean motion (the model at the centroid)
  cv::Vec<double, D> gx{}, gy{};  // its change per px along x and y (zero: the mean alone)
  bool affine = false;

  cv::Vec<double, D> at(const cv::Vec2d& x) const noexcept {
    const cv::Vec2d d = x - centroid;
    return mean + d[0] * gx + d[1] * gy;
  }
};

// The least-squares affine fit of motion[k] against position[k] (n of them), used where it
// interpolates: n >= 4, the positions' spread along its smaller axis >= 2 px (eigenvalue of their
// covariance > 4 px^2), and `where` within Mahalanobis distance 3 of their centroid. Else (or
// with affine false) the mean motion.
template <int D>
NeighbourMotion<D> fitNeighbourMotion(const cv::Vec2d* position, const cv::Vec<double, D>* motion,
                                      int n, const cv::Vec2d& where, bool affine = true) noexcept {
  NeighbourMotion<D> m;
  if (n <= 0) return m;
  for (int k = 0; k < n; ++k) {
    m.centroid += position[k];
    m.mean += motion[k];
  }
  m.centroid *= 1.0 / n;
  m.mean *= 1.0 / n;
  if (!affine || n < 4) return m;
  cv::Matx22d cov = cv::Matx22d::zeros();
  cv::Matx<double, 2, D> cross = cv::Matx<double, 2, D>::zeros();  // rows: x, y; cols: motion
  for (int k = 0; k < n; ++k) {
    const cv::Vec2d x = position[k] - m.centroid;
    const cv::Vec<double, D> v = motion[k] - m.mean;
    cov += x * x.t();
    for (int c = 0; c < D; ++c) {
      cross(0, c) += x[0] * v[c];
      cross(1, c) += x[1] * v[c];
    }
  }
  const double tr = cov(0, 0) + cov(1, 1);
  const double det = cov(0, 0) * cov(1, 1) - cov(0, 1) * cov(1, 0);
  const double small = (0.5 * tr - std::sqrt(std::max(0.0, 0.25 * tr * tr - det))) / n;
  if (!(small > 4.0)) return m;
  const cv::Matx22d inv(cov(1, 1) / det, -cov(0, 1) / det, -cov(1, 0) / det, cov(0, 0) / det);
  const cv::Vec2d off = where - m.centroid;
  if (off.dot((inv * n) * off) > 3.0 * 3.0) return m;
  const cv::Matx<double, 2, D> g = inv * cross;  // d(motion)/d(position): n cancels
  for (int c = 0; c < D; ++c) {
    m.gx[c] = g(0, c);
    m.gy[c] = g(1, c);
  }
  m.affine = true;
  return m;
}

}  // namespace pulsetrack::vision
