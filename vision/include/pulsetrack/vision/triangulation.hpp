#pragma once
// Section 2.C: a feature's 3D position from its two pixels. The midpoint of the two rays
// (eq. 3) starts Levenberg-Marquardt on both reprojection errors through the full distortion
// model, which is the maximum-likelihood point for isotropic pixel noise. noexcept, no
// allocation: called per feature and frame.

#include <opencv2/core/matx.hpp>

#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::vision {

struct Triangulation {
  cv::Vec3d point;              // in the left camera frame {C}, mm
  double reprojection_rms = 0;  // px, over the four residuals' two cameras
  int iterations = 0;
  bool ok = false;  // false: parallel rays, behind a camera, or no convergence
};

Triangulation triangulate(const StereoRig& rig, const cv::Vec2d& left_px,
                          const cv::Vec2d& right_px) noexcept;

}  // namespace pulsetrack::vision
