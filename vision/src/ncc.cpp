#include "pulsetrack/vision/ncc.hpp"

#include <algorithm>
#include <array>
#include <cmath>

namespace pulsetrack::vision {

bool NccTemplate::set(const uint8_t* data, size_t stride, int w, int h) noexcept {
  if (w < 1 || h < 1 || w > kMaxTemplateSize || h > kMaxTemplateSize) return false;
  width = w;
  height = h;
  pixels.fill(0);
  column_mask.fill(0);
  sum = 0;
  sum_sq = 0;
  for (int x = 0; x < w; ++x) column_mask[static_cast<size_t>(x)] = 1;
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const int v = data[static_cast<size_t>(y) * stride + static_cast<size_t>(x)];
      pixels[static_cast<size_t>(y) * kTemplatePad + static_cast<size_t>(x)] =
          static_cast<int16_t>(v);
      sum += v;
      sum_sq += v * v;
    }
  }
  const int64_t n = static_cast<int64_t>(w) * h;
  return n * sum_sq - sum * sum > 0;
}

void nccScoresScalar(const NccTemplate& t, const uint8_t* region, size_t stride, int nx, int ny,
                     float* scores) noexcept {
  const int64_t n = static_cast<int64_t>(t.width) * t.height;
  for (int y = 0; y < ny; ++y) {
    for (int x = 0; x < nx; ++x) {
      int64_t si = 0, sii = 0, sti = 0;
      for (int r = 0; r < t.height; ++r) {
        const uint8_t* row = region + static_cast<size_t>(y + r) * stride + static_cast<size_t>(x);
        const int16_t* trow = t.pixels.data() + r * kTemplatePad;
        for (int c = 0; c < t.width; ++c) {
          const int v = row[c];
          si += v;
          sii += v * v;
          sti += trow[c] * v;
        }
      }
      scores[y * nx + x] = nccFromSums(n, t.sum, t.sum_sq, si, sii, sti);
    }
  }
}

SubPixel quadraticPeak(const float s[9]) noexcept {
  // Least squares on the 3x3 grid x, y in {-1, 0, 1}: the normal equations decouple into
  // closed forms (the grid is symmetric).
  double sum = 0, sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
  for (int j = -1; j <= 1; ++j) {
    for (int i = -1; i <= 1; ++i) {
      const double z = s[(j + 1) * 3 + (i + 1)];
      sum += z;
      sx += i * z;
      sy += j * z;
      sxx += i * i * z;
      syy += j * j * z;
      sxy += i * j * z;
    }
  }
  const double b = sx / 6.0;
  const double c = sy / 6.0;
  const double e = sxy / 4.0;
  // With sum x^2 = 6, sum x^4 = 6, sum x^2 y^2 = 4 over the grid:
  const double d = (sxx - (2.0 / 3.0) * sum) / 2.0;  // = sxx/2 - sum/3
  const double f = (syy - (2.0 / 3.0) * sum) / 2.0;
  const double a = (sum - 6.0 * d - 6.0 * f) / 9.0;
  SubPixel p;
  // Apex: grad = 0 -> [2d e; e 2f] [x y]^T = -[b c]^T; a maximum needs a negative definite form.
  const double det = 4.0 * d * f - e * e;
  if (!(d < 0.0) || !(det > 0.0)) {
    p.peak = s[4];
    return p;
  }
  p.dx = std::clamp((-2.0 * f * b + e * c) / det, -1.0, 1.0);
  p.dy = std::clamp((-2.0 * d * c + e * b) / det, -1.0, 1.0);
  p.peak = a + b * p.dx + c * p.dy + d * p.dx * p.dx + e * p.dx * p.dy + f * p.dy * p.dy;
  return p;
}

namespace {

// c * log(c) for the counts of a patch of up to kTablePixels pixels, filled before main(): the
// entropies then take no log() per bin on the per-frame path.
constexpr int kTablePixels = 4096;
const std::array<double, kTablePixels + 1> kCLogC = [] {
  std::array<double, kTablePixels + 1> t{};
  for (int c = 1; c <= kTablePixels; ++c) t[static_cast<size_t>(c)] = c * std::log(double(c));
  return t;
}();

inline double cLogC(int c) noexcept {
  return c <= kTablePixels ? kCLogC[static_cast<size_t>(c)] : c * std::log(double(c));
}

}  // namespace

namespace {

// The bins of a patch over its own range: floor((v - min) * bins / span) by a multiplication
// (a division per pixel cost more than the rest of NMI); the epsilon keeps exact quotients
// from rounding down (a quotient's fraction is a multiple of 1 / span >= 1 / 256). False
// when the patch is flat.
bool binPatch(const uint8_t* p, size_t stride, int w, int h, int bins, uint8_t* out) noexcept {
  int lo = 255, hi = 0;
  for (int y = 0; y < h; ++y) {
    const uint8_t* row = p + static_cast<size_t>(y) * stride;
    for (int x = 0; x < w; ++x) {
      lo = std::min(lo, int{row[x]});
      hi = std::max(hi, int{row[x]});
    }
  }
  if (hi == lo) return false;
  const float k = static_cast<float>(bins) / static_cast<float>(hi - lo + 1);
  constexpr float kEps = 1e-4F;
  for (int y = 0; y < h; ++y) {
    const uint8_t* row = p + static_cast<size_t>(y) * stride;
    for (int x = 0; x < w; ++x) {
      *out++ = static_cast<uint8_t>(static_cast<float>(row[x] - lo) * k + kEps);
    }
  }
  return true;
}

}  // namespace

bool NmiTemplate::set(const uint8_t* a, size_t stride, int w, int h, int bins) noexcept {
  flat_ = true;
  if (w <= 0 || h <= 0 || w > kMaxTemplateSize || h > kMaxTemplateSize) return false;
  w_ = w;
  h_ = h;
  bins_ = std::clamp(bins, 2, 32);
  if (!binPatch(a, stride, w, h, bins_, bin_.data())) return false;
  count_.fill(0);
  for (int k = 0; k < w * h; ++k) ++count_[bin_[static_cast<size_t>(k)]];
  sum_clogc_ = 0.0;
  for (int i = 0; i < bins_; ++i) sum_clogc_ += cLogC(count_[static_cast<size_t>(i)]);
  flat_ = false;
  return true;
}

double NmiTemplate::score(const uint8_t* b, size_t stride) const noexcept {
  if (flat_) return 0.0;
  std::array<uint8_t, kMaxTemplateSize * kMaxTemplateSize> bb;  // NOLINT: written before read
  if (!binPatch(b, stride, w_, h_, bins_, bb.data())) return 0.0;
  // Only the bins x bins corner is used and cleared.
  std::array<uint16_t, 32 * 32> joint;  // NOLINT(cppcoreguidelines-pro-type-member-init)
  std::fill_n(joint.begin(), bins_ * bins_, uint16_t{0});
  std::array<int, 32> cb{};
  const int n = w_ * h_;
  for (int k = 0; k < n; ++k) {
    const size_t ib = bb[static_cast<size_t>(k)];
    ++joint[bin_[static_cast<size_t>(k)] * static_cast<size_t>(bins_) + ib];
    ++cb[ib];
  }
  // H = log n - (1/n) sum c log c over the bins' counts c.
  double sab = 0.0, sb = 0.0;
  for (int i = 0; i < bins_ * bins_; ++i) sab += cLogC(joint[static_cast<size_t>(i)]);
  for (int i = 0; i < bins_; ++i) sb += cLogC(cb[static_cast<size_t>(i)]);
  const double log_n = cLogC(n) / n;
  const double hab = log_n - sab / n;
  const double ha = log_n - sum_clogc_ / n;
  const double hb = log_n - sb / n;
  if (ha + hb <= 0.0) return 0.0;
  return std::clamp(2.0 * (ha + hb - hab) / (ha + hb), 0.0, 1.0);
}

double normalizedMutualInformation(const uint8_t* a, size_t stride_a, const uint8_t* b,
                                   size_t stride_b, int w, int h, int bins) noexcept {
  NmiTemplate t;
  if (!t.set(a, stride_a, w, h, bins)) return 0.0;
  return t.score(b, stride_b);
}

}  // namespace pulsetrack::vision
