#pragma once
// Where a dark blob is in a rendered (CV_32FC1) image: its darkness-weighted centroid in a
// (2r+1)^2 window around `at`, against a plane fitted to the window's border (the shading
// varies across the window). The probe the rendering-accuracy tests use.

#include <cmath>
#include <opencv2/core.hpp>

namespace pulsetrack::test {

inline cv::Vec2d darkCentroid(const cv::Mat& img, const cv::Vec2d& at, int r) {
  const int x0 = static_cast<int>(std::lround(at[0]));
  const int y0 = static_cast<int>(std::lround(at[1]));
  cv::Mat a(0, 3, CV_64FC1), b(0, 1, CV_64FC1);
  for (int k = -r; k <= r; ++k) {
    for (const cv::Point q : {cv::Point(x0 + k, y0 - r), cv::Point(x0 + k, y0 + r),
                              cv::Point(x0 - r, y0 + k), cv::Point(x0 + r, y0 + k)}) {
      const double row[3] = {1.0, static_cast<double>(q.x - x0), static_cast<double>(q.y - y0)};
      a.push_back(cv::Mat(1, 3, CV_64FC1, const_cast<double*>(row)));
      b.push_back(static_cast<double>(img.at<float>(q)));
    }
  }
  cv::Mat plane;
  cv::solve(a, b, plane, cv::DECOMP_SVD);
  double sw = 0, sx = 0, sy = 0;
  for (int y = y0 - r + 1; y < y0 + r; ++y) {
    for (int x = x0 - r + 1; x < x0 + r; ++x) {
      const double bg =
          plane.at<double>(0) + plane.at<double>(1) * (x - x0) + plane.at<double>(2) * (y - y0);
      const double w = std::max(0.0, bg - img.at<float>(y, x) - 1.0);
      sw += w;
      sx += w * x;
      sy += w * y;
    }
  }
  if (sw <= 0.0) return {std::nan(""), std::nan("")};
  return {sx / sw, sy / sw};
}

}  // namespace pulsetrack::test
