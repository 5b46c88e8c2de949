#include "pulsetrack/sim/rasterizer.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/imgproc.hpp>

namespace pulsetrack::sim {

Rasterizer::Rasterizer(cv::Size image_size, int supersample)
    : size_(image_size), s_(std::max(1, supersample)) {
  value_.create(size_.height * s_, size_.width * s_, CV_32FC1);
  depth_.create(value_.size(), CV_32FC1);
}

void Rasterizer::clear(float background) {
  value_.setTo(background);
  depth_.setTo(std::numeric_limits<float>::infinity());
}

namespace {

inline float sampleBilinear(const cv::Mat& tex, float x, float y) {
  x = std::clamp(x, 0.0F, static_cast<float>(tex.cols - 1) - 1e-3F);
  y = std::clamp(y, 0.0F, static_cast<float>(tex.rows - 1) - 1e-3F);
  const int x0 = static_cast<int>(x);
  const int y0 = static_cast<int>(y);
  const float fx = x - static_cast<float>(x0);
  const float fy = y - static_cast<float>(y0);
  const auto* r0 = tex.ptr<float>(y0) + x0;
  const auto* r1 = tex.ptr<float>(y0 + 1) + x0;
  const float top = r0[0] + fx * (r0[1] - r0[0]);
  const float bottom = r1[0] + fx * (r1[1] - r1[0]);
  return top + fy * (bottom - top);
}

}  // namespace

void Rasterizer::drawTextured(std::span<const ScreenVertex> vertices,
                              std::span<const cv::Vec3i> triangles, const cv::Mat& texture) {
  const float s = static_cast<float>(s_);
  const int w = value_.cols;
  const int h = value_.rows;
  for (const cv::Vec3i& tri : triangles) {
    const ScreenVertex& v0 = vertices[static_cast<size_t>(tri[0])];
    const ScreenVertex& v1 = vertices[static_cast<size_t>(tri[1])];
    const ScreenVertex& v2 = vertices[static_cast<size_t>(tri[2])];
    if (!v0.valid || !v1.valid || !v2.valid) continue;
    // Image coordinates -> sample grid, whose sample centres are the integers.
    const float x0 = (v0.x + 0.5F) * s - 0.5F, y0 = (v0.y + 0.5F) * s - 0.5F;
    const float x1 = (v1.x + 0.5F) * s - 0.5F, y1 = (v1.y + 0.5F) * s - 0.5F;
    const float x2 = (v2.x + 0.5F) * s - 0.5F, y2 = (v2.y + 0.5F) * s - 0.5F;
    const float area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0);
    if (std::abs(area) < 1e-12F) continue;
    const float inv_area = 1.0F / area;
    const int xmin = std::max(0, static_cast<int>(std::ceil(std::min({x0, x1, x2}))));
    const int xmax = std::min(w - 1, static_cast<int>(std::floor(std::max({x0, x1, x2}))));
    const int ymin = std::max(0, static_cast<int>(std::ceil(std::min({y0, y1, y2}))));
    const int ymax = std::min(h - 1, static_cast<int>(std::floor(std::max({y0, y1, y2}))));
    if (xmin > xmax || ymin > ymax) continue;
    // Barycentric weights as affine functions of the sample position: b_i = A_i x + B_i y + C_i.
    const float a0 = (y1 - y2) * inv_area, b0 = (x2 - x1) * inv_area;
    const float c0 = (x1 * y2 - x2 * y1) * inv_area;
    const float a1 = (y2 - y0) * inv_area, b1 = (x0 - x2) * inv_area;
    const float c1 = (x2 * y0 - x0 * y2) * inv_area;
    const float eps = -1e-5F;
    for (int y = ymin; y <= ymax; ++y) {
      float* val = value_.ptr<float>(y);
      float* dep = depth_.ptr<float>(y);
      const float fy = static_cast<float>(y);
      for (int x = xmin; x <= xmax; ++x) {
        const float fx = static_cast<float>(x);
        const float l0 = a0 * fx + b0 * fy + c0;
        const float l1 = a1 * fx + b1 * fy + c1;
        const float l2 = 1.0F - l0 - l1;
        if (l0 < eps || l1 < eps || l2 < eps) continue;
        const float z = l0 * v0.z + l1 * v1.z + l2 * v2.z;
        if (z >= dep[x]) continue;
        dep[x] = z;
        const float u = l0 * v0.a0 + l1 * v1.a0 + l2 * v2.a0;
        const float v = l0 * v0.a1 + l1 * v1.a1 + l2 * v2.a1;
        const float shade = l0 * v0.a2 + l1 * v1.a2 + l2 * v2.a2;
        const float spec = l0 * v0.s + l1 * v1.s + l2 * v2.s;
        val[x] = sampleBilinear(texture, u, v) * shade + spec;
      }
    }
  }
}

void Rasterizer::resolve(cv::Mat& out) const {
  if (s_ == 1) {
    value_.copyTo(out);
    return;
  }
  cv::resize(value_, out, size_, 0, 0, cv::INTER_AREA);
}

}  // namespace pulsetrack::sim
