#pragma once
// Renders a textured plane as a camera of the rig model sees it, distortion included.
//
// Inverse mapping: every output pixel is cut into s x s sub-pixels; each sub-pixel centre is
// undistorted (to machine precision, CameraModel::undistortToNormalized), its ray is cut with
// the plane, and the texture is sampled there; the s x s samples are averaged (box-filter
// anti-aliasing). A rendered point lands where CameraModel::project puts it to well under
// 0.05 px when the texture is finer than the image (tests/sim/planar_render_test.cpp).

#include <opencv2/core.hpp>

#include "pulsetrack/vision/camera_model.hpp"

namespace pulsetrack::sim {

// The undistorted normalized ray (x, y, 1) of every sub-pixel centre of a camera, computed
// once: they do not change from frame to frame.
class CameraRays {
 public:
  CameraRays(const vision::CameraModel& camera, int supersample);
  [[nodiscard]] int supersample() const { return supersample_; }
  [[nodiscard]] cv::Size imageSize() const { return image_size_; }
  // CV_32FC2, (image height * s) x (image width * s): normalized (x, y) per sub-pixel.
  [[nodiscard]] const cv::Mat& normalized() const { return normalized_; }

 private:
  int supersample_;
  cv::Size image_size_;
  cv::Mat normalized_;
};

struct PlaneView {
  cv::Matx33d rotation = cv::Matx33d::eye();  // plane coordinates -> camera: x_c = R x_p + t
  cv::Vec3d translation;
};

// texture: 8-bit grey; texture_from_plane maps plane coordinates (x, y, 1) to texture pixel
// coordinates (pixel-centre convention). Pixels whose ray misses the plane, hits it behind the
// camera or falls outside the texture get `background`.
cv::Mat renderPlane(const CameraRays& rays, const PlaneView& view, const cv::Mat& texture,
                    const cv::Matx33d& texture_from_plane, double background = 128.0);

}  // namespace pulsetrack::sim
