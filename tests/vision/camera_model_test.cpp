// CameraModel and StereoRig geometry against OpenCV's own functions (cv::projectPoints,
// cv::undistortPoints), to 1e-9 relative.

#include "pulsetrack/vision/camera_model.hpp"

#include <gtest/gtest.h>

#include <opencv2/calib3d.hpp>
#include <random>

#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::vision {
namespace {

struct Lens {
  const char* name;
  std::vector<double> dist;
};

// A 25 mm lens on a 1360x1024 sensor (the paper's rig), with distortions from mild to strong.
const cv::Matx33d kK(5376.3, 0, 680.2, 0, 5371.8, 511.7, 0, 0, 1);
const cv::Size kSize(1360, 1024);
const std::vector<Lens> kLenses = {
    {"none", {0, 0, 0, 0, 0}},
    {"four", {-0.21, 0.35, 0.0012, -0.0008}},
    {"five", {-0.21, 0.35, 0.0012, -0.0008, -0.9}},
    {"rational", {-0.3, 0.1, 0.001, -0.002, 0.05, 0.02, -0.01, 0.03}},
    {"strong", {-0.45, 0.25, 0.002, 0.001, -0.08}},
};

CameraModel makeCamera(const Lens& lens, const cv::Matx33d& k = kK) {
  return {k, lens.dist.data(), static_cast<int>(lens.dist.size()), kSize};
}

double relErr(double a, double b) { return std::abs(a - b) / std::max(1.0, std::abs(b)); }

TEST(CameraModel, ProjectMatchesProjectPoints) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> xy(-0.12, 0.12);
  std::uniform_real_distribution<double> z(0.3, 0.9);
  for (const Lens& lens : kLenses) {
    // A wide-angle camera too, so the distortion terms are exercised far from the axis.
    for (const cv::Matx33d& k : {kK, cv::Matx33d(600, 0, 320, 0, 610, 240, 0, 0, 1)}) {
      const CameraModel cam = makeCamera(lens, k);
      std::vector<cv::Point3d> pts;
      for (int i = 0; i < 500; ++i) {
        const double zz = z(rng);
        pts.emplace_back(xy(rng) * zz * 3, xy(rng) * zz * 3, zz);
      }
      std::vector<cv::Point2d> ref;
      cv::projectPoints(pts, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), cv::Mat(k), lens.dist, ref);
      for (size_t i = 0; i < pts.size(); ++i) {
        const cv::Vec2d p = cam.project(cv::Vec3d(pts[i].x, pts[i].y, pts[i].z));
        ASSERT_LT(relErr(p[0], ref[i].x), 1e-9) << lens.name << " point " << i;
        ASSERT_LT(relErr(p[1], ref[i].y), 1e-9) << lens.name << " point " << i;
      }
    }
  }
}

TEST(CameraModel, PointBehindCameraProjectsToNaN) {
  const CameraModel cam = makeCamera(kLenses[2]);
  EXPECT_TRUE(std::isnan(cam.project({0.01, 0.0, -0.5})[0]));
  EXPECT_TRUE(std::isnan(cam.project({0.01, 0.0, 0.0})[1]));
}

TEST(CameraModel, DistortionJacobianMatchesFiniteDifferences) {
  const CameraModel cam = makeCamera(kLenses[3]);
  const double h = 1e-7;
  for (const cv::Vec2d& xy : {cv::Vec2d(0.1, -0.2), cv::Vec2d(-0.3, 0.25), cv::Vec2d(0.0, 0.0)}) {
    cv::Matx22d j;
    (void)cam.distortNormalized(xy, j);
    for (int c = 0; c < 2; ++c) {
      cv::Vec2d d(0, 0);
      d[c] = h;
      const cv::Vec2d fd =
          (cam.distortNormalized(xy + d) - cam.distortNormalized(xy - d)) / (2 * h);
      EXPECT_NEAR(j(0, c), fd[0], 1e-7);
      EXPECT_NEAR(j(1, c), fd[1], 1e-7);
    }
  }
}

TEST(CameraModel, UndistortMatchesUndistortPointsConverged) {
  // cv::undistortPoints with a converged criterion (its default stops after 5 fixed-point
  // iterations, which is not the model's exact inverse).
  const cv::TermCriteria tight(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 1000, 1e-15);
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(0, kSize.width - 1);
  std::uniform_real_distribution<double> v(0, kSize.height - 1);
  for (const Lens& lens : kLenses) {
    const CameraModel cam = makeCamera(lens);
    std::vector<cv::Point2d> px;
    px.reserve(502);
    for (int i = 0; i < 500; ++i) px.emplace_back(u(rng), v(rng));
    px.emplace_back(0, 0);
    px.emplace_back(kSize.width - 1, kSize.height - 1);
    std::vector<cv::Point2d> ref_norm;
    std::vector<cv::Point2d> ref_px;
    cv::undistortPoints(px, ref_norm, cv::Mat(kK), lens.dist, cv::noArray(), cv::noArray(), tight);
    cv::undistortPoints(px, ref_px, cv::Mat(kK), lens.dist, cv::noArray(), cv::Mat(kK), tight);
    for (size_t i = 0; i < px.size(); ++i) {
      const cv::Vec2d n = cam.undistortToNormalized({px[i].x, px[i].y});
      const cv::Vec2d p = cam.undistortPixel({px[i].x, px[i].y});
      ASSERT_LT(relErr(n[0], ref_norm[i].x), 1e-9) << lens.name << " " << i;
      ASSERT_LT(relErr(n[1], ref_norm[i].y), 1e-9) << lens.name << " " << i;
      ASSERT_LT(relErr(p[0], ref_px[i].x), 1e-9) << lens.name << " " << i;
      ASSERT_LT(relErr(p[1], ref_px[i].y), 1e-9) << lens.name << " " << i;
      // And it is the exact inverse of projection.
      const cv::Vec2d back = cam.project(cv::Vec3d(n[0], n[1], 1.0));
      ASSERT_NEAR(back[0], px[i].x, 1e-8);
      ASSERT_NEAR(back[1], px[i].y, 1e-8);
    }
  }
}

TEST(CameraModel, BackProjectedRayIsUnitAndHitsThePoint) {
  const CameraModel cam = makeCamera(kLenses[2]);
  const cv::Vec3d point(12.5, -8.25, 450.0);
  const Ray ray = cam.backProject(cam.project(point));
  EXPECT_NEAR(cv::norm(ray.direction), 1.0, 1e-15);
  const cv::Vec3d on_ray = ray.origin + cv::norm(point) * ray.direction;
  EXPECT_LT(cv::norm(on_ray - point), 1e-8);
}

StereoRig makeRig() {
  StereoRig rig;
  rig.left = makeCamera(kLenses[2]);
  rig.right = makeCamera(kLenses[4]);
  cv::Matx33d r;
  cv::Rodrigues(cv::Vec3d(0.01, -0.14, 0.005), r);  // ~8 deg vergence
  rig.r = r;
  rig.t = cv::Vec3d(-60.0, 0.4, 4.5);
  rig.rms = 0.2;
  return rig;
}

TEST(StereoRig, RaysOfBothCamerasMeetAtThePointAndMidpointRecoversIt) {
  const StereoRig rig = makeRig();
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> xy(-30, 30);
  std::uniform_real_distribution<double> z(400, 500);
  for (int i = 0; i < 200; ++i) {
    const cv::Vec3d p(xy(rng), xy(rng), z(rng));
    const Ray l = rig.backProjectLeft(rig.projectLeft(p));
    const Ray r = rig.backProjectRight(rig.projectRight(p));
    EXPECT_LT(cv::norm(r.origin - rig.rightCentre()), 1e-12);
    const cv::Vec3d x = midpoint(l, r);
    ASSERT_LT(cv::norm(x - p), 1e-7) << i;
    const cv::Vec2d e = rig.epipolarDistances(rig.projectLeft(p), rig.projectRight(p));
    EXPECT_LT(e[0], 1e-7);
    EXPECT_LT(e[1], 1e-7);
  }
}

TEST(StereoRig, MidpointOfSkewRaysIsHalfWay) {
  // Two rays 2 units apart along z, crossing at right angles in projection.
  const Ray a{{0, 0, 0}, {1, 0, 0}};
  const Ray b{{0, 0, 2}, {0, 1, 0}};
  const cv::Vec3d x = midpoint(a, b);
  EXPECT_NEAR(x[0], 0.0, 1e-12);
  EXPECT_NEAR(x[1], 0.0, 1e-12);
  EXPECT_NEAR(x[2], 1.0, 1e-12);
  const cv::Vec3d parallel = midpoint(a, Ray{{0, 1, 0}, {1, 0, 0}});
  EXPECT_TRUE(std::isnan(parallel[0]));
}

TEST(StereoRig, EpipolarDistanceMeasuresAVerticalOffset) {
  StereoRig rig;
  const double d[5] = {0, 0, 0, 0, 0};
  rig.left = CameraModel(kK, d, 5, kSize);
  rig.right = rig.left;
  rig.t = cv::Vec3d(-60, 0, 0);  // rectified: epipolar lines are image rows
  const cv::Vec3d p(5, 3, 450);
  cv::Vec2d r = rig.projectRight(p);
  r[1] += 0.75;
  const cv::Vec2d e = rig.epipolarDistances(rig.projectLeft(p), r);
  EXPECT_NEAR(e[0], 0.75, 1e-9);
  EXPECT_NEAR(e[1], 0.75, 1e-9);
  // Signed: below the row and above it differ in sign, the same for a neighbouring pixel.
  const double below = rig.epipolarOffset(rig.projectLeft(p), r);
  EXPECT_NEAR(std::abs(below), 0.75, 1e-9);
  r[1] -= 1.5;
  EXPECT_NEAR(rig.epipolarOffset(rig.projectLeft(p), r), -below, 1e-9);
  const cv::Vec3d q(9, -4, 455);
  EXPECT_NEAR(rig.epipolarOffset(rig.projectLeft(q), rig.projectRight(q) + cv::Vec2d(0.3, 0.75)),
              below, 1e-9);
}

}  // namespace
}  // namespace pulsetrack::vision
