// The planar renderer puts a point where the rig model projects it: disc centroids and
// chessboard corners rendered through the paper's optics (25 mm lens, 4.65 um pixels, real
// distortion) at 40-50 cm land within 0.05 px of CameraModel::project.

#include "pulsetrack/sim/planar_render.hpp"

#include <gtest/gtest.h>

#include <iostream>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

namespace pulsetrack::sim {
namespace {

vision::CameraModel paperCamera() {
  // f = 25 mm / 4.65 um = 5376 px; a real lens's mild barrel distortion, off-centre principal
  // point.
  const double dist[5] = {-0.18, 0.9, 0.0011, -0.0007, -2.1};
  return {cv::Matx33d(5376.3, 0, 688.4, 0, 5374.9, 505.1, 0, 0, 1), dist, 5, cv::Size(1360, 1024)};
}

// An 80 x 80 mm plate, 40 texture px per mm, white with black discs of radius 0.6 mm on a
// 10 mm grid. Plate (0,0) is the plate's centre.
constexpr double kPxPerMm = 40.0;
constexpr double kHalf = 40.0;

cv::Mat discTexture(std::vector<cv::Point2d>& centres_mm) {
  const int n = static_cast<int>(2 * kHalf * kPxPerMm);
  cv::Mat tex(n, n, CV_8UC1, cv::Scalar(230));
  for (int iy = -3; iy <= 3; ++iy) {
    for (int ix = -3; ix <= 3; ++ix) {
      const cv::Point2d c(ix * 10.0, iy * 10.0);
      centres_mm.push_back(c);
      const int shift = 8;
      const double px = (c.x + kHalf) * kPxPerMm - 0.5;
      const double py = (c.y + kHalf) * kPxPerMm - 0.5;
      cv::circle(
          tex, cv::Point(static_cast<int>(px * (1 << shift)), static_cast<int>(py * (1 << shift))),
          static_cast<int>(0.6 * kPxPerMm * (1 << shift)), cv::Scalar(20), cv::FILLED, cv::LINE_AA,
          shift);
    }
  }
  return tex;
}

cv::Matx33d textureFromPlate() {
  return {kPxPerMm, 0, kHalf * kPxPerMm - 0.5, 0, kPxPerMm, kHalf * kPxPerMm - 0.5, 0, 0, 1};
}

PlaneView pose(double rx_deg, double ry_deg, double rz_deg, const cv::Vec3d& t) {
  cv::Matx33d r;
  cv::Rodrigues(cv::Vec3d(rx_deg, ry_deg, rz_deg) * (CV_PI / 180.0), r);
  return {r, t};
}

TEST(PlanarRender, DiscCentroidsLandOnTheirProjection) {
  const vision::CameraModel cam = paperCamera();
  const CameraRays rays(cam, 3);
  std::vector<cv::Point2d> centres;
  const cv::Mat tex = discTexture(centres);
  double worst = 0.0;
  double sum2 = 0.0;
  int n = 0;
  for (const PlaneView& view : {pose(0, 0, 0, {3, -2, 400}), pose(25, -15, 30, {-8, 5, 450}),
                                pose(-35, 20, 100, {6, 4, 500})}) {
    const cv::Mat img = renderPlane(rays, view, tex, textureFromPlate(), 230.0);
    ASSERT_EQ(img.size(), cam.imageSize());
    for (const cv::Point2d& c : centres) {
      const cv::Vec3d pc = view.rotation * cv::Vec3d(c.x, c.y, 0) + view.translation;
      const cv::Vec2d proj = cam.project(pc);
      // Intensity-weighted centroid of the dark disc in a window around the projection.
      const int r = 14;
      const int x0 = static_cast<int>(std::lround(proj[0]));
      const int y0 = static_cast<int>(std::lround(proj[1]));
      if (x0 - r < 0 || y0 - r < 0 || x0 + r >= img.cols || y0 + r >= img.rows) continue;
      double sw = 0, sx = 0, sy = 0;
      for (int y = y0 - r; y <= y0 + r; ++y) {
        for (int x = x0 - r; x <= x0 + r; ++x) {
          const double w = 230.0 - img.at<uchar>(y, x);
          if (w <= 0.5) continue;
          sw += w;
          sx += w * x;
          sy += w * y;
        }
      }
      ASSERT_GT(sw, 0.0);
      const double e = std::hypot(sx / sw - proj[0], sy / sw - proj[1]);
      worst = std::max(worst, e);
      sum2 += e * e;
      ++n;
    }
  }
  ASSERT_GT(n, 100);
  std::cout << n << " rendered disc centroids: RMS " << std::sqrt(sum2 / n) << " px, max " << worst
            << " px from their projection\n";
  EXPECT_LT(worst, 0.05);
}

TEST(PlanarRender, BackgroundOutsideThePlateAndBehindTheCamera) {
  const vision::CameraModel cam = paperCamera();
  const CameraRays rays(cam, 1);
  std::vector<cv::Point2d> centres;
  const cv::Mat tex = discTexture(centres);
  // Plate far off to the side: the image is all background.
  cv::Mat img = renderPlane(rays, pose(0, 0, 0, {500, 0, 400}), tex, textureFromPlate(), 77.0);
  EXPECT_EQ(cv::countNonZero(img != 77), 0);
  // Plate behind the camera.
  img = renderPlane(rays, pose(0, 0, 0, {0, 0, -400}), tex, textureFromPlate(), 77.0);
  EXPECT_EQ(cv::countNonZero(img != 77), 0);
}

}  // namespace
}  // namespace pulsetrack::sim
