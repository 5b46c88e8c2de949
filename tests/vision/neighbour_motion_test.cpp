// fitNeighbourMotion: a feature's motion from its neighbours'. Exact for an affine motion field
// where they surround the feature; their mean where they are too few, too thin (in a line) or
// the feature lies outside them (an extrapolation); and the mean's error grows with the field's
// gradient while the affine fit's does not.

#include "pulsetrack/vision/neighbour_motion.hpp"

#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <random>

namespace pulsetrack::vision {
namespace {

// An affine motion field: a bowl's slope and a turn (mm of motion per px of position).
cv::Vec3d field(const cv::Vec2d& x) {
  return cv::Vec3d(0.1, -0.2, 0.5) + x[0] * cv::Vec3d(0.004, 0.001, -0.003) +
         x[1] * cv::Vec3d(-0.002, 0.003, 0.006);
}

TEST(NeighbourMotion, ExactForAnAffineFieldAroundTheFeature) {
  std::array<cv::Vec2d, 6> at{};
  std::array<cv::Vec3d, 6> motion{};
  for (size_t k = 0; k < at.size(); ++k) {  // six neighbours, unevenly around the feature
    const double a =
        2.0 * CV_PI * static_cast<double>(k) / 6.0 + 0.3 * std::sin(3.0 * static_cast<double>(k));
    const double r = 10.0 + 4.0 * static_cast<double>(k % 3);
    at[k] = {r * std::cos(a) + 3.0, r * std::sin(a) - 2.0};
    motion[k] = field(at[k]);
  }
  const cv::Vec2d where(1.0, 1.5);
  const auto fit = fitNeighbourMotion(at.data(), motion.data(), 6, where);
  ASSERT_TRUE(fit.affine);
  EXPECT_LT(cv::norm(fit.at(where) - field(where)), 1e-12);
  // The mean blames the field's slope between their centroid and the feature on the feature.
  const auto mean = fitNeighbourMotion(at.data(), motion.data(), 6, where, false);
  EXPECT_FALSE(mean.affine);
  EXPECT_GT(cv::norm(mean.at(where) - field(where)), 0.005);
  EXPECT_LT(cv::norm(mean.at(where) - mean.mean), 1e-15);
}

TEST(NeighbourMotion, TheMeanWhereTheNeighboursDoNotSurroundTheFeature) {
  std::array<cv::Vec2d, 6> at{};
  std::array<cv::Vec3d, 6> motion{};
  cv::Vec3d sum(0, 0, 0);
  for (size_t k = 0; k < at.size(); ++k) {  // in a line (spread 1 px across it)
    at[k] = {5.0 * static_cast<double>(k), k % 2 == 0 ? 0.5 : -0.5};
    motion[k] = field(at[k]);
    sum += motion[k];
  }
  const auto thin = fitNeighbourMotion(at.data(), motion.data(), 6, cv::Vec2d(12, 8));
  EXPECT_FALSE(thin.affine);
  EXPECT_LT(cv::norm(thin.at(cv::Vec2d(12, 8)) - sum / 6.0), 1e-12);
  // Spread wide enough, but the feature far outside them: no extrapolation.
  for (size_t k = 0; k < at.size(); ++k) {
    at[k] = {10.0 * std::cos(static_cast<double>(k)), 10.0 * std::sin(static_cast<double>(k))};
    motion[k] = field(at[k]);
  }
  EXPECT_TRUE(fitNeighbourMotion(at.data(), motion.data(), 6, cv::Vec2d(5, 0)).affine);
  EXPECT_FALSE(fitNeighbourMotion(at.data(), motion.data(), 6, cv::Vec2d(60, 0)).affine);
  // Three neighbours: an affine fit would have no residual to judge it by.
  EXPECT_FALSE(fitNeighbourMotion(at.data(), motion.data(), 3, cv::Vec2d(0, 0)).affine);
  EXPECT_FALSE(fitNeighbourMotion(at.data(), motion.data(), 0, cv::Vec2d(0, 0)).affine);
}

// With noise on the neighbours' motions, the affine fit at a surrounded feature is about as
// noisy as their mean (no amplification), and unbiased where the mean is not.
TEST(NeighbourMotion, NoiseIsNotAmplifiedInside) {
  std::mt19937 rng(5);
  std::normal_distribution<double> noise(0.0, 0.01);
  std::uniform_real_distribution<double> pos(-12.0, 12.0);
  double e_fit = 0.0, e_mean_noise = 0.0;
  int n = 0;
  for (int trial = 0; trial < 2000; ++trial) {
    std::array<cv::Vec2d, 8> at{};
    std::array<cv::Vec3d, 8> motion{}, flat{};
    for (size_t k = 0; k < at.size(); ++k) {
      at[k] = {pos(rng), pos(rng)};
      const cv::Vec3d e(noise(rng), noise(rng), noise(rng));
      motion[k] = field(at[k]) + e;
      flat[k] = e;
    }
    const cv::Vec2d where(0, 0);
    const auto fit = fitNeighbourMotion(at.data(), motion.data(), 8, where);
    if (!fit.affine) continue;
    ++n;
    const cv::Vec3d d = fit.at(where) - field(where);
    e_fit += d.dot(d);
    const auto m = fitNeighbourMotion(at.data(), flat.data(), 8, where, false);
    e_mean_noise += m.mean.dot(m.mean);
  }
  ASSERT_GT(n, 1500);
  // The mean of 8 has sqrt(3) x 0.01 / sqrt(8) = 0.0061 per 3D; the fit stays within 2x of it.
  EXPECT_LT(std::sqrt(e_fit / n), 2.0 * std::sqrt(e_mean_noise / n));
}

}  // namespace
}  // namespace pulsetrack::vision
