#include "pulsetrack/vision/triangulation.hpp"

#include <cmath>
#include <opencv2/core.hpp>  // Matx::solve is defined in operations.hpp

namespace pulsetrack::vision {

namespace {

// Pixel of point p (left frame) in a camera x_c = r p + t, and its 2x3 Jacobian d(pixel)/dp.
bool projectWithJacobian(const CameraModel& cam, const cv::Matx33d& r, const cv::Vec3d& t,
                         const cv::Vec3d& p, cv::Vec2d& px, cv::Matx23d& jac) noexcept {
  const cv::Vec3d pc = r * p + t;
  if (!(pc[2] > 1e-9)) return false;
  const double iz = 1.0 / pc[2];
  const cv::Vec2d n(pc[0] * iz, pc[1] * iz);
  cv::Matx22d jd;
  const cv::Vec2d d = cam.distortNormalized(n, jd);
  px = {cam.fx() * d[0] + cam.cx(), cam.fy() * d[1] + cam.cy()};
  const cv::Matx23d dn(iz, 0, -pc[0] * iz * iz, 0, iz, -pc[1] * iz * iz);
  const cv::Matx22d k(cam.fx(), 0, 0, cam.fy());
  jac = k * jd * dn * r;
  return true;
}

// LM from `start`. (Started from the previous frame's point instead of the midpoint it took
// twice as long: the midpoint is closer to the optimum than a moved point.)
Triangulation refine(const StereoRig& rig, const cv::Vec2d& left_px, const cv::Vec2d& right_px,
                     const cv::Vec3d& start) noexcept {
  Triangulation out;
  cv::Vec3d x = start;
  if (!std::isfinite(x[0]) || !std::isfinite(x[1]) || !std::isfinite(x[2])) return out;
  const cv::Matx33d eye = cv::Matx33d::eye();
  const cv::Vec3d zero(0, 0, 0);
  const auto evaluate = [&](const cv::Vec3d& p, cv::Matx33d* jtj, cv::Vec3d* jtr, double& cost) {
    cv::Vec2d pl, pr;
    cv::Matx23d jl, jr;
    if (!projectWithJacobian(rig.left, eye, zero, p, pl, jl) ||
        !projectWithJacobian(rig.right, rig.r, rig.t, p, pr, jr)) {
      return false;
    }
    const cv::Vec2d rl = pl - left_px;
    const cv::Vec2d rr = pr - right_px;
    cost = rl.dot(rl) + rr.dot(rr);
    if (jtj != nullptr) {
      *jtj = jl.t() * jl + jr.t() * jr;
      *jtr = jl.t() * rl + jr.t() * rr;
    }
    return true;
  };
  double cost = 0.0;
  cv::Matx33d jtj;
  cv::Vec3d jtr;
  if (!evaluate(x, &jtj, &jtr, cost)) return out;
  double lambda = 1e-3;
  int it = 0;
  for (; it < 30; ++it) {
    cv::Matx33d a = jtj;
    for (int i = 0; i < 3; ++i) a(i, i) *= 1.0 + lambda;
    // Matx::solve works on the stack (cv::solve through InputArray may allocate).
    const cv::Vec3d step(a.solve(cv::Matx31d(-jtr[0], -jtr[1], -jtr[2]), cv::DECOMP_CHOLESKY).val);
    if (step == cv::Vec3d(0, 0, 0)) break;  // singular
    const cv::Vec3d candidate = x + step;
    double new_cost = 0.0;
    cv::Matx33d new_jtj;
    cv::Vec3d new_jtr;
    // The Jacobian with the cost: a step is accepted far more often than not.
    if (evaluate(candidate, &new_jtj, &new_jtr, new_cost) && new_cost < cost) {
      x = candidate;
      cost = new_cost;
      jtj = new_jtj;
      jtr = new_jtr;
      lambda *= 0.1;
      // 1 nm: four orders of magnitude below the point's own uncertainty.
      if (cv::norm(step) < 1e-6) break;
    } else {
      lambda *= 10.0;
      if (lambda > 1e8) break;
    }
  }
  out.point = x;
  out.iterations = it;
  out.reprojection_rms = std::sqrt(cost / 4.0);
  out.ok = std::isfinite(cost);
  return out;
}

}  // namespace

Triangulation triangulate(const StereoRig& rig, const cv::Vec2d& left_px,
                          const cv::Vec2d& right_px) noexcept {
  const cv::Vec3d x = midpoint(rig.backProjectLeft(left_px), rig.backProjectRight(right_px));
  if (!std::isfinite(x[0])) return {};
  return refine(rig, left_px, right_px, x);
}

}  // namespace pulsetrack::vision
