// Interlaced frames split into their fields (vision/fields.hpp): each field a full-height image
// at its own instant, its own rows untouched, the other field's rows interpolated in place.

#include "pulsetrack/vision/fields.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/core.hpp>

namespace pulsetrack::vision {
namespace {

// A smooth pattern (periods of 16-23 px, as blurred tissue), moved by (dx, dy) px.
cv::Mat pattern(double dx, double dy) {
  cv::Mat m(96, 128, CV_8UC1);
  for (int y = 0; y < m.rows; ++y) {
    for (int x = 0; x < m.cols; ++x) {
      const double u = x - dx, v = y - dy;
      m.at<uint8_t>(y, x) = cv::saturate_cast<uint8_t>(
          128.0 + 50.0 * std::sin(u * 0.39 + v * 0.11) + 40.0 * std::cos(v * 0.29 - u * 0.07));
    }
  }
  return m;
}

TEST(Fields, EachFieldBecomesAFullHeightImageOfItsOwnInstant) {
  // The top field at t, the bottom field 3 px of horizontal motion later.
  const cv::Mat early = pattern(0.0, 0.0), late = pattern(3.0, 0.0);
  cv::Mat frame = early.clone();
  for (int y = 1; y < frame.rows; y += 2) late.row(y).copyTo(frame.row(y));
  cv::Mat first, second;
  splitFields(frame, FieldOrder::kTopFirst, first, second);
  ASSERT_EQ(first.size(), frame.size());
  ASSERT_EQ(second.size(), frame.size());
  const cv::Rect inner(0, 4, frame.cols, frame.rows - 8);  // the clamped border rows aside
  double own = 0.0;
  for (int y = 0; y < frame.rows; y += 2) own += cv::norm(first.row(y), early.row(y), cv::NORM_L1);
  for (int y = 1; y < frame.rows; y += 2) own += cv::norm(second.row(y), late.row(y), cv::NORM_L1);
  EXPECT_EQ(own, 0.0);  // a field's own rows are kept as they are
  // The interpolated rows: within 2 grey levels of the instant's image on this pattern, while
  // the woven frame is tens of levels off the later instant in its even rows.
  EXPECT_LE(cv::norm(first(inner), early(inner), cv::NORM_INF), 2.0);
  EXPECT_LE(cv::norm(second(inner), late(inner), cv::NORM_INF), 2.0);
  EXPECT_GE(cv::norm(frame(inner), late(inner), cv::NORM_INF), 20.0);
  // Bottom field first: the same images, the other way round.
  cv::Mat b_first, b_second;
  splitFields(frame, FieldOrder::kBottomFirst, b_first, b_second);
  EXPECT_EQ(cv::norm(b_first, second, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(b_second, first, cv::NORM_INF), 0.0);
  // The next frame re-uses the buffers (no allocation per frame).
  const uint8_t* data = first.data;
  splitFields(frame, FieldOrder::kTopFirst, first, second);
  EXPECT_EQ(first.data, data);
}

TEST(Fields, TheFieldsOwnRowsKeepTheirPlace) {
  // A vertical ramp (2 grey levels a row): each interpolated row lands on the ramp where its row
  // is, not half a row off (as a field scaled to full height would), in either field.
  cv::Mat frame(80, 16, CV_8UC1);
  for (int y = 0; y < frame.rows; ++y) frame.row(y).setTo(40 + 2 * y);
  cv::Mat top, bottom;
  splitFields(frame, FieldOrder::kTopFirst, top, bottom);
  const cv::Rect inner(0, 4, frame.cols, frame.rows - 8);
  EXPECT_EQ(cv::norm(top(inner), frame(inner), cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(bottom(inner), frame(inner), cv::NORM_INF), 0.0);
}

}  // namespace
}  // namespace pulsetrack::vision
