#pragma once
// Painting into the simulator's float textures with exact, symmetric anti-aliasing (8 x 8
// sub-samples per texel): cv::circle's anti-aliased polygons are off-centre by a fraction of a
// texel, which moved rendered dots by ~0.05 px.

#include <cmath>
#include <opencv2/core.hpp>

namespace pulsetrack::sim {

// Multiplies the texels of `tex` (CV_32FC1) within `radius_px` of `centre_px` (pixel-centre
// convention) by profile(q), q = distance / radius in [0, 1), averaged over sub-samples.
template <class Profile>
void paintDisc(cv::Mat& tex, cv::Point2d centre_px, double radius_px, Profile profile) {
  constexpr int kSub = 8;
  const int x0 = std::max(0, static_cast<int>(std::floor(centre_px.x - radius_px - 1)));
  const int x1 = std::min(tex.cols - 1, static_cast<int>(std::ceil(centre_px.x + radius_px + 1)));
  const int y0 = std::max(0, static_cast<int>(std::floor(centre_px.y - radius_px - 1)));
  const int y1 = std::min(tex.rows - 1, static_cast<int>(std::ceil(centre_px.y + radius_px + 1)));
  for (int y = y0; y <= y1; ++y) {
    for (int x = x0; x <= x1; ++x) {
      double acc = 0.0;
      for (int sy = 0; sy < kSub; ++sy) {
        for (int sx = 0; sx < kSub; ++sx) {
          const double dx = x - 0.5 + (sx + 0.5) / kSub - centre_px.x;
          const double dy = y - 0.5 + (sy + 0.5) / kSub - centre_px.y;
          const double q = std::sqrt(dx * dx + dy * dy) / radius_px;
          acc += q < 1.0 ? profile(q) : 1.0;
        }
      }
      tex.at<float>(y, x) *= static_cast<float>(acc / (kSub * kSub));
    }
  }
}

}  // namespace pulsetrack::sim
