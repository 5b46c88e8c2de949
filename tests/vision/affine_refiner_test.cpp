// The affine refinement recovers a known sub-pixel shift, rotation, scale and shear of a
// textured patch, through a gain and bias change, from an integer start.

#include "pulsetrack/vision/affine_refiner.hpp"

#include <gtest/gtest.h>

#include <iostream>
#include <opencv2/imgproc.hpp>
#include <random>

#include "pulsetrack/vision/shift_kernel.hpp"

namespace pulsetrack::vision {
namespace {

// A band-limited texture known everywhere: a sum of sinusoids (wavelengths 5-20 px), so both
// the template and the moved image are exact samples of one function. (Generating the moved
// image with cv::remap would itself interpolate, and put 0.05 px errors into the "truth".)
struct Texture {
  std::vector<cv::Vec4d> waves;  // kx, ky, phase, amplitude
  explicit Texture(unsigned seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    for (int i = 0; i < 40; ++i) {
      const double lambda = 5.0 + 15.0 * u(rng);
      const double dir = 2.0 * CV_PI * u(rng);
      waves.emplace_back(2 * CV_PI / lambda * std::cos(dir), 2 * CV_PI / lambda * std::sin(dir),
                         2 * CV_PI * u(rng), 12.0 * u(rng));
    }
  }
  [[nodiscard]] double at(double x, double y) const {
    double v = 125.0;
    for (const cv::Vec4d& w : waves) v += w[3] * std::sin(w[0] * x + w[1] * y + w[2]);
    return v;
  }
  // An 8-bit image whose pixel p shows the texture at `from(p)`, with gain and bias. `from` is
  // affine (every use here is), so each wave's phase is c + a x + b y and its sine separates:
  // sin(a x) cos(c + b y) + cos(a x) sin(c + b y), 16 k sines an image instead of 1.6 M. (The
  // direct sum made this file's tests minutes long under emulation: under qemu 7.2 -cpu max with
  // vectors over 128 bits, plain scalar code runs about 25 times slower once the SVE2 kernel has
  // run a few times, 1.3 s an image instead of 50 ms; the refiners under test take milliseconds.)
  template <class F>
  [[nodiscard]] cv::Mat image(F from, double gain = 1.0, double bias = 0.0) const {
    constexpr int kSide = 200;
    const cv::Vec2d o = from(cv::Vec2d(0, 0));
    const cv::Vec2d ex = from(cv::Vec2d(1, 0)) - o, ey = from(cv::Vec2d(0, 1)) - o;
    const cv::Vec2d far = from(cv::Vec2d(kSide - 1, kSide - 1));
    EXPECT_LT(cv::norm(far - (o + (kSide - 1) * (ex + ey))), 1e-9) << "an affine map";
    cv::Mat acc(kSide, kSide, CV_64FC1, cv::Scalar(125.0));
    std::vector<double> sa(kSide), ca(kSide), sb(kSide), cb(kSide);
    for (const cv::Vec4d& w : waves) {
      const double c = w[0] * o[0] + w[1] * o[1] + w[2];
      const double a = w[0] * ex[0] + w[1] * ex[1], b = w[0] * ey[0] + w[1] * ey[1];
      for (int i = 0; i < kSide; ++i) {
        sa[static_cast<size_t>(i)] = w[3] * std::sin(a * i);
        ca[static_cast<size_t>(i)] = w[3] * std::cos(a * i);
        sb[static_cast<size_t>(i)] = std::sin(c + b * i);
        cb[static_cast<size_t>(i)] = std::cos(c + b * i);
      }
      for (int y = 0; y < kSide; ++y) {
        auto* row = acc.ptr<double>(y);
        const double cy = cb[static_cast<size_t>(y)], sy = sb[static_cast<size_t>(y)];
        for (int x = 0; x < kSide; ++x)
          row[x] += sa[static_cast<size_t>(x)] * cy + ca[static_cast<size_t>(x)] * sy;
      }
    }
    for (const cv::Point p : {cv::Point(0, 0), cv::Point(37, 151), cv::Point(199, 88)}) {
      const cv::Vec2d q = from(cv::Vec2d(p.x, p.y));
      EXPECT_NEAR(acc.at<double>(p), at(q[0], q[1]), 1e-9) << "the direct sum at " << p;
    }
    cv::Mat img(kSide, kSide, CV_8UC1);
    for (int y = 0; y < kSide; ++y)
      for (int x = 0; x < kSide; ++x)
        img.at<uint8_t>(y, x) = cv::saturate_cast<uint8_t>(gain * acc.at<double>(y, x) + bias);
    return img;
  }
};

TEST(AffineRefiner, RecoversAKnownWarpThroughGainAndBias) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  double worst = 0.0, sum2 = 0.0;
  for (int trial = 0; trial < 30; ++trial) {
    const Texture tex(static_cast<unsigned>(trial + 1));
    const cv::Mat src8 = tex.image([](const cv::Vec2d& p) { return p; });
    AffineTemplate t;
    const AffineWarp at_rest{{100.0, 100.0}, cv::Matx22d::eye()};
    ASSERT_TRUE(t.set(src8.data, src8.step, src8.cols, src8.rows, at_rest));
    // The moved image: the patch at rest maps to centre + M x in the new image.
    const double angle = 0.08 * u(rng), scale = 1.0 + 0.05 * u(rng), shear = 0.04 * u(rng);
    const cv::Matx22d m =
        cv::Matx22d(std::cos(angle), -std::sin(angle), std::sin(angle), std::cos(angle)) *
        cv::Matx22d(scale, shear, 0.0, scale);
    const cv::Vec2d centre(103.0 + 2.0 * u(rng), 98.0 + 2.0 * u(rng));
    const cv::Matx22d mi = m.inv();
    // A shadow too: gain and bias.
    const cv::Mat moved8 = tex.image(
        [&](const cv::Vec2d& p) { return cv::Vec2d(100, 100) + mi * (p - centre); }, 0.7, 25.0);
    const AffineWarp start{{std::round(centre[0]), std::round(centre[1])}, cv::Matx22d::eye()};
    const AffineResult r = t.refine(moved8.data, moved8.step, moved8.cols, moved8.rows, start);
    ASSERT_TRUE(r.converged) << trial;
    const double e = cv::norm(r.warp.centre - centre);
    worst = std::max(worst, e);
    sum2 += e * e;
    EXPECT_LT(e, 0.025) << trial;
    EXPECT_LT(cv::norm(r.warp.a - m, cv::NORM_INF), 5e-3) << trial;
    EXPECT_LT(r.rms, 1.5);
  }
  const double rms = std::sqrt(sum2 / 30.0);
  std::cout << "affine refinement, 30 warped 8-bit patches: centre error RMS " << rms
            << " px, worst " << worst << " px\n";
  EXPECT_LT(rms, 0.012);
}

// A sheen lobe or a shadow's edge in one view only: an intensity ramp across the patch. Gain and
// bias do not model it and the match slides along the ramp; the ramp model (project-out) does.
TEST(AffineRefiner, AnIntensityRampInOneViewDoesNotMoveTheRampModelsMatch) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  double sum2_plain = 0.0, sum2_ramp = 0.0, worst_ramp = 0.0, ncc_plain = 0.0, ncc_ramp = 0.0;
  constexpr int kTrials = 30;
  for (int trial = 0; trial < kTrials; ++trial) {
    const Texture tex(static_cast<unsigned>(trial + 101));
    const cv::Mat src8 = tex.image([](const cv::Vec2d& p) { return p; });
    const cv::Vec2d centre(101.0 + u(rng), 99.0 + u(rng));
    cv::Mat moved8 = tex.image(
        [&](const cv::Vec2d& p) { return cv::Vec2d(100, 100) + (p - centre); }, 0.9, 10.0);
    // 1.5 grey levels per px in a random direction: 21 levels across the 15 px template.
    const double dir = CV_PI * u(rng);
    for (int y = 0; y < moved8.rows; ++y) {
      for (int x = 0; x < moved8.cols; ++x) {
        const double ramp = 1.5 * (std::cos(dir) * (x - 100) + std::sin(dir) * (y - 100));
        moved8.at<uint8_t>(y, x) = cv::saturate_cast<uint8_t>(moved8.at<uint8_t>(y, x) + ramp);
      }
    }
    const AffineWarp start{{std::round(centre[0]), std::round(centre[1])}, cv::Matx22d::eye()};
    for (const bool ramp : {false, true}) {
      AffineTemplate t;
      ASSERT_TRUE(t.set(src8.data, src8.step, src8.cols, src8.rows,
                        {{100.0, 100.0}, cv::Matx22d::eye()}, ramp));
      const AffineResult r = t.refine(moved8.data, moved8.step, moved8.cols, moved8.rows, start);
      ASSERT_TRUE(r.converged) << trial << " ramp " << ramp;
      const double e = cv::norm(r.warp.centre - centre);
      (ramp ? sum2_ramp : sum2_plain) += e * e;
      (ramp ? ncc_ramp : ncc_plain) += r.ncc / kTrials;
      if (ramp) worst_ramp = std::max(worst_ramp, e);
    }
  }
  const double plain = std::sqrt(sum2_plain / kTrials), ramp = std::sqrt(sum2_ramp / kTrials);
  std::cout << "a 1.5 grey/px ramp in the moved view, 30 patches: centre error RMS " << plain
            << " px with gain and bias, " << ramp << " px with the ramp modelled (worst "
            << worst_ramp << "); mean NCC " << ncc_plain << " -> " << ncc_ramp << "\n";
  // Measured: 0.158 px unmodelled, 0.012 px (worst 0.036) modelled; mean NCC 0.978 -> 0.9998.
  EXPECT_LT(ramp, 0.02);
  EXPECT_LT(worst_ramp, 0.05);
  EXPECT_GT(plain, 5.0 * ramp);
  EXPECT_GT(ncc_ramp, ncc_plain);
}

// The stereo refresh's match where a glint is near: the light reflects towards one camera, so
// a glint (a saturated core and the sheen around it) sits in one view's patch and not in the
// other's. Left out (AffineMask: the core grown by 5 px, in whichever view has it), it does not
// pull the affine match; counted, it does.
TEST(AffineRefiner, AGlintInEitherViewLeftOutDoesNotPullTheStereoMatch) {
  std::mt19937 rng(23);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  double sum_all = 0.0, sum_masked = 0.0, worst = 0.0, left_out = 0.0;
  constexpr int kTrials = 40;
  const auto add_glint = [](cv::Mat& img, const cv::Vec2d& at) {
    for (int y = 0; y < img.rows; ++y) {
      for (int x = 0; x < img.cols; ++x) {
        const double r2 = (x - at[0]) * (x - at[0]) + (y - at[1]) * (y - at[1]);
        auto& v = img.at<uint8_t>(y, x);
        v = r2 <= 2.5 * 2.5 ? 255 : cv::saturate_cast<uint8_t>(v + 130.0 * std::exp(-r2 / 12.5));
      }
    }
  };
  for (int trial = 0; trial < kTrials; ++trial) {
    const Texture tex(static_cast<unsigned>(trial + 500));
    cv::Mat src8 = tex.image([](const cv::Vec2d& p) { return p; });
    const double angle = 0.05 * u(rng), scale = 1.0 + 0.04 * u(rng), shear = 0.05 * u(rng);
    const cv::Matx22d m =
        cv::Matx22d(std::cos(angle), -std::sin(angle), std::sin(angle), std::cos(angle)) *
        cv::Matx22d(scale, shear, 0.0, scale);
    const cv::Vec2d centre(101.0 + u(rng), 99.0 + u(rng));
    const cv::Matx22d mi = m.inv();
    cv::Mat moved8 = tex.image(
        [&](const cv::Vec2d& p) { return cv::Vec2d(100, 100) + mi * (p - centre); }, 0.8, 15.0);
    // The glint 6.5-8.5 px from the patch's centre, in the right view (even trials) or the left.
    const double dir = CV_PI * u(rng), radius = 7.5 + u(rng);
    const cv::Vec2d off = radius * cv::Vec2d(std::cos(dir), std::sin(dir));
    if (trial % 2 == 0) {
      add_glint(moved8, centre + off);
    } else {
      add_glint(src8, cv::Vec2d(100, 100) + off);
    }
    AffineTemplate t;
    ASSERT_TRUE(
        t.set(src8.data, src8.step, src8.cols, src8.rows, {{100.0, 100.0}, cv::Matx22d::eye()}));
    const AffineWarp start{{std::round(centre[0]), std::round(centre[1])}, cv::Matx22d::eye()};
    const AffineResult all = t.refine(moved8.data, moved8.step, moved8.cols, moved8.rows, start);
    AffineMask mask;
    mask.reset();
    mask.leaveOutGlints(src8.data, src8.step, src8.cols, src8.rows,
                        {{100.0, 100.0}, cv::Matx22d::eye()}, 250, 5);
    const double out =
        mask.leaveOutGlints(moved8.data, moved8.step, moved8.cols, moved8.rows, start, 250, 5);
    EXPECT_GT(out, 0.05) << trial;  // the glint is near: some of the patch is left out
    EXPECT_LT(out, 0.6) << trial;
    left_out += out / kTrials;
    const AffineResult masked =
        t.refine(moved8.data, moved8.step, moved8.cols, moved8.rows, start, mask);
    ASSERT_TRUE(masked.converged) << trial;
    const double e_all = cv::norm(all.warp.centre - centre);
    const double e = cv::norm(masked.warp.centre - centre);
    EXPECT_LT(e, 0.06) << trial;
    EXPECT_GT(masked.ncc, 0.99) << trial;  // the pixels left are the same texture in both views
    worst = std::max(worst, e);
    sum_all += e_all * e_all;
    sum_masked += e * e;
  }
  const double rms_all = std::sqrt(sum_all / kTrials), rms = std::sqrt(sum_masked / kTrials);
  std::cout
      << "a glint 6.5-8.5 px from the centre in one view of 40 affinely warped patches, stereo "
         "match error RMS: counted "
      << rms_all << " px, left out " << rms << " px (worst " << worst << ", " << 100.0 * left_out
      << " % of the patch left out on average)\n";
  EXPECT_LT(rms, 0.03);
  EXPECT_GT(rms_all, 5.0 * rms);
}

// A masked match's NCC and residual are those of the pixels it kept: noise on the image, the left
// half of the template left out; the NCC over the kept half computed here where the match settled.
TEST(AffineRefiner, AMaskedMatchsNccIsThePixelsItKept) {
  const Texture tex(11);
  const cv::Mat src8 = tex.image([](const cv::Vec2d& p) { return p; });
  cv::Mat noisy = tex.image([](const cv::Vec2d& p) { return p - cv::Vec2d(3.0, -2.0); });
  // Seeded noise (cv::randn drew other numbers under qemu-aarch64: the NCC there 0.953).
  std::mt19937 rng(29);
  std::normal_distribution<double> noise(0.0, 12.0);
  for (int y = 0; y < noisy.rows; ++y) {
    for (int x = 0; x < noisy.cols; ++x) {
      auto& v = noisy.at<uint8_t>(y, x);
      v = cv::saturate_cast<uint8_t>(v + noise(rng));
    }
  }
  AffineTemplate t;
  ASSERT_TRUE(
      t.set(src8.data, src8.step, src8.cols, src8.rows, {{100.0, 100.0}, cv::Matx22d::eye()}));
  AffineMask mask;
  mask.reset();
  for (size_t k = 0; k < static_cast<size_t>(kAffinePixels); ++k) {
    if (k % kAffineSide < kAffineHalf) {
      mask.weight[k] = 0.0F;
      --mask.count;
    }
  }
  const AffineWarp start{{103.0, 98.0}, cv::Matx22d::eye()};
  const AffineResult m = t.refine(noisy.data, noisy.step, noisy.cols, noisy.rows, start, mask);
  ASSERT_TRUE(m.converged);
  EXPECT_LT(cv::norm(m.warp.centre - start.centre), 0.5);
  // The patch where the match settled, sampled as the refinement samples (Catmull-Rom).
  double st = 0, sp = 0, stt = 0, spp = 0, stp = 0, n = 0;
  size_t k = 0;
  for (int y = -kAffineHalf; y <= kAffineHalf; ++y) {
    for (int x = -kAffineHalf; x <= kAffineHalf; ++x, ++k) {
      if (mask.weight[k] == 0.0F) continue;
      const cv::Vec2d p = m.warp.centre + m.warp.a * cv::Vec2d(x, y);
      float v = 0.0F;
      ASSERT_TRUE(sampleBicubic(noisy.data, noisy.step, noisy.cols, noisy.rows, p[0], p[1], v));
      const double a = t.pixels()[k], b = v;
      st += a;
      sp += b;
      stt += a * a;
      spp += b * b;
      stp += a * b;
      n += 1.0;
    }
  }
  const double ncc = (stp - st * sp / n) / std::sqrt((stt - st * st / n) * (spp - sp * sp / n));
  std::cout << "masked match, half the template kept, noise 12 grey levels: NCC " << m.ncc
            << ", over the kept pixels there " << ncc << "\n";
  // The noise shows (a normalization by all 225 pixels instead of the kept ones would be off
  // by at least 0.015 then).
  EXPECT_LT(ncc, 0.97);
  EXPECT_NEAR(m.ncc, ncc, 0.002);
}

// A mask that leaves too little, or a ramp-modelling template (its ramps are projected out over
// the whole grid), is not refined: unconverged, never a match from a sliver of the patch.
TEST(AffineRefiner, AMaskThatLeavesTooLittleIsRefused) {
  const Texture tex(7);
  const cv::Mat src8 = tex.image([](const cv::Vec2d& p) { return p; });
  const AffineWarp rest{{100.0, 100.0}, cv::Matx22d::eye()};
  AffineTemplate t, ramp;
  ASSERT_TRUE(t.set(src8.data, src8.step, src8.cols, src8.rows, rest));
  ASSERT_TRUE(ramp.set(src8.data, src8.step, src8.cols, src8.rows, rest, true));
  AffineMask mask;
  mask.reset();
  EXPECT_EQ(mask.count, kAffinePixels);
  // A mask that keeps every pixel is the unmasked refinement, to the last bit of its figures.
  const AffineWarp moved{{101.3, 98.6}, cv::Matx22d::eye()};
  const cv::Mat shifted = tex.image([](const cv::Vec2d& p) { return p - cv::Vec2d(1.4, -1.3); });
  const AffineResult whole =
      t.refine(shifted.data, shifted.step, shifted.cols, shifted.rows, moved);
  const AffineResult all =
      t.refine(shifted.data, shifted.step, shifted.cols, shifted.rows, moved, mask);
  ASSERT_TRUE(whole.converged && all.converged);
  EXPECT_NEAR(cv::norm(whole.warp.centre - all.warp.centre), 0.0, 1e-9);
  EXPECT_NEAR(whole.ncc, all.ncc, 1e-9);
  EXPECT_NEAR(whole.rms, all.rms, 1e-9);
  EXPECT_FALSE(ramp.refine(src8.data, src8.step, src8.cols, src8.rows, rest, mask).converged);
  // A saturated square over all but the patch's last three rows: 45 of 225 pixels left.
  cv::Mat lit = src8.clone();
  lit(cv::Rect(80, 80, 40, 25)).setTo(255);
  const double out = mask.leaveOutGlints(lit.data, lit.step, lit.cols, lit.rows, rest, 250, 0);
  EXPECT_NEAR(out, 1.0 - 45.0 / kAffinePixels, 1e-9);
  EXPECT_EQ(mask.count, 45);
  EXPECT_FALSE(t.refine(src8.data, src8.step, src8.cols, src8.rows, rest, mask).converged);
}

TEST(AffineRefiner, RefusesFlatPatchesAndTheBorder) {
  const cv::Mat flat(50, 50, CV_8UC1, cv::Scalar(100));
  AffineTemplate t;
  EXPECT_FALSE(t.set(flat.data, flat.step, 50, 50, {{25.0, 25.0}, cv::Matx22d::eye()}));
  const cv::Mat img = Texture(1).image([](const cv::Vec2d& p) { return p; });
  EXPECT_FALSE(t.set(img.data, img.step, img.cols, img.rows, {{5.0, 100.0}, cv::Matx22d::eye()}));
  ASSERT_TRUE(t.set(img.data, img.step, img.cols, img.rows, {{100.0, 100.0}, cv::Matx22d::eye()}));
  const AffineResult r =
      t.refine(img.data, img.step, img.cols, img.rows, {{3.0, 100.0}, cv::Matx22d::eye()});
  EXPECT_FALSE(r.converged);
}

// Video matching's translation refinement: sub-pixel shifts through a gain and bias change,
// from a start up to 1.5 px off; the NCC it reports equals the NCC of the resampled patch.
TEST(ShiftRefiner, RecoversAKnownShiftThroughGainAndBias) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  double worst = 0.0, sum2 = 0.0;
  for (int trial = 0; trial < 40; ++trial) {
    const Texture tex(static_cast<unsigned>(trial + 100));
    const cv::Mat src8 = tex.image([](const cv::Vec2d& p) { return p; });
    ShiftTemplate t;
    const cv::Vec2d rest(100.0 + 0.5 * u(rng), 100.0 + 0.5 * u(rng));
    ASSERT_TRUE(t.set(src8.data, src8.step, src8.cols, src8.rows, rest));
    const cv::Vec2d shift(1.5 * u(rng), 1.5 * u(rng));
    const cv::Mat moved8 = tex.image([&](const cv::Vec2d& p) { return p - shift; }, 0.75, 20.0);
    const AffineResult r = t.refine(moved8.data, moved8.step, moved8.cols, moved8.rows, rest);
    ASSERT_TRUE(r.converged) << trial;
    const double e = cv::norm(r.warp.centre - (rest + shift));
    worst = std::max(worst, e);
    sum2 += e * e;
    EXPECT_LT(e, 0.03) << trial;
    EXPECT_GT(r.ncc, 0.99) << trial;
    EXPECT_LE(r.ncc, 1.0 + 1e-9) << trial;
    EXPECT_LE(r.iterations, 8) << trial;
    // The scalar reference kernel takes the same path to the same answer.
    const AffineResult s = t.refine(moved8.data, moved8.step, moved8.cols, moved8.rows, rest, 10,
                                    2e-3, /*scalar=*/true);
    EXPECT_EQ(s.iterations, r.iterations) << trial;
    EXPECT_LT(cv::norm(s.warp.centre - r.warp.centre), 1e-4) << trial;
  }
  const double rms = std::sqrt(sum2 / 40.0);
  std::cout << "translation refinement, 40 shifted 8-bit patches: error RMS " << rms
            << " px, worst " << worst << " px\n";
  EXPECT_LT(rms, 0.015);
}

// A glint is the light's, not the tissue's: it stays where the view puts it while the tissue
// moves under it. Left out of the match (ShiftMask), it no longer pulls the match; counted, it
// does. The glint here: a saturated core of radius 2.5 px and a sheen around it whose excess
// falls off as a Gaussian of 2.5 px (130 grey levels at the core's edge), 5-9 px from the
// patch's centre. The sheen reaches past a mask grown by 1 px around the core; the residual
// (leaveOutSheen) finds it without a size being given.
TEST(ShiftRefiner, AGlintLeftOutDoesNotPullTheMatch) {
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  double sum_all = 0.0, sum_core = 0.0, sum_sheen = 0.0, sum_grown = 0.0, left_out = 0.0;
  constexpr int kTrials = 40;
  const auto refine = [](const ShiftTemplate& t, const cv::Mat& img, const cv::Vec2d& at,
                         const ShiftMask* mask, bool scalar = false) {
    return t.refine(img.data, img.step, img.cols, img.rows, at, 10, 2e-3, scalar, mask);
  };
  for (int trial = 0; trial < kTrials; ++trial) {
    const Texture tex(static_cast<unsigned>(trial + 300));
    const cv::Mat src8 = tex.image([](const cv::Vec2d& p) { return p; });
    ShiftTemplate t;
    const cv::Vec2d rest(100.0 + 0.5 * u(rng), 100.0 + 0.5 * u(rng));
    ASSERT_TRUE(t.set(src8.data, src8.step, src8.cols, src8.rows, rest));
    const cv::Vec2d shift(0.8 * u(rng), 0.8 * u(rng));
    cv::Mat moved8 = tex.image([&](const cv::Vec2d& p) { return p - shift; });
    const double angle = CV_PI * u(rng), radius = 7.0 + 2.0 * u(rng);
    const cv::Vec2d glint = rest + radius * cv::Vec2d(std::cos(angle), std::sin(angle));
    for (int y = 0; y < moved8.rows; ++y) {
      for (int x = 0; x < moved8.cols; ++x) {
        const double r2 = (x - glint[0]) * (x - glint[0]) + (y - glint[1]) * (y - glint[1]);
        auto& v = moved8.at<uint8_t>(y, x);
        v = r2 <= 2.5 * 2.5 ? 255 : cv::saturate_cast<uint8_t>(v + 130.0 * std::exp(-r2 / 12.5));
      }
    }
    const cv::Vec2d truth = rest + shift;
    const auto err = [&](const AffineResult& r) { return cv::norm(r.warp.centre - truth); };
    // Counted, the glint's pixels may keep the match from settling (it moves all the same).
    const double e_all = err(refine(t, moved8, rest, nullptr));
    // The core and 1 px around it left out, then the sheen the residual shows.
    ShiftMask mask;
    mask.leaveOutGlints(moved8.data, moved8.step, moved8.cols, moved8.rows, rest, 250, 1);
    const AffineResult core = refine(t, moved8, rest, &mask);
    const double e_core = err(core);
    left_out += t.leaveOutSheen(moved8.data, moved8.step, moved8.cols, moved8.rows,
                                core.warp.centre, mask, 3.0);
    const AffineResult sheen = refine(t, moved8, core.warp.centre, &mask);
    const double e_sheen = err(sheen);
    // The scalar kernel agrees under a mask too.
    EXPECT_LT(
        cv::norm(refine(t, moved8, core.warp.centre, &mask, true).warp.centre - sheen.warp.centre),
        1e-4)
        << trial;
    // The tracker's way: grown by 5 px around the core, then the sheen the residual shows.
    ShiftMask grown;
    grown.leaveOutGlints(moved8.data, moved8.step, moved8.cols, moved8.rows, rest, 250, 5);
    const AffineResult first = refine(t, moved8, rest, &grown);
    t.leaveOutSheen(moved8.data, moved8.step, moved8.cols, moved8.rows, first.warp.centre, grown,
                    3.0);
    const AffineResult last = refine(t, moved8, first.warp.centre, &grown);
    ASSERT_TRUE(first.converged && last.converged) << trial;
    const double e_grown = err(last);
    EXPECT_LT(e_grown, 0.05) << trial;
    sum_all += e_all * e_all;
    sum_core += e_core * e_core;
    sum_sheen += e_sheen * e_sheen;
    sum_grown += e_grown * e_grown;
  }
  const auto rms = [&](double sum) { return std::sqrt(sum / kTrials); };
  std::cout << "a glint 5-9 px from the centre of 40 shifted patches, match error RMS: counted "
            << rms(sum_all) << " px; core + 1 px left out " << rms(sum_core)
            << " px, and its sheen as the residual shows it " << rms(sum_sheen) << " px ("
            << 100.0 * left_out / kTrials
            << " % of the patch left out on average); core + 5 px and its sheen (the tracker's) "
            << rms(sum_grown) << " px\n";
  EXPECT_LT(rms(sum_grown), 0.02);
  EXPECT_GT(rms(sum_all), 10.0 * rms(sum_grown));
  EXPECT_LT(rms(sum_sheen), 0.6 * rms(sum_core));
}

TEST(ShiftRefiner, SimdKernelMatchesTheScalarReference) {
  const cv::Mat img = Texture(7).image([](const cv::Vec2d& p) { return p; });
  std::mt19937 rng(9);
  std::uniform_real_distribution<float> u(0.0F, 1.0F);
  std::array<float, kShiftRows * kShiftCols> t{}, gx{}, gy{}, mask{};
  for (size_t k = 0; k < t.size(); ++k) {
    const bool pad = k % kShiftCols == kShiftCols - 1;
    t[k] = pad ? 0.0F : 255.0F * u(rng);
    gx[k] = pad ? 0.0F : 40.0F * (u(rng) - 0.5F);
    gy[k] = pad ? 0.0F : 40.0F * (u(rng) - 0.5F);
  }
  // The pad column and a few pixels (a glint's) left out.
  for (size_t k = 0; k < mask.size(); ++k)
    mask[k] = k % kShiftCols == kShiftCols - 1 || k % 37 == 5 ? 0.0F : 1.0F;
  for (int trial = 0; trial < 50; ++trial) {
    ShiftKernelInput in;
    in.image = img.ptr<uint8_t>(20 + trial) + 30 + 2 * trial;
    in.stride = img.step;
    const float fx = u(rng), fy = u(rng);
    // Catmull-Rom weights as the refiner makes them.
    const auto cr = [](float f, float* w) {
      const float f2 = f * f, f3 = f2 * f;
      w[0] = -0.5F * f3 + f2 - 0.5F * f;
      w[1] = 1.5F * f3 - 2.5F * f2 + 1.0F;
      w[2] = -1.5F * f3 + 2.0F * f2 + 0.5F * f;
      w[3] = 0.5F * f3 - 0.5F * f2;
    };
    cr(fx, in.wx);
    cr(fy, in.wy);
    in.t = t.data();
    in.gx = gx.data();
    in.gy = gy.data();
    in.mask = mask.data();
    ShiftSums a, b;
    shiftSums(in, a);
    shiftSumsScalar(in, b);
    // Float sums in a different order: equal to float rounding.
    EXPECT_NEAR(a.p, b.p, 1e-5 * std::abs(b.p) + 1e-3);
    EXPECT_NEAR(a.pp, b.pp, 1e-5 * std::abs(b.pp) + 1e-3);
    EXPECT_NEAR(a.gxp, b.gxp, 1e-4 * std::abs(b.gxp) + 0.5);
    EXPECT_NEAR(a.gyp, b.gyp, 1e-4 * std::abs(b.gyp) + 0.5);
    EXPECT_NEAR(a.tp, b.tp, 1e-5 * std::abs(b.tp) + 1e-3);
  }
}

TEST(ShiftRefiner, RefusesFlatPatchesAndTheBorder) {
  const cv::Mat flat(50, 50, CV_8UC1, cv::Scalar(100));
  ShiftTemplate t;
  EXPECT_FALSE(t.set(flat.data, flat.step, 50, 50, {25.0, 25.0}));
  const cv::Mat img = Texture(1).image([](const cv::Vec2d& p) { return p; });
  EXPECT_FALSE(t.set(img.data, img.step, img.cols, img.rows, {5.0, 100.0}));
  ASSERT_TRUE(t.set(img.data, img.step, img.cols, img.rows, {100.0, 100.0}));
  EXPECT_FALSE(t.refine(img.data, img.step, img.cols, img.rows, {3.0, 100.0}).converged);
  EXPECT_FALSE(t.refine(img.data, img.step, img.cols, img.rows, {192.0, 100.0}).converged);
  EXPECT_FALSE(t.refine(img.data, img.step, img.cols, img.rows, {std::nan(""), 100.0}).converged);
}

}  // namespace
}  // namespace pulsetrack::vision
