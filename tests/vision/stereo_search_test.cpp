// The right ROI from a left ROI alone (findStereoRange), on a real in-vivo pair (the Hamlyn
// beating heart, rectified, 360x288), and a named error where nothing can be matched (the
// real endoscope's side-by-side video: tests/tools/real_video_cli_test.cpp).

#include "pulsetrack/vision/stereo_search.hpp"

#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "hamlyn.hpp"
#include "pulsetrack/vision/tracking_session.hpp"
#include "test_util.hpp"

namespace pulsetrack::vision {
namespace {

using StereoSearchOnTheHeart = hamlyn::PairOne;

TEST_F(StereoSearchOnTheHeart, FindsTheBeatingHeartInTheRightView) {
  const StereoRig* rig = &pair_.rig;
  const cv::Mat& left = pair_.left;
  const cv::Mat& right = pair_.right;
  const cv::Rect roi = hamlyn::kRoi;
  auto found = findStereoRange(*rig, left, right, roi);
  ASSERT_TRUE(found) << found.error().message;
  std::cerr << "hamlyn pair 1: " << found->summary() << "\n";
  // Plain OpenCV NCC on this ROI (the figures): disparity 74-102 px, rows off by 0 or
  // +1 px; well over half the textured patches match.
  EXPECT_GE(found->matched, 50);
  EXPECT_GE(found->disparity_lo_px, 70.0);
  EXPECT_LE(found->disparity_hi_px, 105.0);
  EXPECT_GE(found->vertical_px, 0.0);
  EXPECT_LE(found->vertical_px, 1.0);
  // Z = f B / d with the assumed rig: 579 px x 5.5 mm over 74-102 px.
  EXPECT_GT(found->depth_mm, 579.05693 * 5.507 / 102.0);
  EXPECT_LT(found->depth_mm, 579.05693 * 5.507 / 74.0);
  // The right ROI is the left one shifted by the disparity, same rows.
  EXPECT_NEAR(found->right.y, roi.y, 2);
  EXPECT_NEAR(roi.x - found->right.x, 0.5 * (found->disparity_lo_px + found->disparity_hi_px), 12);
  EXPECT_GT(found->tolerance_mm, found->depth_hi_mm - found->depth_mm);
  EXPECT_NE(found->summary().find("disparity"), std::string::npos);

  // The same pair searched over a depth range the heart is not in: a named error.
  StereoSearchConfig far;
  far.near_mm = 200.0;
  far.far_mm = 1000.0;
  auto none = findStereoRange(*rig, left, right, roi, far);
  ASSERT_FALSE(none);
  EXPECT_NE(none.error().message.find("left ROI 120,60,200,180: nothing matchable"),
            std::string::npos)
      << none.error().message;
  EXPECT_NE(none.error().message.find("within 200-1000 mm"), std::string::npos)
      << none.error().message;
}

// No ROI at all (issue 32): the largest well-textured region free of highlights, narrowed to
// what the right camera sees too.
TEST_F(StereoSearchOnTheHeart, FindsTheHeartWithoutAnRoi) {
  auto region = findTissueRegion(pair_.left, 2 * kAffineSide);
  ASSERT_TRUE(region) << region.error().message;
  std::cerr << "hamlyn pair 1: " << region->summary() << "\n";
  const cv::Rect image(0, 0, pair_.left.cols, pair_.left.rows);
  EXPECT_EQ(region->found & image, region->found);
  EXPECT_EQ(region->roi, region->found);  // not narrowed yet
  EXPECT_GE(region->found.area(), image.area() * 4 / 10);
  // The heart the ROI was drawn over is (mostly) in it.
  EXPECT_GE((region->found & hamlyn::kRoi).area(), hamlyn::kRoi.area() * 7 / 10);
  EXPECT_NE(region->summary().find("found: the best well-textured region"), std::string::npos);

  auto found = findStereoRoi(pair_.rig, pair_.left, pair_.right, cv::Rect(), 2 * kAffineSide);
  ASSERT_TRUE(found) << found.error().message;
  std::cerr << "hamlyn pair 1: " << found->summary() << "\n";
  ASSERT_TRUE(found->region.has_value());
  const TissueRegion narrowed = found->region.value_or(TissueRegion{});
  EXPECT_EQ(found->left, narrowed.roi);
  // Narrowed: the found region's left strip is not in the right view (disparity ~84 px): the
  // left ROI lost it, and its outline in the right view (at the median depth) now starts within
  // a pixel of the right image's edge.
  EXPECT_EQ(narrowed.found & found->left, found->left);
  EXPECT_GT(found->left.x, narrowed.found.x + 40);
  EXPECT_GE(found->right_outline.x, -1.0) << found->summary();
  EXPECT_LE(found->right_outline.x, 8.0) << found->summary();
  EXPECT_GE(found->disparity_lo_px, 70.0);
  EXPECT_LE(found->disparity_hi_px, 105.0);
  EXPECT_NE(found->summary().find("narrowed to "), std::string::npos);
  // A given ROI is used as given.
  auto given = findStereoRoi(pair_.rig, pair_.left, pair_.right, hamlyn::kRoi, 2 * kAffineSide);
  ASSERT_TRUE(given);
  EXPECT_EQ(given->left, hamlyn::kRoi);
  EXPECT_FALSE(given->region.has_value());
}

TEST(StereoSearch, WithoutAnRoiAFlatOrDarkImageSaysWhy) {
  auto rig = parseRectified("579,180,144,5.5", {360, 288});
  ASSERT_TRUE(rig);
  cv::Mat flat(288, 360, CV_8UC1, cv::Scalar(90));
  auto found = findStereoRoi(*rig, flat, flat, cv::Rect(), 30);
  ASSERT_FALSE(found);
  EXPECT_NE(found.error().message.find("no well-textured region of at least 30x30 px"),
            std::string::npos)
      << found.error().message;
  EXPECT_NE(found.error().message.find("of 396 cells of 16 px, 396 are flat"), std::string::npos)
      << found.error().message;
  cv::Mat dark(288, 360, CV_8UC1, cv::Scalar(5));
  found = findStereoRoi(*rig, dark, dark, cv::Rect(), 30);
  ASSERT_FALSE(found);
  EXPECT_NE(found.error().message.find("396 dark"), std::string::npos) << found.error().message;
  // A right ROI needs a left one.
  EXPECT_FALSE(TrackingSession::checkRoi(*rig, {cv::Rect(), cv::Rect(10, 10, 50, 50)}, 10.0));
  EXPECT_TRUE(TrackingSession::checkRoi(*rig, {cv::Rect(), cv::Rect()}, 10.0));
}

TEST(StereoSearch, AFlatOrGlaringRoiSaysWhy) {
  auto rig = parseRectified("579,180,144,5.5", {360, 288});
  ASSERT_TRUE(rig);
  cv::Mat flat(288, 360, CV_8UC1, cv::Scalar(90));
  auto found = findStereoRange(*rig, flat, flat, cv::Rect(100, 60, 200, 180));
  ASSERT_FALSE(found);
  EXPECT_NE(found.error().message.find("are flat (no texture)"), std::string::npos)
      << found.error().message;
  cv::Mat glare(288, 360, CV_8UC1, cv::Scalar(255));
  found = findStereoRange(*rig, glare, glare, cv::Rect(100, 60, 200, 180));
  ASSERT_FALSE(found);
  EXPECT_NE(found.error().message.find("100 on highlights"), std::string::npos)
      << found.error().message;
  EXPECT_FALSE(findStereoRange(*rig, flat, flat, cv::Rect(300, 60, 200, 180)));
  EXPECT_FALSE(parseDepthRange("50"));
  EXPECT_FALSE(parseDepthRange("100,50"));
  EXPECT_FALSE(parseDepthRange("0,50"));
  auto range = parseDepthRange("30,400");
  ASSERT_TRUE(range);
  EXPECT_EQ(range->near_mm, 30.0);
  EXPECT_EQ(range->far_mm, 400.0);
}

}  // namespace
}  // namespace pulsetrack::vision
