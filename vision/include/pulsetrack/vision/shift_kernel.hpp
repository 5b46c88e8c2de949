#pragma once
// The translation refinement's kernel (internal to the vision library, public for its tests):
// Highway in shift_simd.cpp, the scalar reference in affine_refiner.cpp; tests compare the two.

#include <cstddef>
#include <cstdint>

#include "pulsetrack/vision/affine_refiner.hpp"

namespace pulsetrack::vision {

inline constexpr int kShiftRows = kShiftSide;    // 23 rows of the patch
inline constexpr int kShiftCols = kShiftStride;  // 23 columns padded to 24 (the pad weighs 0)

struct ShiftKernelInput {
  const uint8_t* image = nullptr;  // the first tap: (kShiftRows + 3) rows, kShiftCols + 3 columns
  size_t stride = 0;
  float wx[4] = {}, wy[4] = {};  // Catmull-Rom weights of the common fractional offset
  const float* t = nullptr;      // template, gradients: kShiftRows x kShiftCols, pad column 0
  const float* gx = nullptr;
  const float* gy = nullptr;
  // kShiftRows x kShiftCols: 1 for the pixels that take part, 0 for the pad (and a glint's)
  const float* mask = nullptr;
};

// Sums over the resampled patch p times the mask m (0 or 1): m p, m p^2, m gx p, m gy p, m t p.
struct ShiftSums {
  float p = 0, pp = 0, gxp = 0, gyp = 0, tp = 0;
};

void shiftSums(const ShiftKernelInput& in, ShiftSums& out) noexcept;        // Highway
void shiftSumsScalar(const ShiftKernelInput& in, ShiftSums& out) noexcept;  // reference

}  // namespace pulsetrack::vision
