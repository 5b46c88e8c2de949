// The SIMD NCC kernel, compiled once per Highway target and chosen at run time.
#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "ncc_simd.cpp"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>

#include <algorithm>

#include "pulsetrack/vision/ncc.hpp"

HWY_BEFORE_NAMESPACE();
namespace pulsetrack::vision::HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

void NccScoresImpl(const NccTemplate& t, const uint8_t* region, size_t stride, int nx, int ny,
                   float* scores) {
  const hn::ScalableTag<int16_t> d16;
  const hn::ScalableTag<int32_t> d32;
  const hn::Rebind<uint8_t, decltype(d16)> d8;
  const size_t lanes = hn::Lanes(d16);
  // Columns the template covers, rounded up to whole vectors (<= kTemplatePad).
  const size_t cols = (static_cast<size_t>(t.width) + lanes - 1) / lanes * lanes;
  const int64_t n = static_cast<int64_t>(t.width) * t.height;
  for (int y = 0; y < ny; ++y) {
    for (int x = 0; x < nx; ++x) {
      auto acc_ti = hn::Zero(d32);
      auto acc_i = hn::Zero(d32);
      auto acc_ii = hn::Zero(d32);
      auto unused0 = hn::Zero(d32);
      auto unused1 = hn::Zero(d32);
      auto unused2 = hn::Zero(d32);
      for (int r = 0; r < t.height; ++r) {
        const uint8_t* row = region + static_cast<size_t>(y + r) * stride + static_cast<size_t>(x);
        const int16_t* trow = t.pixels.data() + r * kTemplatePad;
        for (size_t c = 0; c < cols; c += lanes) {
          const auto mask = hn::LoadU(d16, t.column_mask.data() + c);
          const auto img = hn::Mul(
              hn::BitCast(
                  d16, hn::PromoteTo(hn::Rebind<uint16_t, decltype(d8)>(), hn::LoadU(d8, row + c))),
              mask);
          acc_ti =
              hn::ReorderWidenMulAccumulate(d32, hn::LoadU(d16, trow + c), img, acc_ti, unused0);
          acc_i = hn::ReorderWidenMulAccumulate(d32, img, mask, acc_i, unused1);
          acc_ii = hn::ReorderWidenMulAccumulate(d32, img, img, acc_ii, unused2);
        }
      }
      // On targets where the widening multiply uses both accumulators, fold them.
      acc_ti = hn::Add(acc_ti, unused0);
      acc_i = hn::Add(acc_i, unused1);
      acc_ii = hn::Add(acc_ii, unused2);
      const int64_t sti = hn::GetLane(hn::SumOfLanes(d32, acc_ti));
      const int64_t si = hn::GetLane(hn::SumOfLanes(d32, acc_i));
      const int64_t sii = hn::GetLane(hn::SumOfLanes(d32, acc_ii));
      scores[y * nx + x] = nccFromSums(n, t.sum, t.sum_sq, si, sii, sti);
    }
  }
}

uint8_t RegionMaxImpl(const uint8_t* p, size_t stride, int w, int h) {
  const hn::CappedTag<uint8_t, 16> d;
  const int lanes = static_cast<int>(hn::Lanes(d));
  auto m = hn::Zero(d);
  uint8_t tail = 0;
  for (int y = 0; y < h; ++y, p += stride) {
    if (w < lanes) {
      for (int x = 0; x < w; ++x) tail = std::max(tail, p[x]);
      continue;
    }
    int x = 0;
    for (; x + lanes <= w; x += lanes) m = hn::Max(m, hn::LoadU(d, p + x));
    if (x < w) m = hn::Max(m, hn::LoadU(d, p + w - lanes));  // overlapping the last vector
  }
  return std::max(tail, hn::GetLane(hn::MaxOfLanes(d, m)));
}

}  // namespace pulsetrack::vision::HWY_NAMESPACE
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace pulsetrack::vision {

HWY_EXPORT(NccScoresImpl);

void nccScores(const NccTemplate& t, const uint8_t* region, size_t stride, int nx, int ny,
               float* scores) noexcept {
  HWY_DYNAMIC_DISPATCH(NccScoresImpl)(t, region, stride, nx, ny, scores);
}

HWY_EXPORT(RegionMaxImpl);

uint8_t regionMax(const uint8_t* p, size_t stride, int w, int h) noexcept {
  if (w <= 0 || h <= 0) return 0;
  return HWY_DYNAMIC_DISPATCH(RegionMaxImpl)(p, stride, w, h);
}

const char* nccTarget() noexcept {
  // The best target this CPU supports among those compiled: what the dispatcher picks.
  const int64_t supported = static_cast<int64_t>(hwy::SupportedTargets()) & HWY_TARGETS;
  return hwy::TargetName(supported & -supported);
}

}  // namespace pulsetrack::vision
#endif
