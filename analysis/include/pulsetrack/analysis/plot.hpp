#pragma once
// Figures for the reports, drawn with OpenCV (no other plotting stack on the appliance or in
// CI): line plots with nice ticks, grids, legends and labelled markers, and box plots (median,
// quartiles, whiskers at 1.5 IQR, outliers) with significance brackets, as the paper's Figs.
// 7-9. A Figure is a grid of Axes saved as PNG.

#include <filesystem>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::analysis {

struct LineSeries {
  std::vector<double> x, y;
  cv::Scalar color{180, 90, 30};
  std::string label;
  int thickness = 1;
};

struct BoxSeries {
  std::string label;
  std::vector<double> values;
};

struct Annotation {  // a vertical dashed line with a text (a named spectral peak)
  double x = 0;
  std::string text;
};

struct Bracket {  // a significant difference between boxes a and b (0-based)
  int a = 0, b = 0;
  std::string text = "*";
};

struct Axes {
  std::string title, xlabel, ylabel;
  std::vector<LineSeries> lines;
  std::vector<BoxSeries> boxes;
  std::vector<Annotation> annotations;
  std::vector<Bracket> brackets;
  double xmin = NAN, xmax = NAN, ymin = NAN, ymax = NAN;  // NAN: from the data
};

class Figure {
 public:
  Figure(int width, int height, int rows = 1, int cols = 1, std::string title = "");
  Axes& at(int row, int col);
  [[nodiscard]] cv::Mat render() const;
  [[nodiscard]] vision::Result<void> save(const std::filesystem::path& png) const;

 private:
  int width_, height_, rows_, cols_;
  std::string title_;
  std::vector<Axes> axes_;
};

// 1-2-5 ticks covering [lo, hi], about `target` of them.
std::vector<double> niceTicks(double lo, double hi, int target = 6);

}  // namespace pulsetrack::analysis
