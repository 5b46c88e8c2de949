#include "pulsetrack/vision/affine_refiner.hpp"

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
  AffineResult res;
  res.warp = start;
  std::array<float, kAffinePixels> patch{};
  for (int it = 0; it < max_iterations; ++it) {
    res.iterations = it + 1;
    if (!warpedPatch<kAffineSide>(image, stride, width, height, res.warp, patch.data())) return res;
    double mean = 0, spread = 0;
    meanSpread(patch, mean, spread);
    const cv::Vec2d moments = ramp_ ? rampMoments(patch) : cv::Vec2d();
    if (ramp_) spread = rampFreeSpread(spread, moments);
    if (spread < 1e-6) return res;
    const double gain = spread_ / spread;
    cv::Vec<double, 6> b = cv::Vec<double, 6>::all(0.0);
    double sse = 0.0;
    for (size_t k = 0; k < static_cast<size_t>(kAffinePixels); ++k) {
      const double e = (patch[k] - mean) * gain + mean_ - t_[k];
      sse += e * e;
      for (size_t i = 0; i < 6; ++i) b[static_cast<int>(i)] += sd_[k][i] * e;
    }
    if (ramp_) {
      // The residual's ramps (its moments follow from the two patches'), left out of the error.
      const cv::Vec2d e = gain * moments - ramp_moments_;
      sse = std::max(0.0, sse - e.dot(e) / kRampNorm);
    }
    res.rms = std::sqrt(sse / kAffinePixels);
    res.ncc = 1.0 - sse / (2.0 * kAffinePixels * spread_ * spread_);
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

constexpr int kShiftBig = kShiftSide + 2;  // the template with a sample of margin

bool ShiftTemplate::set(const uint8_t* image, size_t stride, int width, int height,
                        const cv::Vec2d& centre) noexcept {
  std::array<float, kShiftBig * kShiftBig> big{};
  if (!sampledPatch<kShiftBig>(image, stride, width, height, centre, big.data())) return false;
  cv::Matx22d h = cv::Matx22d::zeros();
  t_.fill(0.0F);
  gx_.fill(0.0F);
  gy_.fill(0.0F);
  sum_t_ = sum_tt_ = sum_gx_ = sum_gy_ = sum_gxt_ = sum_gyt_ = 0.0;
  for (int y = 0; y < kShiftSide; ++y) {
    for (int x = 0; x < kShiftSide; ++x) {
      const auto at = [&](int dx, int dy) {
        return big[static_cast<size_t>(y + 1 + dy) * kShiftBig + static_cast<size_t>(x + 1 + dx)];
      };
      const size_t k = static_cast<size_t>(y) * kCols + static_cast<size_t>(x);
      t_[k] = at(0, 0);
      gx_[k] = 0.5F * (at(1, 0) - at(-1, 0));
      gy_[k] = 0.5F * (at(0, 1) - at(0, -1));
      h(0, 0) += double(gx_[k]) * gx_[k];
      h(0, 1) += double(gx_[k]) * gy_[k];
      h(1, 1) += double(gy_[k]) * gy_[k];
      sum_t_ += t_[k];
      sum_tt_ += double(t_[k]) * t_[k];
      sum_gx_ += gx_[k];
      sum_gy_ += gy_[k];
      sum_gxt_ += double(gx_[k]) * t_[k];
      sum_gyt_ += double(gy_[k]) * t_[k];
    }
  }
  for (int c = 0; c < kCols; ++c) mask_[static_cast<size_t>(c)] = c < kShiftSide ? 1.0F : 0.0F;
  h(1, 0) = h(0, 1);
  mean_ = sum_t_ / kShiftPixels;
  spread_ = std::sqrt(std::max(0.0, sum_tt_ / kShiftPixels - mean_ * mean_));
  if (spread_ < 1.0) return false;
  bool ok = false;
  h_inv_ = h.inv(cv::DECOMP_CHOLESKY, &ok);
  return ok;
}

AffineResult ShiftTemplate::refine(const uint8_t* image, size_t stride, int width, int height,
                                   const cv::Vec2d& start, int max_iterations, double epsilon_px,
                                   bool scalar) const noexcept {
  static_assert(kCols == kShiftCols && kShiftSide == kShiftRows);
  AffineResult res;
  res.warp.centre = start;
  ShiftKernelInput in;
  in.stride = stride;
  in.t = t_.data();
  in.gx = gx_.data();
  in.gy = gy_.data();
  in.mask = mask_.data();
  constexpr double n = kShiftPixels;
  for (int it = 0; it < max_iterations; ++it) {
    res.iterations = it + 1;
    const cv::Vec2d& c = res.warp.centre;
    const double fx0 = std::floor(c[0]), fy0 = std::floor(c[1]);
    if (!(std::abs(fx0) < 1e6) || !(std::abs(fy0) < 1e6)) return res;
    const int x0 = static_cast<int>(fx0) - kShiftHalf - 1;  // first tap
    const int y0 = static_cast<int>(fy0) - kShiftHalf - 1;
    if (x0 < 0 || y0 < 0 || x0 + kCols + 3 > width || y0 + kShiftSide + 3 > height) return res;
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
    const double g = spread_ / std::sqrt(var);
    const double o = mean_ - g * mean;
    const double bx = g * s.gxp + o * sum_gx_ - sum_gxt_;
    const double by = g * s.gyp + o * sum_gy_ - sum_gyt_;
    const double sse = std::max(0.0, g * g * s.pp + 2.0 * g * o * s.p - 2.0 * g * s.tp + n * o * o -
                                         2.0 * o * sum_t_ + sum_tt_);
    res.rms = std::sqrt(sse / n);
    res.ncc = 1.0 - sse / (2.0 * n * spread_ * spread_);
    const cv::Vec2d dp = h_inv_ * cv::Vec2d(bx, by);
    res.warp.centre -= dp;  // inverse composition of a translation
    if (dp.dot(dp) < epsilon_px * epsilon_px) {
      res.converged = true;
      break;
    }
  }
  return res;
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
                      in.mask[c];
      out.p += p;
      out.pp += p * p;
      out.gxp += in.gx[k] * p;
      out.gyp += in.gy[k] * p;
      out.tp += in.t[k] * p;
    }
  }
}

}  // namespace pulsetrack::vision
