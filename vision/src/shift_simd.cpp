// The translation refinement's per-iteration kernel (ShiftTemplate::refine), compiled once per
// Highway target and chosen at run time: a separable Catmull-Rom resampling of the 23x23 patch
// and the five sums one Gauss-Newton step needs, in one pass over 26 image rows.
#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "shift_simd.cpp"
#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>

#include "pulsetrack/vision/shift_kernel.hpp"

HWY_BEFORE_NAMESPACE();
namespace pulsetrack::vision::HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

void ShiftSumsImpl(const ShiftKernelInput& in, ShiftSums& out) {
  const hn::CappedTag<float, 8> df;  // 8 lanes at most: they divide a padded row (24)
  const hn::Rebind<int32_t, decltype(df)> di;
  const hn::Rebind<uint8_t, decltype(df)> d8;
  const size_t lanes = hn::Lanes(df);
  const auto load = [&](const uint8_t* p) {
    return hn::ConvertTo(df, hn::PromoteTo(di, hn::LoadU(d8, p)));
  };
  // Horizontal pass: the 26 source rows the vertical taps need, 24 columns each.
  HWY_ALIGN float h[kShiftRows + 3][kShiftCols];
  const auto wx0 = hn::Set(df, in.wx[0]), wx1 = hn::Set(df, in.wx[1]);
  const auto wx2 = hn::Set(df, in.wx[2]), wx3 = hn::Set(df, in.wx[3]);
  for (int r = 0; r < kShiftRows + 3; ++r) {
    const uint8_t* row = in.image + static_cast<size_t>(r) * in.stride;
    for (size_t c = 0; c < kShiftCols; c += lanes) {
      auto acc = hn::Mul(wx0, load(row + c));
      acc = hn::MulAdd(wx1, load(row + c + 1), acc);
      acc = hn::MulAdd(wx2, load(row + c + 2), acc);
      acc = hn::MulAdd(wx3, load(row + c + 3), acc);
      hn::Store(acc, df, h[r] + c);
    }
  }
  // Vertical pass and the sums.
  const auto wy0 = hn::Set(df, in.wy[0]), wy1 = hn::Set(df, in.wy[1]);
  const auto wy2 = hn::Set(df, in.wy[2]), wy3 = hn::Set(df, in.wy[3]);
  auto sp = hn::Zero(df), spp = hn::Zero(df), sgx = hn::Zero(df), sgy = hn::Zero(df);
  auto stp = hn::Zero(df);
  for (int r = 0; r < kShiftRows; ++r) {
    const size_t k0 = static_cast<size_t>(r) * kShiftCols;
    for (size_t c = 0; c < kShiftCols; c += lanes) {
      auto p = hn::Mul(wy0, hn::Load(df, h[r] + c));
      p = hn::MulAdd(wy1, hn::Load(df, h[r + 1] + c), p);
      p = hn::MulAdd(wy2, hn::Load(df, h[r + 2] + c), p);
      p = hn::MulAdd(wy3, hn::Load(df, h[r + 3] + c), p);
      p = hn::Mul(p, hn::LoadU(df, in.mask + k0 + c));  // the pad (a glint) counts for nothing
      sp = hn::Add(sp, p);
      spp = hn::MulAdd(p, p, spp);
      sgx = hn::MulAdd(hn::LoadU(df, in.gx + k0 + c), p, sgx);
      sgy = hn::MulAdd(hn::LoadU(df, in.gy + k0 + c), p, sgy);
      stp = hn::MulAdd(hn::LoadU(df, in.t + k0 + c), p, stp);
    }
  }
  out.p = hn::GetLane(hn::SumOfLanes(df, sp));
  out.pp = hn::GetLane(hn::SumOfLanes(df, spp));
  out.gxp = hn::GetLane(hn::SumOfLanes(df, sgx));
  out.gyp = hn::GetLane(hn::SumOfLanes(df, sgy));
  out.tp = hn::GetLane(hn::SumOfLanes(df, stp));
}

}  // namespace pulsetrack::vision::HWY_NAMESPACE
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace pulsetrack::vision {

HWY_EXPORT(ShiftSumsImpl);

void shiftSums(const ShiftKernelInput& in, ShiftSums& out) noexcept {
  HWY_DYNAMIC_DISPATCH(ShiftSumsImpl)(in, out);
}

}  // namespace pulsetrack::vision
#endif
