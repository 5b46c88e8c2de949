// The calibration figure: per-view reprojection error bars on top, corner coverage of each
// camera's image below. Drawn with OpenCV so the tool needs nothing else.

#include <fmt/format.h>

#include <algorithm>
#include <opencv2/imgproc.hpp>

#include "pulsetrack/vision/calibration.hpp"

namespace pulsetrack::vision {

namespace {

const cv::Scalar kInk(30, 30, 30);
const cv::Scalar kGrid(215, 215, 215);
const cv::Scalar kLeft(180, 110, 30);   // blue-ish (BGR)
const cv::Scalar kRight(40, 140, 240);  // orange
const cv::Scalar kReject(40, 40, 200);  // red

void text(cv::Mat& img, const std::string& s, cv::Point at, double scale = 0.5,
          const cv::Scalar& colour = kInk, int thickness = 1) {
  cv::putText(img, s, at, cv::FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv::LINE_AA);
}

cv::Scalar viewColour(size_t i, size_t n) {
  const double hue = 170.0 * static_cast<double>(i) / static_cast<double>(std::max<size_t>(n, 1));
  cv::Mat hsv(1, 1, CV_8UC3, cv::Scalar(hue, 220, 210));
  cv::Mat bgr;
  cv::cvtColor(hsv, bgr, cv::COLOR_HSV2BGR);
  const cv::Vec3b c = bgr.at<cv::Vec3b>(0, 0);
  return {static_cast<double>(c[0]), static_cast<double>(c[1]), static_cast<double>(c[2])};
}

}  // namespace

cv::Mat renderCalibrationReport(const CalibrationResult& result,
                                const std::vector<ViewInput>& views, cv::Size image_size) {
  const int width = 1400;
  const int chart_h = 420;
  const int panel_w = (width - 60) / 2;
  const int panel_h = static_cast<int>(panel_w * static_cast<double>(image_size.height) /
                                       std::max(image_size.width, 1));
  const int height = 70 + chart_h + 60 + panel_h + 40;
  cv::Mat img(height, width, CV_8UC3, cv::Scalar(255, 255, 255));

  text(img,
       fmt::format("Stereo calibration: {} of {} views used | RMS left {:.3f} px, right {:.3f} px, "
                   "stereo {:.3f} px | epipolar {:.3f} px | baseline {:.3f}",
                   result.views_used, result.views.size(), result.left_rms, result.right_rms,
                   result.stereo_rms, result.epipolar_mean_px, result.rig.baseline()),
       {20, 30}, 0.6, kInk, 1);

  // Per-view error chart.
  const cv::Rect chart(70, 60, width - 100, chart_h - 60);
  double vmax = 0.0;
  for (const ViewReport& v : result.views) vmax = std::max({vmax, v.left_rms, v.right_rms});
  vmax = vmax > 0 ? vmax * 1.15 : 1.0;
  for (int k = 0; k <= 5; ++k) {
    const int y = chart.y + chart.height - k * chart.height / 5;
    cv::line(img, {chart.x, y}, {chart.x + chart.width, y}, kGrid, 1);
    text(img, fmt::format("{:.2f}", vmax * k / 5), {chart.x - 55, y + 5}, 0.45);
  }
  text(img, "reprojection RMS per view (px)", {chart.x, chart.y - 10}, 0.5);
  const size_t n = result.views.size();
  const double slot =
      static_cast<double>(chart.width) / static_cast<double>(std::max<size_t>(n, 1));
  for (size_t i = 0; i < n; ++i) {
    const ViewReport& v = result.views[i];
    const int x0 = chart.x + static_cast<int>(slot * static_cast<double>(i) + slot * 0.15);
    const int bw = std::max(2, static_cast<int>(slot * 0.33));
    const auto bar = [&](double value, int x, const cv::Scalar& c) {
      if (value < 0) return;
      const int h = static_cast<int>(chart.height * value / vmax);
      cv::rectangle(img, cv::Rect(x, chart.y + chart.height - h, bw, h), c, cv::FILLED);
    };
    bar(v.left_rms, x0, kLeft);
    bar(v.right_rms, x0 + bw, kRight);
    text(img, std::to_string(i + 1), {x0, chart.y + chart.height + 18}, 0.45,
         v.used ? kInk : kReject);
    if (!v.used) {
      text(img, "x", {x0 + bw / 2, chart.y + chart.height - 6}, 0.7, kReject, 2);
    }
  }
  const int ly = chart.y + chart.height + 40;
  cv::rectangle(img, cv::Rect(chart.x, ly - 10, 12, 12), kLeft, cv::FILLED);
  text(img, "left", {chart.x + 18, ly}, 0.45);
  cv::rectangle(img, cv::Rect(chart.x + 80, ly - 10, 12, 12), kRight, cv::FILLED);
  text(img, "right", {chart.x + 98, ly}, 0.45);
  text(img, "x / red number: view rejected (see the summary for why)", {chart.x + 170, ly}, 0.45,
       kReject);

  // Coverage panels.
  const int py = 70 + chart_h + 40;
  for (int side = 0; side < 2; ++side) {
    const cv::Rect panel(20 + side * (panel_w + 20), py, panel_w, panel_h);
    cv::rectangle(img, panel, cv::Scalar(245, 245, 245), cv::FILLED);
    cv::rectangle(img, panel, kInk, 1);
    text(img,
         side == 0 ? "left image: corners of every view" : "right image: corners of every view",
         {panel.x, panel.y - 8}, 0.5);
    const double sx = static_cast<double>(panel.width) / image_size.width;
    const double sy = static_cast<double>(panel.height) / image_size.height;
    for (size_t i = 0; i < views.size() && i < n; ++i) {
      const Detection& d = side == 0 ? views[i].left : views[i].right;
      const cv::Scalar c = result.views[i].used ? viewColour(i, n) : cv::Scalar(170, 170, 170);
      for (const cv::Point2f& p : d.corners) {
        cv::circle(
            img,
            cv::Point(panel.x + static_cast<int>(p.x * sx), panel.y + static_cast<int>(p.y * sy)),
            2, c, cv::FILLED, cv::LINE_AA);
      }
    }
  }
  return img;
}

}  // namespace pulsetrack::vision
