// ChArUco acceptance: board views rendered through a known stereo rig with lens distortion,
// every third view with a third of the board hidden, some turned upside down. The calibration
// recovers the focal lengths within 0.2 % with a reprojection RMS <= 0.1 px.

#include <gtest/gtest.h>

#include <iostream>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>

#include "pulsetrack/sim/planar_render.hpp"
#include "pulsetrack/vision/calibration.hpp"
#include "test_util.hpp"

namespace pulsetrack::vision {
namespace {

PatternSpec charucoSpec() {
  PatternSpec spec;
  spec.kind = PatternKind::kCharuco;
  spec.cols = 9;
  spec.rows = 7;
  spec.square = 30.0;
  spec.marker = 22.0;
  spec.dictionary = "DICT_5X5_100";
  return spec;
}

StereoRig trueRig() {
  StereoRig rig;
  const cv::Size size(1024, 768);
  const double d1[5] = {-0.24, 0.11, 0.0009, -0.0006, -0.02};
  const double d2[5] = {-0.22, 0.09, -0.0004, 0.0008, -0.01};
  rig.left = CameraModel({1510.0, 0, 515.3, 0, 1507.5, 380.2, 0, 0, 1}, d1, 5, size);
  rig.right = CameraModel({1495.0, 0, 506.8, 0, 1496.2, 389.6, 0, 0, 1}, d2, 5, size);
  cv::Matx33d r;
  cv::Rodrigues(cv::Vec3d(0.004, -0.09, 0.003), r);  // ~5 deg vergence
  rig.r = r;
  rig.t = {-80.0, 0.6, 3.0};
  return rig;
}

TEST(CalibrationTarget, CharucoTextureMatchesTheBoardCoordinates) {
  // The drawn board's texture_from_board must agree with what the detector finds in it.
  auto target = CalibrationTarget::create(charucoSpec());
  ASSERT_TRUE(target) << target.error().message;
  cv::Matx33d h;
  const cv::Mat tex = target->draw(60, 30, h);
  const Detection det = target->detect(tex);
  ASSERT_EQ(det.ids.size(), 48U);  // (9-1) x (7-1) inner corners
  for (size_t i = 0; i < det.ids.size(); ++i) {
    const cv::Point3f p = target->objectPoints()[static_cast<size_t>(det.ids[i])];
    const cv::Vec3d t = h * cv::Vec3d(p.x, p.y, 1.0);
    EXPECT_NEAR(det.corners[i].x, t[0], 0.1) << "corner " << det.ids[i];
    EXPECT_NEAR(det.corners[i].y, t[1], 0.1) << "corner " << det.ids[i];
  }
}

TEST(CharucoCalibration, RenderedViewsWithOcclusionRecoverTheRig) {
  auto target = CalibrationTarget::create(charucoSpec());
  ASSERT_TRUE(target) << target.error().message;
  cv::Matx33d texture_from_board;
  const cv::Mat board = target->draw(120, 60, texture_from_board);
  const StereoRig truth = trueRig();
  const sim::CameraRays left_rays(truth.left, 2);
  const sim::CameraRays right_rays(truth.right, 2);
  const double board_w = 9 * 30.0;
  const double board_h = 7 * 30.0;

  test::TempDir dir;
  std::mt19937 rng(2024);
  std::uniform_real_distribution<double> tilt(-35.0, 35.0);
  std::uniform_real_distribution<double> spin(-180.0, 180.0);
  std::uniform_real_distribution<double> off(-50.0, 50.0);
  std::uniform_real_distribution<double> depth(600.0, 800.0);
  std::normal_distribution<double> noise(0.0, 1.0);
  std::vector<std::pair<std::string, std::string>> pairs;
  std::vector<bool> occluded;
  const int kViews = 16;
  for (int v = 0; v < kViews; ++v) {
    cv::Matx33d r;
    const double rz = v % 4 == 3 ? spin(rng) : 0.3 * spin(rng) / 3.0;
    cv::Rodrigues(cv::Vec3d(tilt(rng), tilt(rng), rz) * (CV_PI / 180.0), r);
    // Board centre in front of the middle of the rig.
    const cv::Vec3d centre(40.0 + off(rng), off(rng), depth(rng));
    const sim::PlaneView view{r, centre - r * cv::Vec3d(board_w / 2, board_h / 2, 0)};
    cv::Mat tex = board.clone();
    const bool hide = v % 3 == 1;
    if (hide) {
      // A third of the board covered, cut along square boundaries (a sheet laid over it).
      const int third = 3 * 120;
      tex(cv::Rect(60 + (v % 2) * 6 * 120, 0, third, tex.rows)).setTo(128);
    }
    occluded.push_back(hide);
    for (int side = 0; side < 2; ++side) {
      sim::PlaneView cam_view = view;
      if (side == 1) cam_view = {truth.r * view.rotation, truth.r * view.translation + truth.t};
      cv::Mat img = sim::renderPlane(side == 0 ? left_rays : right_rays, cam_view, tex,
                                     texture_from_board, 140.0);
      cv::Mat noisy(img.size(), CV_8UC1);
      for (int i = 0; i < static_cast<int>(img.total()); ++i) {
        noisy.data[i] = cv::saturate_cast<uchar>(img.data[i] + noise(rng));
      }
      const std::string path =
          dir / ((side == 0 ? "left" : "right") + std::to_string(100 + v) + ".png");
      ASSERT_TRUE(cv::imwrite(path, noisy));
      (side == 0 ? pairs.emplace_back(path, "").first : pairs.back().second) = path;
    }
  }

  cv::Size size;
  auto views = detectViews(pairs, *target, size);
  ASSERT_TRUE(views) << views.error().message;
  auto result = calibrateStereo(*views, *target, size);
  ASSERT_TRUE(result) << result.error().message;

  const StereoRig& rig = result->rig;
  const double efx_l = std::abs(rig.left.fx() / truth.left.fx() - 1.0);
  const double efy_l = std::abs(rig.left.fy() / truth.left.fy() - 1.0);
  const double efx_r = std::abs(rig.right.fx() / truth.right.fx() - 1.0);
  const double efy_r = std::abs(rig.right.fy() / truth.right.fy() - 1.0);
  const double ebase = std::abs(rig.baseline() / truth.baseline() - 1.0);
  std::cout << result->views_used << "/" << kViews << " views, stereo RMS " << result->stereo_rms
            << " px, mono " << result->left_rms << " / " << result->right_rms
            << " px, focal errors (%) " << 100 * efx_l << " " << 100 * efy_l << " " << 100 * efx_r
            << " " << 100 * efy_r << ", baseline error " << 100 * ebase << " %, epipolar "
            << result->epipolar_mean_px << " px\n";
  EXPECT_LE(result->stereo_rms, 0.1);
  EXPECT_LE(result->left_rms, 0.1);
  EXPECT_LE(result->right_rms, 0.1);
  EXPECT_LT(efx_l, 0.002);
  EXPECT_LT(efy_l, 0.002);
  EXPECT_LT(efx_r, 0.002);
  EXPECT_LT(efy_r, 0.002);
  EXPECT_LT(ebase, 0.005);
  // The occluded views were detected partially and still used.
  int partial_used = 0;
  for (int v = 0; v < kViews; ++v) {
    const ViewReport& rep = result->views[static_cast<size_t>(v)];
    if (occluded[static_cast<size_t>(v)] && rep.used && rep.common_corners < 48) ++partial_used;
  }
  EXPECT_GE(partial_used, 4);
}

}  // namespace
}  // namespace pulsetrack::vision
