// The plate phantom: eqs. (4)-(5) geometry, rendered features and divots where the model
// projects them, the reference tracker's noise, and the protocols' shape (Table I, speeds).

#include "pulsetrack/sim/plate.hpp"

#include <gtest/gtest.h>

#include <iostream>
#include <opencv2/calib3d.hpp>

#include "pulsetrack/sim/paper_rig.hpp"
#include "sim/image_probe.hpp"

namespace pulsetrack::sim {
namespace {

TEST(Plate, NominalCoordinatesAreTheEquations) {
  // Eq. (4), columns in order 1..8; eq. (5), 1..6.
  const double dx[8] = {30, 15, 30, 15, -15, -30, -15, -30};
  const double dy[8] = {15, 30, -15, -30, 30, 15, -30, -15};
  for (size_t i = 0; i < 8; ++i)
    EXPECT_EQ(nominalDivots()[i], cv::Vec3d(dx[i], dy[i], 0)) << "divot " << i + 1;
  const double fx[6] = {10, 5, 0, 0, 0, 0};
  const double fy[6] = {0, 0, 10, 5, -5, -10};
  for (size_t i = 0; i < 6; ++i)
    EXPECT_EQ(nominalFeatures()[i], cv::Vec3d(fx[i], fy[i], 0)) << "feature " << i + 1;
}

TEST(Plate, FeaturesAndDivotsRenderWhereTheEquationsPutThem) {
  const vision::StereoRig rig = paperRig();
  PlateSpec spec;
  PlateScene plate(spec, 10.0, 3);
  Rasterizer raster(rig.left.imageSize(), 3);
  cv::Mat left, right;
  double worst_feature = 0.0, worst_divot = 0.0;
  int n = 0;
  for (size_t s = 0; s < 6; ++s) {
    const Pose& pose = plate.samples()[s].c_t_p;
    plate.render(rig, pose, raster, left, right);
    for (int cam = 0; cam < 2; ++cam) {
      const cv::Mat& img = cam == 0 ? left : right;
      const auto project = [&](const cv::Vec3d& p_plate) {
        const cv::Vec3d p = pose * p_plate;
        return cam == 0 ? rig.projectLeft(p) : rig.projectRight(p);
      };
      for (const cv::Vec3d& f : nominalFeatures()) {
        const cv::Vec2d proj = project(f);
        const double e = cv::norm(test::darkCentroid(img, proj, 6) - proj);
        worst_feature = std::max(worst_feature, e);
        ++n;
      }
      for (const cv::Vec3d& d : nominalDivots()) {
        const cv::Vec2d proj = project(d);
        if (proj[0] < 40 || proj[1] < 40 || proj[0] > img.cols - 41 || proj[1] > img.rows - 41)
          continue;
        worst_divot = std::max(worst_divot, cv::norm(test::darkCentroid(img, proj, 30) - proj));
      }
    }
  }
  std::cout << n << " plate features: worst " << worst_feature << " px; divots: worst "
            << worst_divot << " px from their projection\n";
  EXPECT_LT(worst_feature, 0.05);
  EXPECT_LT(worst_divot, 0.05);
}

TEST(Plate, StaticProtocolShape) {
  PlateSpec spec;
  const PlateScene plate(spec, 10.0, 5);
  ASSERT_EQ(plate.samples().size(), 50U);  // 10 registration + 4 sets x 10 (Table I)
  std::vector<double> depth(5, 0.0);
  for (const PlateSample& s : plate.samples())
    depth[static_cast<size_t>(s.set)] += s.c_t_p.t[2] / 10.0;
  for (int set = 1; set <= 4; ++set) {
    EXPECT_NEAR(depth[static_cast<size_t>(set)], spec.set_depths_mm[static_cast<size_t>(set - 1)],
                8.0);
  }
  // Every plate faces the rig within the workspace's tilt.
  for (const PlateSample& s : plate.samples()) {
    const cv::Vec3d normal = s.c_t_p.r * cv::Vec3d(0, 0, 1);
    EXPECT_LT(normal[2], -std::cos(45.0 * CV_PI / 180.0));
  }
}

TEST(Plate, DynamicProtocolSpeedsSpanTheWorkspaceLimits) {
  PlateSpec spec;
  spec.protocol = PlateProtocol::kDynamic;
  const PlateScene plate(spec, 10.0, 9);
  ASSERT_EQ(plate.samples().size(), 2000U);  // 4 sets x 10 acquisitions x 50 frames
  double vmax = 0.0, wmax = 0.0, vsum = 0.0;
  int n = 0;
  for (size_t i = 1; i < plate.samples().size(); ++i) {
    const PlateSample& a = plate.samples()[i - 1];
    const PlateSample& b = plate.samples()[i];
    if (a.acquisition != b.acquisition || a.set != b.set) continue;
    const double dt = b.t - a.t;
    const double v = cv::norm(b.c_t_p.t - a.c_t_p.t) / dt;
    cv::Vec3d rv;
    cv::Rodrigues(b.c_t_p.r * a.c_t_p.r.t(), rv);
    const double w = cv::norm(rv) / dt * 180.0 / CV_PI;
    vmax = std::max(vmax, v);
    wmax = std::max(wmax, w);
    vsum += v;
    ++n;
  }
  std::cout << "dynamic protocol: linear speed mean " << vsum / n << " mm/s, max " << vmax
            << " mm/s; angular max " << wmax << " deg/s\n";
  EXPECT_LE(vmax, 25.0 * 1.001);
  EXPECT_GE(vmax, 15.0);
  EXPECT_LE(wmax, 9.7 * 1.001);
  EXPECT_GE(wmax, 5.0);
}

TEST(Plate, TrackerNoiseOnTheDivotsIsAbout0p1mmRms) {
  PlateSpec spec;
  spec.protocol = PlateProtocol::kDynamic;
  const PlateScene plate(spec, 10.0, 21);
  double sum2 = 0.0;
  int n = 0;
  for (const PlateSample& s : plate.samples()) {
    const Pose truth_o_t_p = plate.oTc() * s.c_t_p;
    const Pose measured_o_t_p = s.o_t_m * plate.pTm().inverse();
    for (const cv::Vec3d& d : nominalDivots()) {
      const double e = cv::norm(measured_o_t_p * d - truth_o_t_p * d);
      sum2 += e * e;
      ++n;
    }
  }
  const double rms = std::sqrt(sum2 / n);
  std::cout << "reference tracker: divot RMS error " << rms << " mm\n";
  EXPECT_GT(rms, 0.09);
  EXPECT_LT(rms, 0.11);
  // The digitized divots (section 4.A) are where the plate put them, within the noise.
  const Pose first = plate.oTc() * plate.samples().front().c_t_p;
  for (size_t i = 0; i < 8; ++i) {
    EXPECT_LT(cv::norm(plate.digitizedDivots()[i] - first * nominalDivots()[i]), 0.5);
  }
}

}  // namespace
}  // namespace pulsetrack::sim
