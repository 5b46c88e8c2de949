#include "pulsetrack/vision/affine_refiner.hpp"

#include <algorithm>
#include <cmath>
#include <opencv2/core.hpp>  // Matx::solve / inv (operations.hpp)

#include "pulsetrack/vision/shift_kernel.hpp"

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

// Samples the side x side patch through the warp (bicubic: bilinear sampling is biased by up to
// 0.04 px on textures of a few pixels' scale, see tests/vision/affine_refiner_test.cpp); false
// when it leaves the image. The patch is affine, so checking its four corners bounds every
// sample, and the sample position steps by the warp's columns along a row.
template <int kSideT>
bool warpedPatch(const uint8_t* image, size_t stride, int width, int height, const AffineWarp& w,
                 float* out) noexcept {
  constexpr int kHalfT = kSideT / 2;
  for (const int cy : {-kHalfT, kHalfT}) {
    for (const int cx : {-kHalfT, kHalfT}) {
      const double u = w.centre[0] + w.a(0, 0) * cx + w.a(0, 1) * cy;
      const double v = w.centre[1] + w.a(1, 0) * cx + w.a(1, 1) * cy;
      if (!(u >= 1.0) || !(v >= 1.0) || u >= width - 2 || v >= height - 2) return false;
    }
  }
  size_t k = 0;
  for (int y = -kHalfT; y <= kHalfT; ++y) {
    double u = w.centre[0] - w.a(0, 0) * kHalfT + w.a(0, 1) * y;
    double v = w.centre[1] - w.a(1, 0) * kHalfT + w.a(1, 1) * y;
    for (int x = -kHalfT; x <= kHalfT; ++x, ++k, u += w.a(0, 0), v += w.a(1, 0)) {
      const int x0 = static_cast<int>(u);
      const int y0 = static_cast<int>(v);
      out[k] =
          bicubicAt(image, stride, x0, y0, static_cast<float>(u - x0), static_cast<float>(v - y0));
    }
  }
  return true;
}

// The side x side patch around `centre` (the template, or with one pixel of margin for its
// gradients), by separable Catmull-Rom: a horizontal pass over the rows the vertical pass
// needs, then the vertical pass. False when a tap would leave the image.
template <int kSideT>
bool sampledPatch(const uint8_t* image, size_t stride, int width, int height,
                  const cv::Vec2d& centre, float* out) noexcept {
  constexpr int kHalfT = kSideT / 2;
  constexpr size_t kS = kSideT;
  const double fx0 = std::floor(centre[0]), fy0 = std::floor(centre[1]);
  if (!(std::abs(fx0) < 1e6) || !(std::abs(fy0) < 1e6)) return false;
  const int x0 = static_cast<int>(fx0) - kHalfT - 1;  // first tap column
  const int y0 = static_cast<int>(fy0) - kHalfT - 1;
  if (x0 < 0 || y0 < 0 || x0 + kSideT + 3 > width || y0 + kSideT + 3 > height) return false;
  float wx[4], wy[4];
  catmullRom(static_cast<float>(centre[0] - fx0), wx);
  catmullRom(static_cast<float>(centre[1] - fy0), wy);
  // (side + 3) rows x side columns; every element is written before it is read.
  std::array<float, (kSideT + 3) * kS> rows;  // NOLINT(cppcoreguidelines-pro-type-member-init)
  for (size_t r = 0; r < kS + 3; ++r) {
    const uint8_t* p = image + (static_cast<size_t>(y0) + r) * stride + static_cast<size_t>(x0);
    float* o = rows.data() + r * kS;
    for (size_t c = 0; c < kS; ++c) {
      o[c] = wx[0] * static_cast<float>(p[c]) + wx[1] * static_cast<float>(p[c + 1]) +
             wx[2] * static_cast<float>(p[c + 2]) + wx[3] * static_cast<float>(p[c + 3]);
    }
  }
  for (size_t r = 0; r < kS; ++r) {
    const float* a = rows.data() + r * kS;
    float* o = out + r * kS;
    for (size_t c = 0; c < kS; ++c)
      o[c] = wy[0] * a[c] + wy[1] * a[kS + c] + wy[2] * a[2 * kS + c] + wy[3] * a[3 * kS + c];
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

// Sum of x^2 (and of y^2) over the template's grid, x in [-kAffineHalf, kAffineHalf].
// (The sum of squares 1..n is n (n + 1) (2n + 1) / 6, an integer.)
constexpr int kSquares = kAffineHalf * (kAffineHalf + 1) * (2 * kAffineHalf + 1) / 6;
constexpr double kRampNorm = kAffineSide * 2.0 * kSquares;

// A patch's ramp moments (sum of x v and of y v over its pixels v): the x and y ramps it holds
// are these over kRampNorm. (The grid is symmetric: the mean does not change them.)
cv::Vec2d rampMoments(const std::array<float, kAffinePixels>& p) noexcept {
  double sx = 0.0, sy = 0.0;
  size_t k = 0;
  for (int y = -kAffineHalf; y <= kAffineHalf; ++y) {
    for (int x = -kAffineHalf; x <= kAffineHalf; ++x, ++k) {
      sx += x * static_cast<double>(p[k]);
      sy += y * static_cast<double>(p[k]);
    }
  }
  return {sx, sy};
}

// A patch's spread less what its ramps explain.
double rampFreeSpread(double spread, const cv::Vec2d& moments) noexcept {
  return std::sqrt(
      std::max(0.0, spread * spread - moments.dot(moments) / kRampNorm / kAffinePixels));
}

}  // namespace

bool AffineTemplate::set(const uint8_t* image, size_t stride, int width, int height,
                         const AffineWarp& warp, bool ramp) noexcept {
  // The warped patch with one sample of margin: the template is its interior, the gradients
  // its central differences (the samples one template pixel away).
  constexpr int kBig = kAffineSide + 2;
  std::array<float, static_cast<size_t>(kBig) * kBig> big{};
  if (warp.a == cv::Matx22d::eye()) {
    if (!sampledPatch<kBig>(image, stride, width, height, warp.centre, big.data())) return false;
  } else if (!warpedPatch<kBig>(image, stride, width, height, warp, big.data())) {
    return false;
  }
  const auto at = [&](int x, int y) {  // x, y in [-kAffineHalf - 1, kAffineHalf + 1]
    return big[static_cast<size_t>(y + kAffineHalf + 1) * kBig +
               static_cast<size_t>(x + kAffineHalf + 1)];
  };
  int k = 0;
  for (int y = -kAffineHalf; y <= kAffineHalf; ++y) {
    for (int x = -kAffineHalf; x <= kAffineHalf; ++x, ++k) {
      t_[static_cast<size_t>(k)] = at(x, y);
      const double gx = 0.5 * (at(x + 1, y) - at(x - 1, y));
      const double gy = 0.5 * (at(x, y + 1) - at(x, y - 1));
      // d(warp)/d(params) at identity, params = (da00, da10, da01, da11, dtx, dty).
      const double sd[6] = {gx * x, gy * x, gx * y, gy * y, gx, gy};
      auto& row = sd_[static_cast<size_t>(k)];
      for (int i = 0; i < 6; ++i) row[static_cast<size_t>(i)] = static_cast<float>(sd[i]);
    }
  }
  ramp_ = ramp;
  if (ramp) {
    // Project-out: the steepest-descent images made orthogonal to the constant and the two
    // ramps, so that b = SD^T e ignores whatever of the residual those explain.
    std::array<double, 6> m{}, rx{}, ry{};
    k = 0;
    for (int y = -kAffineHalf; y <= kAffineHalf; ++y) {
      for (int x = -kAffineHalf; x <= kAffineHalf; ++x, ++k) {
        for (size_t i = 0; i < 6; ++i) {
          const double v = sd_[static_cast<size_t>(k)][i];
          m[i] += v;
          rx[i] += x * v;
          ry[i] += y * v;
        }
      }
    }
    k = 0;
    for (int y = -kAffineHalf; y <= kAffineHalf; ++y) {
      for (int x = -kAffineHalf; x <= kAffineHalf; ++x, ++k) {
        for (size_t i = 0; i < 6; ++i) {
          sd_[static_cast<size_t>(k)][i] -=
              static_cast<float>(m[i] / kAffinePixels + (rx[i] * x + ry[i] * y) / kRampNorm);
        }
      }
    }
  }
  cv::Matx<double, 6, 6> h = cv::Matx<double, 6, 6>::zeros();
  for (const auto& row : sd_) {
    for (int i = 0; i < 6; ++i) {
      for (int j = i; j < 6; ++j)
        h(i, j) += double(row[static_cast<size_t>(i)]) * row[static_cast<size_t>(j)];
    }
  }
  for (int i = 0; i < 6; ++i) {
    for (int j = 0; j < i; ++j) h(i, j) = h(j, i);
  }
  meanSpread(t_, mean_, spread_);
  if (ramp) {
    ramp_moments_ = rampMoments(t_);
    spread_ = rampFreeSpread(spread_, ramp_moments_);
  }
  if (spread_ < 1.0) return false;
  bool ok = false;
  h_inv_ = h.inv(cv::DECOMP_CHOLESKY, &ok);
  return ok;
}

AffineResult AffineTemplate::refine(const uint8_t* image, size_t stride, int width, int height,
                                    const AffineWarp& start, int max_iterations,
                                    double epsilon_px) const noexcept {
  return iterate(image, stride, width, height, start, max_iterations, epsilon_px, nullptr, h_inv_,
                 mean_, spread_, kAffinePixels);
}

AffineResult AffineTemplate::refine(const uint8_t* image, size_t stride, int width, int height,
                                    const AffineWarp& start, const AffineMask& mask,
                                    int max_iterations, double epsilon_px) const noexcept {
  AffineResult res;
  res.warp = start;
  if (ramp_) return res;
  // The template's mean, spread and Hessian over the pixels taking part.
  double n = 0.0, s = 0.0, s2 = 0.0;
  cv::Matx<double, 6, 6> h = cv::Matx<double, 6, 6>::zeros();
  for (size_t k = 0; k < static_cast<size_t>(kAffinePixels); ++k) {
    if (mask.weight[k] == 0.0F) continue;
    n += 1.0;
    s += t_[k];
    s2 += static_cast<double>(t_[k]) * t_[k];
    const auto& row = sd_[k];
    for (int i = 0; i < 6; ++i) {
      for (int j = i; j < 6; ++j)
        h(i, j) += double(row[static_cast<size_t>(i)]) * row[static_cast<size_t>(j)];
    }
  }
  for (int i = 0; i < 6; ++i) {
    for (int j = 0; j < i; ++j) h(i, j) = h(j, i);
  }
  if (4.0 * n < kAffinePixels) return res;  // too little left to say where it is
  const double mean = s / n;
  const double spread = std::sqrt(std::max(0.0, s2 / n - mean * mean));
  if (spread < 1.0) return res;
  bool ok = false;
  const cv::Matx<double, 6, 6> h_inv = h.inv(cv::DECOMP_CHOLESKY, &ok);
  if (!ok) return res;
  return iterate(image, stride, width, height, start, max_iterations, epsilon_px,
                 mask.weight.data(), h_inv, mean, spread, static_cast<int>(n));
}

AffineResult AffineTemplate::iterate(const uint8_t* image, size_t stride, int width, int height,
                                     const AffineWarp& start, int max_iterations, double epsilon_px,
                                     const float* weight, const cv::Matx<double, 6, 6>& h_inv,
                                     double t_mean, double t_spread, int count) const noexcept {
  AffineResult res;
  res.warp = start;
  std::array<float, kAffinePixels> patch{};
  const bool ramp = ramp_ && weight == nullptr;
  for (int it = 0; it < max_iterations; ++it) {
    res.iterations = it + 1;
    if (!warpedPatch<kAffineSide>(image, stride, width, height, res.warp, patch.data())) return res;
    double mean = 0, spread = 0;
    if (weight == nullptr) {
      meanSpread(patch, mean, spread);
    } else {
      double s = 0.0, s2 = 0.0;
      for (size_t k = 0; k < static_cast<size_t>(kAffinePixels); ++k) {
        s += weight[k] * patch[k];
        s2 += weight[k] * static_cast<double>(patch[k]) * patch[k];
      }
      mean = s / count;
      spread = std::sqrt(std::max(0.0, s2 / count - mean * mean));
    }
    const cv::Vec2d moments = ramp ? rampMoments(patch) : cv::Vec2d();
    if (ramp) spread = rampFreeSpread(spread, moments);
    if (spread < 1e-6) return res;
    const double gain = t_spread / spread;
    cv::Vec<double, 6> b = cv::Vec<double, 6>::all(0.0);
    double sse = 0.0;
    for (size_t k = 0; k < static_cast<size_t>(kAffinePixels); ++k) {
      if (weight != nullptr && weight[k] == 0.0F) continue;
      const double e = (patch[k] - mean) * gain + t_mean - t_[k];
      sse += e * e;
      for (size_t i = 0; i < 6; ++i) b[static_cast<int>(i)] += sd_[k][i] * e;
    }
    if (ramp) {
      // The residual's ramps (its moments follow from the two patches'), left out of the error.
      const cv::Vec2d e = gain * moments - ramp_moments_;
      sse = std::max(0.0, sse - e.dot(e) / kRampNorm);
    }
    res.rms = std::sqrt(sse / count);
    res.ncc = 1.0 - sse / (2.0 * count * t_spread * t_spread);
    const cv::Vec<double, 6> dp = h_inv * b;
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

void AffineMask::reset() noexcept {
  weight.fill(1.0F);
  count = kAffinePixels;
}

namespace {
// Calls f(k, cx, cy) for each pixel k of the mask that takes part, with the nearest image pixel
// (cx, cy) that `warp` places it on (unclipped; positions beyond +-1e6 skipped).
template <class F>
void forKeptPixels(const std::array<float, kAffinePixels>& weight, const AffineWarp& warp,
                   F&& f) noexcept {
  size_t k = 0;
  for (int y = -kAffineHalf; y <= kAffineHalf; ++y) {
    for (int x = -kAffineHalf; x <= kAffineHalf; ++x, ++k) {
      if (weight[k] == 0.0F) continue;
      const double u = warp.centre[0] + warp.a(0, 0) * x + warp.a(0, 1) * y;
      const double v = warp.centre[1] + warp.a(1, 0) * x + warp.a(1, 1) * y;
      if (!(std::abs(u) < 1e6) || !(std::abs(v) < 1e6)) continue;
      f(k, static_cast<int>(std::lround(u)), static_cast<int>(std::lround(v)));
    }
  }
}
}  // namespace

double AffineMask::meanOver(const uint8_t* image, size_t stride, int width, int height,
                            const AffineWarp& warp) const noexcept {
  double sum = 0.0;
  int n = 0;
  forKeptPixels(weight, warp, [&](size_t, int cx, int cy) {
    if (cx < 0 || cy < 0 || cx >= width || cy >= height) return;
    sum += image[static_cast<size_t>(cy) * stride + static_cast<size_t>(cx)];
    ++n;
  });
  return n > 0 ? sum / n : 0.0;
}

double AffineMask::leaveOutGlints(const uint8_t* image, size_t stride, int width, int height,
                                  const AffineWarp& warp, int threshold, int grow_px) noexcept {
  const int g = std::max(0, grow_px);
  forKeptPixels(weight, warp, [&](size_t k, int cx, int cy) {
    for (int yy = std::max(0, cy - g); yy <= std::min(height - 1, cy + g); ++yy) {
      const uint8_t* row = image + static_cast<size_t>(yy) * stride;
      for (int xx = std::max(0, cx - g); xx <= std::min(width - 1, cx + g); ++xx) {
        if (row[xx] >= threshold) {
          weight[k] = 0.0F;  // forKeptPixels read it before the call: safe to clear
          --count;
          return;
        }
      }
    }
  });
  return 1.0 - static_cast<double>(count) / kAffinePixels;
}

constexpr int kShiftBig = kShiftSide + 2;  // the template with a sample of margin

// Every pixel of the patch takes part, the pad column none.
constexpr std::array<float, kShiftPadded> kWholePatch = [] {
  std::array<float, kShiftPadded> w{};
  for (size_t k = 0; k < w.size(); ++k) w[k] = k % kShiftStride < kShiftSide ? 1.0F : 0.0F;
  return w;
}();

double ShiftMask::leaveOutGlints(const uint8_t* image, size_t stride, int width, int height,
                                 const cv::Vec2d& centre, int threshold, int grow_px) noexcept {
  weight = kWholePatch;
  count = kShiftPixels;
  if (!(std::abs(centre[0]) < 1e6) || !(std::abs(centre[1]) < 1e6)) return 0.0;
  const int x0 = static_cast<int>(std::lround(centre[0])) - kShiftHalf;  // the patch's corner
  const int y0 = static_cast<int>(std::lround(centre[1])) - kShiftHalf;
  const int g = std::max(0, grow_px);
  for (int y = std::max(0, y0 - g); y < std::min(height, y0 + kShiftSide + g); ++y) {
    const uint8_t* row = image + static_cast<size_t>(y) * stride;
    for (int x = std::max(0, x0 - g); x < std::min(width, x0 + kShiftSide + g); ++x) {
      if (row[x] < threshold) continue;
      for (int py = std::max(0, y - y0 - g); py <= std::min(kShiftSide - 1, y - y0 + g); ++py) {
        for (int px = std::max(0, x - x0 - g); px <= std::min(kShiftSide - 1, x - x0 + g); ++px) {
          float& w = weight[static_cast<size_t>(py) * kShiftStride + static_cast<size_t>(px)];
          count -= w != 0.0F ? 1 : 0;
          w = 0.0F;
        }
      }
    }
  }
  return 1.0 - static_cast<double>(count) / kShiftPixels;
}

bool ShiftTemplate::set(const uint8_t* image, size_t stride, int width, int height,
                        const cv::Vec2d& centre) noexcept {
  std::array<float, kShiftBig * kShiftBig> big{};
  if (!sampledPatch<kShiftBig>(image, stride, width, height, centre, big.data())) return false;
  t_.fill(0.0F);
  gx_.fill(0.0F);
  gy_.fill(0.0F);
  for (int y = 0; y < kShiftSide; ++y) {
    for (int x = 0; x < kShiftSide; ++x) {
      const auto at = [&](int dx, int dy) {
        return big[static_cast<size_t>(y + 1 + dy) * kShiftBig + static_cast<size_t>(x + 1 + dx)];
      };
      const size_t k = static_cast<size_t>(y) * kShiftStride + static_cast<size_t>(x);
      t_[k] = at(0, 0);
      gx_[k] = 0.5F * (at(1, 0) - at(-1, 0));
      gy_[k] = 0.5F * (at(0, 1) - at(0, -1));
    }
  }
  all_ = moments(kWholePatch);
  return all_.ok;
}

ShiftTemplate::Moments ShiftTemplate::moments(
    const std::array<float, kShiftPadded>& weight) const noexcept {
  Moments m;
  cv::Matx22d h = cv::Matx22d::zeros();
  for (size_t k = 0; k < weight.size(); ++k) {
    if (weight[k] == 0.0F) continue;
    const double t = t_[k], gx = gx_[k], gy = gy_[k];
    h(0, 0) += gx * gx;
    h(0, 1) += gx * gy;
    h(1, 1) += gy * gy;
    m.n += 1.0;
    m.t += t;
    m.tt += t * t;
    m.gx += gx;
    m.gy += gy;
    m.gxt += gx * t;
    m.gyt += gy * t;
  }
  if (m.n < 1.0) return m;
  h(1, 0) = h(0, 1);
  m.mean = m.t / m.n;
  m.spread = std::sqrt(std::max(0.0, m.tt / m.n - m.mean * m.mean));
  if (m.spread < 1.0) return m;
  m.h_inv = h.inv(cv::DECOMP_CHOLESKY, &m.ok);
  return m;
}

AffineResult ShiftTemplate::refine(const uint8_t* image, size_t stride, int width, int height,
                                   const cv::Vec2d& start, int max_iterations, double epsilon_px,
                                   bool scalar, const ShiftMask* mask) const noexcept {
  static_assert(kShiftStride == kShiftCols && kShiftSide == kShiftRows);
  AffineResult res;
  res.warp.centre = start;
  // Over the pixels that take part: all, or those the mask leaves in.
  const Moments part = mask == nullptr ? all_ : moments(mask->weight);
  if (!part.ok) return res;
  ShiftKernelInput in;
  in.stride = stride;
  in.t = t_.data();
  in.gx = gx_.data();
  in.gy = gy_.data();
  in.mask = mask == nullptr ? kWholePatch.data() : mask->weight.data();
  const double n = part.n;
  for (int it = 0; it < max_iterations; ++it) {
    res.iterations = it + 1;
    const cv::Vec2d& c = res.warp.centre;
    const double fx0 = std::floor(c[0]), fy0 = std::floor(c[1]);
    if (!(std::abs(fx0) < 1e6) || !(std::abs(fy0) < 1e6)) return res;
    const int x0 = static_cast<int>(fx0) - kShiftHalf - 1;  // first tap
    const int y0 = static_cast<int>(fy0) - kShiftHalf - 1;
    if (x0 < 0 || y0 < 0 || x0 + kShiftStride + 3 > width || y0 + kShiftSide + 3 > height)
      return res;
    in.image = image + static_cast<size_t>(y0) * stride + static_cast<size_t>(x0);
    catmullRom(static_cast<float>(c[0] - fx0), in.wx);
    catmullRom(static_cast<float>(c[1] - fy0), in.wy);
    ShiftSums s;
    if (scalar) {
      shiftSumsScalar(in, s);
    } else {
      shiftSums(in, s);
    }
    const double mean = s.p / n;
    const double var = s.pp / n - mean * mean;
    if (!(var > 1e-6)) return res;
    // The patch normalized to the template's mean and spread: g p + o.
    const double g = part.spread / std::sqrt(var);
    const double o = part.mean - g * mean;
    const double bx = g * s.gxp + o * part.gx - part.gxt;
    const double by = g * s.gyp + o * part.gy - part.gyt;
    const double sse = std::max(0.0, g * g * s.pp + 2.0 * g * o * s.p - 2.0 * g * s.tp + n * o * o -
                                         2.0 * o * part.t + part.tt);
    res.rms = std::sqrt(sse / n);
    res.ncc = 1.0 - sse / (2.0 * n * part.spread * part.spread);
    const cv::Vec2d dp = part.h_inv * cv::Vec2d(bx, by);
    res.warp.centre -= dp;  // inverse composition of a translation
    if (dp.dot(dp) < epsilon_px * epsilon_px) {
      res.converged = true;
      break;
    }
  }
  return res;
}

double ShiftTemplate::leaveOutSheen(const uint8_t* image, size_t stride, int width, int height,
                                    const cv::Vec2d& centre, ShiftMask& mask,
                                    double sigmas) const noexcept {
  std::array<float, kShiftPixels> p;  // NOLINT(cppcoreguidelines-pro-type-member-init): written
  if (!sampledPatch<kShiftSide>(image, stride, width, height, centre, p.data())) return 1.0;
  const auto at = [](size_t k) {  // template index -> patch index (no pad)
    return k / kShiftStride * kShiftSide + k % kShiftStride;
  };
  double n = 0.0, sp = 0.0, spp = 0.0;
  for (size_t k = 0; k < mask.weight.size(); ++k) {
    if (mask.weight[k] == 0.0F) continue;
    const double v = p[at(k)];
    n += 1.0;
    sp += v;
    spp += v * v;
  }
  const Moments m = moments(mask.weight);
  const double mean = n > 0.0 ? sp / n : 0.0;
  const double var = n > 0.0 ? spp / n - mean * mean : 0.0;
  if (!m.ok || !(var > 1e-6)) return 1.0;
  const double g = m.spread / std::sqrt(var), o = m.mean - g * mean;
  std::array<float, kShiftPadded> e;      // NOLINT(cppcoreguidelines-pro-type-member-init): written
  std::array<float, kShiftPixels> abs_e;  // NOLINT(cppcoreguidelines-pro-type-member-init)
  size_t used = 0;
  for (size_t k = 0; k < mask.weight.size(); ++k) {
    if (mask.weight[k] == 0.0F) continue;
    e[k] = static_cast<float>(g * p[at(k)] + o - t_[k]);
    abs_e[used++] = std::abs(e[k]);
  }
  const auto mid = abs_e.begin() + static_cast<long>(used / 2);
  std::nth_element(abs_e.begin(), mid, abs_e.begin() + static_cast<long>(used));
  const double limit = std::max(1.0, sigmas * 1.4826 * *mid);  // a grey level at least
  for (size_t k = 0; k < mask.weight.size(); ++k) {
    if (mask.weight[k] == 0.0F || e[k] <= limit) continue;
    mask.weight[k] = 0.0F;
    --mask.count;
  }
  return 1.0 - static_cast<double>(mask.count) / kShiftPixels;
}

void shiftSumsScalar(const ShiftKernelInput& in, ShiftSums& out) noexcept {
  float h[kShiftRows + 3][kShiftCols];
  for (int r = 0; r < kShiftRows + 3; ++r) {
    const uint8_t* row = in.image + static_cast<size_t>(r) * in.stride;
    for (int c = 0; c < kShiftCols; ++c) {
      h[r][c] = in.wx[0] * float(row[c]) + in.wx[1] * float(row[c + 1]) +
                in.wx[2] * float(row[c + 2]) + in.wx[3] * float(row[c + 3]);
    }
  }
  out = {};
  for (int r = 0; r < kShiftRows; ++r) {
    for (int c = 0; c < kShiftCols; ++c) {
      const size_t k = static_cast<size_t>(r) * kShiftCols + static_cast<size_t>(c);
      const float p = (in.wy[0] * h[r][c] + in.wy[1] * h[r + 1][c] + in.wy[2] * h[r + 2][c] +
                       in.wy[3] * h[r + 3][c]) *
                      in.mask[k];
      out.p += p;
      out.pp += p * p;
      out.gxp += in.gx[k] * p;
      out.gyp += in.gy[k] * p;
      out.tp += in.t[k] * p;
    }
  }
}

}  // namespace pulsetrack::vision
