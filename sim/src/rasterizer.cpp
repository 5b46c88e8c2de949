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
  const int w = value_.cols;
  const int h = value_.rows;
  for (const cv::Vec3i& tri : triangles) {
    const ScreenVertex& v0 = vertices[static_cast<size_t>(tri[0])];
    const ScreenVertex& v1 = vertices[static_cast<size_t>(tri[1])];
    const ScreenVertex& v2 = vertices[static_cast<size_t>(tri[2])];
    if (!v0.valid || !v1.valid || !v2.valid) continue;
    // Image coordinates -> sample grid, whose sample centres are the integers. The edge
    // functions are set up in double and relative to vertex 0: in float, on absolute
    // coordinates of a few thousand, x1 y2 - x2 y1 cancels down to ~1 % of a small triangle's
    // area, which moved rendered points by up to 0.17 px (tests/sim/cortex_test.cpp).
    const double sd = s_;
    const double x0 = (v0.x + 0.5) * sd - 0.5, y0 = (v0.y + 0.5) * sd - 0.5;
    const double x1 = (v1.x + 0.5) * sd - 0.5 - x0, y1 = (v1.y + 0.5) * sd - 0.5 - y0;
    const double x2 = (v2.x + 0.5) * sd - 0.5 - x0, y2 = (v2.y + 0.5) * sd - 0.5 - y0;
    const double area = x1 * y2 - x2 * y1;
    if (std::abs(area) < 1e-12) continue;
    const double inv_area = 1.0 / area;
    const int xmin = std::max(0, static_cast<int>(std::ceil(x0 + std::min({0.0, x1, x2}))));
    const int xmax = std::min(w - 1, static_cast<int>(std::floor(x0 + std::max({0.0, x1, x2}))));
    const int ymin = std::max(0, static_cast<int>(std::ceil(y0 + std::min({0.0, y1, y2}))));
    const int ymax = std::min(h - 1, static_cast<int>(std::floor(y0 + std::max({0.0, y1, y2}))));
    if (xmin > xmax || ymin > ymax) continue;
    // Barycentric weights of vertices 1 and 2 as functions of (dx, dy) = sample - vertex 0.
    const double a1 = y2 * inv_area, b1 = -x2 * inv_area;
    const double a2 = -y1 * inv_area, b2 = x1 * inv_area;
    const double eps = -1e-9;
    for (int y = ymin; y <= ymax; ++y) {
      float* val = value_.ptr<float>(y);
      float* dep = depth_.ptr<float>(y);
      const double dy = y - y0;
      for (int x = xmin; x <= xmax; ++x) {
        const double dx = x - x0;
        const double l1 = a1 * dx + b1 * dy;
        const double l2 = a2 * dx + b2 * dy;
        const double l0 = 1.0 - l1 - l2;
        if (l0 < eps || l1 < eps || l2 < eps) continue;
        const auto z = static_cast<float>(l0 * v0.z + l1 * v1.z + l2 * v2.z);
        if (z >= dep[x]) continue;
        dep[x] = z;
        const auto u = static_cast<float>(l0 * v0.a0 + l1 * v1.a0 + l2 * v2.a0);
        const auto v = static_cast<float>(l0 * v0.a1 + l1 * v1.a1 + l2 * v2.a1);
        const auto shade = static_cast<float>(l0 * v0.a2 + l1 * v1.a2 + l2 * v2.a2);
        const auto spec = static_cast<float>(l0 * v0.s + l1 * v1.s + l2 * v2.s);
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
