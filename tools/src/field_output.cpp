#include "pulsetrack/tools/field_output.hpp"

#include <fmt/format.h>

#include <cmath>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "pulsetrack/analysis/plot.hpp"

namespace pulsetrack::tools {

namespace {

// The probes: the grid's centre and four points halfway to its corners (row, col).
std::vector<std::pair<int, int>> probes(int rows, int cols) {
  return {{rows / 2, cols / 2},
          {rows / 4, cols / 4},
          {rows / 4, 3 * cols / 4},
          {3 * rows / 4, cols / 4},
          {3 * rows / 4, 3 * cols / 4}};
}

std::filesystem::path sibling(const std::string& csv, const std::string& suffix) {
  const std::filesystem::path p(csv);
  return p.parent_path() / (p.stem().string() + suffix);
}

// The normal displacement over the grid as a colour map from its least (blue) to its largest
// (red) value, so that the surface's uneven motion shows, with a colour bar and labels. Grey:
// beyond the features' reach.
cv::Mat drawMap(const std::vector<double>& map, int rows, int cols, double spacing, double t) {
  double vmin = 1e300, vmax = -1e300;
  for (double v : map) {
    if (!std::isfinite(v)) continue;
    vmin = std::min(vmin, v);
    vmax = std::max(vmax, v);
  }
  if (vmin > vmax) vmin = vmax = 0.0;
  const double span = std::max(vmax - vmin, 1e-6);
  const int cell = std::clamp(560 / std::max(rows, cols), 2, 24);
  const int w = cols * cell, h = rows * cell, left = 70, top = 60, bar = 24;
  cv::Mat img(h + top + 70, w + left + bar + 110, CV_8UC3, cv::Scalar(255, 255, 255));
  cv::Mat grey(1, 256, CV_8UC1);
  for (int i = 0; i < 256; ++i) grey.at<uint8_t>(0, i) = static_cast<uint8_t>(i);
  cv::Mat lut;
  cv::applyColorMap(grey, lut, cv::COLORMAP_JET);
  const auto colour = [&](double v) {
    const int i = std::clamp(static_cast<int>(std::lround((v - vmin) / span * 255.0)), 0, 255);
    const cv::Vec3b c = lut.at<cv::Vec3b>(0, i);
    return cv::Scalar(c[0], c[1], c[2]);
  };
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      const double v = map[static_cast<size_t>(r) * static_cast<size_t>(cols) + c];
      // Row 0 at the bottom: t (the grid's second axis) upwards.
      const cv::Rect cellr(left + c * cell, top + (rows - 1 - r) * cell, cell, cell);
      cv::rectangle(img, cellr, std::isfinite(v) ? colour(v) : cv::Scalar(200, 200, 200),
                    cv::FILLED);
    }
  }
  cv::rectangle(img, cv::Rect(left, top, w, h), cv::Scalar(0, 0, 0), 1);
  const auto text = [&](const std::string& s, cv::Point at, double scale = 0.5) {
    cv::putText(img, s, at, cv::FONT_HERSHEY_SIMPLEX, scale, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
  };
  text(fmt::format("displacement along the surface normal at t = {:.2f} s (mm)", t), {left, 30},
       0.6);
  text(fmt::format("s (mm), {} x {} grid at {:g} mm", cols, rows, spacing), {left, top + h + 40});
  text("t (mm)", {left - 60, top - 12});
  for (int k = 0; k <= 4; ++k) {  // axis ticks in mm
    const int c = (cols - 1) * k / 4, r = (rows - 1) * k / 4;
    text(fmt::format("{:.0f}", c * spacing), {left + c * cell, top + h + 18}, 0.4);
    text(fmt::format("{:.0f}", r * spacing), {left - 30, top + (rows - 1 - r) * cell + cell}, 0.4);
  }
  const int bx = left + w + 20;
  for (int y = 0; y < h; ++y) {
    const double v = vmax - span * y / std::max(1, h - 1);
    cv::line(img, {bx, top + y}, {bx + bar, top + y}, colour(v));
  }
  cv::rectangle(img, cv::Rect(bx, top, bar, h), cv::Scalar(0, 0, 0), 1);
  text(fmt::format("{:+.3f}", vmax), {bx + bar + 5, top + 10}, 0.45);
  text(fmt::format("{:+.3f}", 0.5 * (vmin + vmax)), {bx + bar + 5, top + h / 2 + 5}, 0.45);
  text(fmt::format("{:+.3f}", vmin), {bx + bar + 5, top + h}, 0.45);
  return img;
}

}  // namespace

vision::Result<std::vector<cv::Vec3d>> readPoints(const std::filesystem::path& path) {
  std::ifstream in(path);
  if (!in) return vision::fail(fmt::format("{}: cannot open", path.string()));
  std::vector<cv::Vec3d> out;
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty() || line[0] == '#') continue;
    std::istringstream ss(line);
    cv::Vec3d p;
    char c1 = 0, c2 = 0;
    std::string rest;
    if (!(ss >> p[0] >> c1 >> p[1] >> c2 >> p[2]) || c1 != ',' || c2 != ',' || (ss >> rest)) {
      if (out.empty() && n == 1 && line.find_first_of("0123456789") == std::string::npos)
        continue;  // a header line
      return vision::fail(fmt::format("{}:{}: '{}': expected x,y,z in mm", path.string(), n, line));
    }
    if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2]) || cv::norm(p) > 1e5)
      return vision::fail(
          fmt::format("{}:{}: '{}': not a point within 100 m", path.string(), n, line));
    out.push_back(p);
  }
  if (out.empty()) return vision::fail(fmt::format("{}: no point in it", path.string()));
  if (out.size() > 10000)
    return vision::fail(fmt::format("{}: {} points, at most 10000", path.string(), out.size()));
  return out;
}

vision::Result<FieldOutput> FieldOutput::open(const std::string& field_csv, int every,
                                              const std::vector<cv::Vec3d>& targets,
                                              const std::string& targets_csv,
                                              const vision::FieldConfig& config, int max_features) {
  FieldOutput o(config, max_features);
  o.every_ = std::max(1, every);
  o.targets_ = targets;
  o.spacing_ = config.spacing_mm;
  if (!field_csv.empty()) {
    o.field_path_ = field_csv;
    o.field_out_.open(field_csv);
    if (!o.field_out_) return vision::fail(fmt::format("{}: cannot write", field_csv));
    o.field_out_ << "frame,t,signal,row,col,x,y,z,dx,dy,dz,confidence\n";
  }
  if (!targets.empty()) {
    o.targets_path_ = targets_csv;
    o.targets_out_.open(targets_csv);
    if (!o.targets_out_) return vision::fail(fmt::format("{}: cannot write", targets_csv));
    o.targets_out_ << "frame,t,target,x,y,z,dx,dy,dz,confidence\n";
  }
  return o;
}

vision::Result<void> FieldOutput::add(long frame, double t,
                                      std::span<const vision::Feature> features, bool detected,
                                      uint32_t detections, const cv::Vec3d& mean_displacement) {
  if (!field_.update(features, detected, detections)) return {};
  ++with_field_;
  const vision::DeformationField& f = field_;
  if (f.signal() != signal_) {  // a new grid: the figures follow the newest signal
    signal_ = f.signal();
    series_ = {};
    series_.at.resize(5);
    best_mean_ = -1.0;
  }
  const cv::Vec3d n = f.normal();
  // The figures' series.
  series_.t.push_back(t);
  series_.mean.push_back(mean_displacement.dot(n));
  const auto pr = probes(f.rows(), f.cols());
  for (size_t k = 0; k < pr.size(); ++k) {
    const int i = pr[k].first * f.cols() + pr[k].second;
    series_.at[k].push_back(f.confidence(i) > 0 ? f.displacement(i).dot(n) : NAN);
  }
  double sum = 0;
  int valid = 0;
  for (int i = 0; i < f.points(); ++i) {
    if (f.confidence(i) <= 0) continue;
    sum += f.displacement(i).dot(n);
    ++valid;
  }
  const double mean = valid > 0 ? std::abs(sum / valid) : 0.0;
  if (mean > best_mean_) {
    best_mean_ = mean;
    best_t_ = t;
    best_cols_ = f.cols();
    best_rows_ = f.rows();
    best_map_.resize(static_cast<size_t>(f.points()));
    for (int i = 0; i < f.points(); ++i)
      best_map_[static_cast<size_t>(i)] = f.confidence(i) > 0 ? f.displacement(i).dot(n) : NAN;
  }
  if (field_out_.is_open() && (with_field_ - 1) % every_ == 0) {
    ++field_rows_pairs_;
    for (int r = 0; r < f.rows(); ++r) {
      for (int c = 0; c < f.cols(); ++c) {
        const int i = r * f.cols() + c;
        const double conf = f.confidence(i);
        if (conf <= 0) {
          field_out_ << fmt::format("{},{:.6f},{},{},{},,,,,,,0\n", frame, t, f.signal(), r, c);
          continue;
        }
        const cv::Vec3d d = f.displacement(i), p = f.rest(i) + d;
        field_out_ << fmt::format(
            "{},{:.6f},{},{},{},{:.5f},{:.5f},{:.5f},{:.5f},{:.5f},{:.5f},{:.3f}\n", frame, t,
            f.signal(), r, c, p[0], p[1], p[2], d[0], d[1], d[2], conf);
      }
    }
    if (!field_out_) return vision::fail(fmt::format("{}: write failed", field_path_));
  }
  if (targets_out_.is_open()) {
    for (size_t k = 0; k < targets_.size(); ++k) {
      const vision::FieldQuery q = f.at(targets_[k]);
      targets_out_ << fmt::format("{},{:.6f},{},{:.5f},{:.5f},{:.5f},{:.5f},{:.5f},{:.5f},{:.3f}\n",
                                  frame, t, k, q.position[0], q.position[1], q.position[2],
                                  q.displacement[0], q.displacement[1], q.displacement[2],
                                  q.confidence);
      ++target_rows_;
    }
    if (!targets_out_) return vision::fail(fmt::format("{}: write failed", targets_path_));
  }
  return {};
}

vision::Result<std::vector<std::string>> FieldOutput::finish() {
  std::vector<std::string> lines;
  if (targets_out_.is_open()) {
    targets_out_.close();
    if (!targets_out_) return vision::fail(fmt::format("{}: write failed", targets_path_));
    lines.push_back(fmt::format("targets           {} ({} targets, {} rows)", targets_path_,
                                targets_.size(), target_rows_));
  }
  if (!field_out_.is_open()) return lines;
  field_out_.close();
  if (!field_out_) return vision::fail(fmt::format("{}: write failed", field_path_));
  lines.push_back(fmt::format("field             {} ({} of {} pairs with a field, every {})",
                              field_path_, field_rows_pairs_, with_field_, every_));
  if (with_field_ == 0) return lines;
  const std::filesystem::path map = sibling(field_path_, "-map.png");
  try {
    if (!cv::imwrite(map.string(), drawMap(best_map_, best_rows_, best_cols_, spacing_, best_t_)))
      return vision::fail(fmt::format("{}: cannot write", map.string()));
  } catch (const cv::Exception& e) {
    return vision::fail(fmt::format("{}: cannot write: {}", map.string(), e.err));
  }
  analysis::Figure fig(1100, 500, 1, 1, "the dense field over time");
  analysis::Axes& ax = fig.at(0, 0);
  ax.title = "displacement along the surface normal";
  ax.xlabel = "t (s)";
  ax.ylabel = "mm";
  static const char* const kNames[5] = {"grid centre", "1/4, 1/4", "1/4, 3/4", "3/4, 1/4",
                                        "3/4, 3/4"};
  static const cv::Scalar kColours[5] = {
      {180, 90, 30}, {40, 160, 40}, {30, 30, 200}, {160, 40, 160}, {20, 140, 200}};
  for (size_t k = 0; k < series_.at.size(); ++k)
    ax.lines.push_back({series_.t, series_.at[k], kColours[k], kNames[k], 1});
  ax.lines.push_back({series_.t, series_.mean, cv::Scalar(0, 0, 0), "features' mean", 2});
  const std::filesystem::path points = sibling(field_path_, "-points.png");
  if (auto ok = fig.save(points); !ok) return std::unexpected(ok.error());
  lines.push_back(fmt::format("field figures     {} (at t = {:.2f} s), {}", map.string(), best_t_,
                              points.string()));
  return lines;
}

}  // namespace pulsetrack::tools
