#include "pulsetrack/vision/ncc.hpp"

#include <algorithm>
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

double normalizedMutualInformation(const uint8_t* a, size_t stride_a, const uint8_t* b,
                                   size_t stride_b, int w, int h, int bins) noexcept {
  bins = std::clamp(bins, 2, 32);
  int amin = 255, amax = 0, bmin = 255, bmax = 0;
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const int va = a[static_cast<size_t>(y) * stride_a + static_cast<size_t>(x)];
      const int vb = b[static_cast<size_t>(y) * stride_b + static_cast<size_t>(x)];
      amin = std::min(amin, va);
      amax = std::max(amax, va);
      bmin = std::min(bmin, vb);
      bmax = std::max(bmax, vb);
    }
  }
  if (amax == amin || bmax == bmin) return 0.0;
  std::array<int, 32 * 32> joint{};
  const auto bin = [bins](int v, int lo, int hi) {
    return std::min(bins - 1, (v - lo) * bins / (hi - lo + 1));
  };
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const int ia = bin(a[static_cast<size_t>(y) * stride_a + static_cast<size_t>(x)], amin, amax);
      const int ib = bin(b[static_cast<size_t>(y) * stride_b + static_cast<size_t>(x)], bmin, bmax);
      ++joint[static_cast<size_t>(ia) * 32 + static_cast<size_t>(ib)];
    }
  }
  const double n = static_cast<double>(w) * h;
  std::array<double, 32> pa{}, pb{};
  double hab = 0.0;
  for (int i = 0; i < bins; ++i) {
    for (int j = 0; j < bins; ++j) {
      const int c = joint[static_cast<size_t>(i) * 32 + static_cast<size_t>(j)];
      if (c == 0) continue;
      const double p = c / n;
      pa[static_cast<size_t>(i)] += p;
      pb[static_cast<size_t>(j)] += p;
      hab -= p * std::log(p);
    }
  }
  double ha = 0.0, hb = 0.0;
  for (int i = 0; i < bins; ++i) {
    if (pa[static_cast<size_t>(i)] > 0)
      ha -= pa[static_cast<size_t>(i)] * std::log(pa[static_cast<size_t>(i)]);
    if (pb[static_cast<size_t>(i)] > 0)
      hb -= pb[static_cast<size_t>(i)] * std::log(pb[static_cast<size_t>(i)]);
  }
  if (ha + hb <= 0.0) return 0.0;
  return std::clamp(2.0 * (ha + hb - hab) / (ha + hb), 0.0, 1.0);
}

}  // namespace pulsetrack::vision
