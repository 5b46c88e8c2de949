#pragma once
// Sub-pixel refinement of a match by an affine warp, inverse compositional (Baker & Matthews):
// the template's steepest-descent images and Hessian are computed once (frame 0), so each
// frame costs one bilinear warp of the patch per iteration and a 6x6 solve, with no
// allocation. The warped patch is normalized to the template's mean and spread before the
// residual is taken (gain and bias compensation): shadows and illumination drift do not pull
// the match, as NCC would not let them.
//
// Why: the paper's 3x3 quadratic NCC peak is biased towards integer positions and between the
// foreshortened views of a tilted surface (design notes: 0.11-0.21 mm RMS on rendered data,
// 0.016-0.020 mm with an affine refinement).

#include <array>
#include <cstddef>
#include <cstdint>
#include <opencv2/core/matx.hpp>

namespace pulsetrack::vision {

inline constexpr int kAffineHalf = 7;  // 15x15 templates
inline constexpr int kAffineSide = 2 * kAffineHalf + 1;
inline constexpr int kAffinePixels = kAffineSide * kAffineSide;
// Video matching's translation refinement works on a larger patch than the 15x15 NCC template:
// its position noise falls with the patch's gradient energy (23x23: about 0.65x of 15x15's), and
// a camera's view of a patch barely changes shape between frames, so the size adds no model error
// (the stereo match's affine model does: there the larger patch's bias outweighs its lower noise).
inline constexpr int kShiftHalf = 11;
inline constexpr int kShiftSide = 2 * kShiftHalf + 1;
inline constexpr int kShiftPixels = kShiftSide * kShiftSide;
inline constexpr int kShiftStride = 24;  // a row of the translation template, padded to 24 floats
inline constexpr int kShiftPadded = kShiftSide * kShiftStride;

// Which of the translation template's pixels take part in a match (1) and which are left out
// (0): those a glint covers in the image being matched. A glint is the light's reflection, not
// the tissue's: it stays where the view makes it while the tissue moves under it, and its
// pixels pull the match (or fail it) if they count.
struct ShiftMask {
  // 0 or 1 (nothing between), row-major, kShiftStride per row, the pad column always 0
  std::array<float, kShiftPadded> weight{};
  int count = 0;  // pixels taking part

  // Leaves out every pixel of the patch centred on `centre` (nearest pixel) within `grow_px`
  // (Chebyshev distance) of an image pixel at or above `threshold`: a glint's saturated core
  // and the sheen around it. Returns the fraction left out (pixels outside the image are not
  // glints).
  double leaveOutGlints(const uint8_t* image, size_t stride, int width, int height,
                        const cv::Vec2d& centre, int threshold, int grow_px) noexcept;
};

// Warp: x' = centre + A x, x in template coordinates [-7, 7]^2, A = [a00 a01; a10 a11].
struct AffineWarp {
  cv::Vec2d centre;
  cv::Matx22d a = cv::Matx22d::eye();
};

struct AffineResult {
  AffineWarp warp;
  double rms = 0.0;  // residual after normalization, grey levels
  // NCC of the warped patch with the template, from the same residual: for a patch normalized
  // to the template's mean and spread s, sum(e^2) = 2 n s^2 (1 - NCC).
  double ncc = 0.0;
  int iterations = 0;
  bool converged = false;
};

// Which of the affine template's pixels take part in a match (1) and which are left out (0):
// the stereo match's ShiftMask. A glint differs between the views (the light reflects towards
// one camera), so a pixel is left out where either view has one near.
struct AffineMask {
  std::array<float, kAffinePixels> weight{};  // 0 or 1, row-major
  int count = 0;                              // pixels taking part

  // Every pixel taking part.
  void reset() noexcept;
  // Leaves out, besides those already left out (it does not reset: call it once per view, the
  // left template's and the right match's), the pixels of the patch that `warp` places on
  // `image` within `grow_px` (Chebyshev distance) of a pixel at or above `threshold`. Returns
  // the fraction left out so far.
  double leaveOutGlints(const uint8_t* image, size_t stride, int width, int height,
                        const AffineWarp& warp, int threshold, int grow_px) noexcept;
  // The mean grey level of the pixels taking part, as `warp` places the patch on `image`
  // (nearest pixel; those outside the image skipped); 0 when none is left.
  [[nodiscard]] double meanOver(const uint8_t* image, size_t stride, int width, int height,
                                const AffineWarp& warp) const noexcept;
};

class AffineTemplate {
 public:
  // Samples the template around `centre` (sub-pixel, bilinear) of an 8-bit image with the
  // given warp (identity for a fresh template). False near the border or on a flat patch.
  // With `ramp`, an intensity ramp across the patch (x and y) is modelled as well as gain and
  // bias, by projecting it out (Baker & Matthews' project-out: the Hessian stays constant): a
  // specular lobe or a shadow's edge adds such a ramp to one view and not the other, and unmodelled
  // it pulls the match along its gradient. The NCC is then the ramp-free patches' correlation.
  bool set(const uint8_t* image, size_t stride, int width, int height, const AffineWarp& warp,
           bool ramp = false) noexcept;

  // Refines `start` on `image`: at most `max_iterations`, stops when the update moves the
  // patch corners by less than `epsilon_px`.
  [[nodiscard]] AffineResult refine(const uint8_t* image, size_t stride, int width, int height,
                                    const AffineWarp& start, int max_iterations = 20,
                                    double epsilon_px = 1e-3) const noexcept;
  // The same over `mask`'s pixels only (weighted inverse compositional: the template's mean,
  // spread and Hessian over them, once per call; the NCC is theirs). Not with `ramp` (the ramps
  // are projected out over the whole grid): unconverged. Unconverged too when fewer than a
  // quarter of the pixels are left or what is left is flat or its Hessian singular.
  [[nodiscard]] AffineResult refine(const uint8_t* image, size_t stride, int width, int height,
                                    const AffineWarp& start, const AffineMask& mask,
                                    int max_iterations = 20,
                                    double epsilon_px = 1e-3) const noexcept;

  [[nodiscard]] const std::array<float, kAffinePixels>& pixels() const { return t_; }

 private:
  // The Gauss-Newton iterations over `weight`'s pixels (nullptr: all), with the template's
  // Hessian inverse, mean and spread over them and their count.
  [[nodiscard]] AffineResult iterate(const uint8_t* image, size_t stride, int width, int height,
                                     const AffineWarp& start, int max_iterations, double epsilon_px,
                                     const float* weight, const cv::Matx<double, 6, 6>& h_inv,
                                     double t_mean, double t_spread, int count) const noexcept;

  std::array<float, kAffinePixels> t_{};
  std::array<std::array<float, 6>, kAffinePixels> sd_{};  // steepest-descent images
  cv::Matx<double, 6, 6> h_inv_;
  double mean_ = 0.0;
  double spread_ = 0.0;
  bool ramp_ = false;
  cv::Vec2d ramp_moments_;  // the template's x and y ramp moments (with ramp_)
};

// The same refinement for a pure translation, for video matching: a camera's frame-0
// template against the same camera's later frames, where the surface's shape in the image
// changes by far less than a pixel over the patch (it moves under a millimetre at 45 cm).
// Every sample of a translated patch shares one fractional offset, so the bicubic warp is
// separable (4 + 4 taps per pixel instead of 16), and the Hessian is 2x2.
class ShiftTemplate {
 public:
  // The patch centred on `centre` (sub-pixel, bicubic). False near the border or when flat.
  bool set(const uint8_t* image, size_t stride, int width, int height,
           const cv::Vec2d& centre) noexcept;

  // Refines `start`; stops when the update is below `epsilon_px`. `warp.a` stays identity.
  // Each iteration is one pass of a Highway kernel (shift_kernel.hpp); `scalar` runs the
  // reference kernel instead (tests). With `mask`, only its pixels take part (weighted inverse
  // compositional: the template's sums and Hessian over them, once per call); unconverged when
  // what is left is flat or its Hessian is singular.
  [[nodiscard]] AffineResult refine(const uint8_t* image, size_t stride, int width, int height,
                                    const cv::Vec2d& start, int max_iterations = 10,
                                    double epsilon_px = 2e-3, bool scalar = false,
                                    const ShiftMask* mask = nullptr) const noexcept;

  // Leaves out, besides what `mask` already does, the pixels of the patch at `centre` that are
  // brighter than the template (normalized to it over the pixels taking part) by more than
  // `sigmas` robust standard deviations of the residual (1.4826 x its median absolute value):
  // the sheen a glint spreads around its saturated core, which has no fixed size. Returns the
  // fraction of the patch left out (1 where the patch leaves the image or what is left is flat).
  double leaveOutSheen(const uint8_t* image, size_t stride, int width, int height,
                       const cv::Vec2d& centre, ShiftMask& mask, double sigmas) const noexcept;

 private:
  // The template's sums over the pixels that take part, and its Gauss-Newton Hessian's inverse.
  struct Moments {
    double n = 0.0, t = 0.0, tt = 0.0, gx = 0.0, gy = 0.0, gxt = 0.0, gyt = 0.0;
    double mean = 0.0, spread = 0.0;
    cv::Matx22d h_inv;
    bool ok = false;
  };
  [[nodiscard]] Moments moments(const std::array<float, kShiftPadded>& weight) const noexcept;

  std::array<float, kShiftPadded> t_{}, gx_{}, gy_{};
  Moments all_;
};

// Bicubic (Catmull-Rom) sample; false outside [1, w-2) x [1, h-2).
bool sampleBicubic(const uint8_t* image, size_t stride, int width, int height, double x, double y,
                   float& out) noexcept;

}  // namespace pulsetrack::vision
