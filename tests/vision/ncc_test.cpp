// NCC kernels: the Highway SIMD kernel equals the scalar reference bit for bit, both agree with
// cv::matchTemplate(TM_CCOEFF_NORMED); the quadratic peak and NMI behave as defined.

#include "pulsetrack/vision/ncc.hpp"

#include <gtest/gtest.h>
#include <hwy/targets.h>

#include <cstdlib>
#include <iostream>
#include <opencv2/imgproc.hpp>
#include <random>

namespace pulsetrack::vision {
namespace {

cv::Mat texture(cv::Size size, unsigned seed) {
  cv::Mat img(size, CV_8UC1);
  cv::RNG rng(seed);
  rng.fill(img, cv::RNG::UNIFORM, 0, 256);
  cv::GaussianBlur(img, img, cv::Size(0, 0), 1.2);
  cv::normalize(img, img, 0, 255, cv::NORM_MINMAX);
  return img;
}

void expectSimdEqualsScalar();

// Every SIMD target compiled in and supported by this CPU (AVX-512, AVX2, SSE4, ... here;
// NEON or SVE on ARM), forced one at a time.
TEST(Ncc, SimdEqualsScalarBitForBitOnEveryTarget) {
  std::cout << "NCC kernel dispatches to " << nccTarget() << " on this CPU\n";
  const std::vector<int64_t> targets = hwy::SupportedAndGeneratedTargets();
  ASSERT_FALSE(targets.empty());
  for (const int64_t target : targets) {
    hwy::SetSupportedTargetsForTest(target);
    std::cout << "  checking " << nccTarget() << "\n";
    EXPECT_STREQ(nccTarget(), hwy::TargetName(target));
    expectSimdEqualsScalar();
  }
  hwy::SetSupportedTargetsForTest(0);  // back to the real CPU
}

// The cross build's test presets name the target qemu's CPU must select (arm64-neon: NEON on
// -cpu cortex-a72; arm64-sve: SVE2 on -cpu max), so a run that silently fell back to another
// target (or to the scalar code) fails instead of passing on the wrong kernels.
TEST(Ncc, DispatchesToTheTargetThisRunExpects) {
  const char* expected = std::getenv("PULSETRACK_EXPECT_SIMD_TARGET");
  if (expected == nullptr) GTEST_SKIP() << "PULSETRACK_EXPECT_SIMD_TARGET not set (native run)";
  EXPECT_STREQ(nccTarget(), expected);
}

void expectSimdEqualsScalar() {
  for (const cv::Size& tsize :
       {cv::Size(15, 15), cv::Size(7, 7), cv::Size(31, 31), cv::Size(9, 13), cv::Size(16, 5)}) {
    for (unsigned seed = 1; seed <= 3; ++seed) {
      const cv::Mat img = texture({120, 100}, seed);
      NccTemplate t;
      ASSERT_TRUE(t.set(img.ptr(40, 50), img.step, tsize.width, tsize.height));
      const int nx = 17, ny = 17;
      // A region with room for the kernel's whole-vector loads.
      cv::Mat region = img(cv::Rect(30, 20, nx - 1 + kTemplatePad, ny - 1 + tsize.height)).clone();
      region.row(3).setTo(77);  // a flat stripe: flat placements must agree too
      std::vector<float> simd(nx * ny), scalar(nx * ny);
      nccScores(t, region.data, region.step, nx, ny, simd.data());
      nccScoresScalar(t, region.data, region.step, nx, ny, scalar.data());
      for (int i = 0; i < nx * ny; ++i)
        ASSERT_EQ(simd[i], scalar[i]) << tsize << " seed " << seed << " at " << i;
    }
  }
}

TEST(Ncc, AgreesWithMatchTemplate) {
  const cv::Mat img = texture({200, 160}, 9);
  NccTemplate t;
  ASSERT_TRUE(t.set(img.ptr(70, 80), img.step, 15, 15));
  const int nx = 17, ny = 17;
  const cv::Rect roi(72, 62, nx - 1 + 15, ny - 1 + 15);
  cv::Mat ref;
  cv::matchTemplate(img(roi), img(cv::Rect(80, 70, 15, 15)), ref, cv::TM_CCOEFF_NORMED);
  cv::Mat region = img(cv::Rect(roi.x, roi.y, nx - 1 + kTemplatePad, ny - 1 + 15));
  std::vector<float> ours(nx * ny);
  nccScores(t, region.data, region.step, nx, ny, ours.data());
  for (int y = 0; y < ny; ++y) {
    for (int x = 0; x < nx; ++x)
      EXPECT_NEAR(ours[y * nx + x], ref.at<float>(y, x), 1e-5) << x << "," << y;
  }
  EXPECT_FLOAT_EQ(ours[8 * nx + 8], 1.0F);  // the template's own place
}

TEST(Ncc, InvariantToGainAndBias) {
  const cv::Mat img = texture({80, 80}, 4);
  NccTemplate t;
  ASSERT_TRUE(t.set(img.ptr(30, 30), img.step, 15, 15));
  cv::Mat darker;
  img.convertTo(darker, CV_8UC1, 0.6, 20);  // a shadow: gain and bias
  cv::Mat region = darker(cv::Rect(22, 22, 16 + kTemplatePad, 31));
  std::vector<float> s(17 * 17);
  nccScores(t, region.data, region.step, 17, 17, s.data());
  const auto best = std::max_element(s.begin(), s.end()) - s.begin();
  EXPECT_EQ(best, 8 * 17 + 8);
  EXPECT_GT(s[static_cast<size_t>(best)], 0.99F);
}

TEST(Ncc, FlatTemplateIsRefused) {
  const cv::Mat flat(20, 20, CV_8UC1, cv::Scalar(100));
  NccTemplate t;
  EXPECT_FALSE(t.set(flat.data, flat.step, 15, 15));
  EXPECT_FALSE(t.set(flat.data, flat.step, 33, 15));
}

TEST(QuadraticPeak, RecoversTheApexOfAQuadratic) {
  for (const cv::Vec2d& apex : {cv::Vec2d(0.3, -0.2), cv::Vec2d(-0.45, 0.1), cv::Vec2d(0, 0)}) {
    float s[9];
    for (int j = -1; j <= 1; ++j) {
      for (int i = -1; i <= 1; ++i) {
        const double dx = i - apex[0], dy = j - apex[1];
        s[(j + 1) * 3 + i + 1] =
            static_cast<float>(0.9 - 0.2 * dx * dx - 0.05 * dx * dy - 0.15 * dy * dy);
      }
    }
    const SubPixel p = quadraticPeak(s);
    EXPECT_NEAR(p.dx, apex[0], 1e-5);
    EXPECT_NEAR(p.dy, apex[1], 1e-5);
    EXPECT_NEAR(p.peak, 0.9, 1e-5);
  }
  const float saddle[9] = {0, 1, 0, -1, 0, -1, 0, 1, 0};
  const SubPixel p = quadraticPeak(saddle);
  EXPECT_EQ(p.dx, 0.0);
  EXPECT_EQ(p.dy, 0.0);
}

TEST(Nmi, IdenticalInvertedAndUnrelatedPatches) {
  const cv::Mat a = texture({15, 15}, 1);
  const cv::Mat b = texture({15, 15}, 2);
  cv::Mat inverted;
  cv::bitwise_not(a, inverted);
  EXPECT_NEAR(normalizedMutualInformation(a.data, a.step, a.data, a.step, 15, 15), 1.0, 1e-12);
  // Mutual information ignores any one-to-one remapping of intensities (NCC would say -1).
  EXPECT_GT(normalizedMutualInformation(a.data, a.step, inverted.data, inverted.step, 15, 15), 0.9);
  EXPECT_LT(normalizedMutualInformation(a.data, a.step, b.data, b.step, 15, 15), 0.5);
  const cv::Mat flat(15, 15, CV_8UC1, cv::Scalar(9));
  EXPECT_EQ(normalizedMutualInformation(a.data, a.step, flat.data, flat.step, 15, 15), 0.0);
}

// The per-frame NMI (bins by multiplication, entropies from a c log c table) against the
// textbook formula (bins by division, log per bin), on random and on quantized patches.
double nmiReference(const cv::Mat& a, const cv::Mat& b, int bins) {
  double amin = 0, amax = 0, bmin = 0, bmax = 0;
  cv::minMaxLoc(a, &amin, &amax);
  cv::minMaxLoc(b, &bmin, &bmax);
  std::vector<double> joint(static_cast<size_t>(bins * bins), 0.0), pa(static_cast<size_t>(bins)),
      pb(static_cast<size_t>(bins));
  const double n = static_cast<double>(a.total());
  for (int y = 0; y < a.rows; ++y) {
    for (int x = 0; x < a.cols; ++x) {
      const int ia = (a.at<uint8_t>(y, x) - int(amin)) * bins / (int(amax) - int(amin) + 1);
      const int ib = (b.at<uint8_t>(y, x) - int(bmin)) * bins / (int(bmax) - int(bmin) + 1);
      joint[static_cast<size_t>(ia) * static_cast<size_t>(bins) + static_cast<size_t>(ib)] +=
          1.0 / n;
      pa[static_cast<size_t>(ia)] += 1.0 / n;
      pb[static_cast<size_t>(ib)] += 1.0 / n;
    }
  }
  const auto entropy = [](const std::vector<double>& p) {
    double h = 0;
    for (double v : p) h -= v > 0 ? v * std::log(v) : 0.0;
    return h;
  };
  const double ha = entropy(pa), hb = entropy(pb), hab = entropy(joint);
  return 2.0 * (ha + hb - hab) / (ha + hb);
}

TEST(Nmi, MatchesTheTextbookFormula) {
  cv::RNG rng(11);
  for (int trial = 0; trial < 200; ++trial) {
    cv::Mat a(15, 15, CV_8UC1), b(15, 15, CV_8UC1);
    const int span = 2 + trial % 200;  // narrow ranges hit exact bin edges
    rng.fill(a, cv::RNG::UNIFORM, 10, 10 + span);
    b = a / 2 + 7;
    cv::Mat noise(15, 15, CV_8UC1);
    rng.fill(noise, cv::RNG::UNIFORM, 0, 1 + trial % 30);
    b += noise;
    for (const int bins : {8, 16, 32}) {
      const double ours = normalizedMutualInformation(a.data, a.step, b.data, b.step, 15, 15, bins);
      NmiTemplate t;
      ASSERT_TRUE(t.set(a.data, a.step, 15, 15, bins));
      EXPECT_EQ(t.score(b.data, b.step), ours);
      EXPECT_NEAR(ours, std::clamp(nmiReference(a, b, bins), 0.0, 1.0), 1e-12)
          << trial << " " << bins;
    }
  }
}

TEST(RegionMax, MatchesOpenCv) {
  cv::RNG rng(12);
  cv::Mat img(80, 90, CV_8UC1);
  rng.fill(img, cv::RNG::UNIFORM, 0, 200);
  for (int trial = 0; trial < 300; ++trial) {
    const int w = 1 + trial % 60, h = 1 + (trial * 7) % 50;
    const int x = trial % (90 - w + 1), y = (trial * 3) % (80 - h + 1);
    img.at<uint8_t>(y + trial % h, x + (trial * 5) % w) = static_cast<uint8_t>(200 + trial % 56);
    double mx = 0;
    cv::minMaxLoc(img(cv::Rect(x, y, w, h)), nullptr, &mx);
    EXPECT_EQ(regionMax(img.ptr<uint8_t>(y) + x, img.step, w, h), static_cast<int>(mx))
        << w << "x" << h << " at " << x << "," << y;
  }
  EXPECT_EQ(regionMax(img.data, img.step, 0, 5), 0);
}

}  // namespace
}  // namespace pulsetrack::vision
