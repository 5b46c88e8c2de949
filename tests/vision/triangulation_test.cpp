// Triangulation: exact without noise (through strong distortion); with pixel noise the LM
// refinement beats the midpoint of eq. (3), as a maximum-likelihood estimate should.

#include "pulsetrack/vision/triangulation.hpp"

#include <gtest/gtest.h>

#include <iostream>
#include <random>

#include "pulsetrack/sim/paper_rig.hpp"

namespace pulsetrack::vision {
namespace {

TEST(Triangulation, ExactWithoutNoise) {
  const StereoRig rig = sim::paperRig();
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> xy(-40, 40), z(380, 520);
  for (int i = 0; i < 500; ++i) {
    const cv::Vec3d p(xy(rng), xy(rng), z(rng));
    const Triangulation t = triangulate(rig, rig.projectLeft(p), rig.projectRight(p));
    ASSERT_TRUE(t.ok);
    ASSERT_LT(cv::norm(t.point - p), 1e-8) << i;
    EXPECT_LT(t.reprojection_rms, 1e-8);
  }
}

// With exactly undistorted rays the midpoint is already close to the maximum-likelihood point on
// a near-symmetric rig: LM lowers the reprojection error and is no worse in 3D. (The paper
// needed LM to bring in the distortion; here the rays carry it.)
TEST(Triangulation, LevenbergMarquardtMinimizesReprojectionAndIsNoWorseIn3D) {
  const StereoRig rig = sim::paperRig();
  std::mt19937 rng(2);
  std::uniform_real_distribution<double> xy(-40, 40), z(380, 520);
  std::normal_distribution<double> noise(0.0, 0.1);
  double mid2 = 0, lm2 = 0, mid_reproj = 0, lm_reproj = 0;
  const int n = 4000;
  for (int i = 0; i < n; ++i) {
    const cv::Vec3d p(xy(rng), xy(rng), z(rng));
    const cv::Vec2d l = rig.projectLeft(p) + cv::Vec2d(noise(rng), noise(rng));
    const cv::Vec2d r = rig.projectRight(p) + cv::Vec2d(noise(rng), noise(rng));
    const cv::Vec3d m = midpoint(rig.backProjectLeft(l), rig.backProjectRight(r));
    const Triangulation t = triangulate(rig, l, r);
    ASSERT_TRUE(t.ok);
    mid2 += cv::norm(m - p) * cv::norm(m - p);
    lm2 += cv::norm(t.point - p) * cv::norm(t.point - p);
    const auto reproj = [&](const cv::Vec3d& x) {
      return cv::norm(rig.projectLeft(x) - l) + cv::norm(rig.projectRight(x) - r);
    };
    mid_reproj += reproj(m);
    lm_reproj += reproj(t.point);
  }
  std::cout << "0.1 px noise: 3D RMS error midpoint " << std::sqrt(mid2 / n) << " mm, LM "
            << std::sqrt(lm2 / n) << " mm; mean reprojection sum midpoint " << mid_reproj / n
            << " px, LM " << lm_reproj / n << " px\n";
  EXPECT_LT(lm_reproj, mid_reproj);
  EXPECT_LE(std::sqrt(lm2 / n), std::sqrt(mid2 / n) * 1.0001);
  // The physical limit the design notes give: ~0.01-0.02 mm in depth per 0.03-0.05 px; 0.1 px
  // noise on the paper's rig at 45 cm is some 0.05-0.1 mm.
  EXPECT_LT(std::sqrt(lm2 / n), 0.12);
}

TEST(Triangulation, ParallelRaysFail) {
  StereoRig rig = sim::paperRig();
  rig.r = cv::Matx33d::eye();
  // The same pixel in both cameras of a parallel rig: rays parallel, point at infinity.
  const Triangulation t =
      triangulate(rig, {rig.left.cx(), rig.left.cy()}, {rig.right.cx(), rig.right.cy()});
  EXPECT_FALSE(t.ok) << "a point at z = " << t.point[2] << " mm";
}

}  // namespace
}  // namespace pulsetrack::vision
