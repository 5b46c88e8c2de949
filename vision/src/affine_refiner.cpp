#include "pulsetrack/vision/affine_refiner.hpp"

#include <cmath>
#include <opencv2/core.hpp>  // Matx::solve / inv (operations.hpp)

namespace pulsetrack::vision {

namespace {

// Catmull-Rom (Keys, a = -0.5) weights of the four taps around a sample at fraction t.
inline void catmullRom(float t, float w[4]) noexcept {
  const float t2 = t * t, t3 = t2 * t;
  w[0] = -0.5F * t3 + t2 - 0.5F * t;
  w[1] = 1.5F * t3 - 2.5F * t2 + 1.0F;
  w[2] = -1.5F * t3 + 2.0F * t2 + 0.5F * t;
  w[3] = 0.5F * t3 - 0.5F * t2;
}

// The 4x4 bicubic sum at integer (x0, y0) with fractions (fx, fy); no bounds check.
inline float bicubicAt(const uint8_t* image, size_t stride, int x0, int y0, float fx,
                       float fy) noexcept {
  float wx[4], wy[4];
  catmullRom(fx, wx);
  catmullRom(fy, wy);
  const uint8_t* p = image + static_cast<size_t>(y0 - 1) * stride + static_cast<size_t>(x0 - 1);
  float acc = 0.0F;
  for (int j = 0; j < 4; ++j, p += stride) {
    acc += wy[j] * (wx[0] * static_cast<float>(p[0]) + wx[1] * static_cast<float>(p[1]) +
                    wx[2] * static_cast<float>(p[2]) + wx[3] * static_cast<float>(p[3]));
  }
  return acc;
}

}  // namespace

bool sampleBicubic(const uint8_t* image, size_t stride, int width, int height, double x, double y,
                   float& out) noexcept {
  if (!(x >= 1.0) || !(y >= 1.0) || x >= width - 2 || y >= height - 2) return false;
  const int x0 = static_cast<int>(x);
  const int y0 = static_cast<int>(y);
  out = bicubicAt(image, stride, x0, y0, static_cast<float>(x - x0), static_cast<float>(y - y0));
  return true;
}

namespace {

// Samples the warped patch (bicubic: bilinear sampling is biased by up to 0.04 px on
// textures of a few pixels' scale, see tests/vision/affine_refiner_test.cpp); false when it
// leaves the image. The patch is affine, so checking its four corners bounds every sample,
// and the sample position steps by the warp's columns along a row.
bool warpPatch(const uint8_t* image, size_t stride, int width, int height, const AffineWarp& w,
               std::array<float, kAffinePixels>& out) noexcept {
  for (const int cy : {-kAffineHalf, kAffineHalf}) {
    for (const int cx : {-kAffineHalf, kAffineHalf}) {
      const double u = w.centre[0] + w.a(0, 0) * cx + w.a(0, 1) * cy;
      const double v = w.centre[1] + w.a(1, 0) * cx + w.a(1, 1) * cy;
      if (!(u >= 1.0) || !(v >= 1.0) || u >= width - 2 || v >= height - 2) return false;
    }
  }
  int k = 0;
  for (int y = -kAffineHalf; y <= kAffineHalf; ++y) {
    double u = w.centre[0] - w.a(0, 0) * kAffineHalf + w.a(0, 1) * y;
    double v = w.centre[1] - w.a(1, 0) * kAffineHalf + w.a(1, 1) * y;
    for (int x = -kAffineHalf; x <= kAffineHalf; ++x, ++k, u += w.a(0, 0), v += w.a(1, 0)) {
      const int x0 = static_cast<int>(u);
      const int y0 = static_cast<int>(v);
      out[static_cast<size_t>(k)] =
          bicubicAt(image, stride, x0, y0, static_cast<float>(u - x0), static_cast<float>(v - y0));
    }
  }
  return true;
}

void meanSpread(const std::array<float, kAffinePixels>& p, double& mean, double& spread) noexcept {
  double s = 0, s2 = 0;
  for (float v : p) {
    s += v;
    s2 += static_cast<double>(v) * v;
  }
  mean = s / kAffinePixels;
  spread = std::sqrt(std::max(0.0, s2 / kAffinePixels - mean * mean));
}

}  // namespace

bool AffineTemplate::set(const uint8_t* image, size_t stride, int width, int height,
                         const AffineWarp& warp) noexcept {
  if (!warpPatch(image, stride, width, height, warp, t_)) return false;
  meanSpread(t_, mean_, spread_);
  if (spread_ < 1.0) return false;
  // Gradients of the template by central differences on a one-pixel-larger warped patch.
  cv::Matx<double, 6, 6> h = cv::Matx<double, 6, 6>::zeros();
  int k = 0;
  for (int y = -kAffineHalf; y <= kAffineHalf; ++y) {
    for (int x = -kAffineHalf; x <= kAffineHalf; ++x, ++k) {
      float xp = 0, xm = 0, yp = 0, ym = 0;
      const auto at = [&](double dx, double dy, float& o) {
        const double u = warp.centre[0] + warp.a(0, 0) * (x + dx) + warp.a(0, 1) * (y + dy);
        const double v = warp.centre[1] + warp.a(1, 0) * (x + dx) + warp.a(1, 1) * (y + dy);
        return sampleBicubic(image, stride, width, height, u, v, o);
      };
      if (!at(1, 0, xp) || !at(-1, 0, xm) || !at(0, 1, yp) || !at(0, -1, ym)) return false;
      const double gx = 0.5 * (xp - xm);
      const double gy = 0.5 * (yp - ym);
      // d(warp)/d(params) at identity, params = (da00, da10, da01, da11, dtx, dty).
      const double sd[6] = {gx * x, gy * x, gx * y, gy * y, gx, gy};
      auto& row = sd_[static_cast<size_t>(k)];
      for (int i = 0; i < 6; ++i) {
        row[static_cast<size_t>(i)] = static_cast<float>(sd[i]);
        for (int j = 0; j < 6; ++j) h(i, j) += sd[i] * sd[j];
      }
    }
  }
  bool ok = false;
  h_inv_ = h.inv(cv::DECOMP_CHOLESKY, &ok);
  return ok;
}

AffineResult AffineTemplate::refine(const uint8_t* image, size_t stride, int width, int height,
                                    const AffineWarp& start, int max_iterations,
                                    double epsilon_px) const noexcept {
  AffineResult res;
  res.warp = start;
  std::array<float, kAffinePixels> patch{};
  for (int it = 0; it < max_iterations; ++it) {
    res.iterations = it + 1;
    if (!warpPatch(image, stride, width, height, res.warp, patch)) return res;
    double mean = 0, spread = 0;
    meanSpread(patch, mean, spread);
    if (spread < 1e-6) return res;
    const double gain = spread_ / spread;
    cv::Vec<double, 6> b = cv::Vec<double, 6>::all(0.0);
    double sse = 0.0;
    for (size_t k = 0; k < static_cast<size_t>(kAffinePixels); ++k) {
      const double e = (patch[k] - mean) * gain + mean_ - t_[k];
      sse += e * e;
      for (size_t i = 0; i < 6; ++i) b[static_cast<int>(i)] += sd_[k][i] * e;
    }
    res.rms = std::sqrt(sse / kAffinePixels);
    const cv::Vec<double, 6> dp = h_inv_ * b;
    // Inverse composition: W <- W o W(dp)^-1, with W(dp) = [I + D | t].
    const cv::Matx22d d(1.0 + dp[0], dp[2], dp[1], 1.0 + dp[3]);
    const cv::Matx22d d_inv = d.inv();
    const cv::Vec2d t(dp[4], dp[5]);
    const cv::Matx22d a_new = res.warp.a * d_inv;
    const cv::Vec2d c_new = res.warp.centre - a_new * t;
    // Largest movement of a patch corner.
    double move = 0.0;
    for (const cv::Vec2d& corner :
         {cv::Vec2d(-kAffineHalf, -kAffineHalf), cv::Vec2d(kAffineHalf, -kAffineHalf),
          cv::Vec2d(-kAffineHalf, kAffineHalf), cv::Vec2d(kAffineHalf, kAffineHalf)}) {
      const cv::Vec2d before = res.warp.centre + res.warp.a * corner;
      const cv::Vec2d after = c_new + a_new * corner;
      move = std::max(move, cv::norm(after - before));
    }
    res.warp.a = a_new;
    res.warp.centre = c_new;
    if (move < epsilon_px) {
      res.converged = true;
      break;
    }
  }
  return res;
}

}  // namespace pulsetrack::vision
