#pragma once
// Normalized cross-correlation of a small template over a search window: the matching kernel of
// the tracker (section 2.B of the paper: 15x15 templates, NCC, 3x3 quadratic peak fit).
//
// Exact integer sums (sum T*I, sum I, sum I^2 over the template's pixels) feed one scalar
// formula, so the SIMD kernel (Google Highway, dynamic dispatch: AVX2 on x86, NEON on ARM) and
// the scalar reference agree bit for bit; tests check it. Nothing here allocates or throws.

#include <array>
#include <cstddef>
#include <cstdint>

namespace pulsetrack::vision {

inline constexpr int kMaxTemplateSize = 31;  // odd sizes up to 31x31
inline constexpr int kTemplatePad = 32;      // rows padded with zero weights to a whole vector

// A template prepared once (frame 0): pixels widened to int16 and padded, its sums.
struct NccTemplate {
  int width = 0;
  int height = 0;
  std::array<int16_t, kMaxTemplateSize * kTemplatePad> pixels{};  // row-major, stride kTemplatePad
  std::array<int16_t, kTemplatePad> column_mask{};                // 1 for the template's columns
  int64_t sum = 0;
  int64_t sum_sq = 0;

  // Copies a width x height template from an 8-bit image (top-left at `data`). False when the
  // size is unsupported or the template is flat (zero variance: NCC undefined).
  bool set(const uint8_t* data, size_t stride, int w, int h) noexcept;
};

// NCC for every placement of the template's top-left corner at (x, y), 0 <= x < nx,
// 0 <= y < ny, in `region` (8-bit, row stride `stride`). `region` must be readable for
// (nx - 1 + kTemplatePad) columns and (ny - 1 + height) rows. scores: ny rows of nx, row-major.
// Placements on a flat patch score 0.
void nccScores(const NccTemplate& t, const uint8_t* region, size_t stride, int nx, int ny,
               float* scores) noexcept;
// The same, plain C++: the reference the SIMD kernel is tested against.
void nccScoresScalar(const NccTemplate& t, const uint8_t* region, size_t stride, int nx, int ny,
                     float* scores) noexcept;
// The name of the SIMD target the dispatcher chose (for benchmarks and logs).
const char* nccTarget() noexcept;

// The NCC from the exact sums (shared by both kernels).
inline float nccFromSums(int64_t n, int64_t st, int64_t stt, int64_t si, int64_t sii,
                         int64_t sti) noexcept;

// Sub-pixel apex of a quadratic surface z = a + bx + cy + dx^2 + exy + fy^2 fitted by least
// squares to the 3x3 scores around an integer peak (paper, section 2.B). Returns the offset
// from the centre, each coordinate clamped to [-1, 1]; (0, 0) when the fit has no maximum.
struct SubPixel {
  double dx = 0.0;
  double dy = 0.0;
  double peak = 0.0;  // the fitted surface's value at the apex
};
SubPixel quadraticPeak(const float scores3x3[9]) noexcept;

// The brightest pixel of a w x h region (Highway).
uint8_t regionMax(const uint8_t* p, size_t stride, int w, int h) noexcept;

// Normalized mutual information 2 I(A;B) / (H(A) + H(B)) in [0, 1] between two equally sized
// 8-bit patches, with `bins` (<= 32) intensity bins over each patch's own range.
double normalizedMutualInformation(const uint8_t* a, size_t stride_a, const uint8_t* b,
                                   size_t stride_b, int w, int h, int bins = 16) noexcept;

// The same with patch A fixed (a feature's frame-0 template): its bins and entropy are
// computed once, so each frame bins only B. At most kMaxTemplateSize^2 pixels.
class NmiTemplate {
 public:
  // False when the patch is too large or flat (NMI is then 0 for every B).
  bool set(const uint8_t* a, size_t stride, int w, int h, int bins = 16) noexcept;
  [[nodiscard]] double score(const uint8_t* b, size_t stride) const noexcept;

 private:
  std::array<uint8_t, kMaxTemplateSize * kMaxTemplateSize> bin_{};
  std::array<int, 32> count_{};
  int w_ = 0, h_ = 0, bins_ = 16;
  double sum_clogc_ = 0.0;  // sum over A's bins of c log c
  bool flat_ = true;
};

inline float nccFromSums(int64_t n, int64_t st, int64_t stt, int64_t si, int64_t sii,
                         int64_t sti) noexcept {
  const double var_t = static_cast<double>(n * stt - st * st);
  const double var_i = static_cast<double>(n * sii - si * si);
  if (var_t <= 0.0 || var_i <= 0.0) return 0.0F;
  const double cov = static_cast<double>(n * sti - st * si);
  return static_cast<float>(cov / __builtin_sqrt(var_t * var_i));
}

}  // namespace pulsetrack::vision
