#pragma once
// A small z-buffered triangle rasterizer for the simulator's scenes. Vertices are projected
// through the exact camera model (distortion included) by the caller; inside a triangle the
// attributes are interpolated linearly in the image. With triangles of a few pixels the error
// of that against the exact (perspective, distorted) mapping is below 0.002 px, far under the
// 0.05 px the simulator promises (tests/sim/cortex_test.cpp measures it).
//
// Samples sit on an s x s grid per pixel (supersampling for anti-aliasing); the frame is the
// box-filtered average. The sample buffers are sized once, at construction.

#include <opencv2/core.hpp>
#include <span>

namespace pulsetrack::sim {

// A projected vertex: image position (px), depth (mm, for the z-test) and three attributes.
// For textured surfaces a0, a1 are texture coordinates (texture px) and a2 the shading factor;
// s is the specular term added after texturing.
struct ScreenVertex {
  float x = 0, y = 0, z = 0;
  float a0 = 0, a1 = 0, a2 = 0, s = 0;
  bool valid =
      false;  // false: behind the camera or not projectable; triangles using it are skipped
};

class Rasterizer {
 public:
  Rasterizer(cv::Size image_size, int supersample);

  void clear(float background);
  // Draws triangles (index triples into `vertices`) textured by `texture` (CV_32FC1, sampled
  // bilinearly at (a0, a1), clamped at the border): value = texture * a2 + s.
  void drawTextured(std::span<const ScreenVertex> vertices, std::span<const cv::Vec3i> triangles,
                    const cv::Mat& texture);
  // Box-filters the samples into `out` (CV_32FC1, image size; reallocated only if needed).
  void resolve(cv::Mat& out) const;

  [[nodiscard]] int supersample() const { return s_; }
  [[nodiscard]] cv::Size imageSize() const { return size_; }

 private:
  cv::Size size_;
  int s_;
  cv::Mat value_;  // CV_32FC1, s x image
  cv::Mat depth_;  // CV_32FC1, s x image
};

}  // namespace pulsetrack::sim
