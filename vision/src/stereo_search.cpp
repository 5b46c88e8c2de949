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
  std::string s = region ? region->summary() + "; " : std::string();
  s += fmt::format(
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
  if (!outline.empty()) {
    float x0 = outline[0].x, x1 = x0, y0 = outline[0].y, y1 = y0;
    for (const cv::Point2f& q : outline) {
      x0 = std::min(x0, q.x);
      x1 = std::max(x1, q.x);
      y0 = std::min(y0, q.y);
      y1 = std::max(y1, q.y);
    }
    out.right_outline = cv::Rect2d(x0, y0, x1 - x0, y1 - y0);
  }
  out.right = outline.empty() ? cv::Rect() : cv::boundingRect(outline) & frame;
  out.left = roi;
  return out;
}

std::string TissueRegion::summary() const {
  return fmt::format(
      "left ROI {} found: the best well-textured region, glare and dark borders left out ({} of "
      "{} cells tissue; {} flat, {} on highlights, {} dark){}",
      roiText(found), tissue, cells, flat, highlights, dark,
      roi == found
          ? std::string()
          : fmt::format(", narrowed to {} (the part the right camera sees too)", roiText(roi)));
}

Result<TissueRegion> findTissueRegion(const cv::Mat& left, int min_side,
                                      const StereoSearchConfig& config) {
  if (left.type() != CV_8UC1)
    return fail(
        fmt::format("no ROI given, and the left image is not 8-bit grey (type {})", left.type()));
  const int side = std::max(16, std::min(left.cols, left.rows) / 20);
  if (left.cols < std::max(side, min_side) || left.rows < std::max(side, min_side)) {
    return fail(fmt::format("no ROI given, and the left image ({}x{}) is too small to find one in",
                            left.cols, left.rows));
  }
  const int cols = left.cols / side, rows = left.rows / side;
  // The cells' grid is centred (the remainder split over both borders).
  const int x0 = (left.cols - cols * side) / 2, y0 = (left.rows - rows * side) / 2;
  TissueRegion out;
  out.cells = cols * rows;
  // Per cell: 1 tissue, 0 not (flat, glare), and dark cells (outside the field of view) are
  // never inside. Prefix sums of both over the grid.
  std::vector<int> tissue_sum(static_cast<size_t>((cols + 1) * (rows + 1)), 0);
  std::vector<int> dark_sum(tissue_sum.size(), 0);
  const auto at = [&](std::vector<int>& v, int c, int r) -> int& {
    return v[static_cast<size_t>(r) * static_cast<size_t>(cols + 1) + static_cast<size_t>(c)];
  };
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      const cv::Mat cell = left(cv::Rect(x0 + c * side, y0 + r * side, side, side));
      cv::Scalar mean, sd;
      cv::meanStdDev(cell, mean, sd);
      // A few glinting pixels the tracker's own glint mask handles; a cell a tenth glare is lost.
      const int glare = cv::countNonZero(cell >= config.highlight);
      const bool dark = mean[0] < config.region_dark;
      const bool highlight = !dark && glare * 10 > side * side;
      const bool flat = !dark && !highlight && sd[0] < config.region_texture;
      const bool tissue = !dark && !highlight && !flat;
      out.dark += dark ? 1 : 0;
      out.highlights += highlight ? 1 : 0;
      out.flat += flat ? 1 : 0;
      out.tissue += tissue ? 1 : 0;
      at(tissue_sum, c + 1, r + 1) = (tissue ? 1 : 0) + at(tissue_sum, c, r + 1) +
                                     at(tissue_sum, c + 1, r) - at(tissue_sum, c, r);
      at(dark_sum, c + 1, r + 1) =
          (dark ? 1 : 0) + at(dark_sum, c, r + 1) + at(dark_sum, c + 1, r) - at(dark_sum, c, r);
    }
  }
  // The rectangle of cells with the most tissue less kBadWeight per other cell, no dark one,
  // at most kMaxAspect times longer than wide (a strip along the image's edge tracks poorly).
  constexpr int kBadWeight = 3;
  constexpr int kMaxAspect = 2;
  int best = 0;
  const auto sum = [&](std::vector<int>& v, int c0, int r0, int c1, int r1) {
    return at(v, c1, r1) - at(v, c0, r1) - at(v, c1, r0) + at(v, c0, r0);
  };
  for (int r0 = 0; r0 < rows; ++r0) {
    for (int r1 = r0 + 1; r1 <= rows; ++r1) {
      for (int c0 = 0; c0 < cols; ++c0) {
        for (int c1 = c0 + 1; c1 <= cols; ++c1) {
          const int w = c1 - c0, h = r1 - r0;
          if (w > kMaxAspect * h || h > kMaxAspect * w) continue;
          if (w * side < min_side || h * side < min_side) continue;
          if (sum(dark_sum, c0, r0, c1, r1) > 0) break;  // wider only adds the dark cell
          const int good = sum(tissue_sum, c0, r0, c1, r1);
          const int score = good - kBadWeight * (w * h - good);
          if (score > best) {
            best = score;
            out.found = cv::Rect(x0 + c0 * side, y0 + r0 * side, w * side, h * side);
          }
        }
      }
    }
  }
  out.roi = out.found;
  if (best <= 0) {
    return fail(fmt::format(
        "no ROI given, and no well-textured region of at least {}x{} px (glare and dark borders "
        "left out) in the left image: of {} cells of {} px, {} are flat (grey SD under {:g}), {} "
        "on highlights (>= {}), {} dark (mean under {:g}); give a left ROI (--roi-left, or "
        "set_roi's roi_left)",
        min_side, min_side, out.cells, side, out.flat, config.region_texture, out.highlights,
        config.highlight, out.dark, config.region_dark));
  }
  return out;
}

Result<StereoRange> findStereoRoi(const StereoRig& rig, const cv::Mat& left, const cv::Mat& right,
                                  const cv::Rect& roi_left, int min_side,
                                  const StereoSearchConfig& config) {
  if (roi_left != cv::Rect()) return findStereoRange(rig, left, right, roi_left, config);
  auto region = findTissueRegion(left, min_side, config);
  if (!region) return std::unexpected(region.error());
  auto range = findStereoRange(rig, left, right, region->roi, config);
  if (!range) return fail(fmt::format("{}; but {}", region->summary(), range.error().message));
  // Narrowed to what the right camera sees too: where the right ROI was cut at the image's
  // border, the left one loses as much on that side (the views map almost by a shift).
  // The outline runs along the ROI's outer edges (x + width): it fits while within [0, size].
  const cv::Rect l = region->roi;
  const cv::Rect2d& r = range->right_outline;
  const cv::Size size = rig.right.imageSize();
  const auto cut = [](double over) { return over > 0.0 ? static_cast<int>(std::ceil(over)) : 0; };
  const int cut_left = cut(-r.x);
  const int cut_right = cut(r.x + r.width - size.width);
  const int cut_top = cut(-r.y);
  const int cut_bottom = cut(r.y + r.height - size.height);
  if (cut_left + cut_right + cut_top + cut_bottom > 0) {
    const cv::Rect narrowed(l.x + cut_left, l.y + cut_top, l.width - cut_left - cut_right,
                            l.height - cut_top - cut_bottom);
    if (narrowed.width < min_side || narrowed.height < min_side) {
      return fail(fmt::format(
          "{}; but the right camera sees only {} of it: give a left ROI (--roi-left, or "
          "set_roi's roi_left)",
          region->summary(), roiText(range->right)));
    }
    region->roi = narrowed;
    range = findStereoRange(rig, left, right, narrowed, config);
    if (!range) return fail(fmt::format("{}; but {}", region->summary(), range.error().message));
  }
  range->region = *region;
  return range;
}

}  // namespace pulsetrack::vision
