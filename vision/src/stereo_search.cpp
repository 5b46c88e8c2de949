#include "pulsetrack/vision/stereo_search.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "pulsetrack/vision/triangulation.hpp"

namespace pulsetrack::vision {

namespace {

double percentile(std::vector<double> v, double p) {
  std::sort(v.begin(), v.end());
  const auto k = static_cast<size_t>(std::lround(p * static_cast<double>(v.size() - 1)));
  return v[std::min(k, v.size() - 1)];
}

// The vertex of a parabola through three scores, as an offset from the middle one.
double parabolaPeak(float a, float b, float c) {
  const double den = double(a) - 2.0 * b + c;
  return den < 0.0 ? std::clamp(0.5 * (double(a) - c) / den, -0.5, 0.5) : 0.0;
}

std::string roiText(const cv::Rect& r) {
  return fmt::format("{},{},{},{}", r.x, r.y, r.width, r.height);
}

}  // namespace

std::string StereoRange::summary() const {
  std::string s = fmt::format(
      "disparity {:.0f} to {:.0f} px, depth {:.1f} to {:.1f} mm (median {:.1f} mm; {} of {} "
      "patches "
      "matched, {} flat, {} on highlights); right ROI {}, depth tolerance {:.1f} mm",
      disparity_lo_px, disparity_hi_px, depth_lo_mm, depth_hi_mm, depth_mm, matched, patches, flat,
      highlights, roiText(right), tolerance_mm);
  if (std::abs(vertical_px) >= 0.5) {
    s += fmt::format(
        "; the rig's epipolar lines are off by {:+.1f} px on these images (spread {:.1f} px): "
        "recalibrate for better depth",
        vertical_px, vertical_spread_px);
  }
  return s;
}

Result<StereoSearchConfig> parseDepthRange(const std::string& text) {
  StereoSearchConfig c;
  const size_t comma = text.find(',');
  char* end = nullptr;
  const std::string a = text.substr(0, comma);
  const std::string b = comma == std::string::npos ? std::string() : text.substr(comma + 1);
  c.near_mm = std::strtod(a.c_str(), &end);
  const bool a_ok = !a.empty() && end == a.c_str() + a.size();
  c.far_mm = std::strtod(b.c_str(), &end);
  const bool b_ok = !b.empty() && end == b.c_str() + b.size();
  if (!a_ok || !b_ok || !(c.near_mm > 0.0) || !(c.far_mm > c.near_mm) || !std::isfinite(c.far_mm)) {
    return fail(fmt::format(
        "--depth-range {}: expected near,far in mm with 0 < near < far (e.g. 20,1000)", text));
  }
  return c;
}

Result<StereoRange> findStereoRange(const StereoRig& rig, const cv::Mat& left, const cv::Mat& right,
                                    const cv::Rect& roi, const StereoSearchConfig& config) {
  const cv::Size size = rig.left.imageSize();
  for (const cv::Mat* img : {&left, &right}) {
    if (img->type() != CV_8UC1 || img->size() != size) {
      return fail(
          fmt::format("stereo search: images must be {}x{} 8-bit grey (the rig's), got {}x{}",
                      size.width, size.height, img->cols, img->rows));
    }
  }
  const cv::Rect frame(0, 0, size.width, size.height);
  if (roi.width <= 0 || roi.height <= 0 || (roi & frame) != roi) {
    return fail(fmt::format("left ROI {}: not inside the {}x{} image", roiText(roi), size.width,
                            size.height));
  }
  if (!(config.near_mm > 0.0) || !(config.far_mm > config.near_mm))
    return fail("stereo search: the depth range must be 0 < near < far (mm)");
  // The patch follows the image's scale: 17x17 px at 360x288, 33x33 at 1280x1024 and up.
  const int half =
      std::clamp(static_cast<int>(std::lround(std::min(size.width, size.height) / 36.0)), 7, 16);
  const int side = 2 * half + 1;
  if (roi.width < side || roi.height < side) {
    return fail(fmt::format("left ROI {}: smaller than the {}x{} px patches searched", roiText(roi),
                            side, side));
  }
  const int nx = std::clamp(roi.width / side, 1, config.grid);
  const int ny = std::clamp(roi.height / side, 1, config.grid);
  const int band = static_cast<int>(std::ceil(config.band_px));
  constexpr int kDepthSamples = 128;

  StereoRange out;
  std::vector<double> depth, disparity, vertical;
  std::vector<cv::Point> curve;
  cv::Mat scores, mask;
  int unmatched = 0, outside = 0;
  for (int gy = 0; gy < ny; ++gy) {
    for (int gx = 0; gx < nx; ++gx) {
      const cv::Point p(roi.x + half + (roi.width - side) * (2 * gx + 1) / (2 * nx),
                        roi.y + half + (roi.height - side) * (2 * gy + 1) / (2 * ny));
      ++out.patches;
      const cv::Mat patch = left(cv::Rect(p.x - half, p.y - half, side, side));
      cv::Scalar mean, sd;
      cv::meanStdDev(patch, mean, sd);
      double lo = 0, hi = 0;
      cv::minMaxLoc(patch, &lo, &hi);
      if (hi >= config.highlight) {
        ++out.highlights;
        continue;
      }
      if (sd[0] < config.min_texture) {
        ++out.flat;
        continue;
      }
      // The epipolar curve from the near to the far depth (log-spaced: even in disparity).
      const Ray ray = rig.backProjectLeft(cv::Vec2d(p.x, p.y));
      curve.clear();
      if (ray.direction[2] > 0.0) {
        for (int k = 0; k < kDepthSamples; ++k) {
          const double z = config.near_mm *
                           std::pow(config.far_mm / config.near_mm, k / double(kDepthSamples - 1));
          const double s = (z - ray.origin[2]) / ray.direction[2];
          const cv::Vec2d q = rig.projectRight(ray.origin + s * ray.direction);
          if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || std::abs(q[0]) > 4.0 * size.width ||
              std::abs(q[1]) > 4.0 * size.height)
            continue;
          curve.emplace_back(static_cast<int>(std::lround(q[0])),
                             static_cast<int>(std::lround(q[1])));
        }
      }
      cv::Rect box;
      if (!curve.empty()) {
        const int m = half + band;
        const cv::Rect hull = cv::boundingRect(curve);
        box = cv::Rect(hull.x - m, hull.y - m, hull.width + 1 + 2 * m, hull.height + 1 + 2 * m) &
              frame;
      }
      if (box.width < side + 2 || box.height < side + 2) {
        ++outside;
        continue;
      }
      cv::matchTemplate(right(box), patch, scores, cv::TM_CCOEFF_NORMED);
      mask = cv::Mat::zeros(scores.size(), CV_8U);
      for (cv::Point& c : curve) c -= cv::Point(box.x + half, box.y + half);
      cv::polylines(mask, curve, false, cv::Scalar(255), 2 * band + 1, cv::LINE_8);
      double best = -1.0;
      cv::Point at;
      cv::minMaxLoc(scores, nullptr, &best, nullptr, &at, mask);
      if (!(best >= config.min_ncc)) {
        ++unmatched;
        continue;
      }
      double dx = 0.0, dy = 0.0;
      if (at.x > 0 && at.x + 1 < scores.cols) {
        dx = parabolaPeak(scores.at<float>(at.y, at.x - 1), scores.at<float>(at.y, at.x),
                          scores.at<float>(at.y, at.x + 1));
      }
      if (at.y > 0 && at.y + 1 < scores.rows) {
        dy = parabolaPeak(scores.at<float>(at.y - 1, at.x), scores.at<float>(at.y, at.x),
                          scores.at<float>(at.y + 1, at.x));
      }
      const cv::Vec2d q(box.x + half + at.x + dx, box.y + half + at.y + dy);
      const Triangulation t = triangulate(rig, cv::Vec2d(p.x, p.y), q);
      if (!t.ok || !(t.point[2] > 0.0)) {
        ++unmatched;
        continue;
      }
      ++out.matched;
      depth.push_back(t.point[2]);
      disparity.push_back(p.x - q[0]);
      vertical.push_back(rig.epipolarOffset(cv::Vec2d(p.x, p.y), q));
    }
  }
  const int textured = out.patches - out.flat - out.highlights;
  const int needed = std::max(4, textured / 5);
  if (out.matched < needed) {
    return fail(fmt::format(
        "left ROI {}: nothing matchable in the right view ({} matched, {} needed): of {} patches "
        "{} are flat (no texture), {} on highlights, {} found no match above NCC {:.2f} within "
        "{:g}-{:g} mm (the surface is out of that depth range, or not in the right view){}",
        roiText(roi), out.matched, needed, out.patches, out.flat, out.highlights, unmatched,
        config.min_ncc, config.near_mm, config.far_mm,
        outside > 0 ? fmt::format(", {} whose epipolar band leaves the right image", outside)
                    : std::string()));
  }
  out.depth_mm = percentile(depth, 0.5);
  out.depth_lo_mm = percentile(depth, 0.05);
  out.depth_hi_mm = percentile(depth, 0.95);
  out.disparity_lo_px = percentile(disparity, 0.05);
  out.disparity_hi_px = percentile(disparity, 0.95);
  out.vertical_px = percentile(vertical, 0.5);
  std::vector<double> dev(vertical.size());
  for (size_t k = 0; k < vertical.size(); ++k) dev[k] = std::abs(vertical[k] - out.vertical_px);
  out.vertical_spread_px = 1.4826 * percentile(dev, 0.5);
  // The tolerance covers the spread, and a margin for the surface's motion and the patches
  // between the grid's (5 % of the depth, 1 mm at least).
  out.tolerance_mm = std::max(out.depth_mm - out.depth_lo_mm, out.depth_hi_mm - out.depth_mm) +
                     std::max(1.0, 0.05 * out.depth_mm);
  // The right ROI: the left ROI's outline at the median depth, seen by the right camera.
  std::vector<cv::Point2f> outline;
  constexpr int kPerSide = 8;
  for (int k = 0; k <= kPerSide; ++k) {
    const double u = roi.x + roi.width * k / double(kPerSide);
    const double v = roi.y + roi.height * k / double(kPerSide);
    for (const cv::Vec2d& px : {cv::Vec2d(u, roi.y), cv::Vec2d(u, roi.y + roi.height),
                                cv::Vec2d(roi.x, v), cv::Vec2d(roi.x + roi.width, v)}) {
      const Ray ray = rig.backProjectLeft(px);
      if (!(ray.direction[2] > 0.0)) continue;
      const double s = (out.depth_mm - ray.origin[2]) / ray.direction[2];
      const cv::Vec2d q = rig.projectRight(ray.origin + s * ray.direction);
      if (std::isfinite(q[0]) && std::isfinite(q[1]))
        outline.emplace_back(static_cast<float>(q[0]), static_cast<float>(q[1]));
    }
  }
  out.right = outline.empty() ? cv::Rect() : cv::boundingRect(outline) & frame;
  return out;
}

}  // namespace pulsetrack::vision
