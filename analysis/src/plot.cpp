#include "pulsetrack/analysis/plot.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "pulsetrack/analysis/stats.hpp"

namespace pulsetrack::analysis {

namespace {

const cv::Scalar kBlack(0, 0, 0), kGrid(225, 225, 225), kBox(200, 150, 90), kMedian(40, 40, 200);
constexpr int kFont = cv::FONT_HERSHEY_SIMPLEX;

void text(cv::Mat& img, const std::string& s, cv::Point p, double scale, int align = 0,
          const cv::Scalar& color = kBlack, int thickness = 1) {
  int base = 0;
  const cv::Size sz = cv::getTextSize(s, kFont, scale, thickness, &base);
  if (align == 1) p.x -= sz.width / 2;
  if (align == 2) p.x -= sz.width;
  cv::putText(img, s, p, kFont, scale, color, thickness, cv::LINE_AA);
}

void verticalText(cv::Mat& img, const std::string& s, cv::Point centre, double scale) {
  int base = 0;
  const cv::Size sz = cv::getTextSize(s, kFont, scale, 1, &base);
  cv::Mat t(sz.height + base + 4, sz.width + 4, CV_8UC3, cv::Scalar(255, 255, 255));
  cv::putText(t, s, cv::Point(2, sz.height + 2), kFont, scale, kBlack, 1, cv::LINE_AA);
  cv::Mat r;
  cv::rotate(t, r, cv::ROTATE_90_COUNTERCLOCKWISE);
  const cv::Rect dst(centre.x - r.cols / 2, centre.y - r.rows / 2, r.cols, r.rows);
  const cv::Rect clip = dst & cv::Rect(0, 0, img.cols, img.rows);
  if (clip.area() > 0)
    r(cv::Rect(clip.x - dst.x, clip.y - dst.y, clip.width, clip.height)).copyTo(img(clip));
}

std::string tickLabel(double v, double step) {
  const int decimals = std::max(0, static_cast<int>(std::ceil(-std::log10(step) - 1e-9)));
  return fmt::format("{:.{}f}", std::fabs(v) < step * 1e-6 ? 0.0 : v, decimals);
}

void drawAxes(cv::Mat& img, const cv::Rect& cell, const Axes& ax) {
  const cv::Rect plot(cell.x + 75, cell.y + 32, cell.width - 95, cell.height - 82);
  // Data range.
  double x0 = ax.xmin, x1 = ax.xmax, y0 = ax.ymin, y1 = ax.ymax;
  double dx0 = 1e300, dx1 = -1e300, dy0 = 1e300, dy1 = -1e300;
  for (const LineSeries& l : ax.lines) {
    for (size_t i = 0; i < l.x.size() && i < l.y.size(); ++i) {
      if (!std::isfinite(l.x[i]) || !std::isfinite(l.y[i])) continue;
      dx0 = std::min(dx0, l.x[i]);
      dx1 = std::max(dx1, l.x[i]);
      dy0 = std::min(dy0, l.y[i]);
      dy1 = std::max(dy1, l.y[i]);
    }
  }
  const bool boxes = !ax.boxes.empty();
  double box_top = 0, box_span = 1;  // the boxes' data: brackets stack above it
  if (boxes) {
    dx0 = 0.5;
    dx1 = static_cast<double>(ax.boxes.size()) + 0.5;
    for (const BoxSeries& b : ax.boxes) {
      for (const double v : b.values) {
        dy0 = std::min(dy0, v);
        dy1 = std::max(dy1, v);
      }
    }
    if (dy0 > 0) dy0 = 0;
    box_top = dy1;
    box_span = dy1 > dy0 ? dy1 - dy0 : 1.0;
    if (!ax.brackets.empty())
      dy1 = box_top + box_span * 0.1 * (static_cast<double>(ax.brackets.size()) + 0.6);
  }
  if (dx0 > dx1) dx0 = 0, dx1 = 1;
  if (dy0 > dy1) dy0 = 0, dy1 = 1;
  if (std::isnan(x0)) x0 = dx0;
  if (std::isnan(x1)) x1 = dx1;
  if (std::isnan(y0)) y0 = dy0 - 0.05 * (dy1 - dy0);
  if (std::isnan(y1)) y1 = dy1 + 0.05 * (dy1 - dy0);
  if (x1 <= x0) x1 = x0 + 1;
  if (y1 <= y0) y1 = y0 + 1;
  const auto px = [&](double x) {
    return plot.x + static_cast<int>(std::lround((x - x0) / (x1 - x0) * plot.width));
  };
  const auto py = [&](double y) {
    return plot.y + plot.height - static_cast<int>(std::lround((y - y0) / (y1 - y0) * plot.height));
  };
  // Grid and ticks.
  const std::vector<double> yt = niceTicks(y0, y1);
  const double ystep = yt.size() > 1 ? yt[1] - yt[0] : 1.0;
  for (const double y : yt) {
    cv::line(img, {plot.x, py(y)}, {plot.x + plot.width, py(y)}, kGrid, 1);
    text(img, tickLabel(y, ystep), {plot.x - 6, py(y) + 4}, 0.38, 2);
  }
  if (boxes) {
    for (size_t i = 0; i < ax.boxes.size(); ++i)
      text(img, ax.boxes[i].label, {px(static_cast<double>(i + 1)), plot.y + plot.height + 16},
           0.38, 1);
  } else {
    const std::vector<double> xt = niceTicks(x0, x1);
    const double xstep = xt.size() > 1 ? xt[1] - xt[0] : 1.0;
    for (const double x : xt) {
      cv::line(img, {px(x), plot.y}, {px(x), plot.y + plot.height}, kGrid, 1);
      text(img, tickLabel(x, xstep), {px(x), plot.y + plot.height + 16}, 0.38, 1);
    }
  }
  cv::rectangle(img, plot, kBlack, 1);
  text(img, ax.title, {plot.x + plot.width / 2, cell.y + 20}, 0.5, 1, kBlack, 1);
  text(img, ax.xlabel, {plot.x + plot.width / 2, plot.y + plot.height + 38}, 0.42, 1);
  verticalText(img, ax.ylabel, {cell.x + 14, plot.y + plot.height / 2}, 0.42);

  cv::Mat clip = img(plot);
  const cv::Point off(-plot.x, -plot.y);
  for (size_t k = 0; k < ax.annotations.size(); ++k) {
    const Annotation& a = ax.annotations[k];
    const int x = px(a.x);
    for (int y = plot.y; y < plot.y + plot.height; y += 8)
      cv::line(img, {x, y}, {x, std::min(y + 4, plot.y + plot.height)}, cv::Scalar(120, 120, 120),
               1);
    // Staggered, so that close peaks' labels do not overwrite each other.
    int base = 0;
    const int w = cv::getTextSize(a.text, kFont, 0.36, 1, &base).width;
    const bool left_of_line = x + 3 + w > plot.x + plot.width;  // near the right edge
    text(img, a.text, {left_of_line ? x - 3 : x + 3, plot.y + 12 + static_cast<int>(k % 6) * 13},
         0.36, left_of_line ? 2 : 0, cv::Scalar(60, 60, 60));
  }
  for (const LineSeries& l : ax.lines) {
    std::vector<cv::Point> pts;
    for (size_t i = 0; i < l.x.size() && i < l.y.size(); ++i) {
      if (std::isfinite(l.x[i]) && std::isfinite(l.y[i]))
        pts.emplace_back(cv::Point(px(l.x[i]), py(l.y[i])) + off);
    }
    if (pts.size() >= 2) cv::polylines(clip, pts, false, l.color, l.thickness, cv::LINE_AA);
  }
  const int half =
      std::max(6, plot.width / static_cast<int>(std::max<size_t>(1, ax.boxes.size())) / 5);
  for (size_t i = 0; i < ax.boxes.size(); ++i) {
    const BoxSeries& b = ax.boxes[i];
    if (b.values.empty()) continue;
    const Summary s = summarize(b.values);
    const double iqr = s.q3 - s.q1;
    double lo = s.q1, hi = s.q3;
    for (const double v : b.values) {
      if (v >= s.q1 - 1.5 * iqr) lo = std::min(lo, v);
      if (v <= s.q3 + 1.5 * iqr) hi = std::max(hi, v);
    }
    const int cx = px(static_cast<double>(i + 1));
    cv::rectangle(img, cv::Point(cx - half, py(s.q3)), cv::Point(cx + half, py(s.q1)), kBox,
                  cv::FILLED);
    cv::rectangle(img, cv::Point(cx - half, py(s.q3)), cv::Point(cx + half, py(s.q1)), kBlack, 1);
    cv::line(img, {cx - half, py(s.median)}, {cx + half, py(s.median)}, kMedian, 2);
    cv::line(img, {cx, py(s.q3)}, {cx, py(hi)}, kBlack, 1);
    cv::line(img, {cx, py(s.q1)}, {cx, py(lo)}, kBlack, 1);
    cv::line(img, {cx - half / 2, py(hi)}, {cx + half / 2, py(hi)}, kBlack, 1);
    cv::line(img, {cx - half / 2, py(lo)}, {cx + half / 2, py(lo)}, kBlack, 1);
    for (const double v : b.values) {
      if (v < lo || v > hi) cv::circle(img, {cx, py(v)}, 3, kMedian, 1, cv::LINE_AA);
    }
  }
  // Significance brackets, stacked above the boxes.
  for (size_t k = 0; k < ax.brackets.size(); ++k) {
    const Bracket& br = ax.brackets[k];
    const int y = py(box_top + box_span * 0.1 * static_cast<double>(k + 1));
    const int xa = px(br.a + 1.0), xb = px(br.b + 1.0);
    cv::line(img, {xa, y + 6}, {xa, y}, kBlack, 1);
    cv::line(img, {xa, y}, {xb, y}, kBlack, 1);
    cv::line(img, {xb, y}, {xb, y + 6}, kBlack, 1);
    text(img, br.text, {(xa + xb) / 2, y - 3}, 0.5, 1);
  }
  // Legend.
  int ly = plot.y + 14;
  for (const LineSeries& l : ax.lines) {
    if (l.label.empty()) continue;
    int base = 0;
    const int w = cv::getTextSize(l.label, kFont, 0.38, 1, &base).width;
    const int x = plot.x + plot.width - w - 40;
    cv::line(img, {x, ly - 4}, {x + 24, ly - 4}, l.color, 2, cv::LINE_AA);
    text(img, l.label, {x + 30, ly}, 0.38);
    ly += 16;
  }
}

}  // namespace

std::vector<double> niceTicks(double lo, double hi, int target) {
  std::vector<double> t;
  if (!(hi > lo)) return {lo};
  const double raw = (hi - lo) / std::max(1, target);
  const double mag = std::pow(10.0, std::floor(std::log10(raw)));
  const double norm = raw / mag;
  const double step = (norm < 1.5 ? 1 : norm < 3 ? 2 : norm < 7 ? 5 : 10) * mag;
  for (double v = std::ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) t.push_back(v);
  return t;
}

Figure::Figure(int width, int height, int rows, int cols, std::string title)
    : width_(width),
      height_(height),
      rows_(rows),
      cols_(cols),
      title_(std::move(title)),
      axes_(static_cast<size_t>(rows * cols)) {}

Axes& Figure::at(int row, int col) { return axes_[(static_cast<size_t>(row) * cols_) + col]; }

cv::Mat Figure::render() const {
  cv::Mat img(height_, width_, CV_8UC3, cv::Scalar(255, 255, 255));
  const int top = title_.empty() ? 0 : 30;
  if (!title_.empty()) text(img, title_, {width_ / 2, 22}, 0.6, 1, kBlack, 1);
  const int cw = width_ / cols_, ch = (height_ - top) / rows_;
  for (int r = 0; r < rows_; ++r) {
    for (int c = 0; c < cols_; ++c)
      drawAxes(img, {c * cw, top + r * ch, cw, ch}, axes_[(static_cast<size_t>(r) * cols_) + c]);
  }
  return img;
}

vision::Result<void> Figure::save(const std::filesystem::path& png) const {
  bool ok = false;
  try {
    ok = cv::imwrite(png.string(), render());
  } catch (const cv::Exception& e) {
    return vision::fail(fmt::format("{}: cannot write: {}", png.string(), e.err));
  }
  if (!ok) return vision::fail(fmt::format("{}: cannot write", png.string()));
  return {};
}

}  // namespace pulsetrack::analysis
