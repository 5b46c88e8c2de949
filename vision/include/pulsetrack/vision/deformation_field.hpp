#pragma once
// DeformationField: how every point of the tracked surface moves, not only the features and
// their mean. From each pair's tracked features, a smoothing thin-plate spline (TPS) of the
// displacement over the surface, fitted robustly (IRLS, down-weighting outliers), evaluated on a
// regular grid and at any point a robot asks about.
//
// Coordinates. The field is a function of the material point, named by its position in the
// reference pair (the first pair of the session's signal), in the left camera frame {C}, mm.
// At the first detection the field fixes its surface frame: origin at the reference features'
// centroid, normal the least-squares plane's (towards the cameras), e1 the camera's x in that
// plane, e2 = normal x e1. The spline runs over the plane coordinates (s, t) of the reference
// positions; the grid spans the features' extent in (s, t) plus a margin, at `spacing_mm`, and
// its rest positions lie on a spline of the reference surface's height: grid point k is the
// same material point for the whole signal.
//
// A feature's displacement since the reference pair: point - point0, plus, for a feature that a
// re-detection added later, the field's displacement at its reference position when it came
// (its reference position is where the field maps it back to: it joins without a jump).
//
// Per pair (update(), after the first detection): no allocation, no lock, no exception. The
// linear system is factored again only when the set of ok features or a robust weight changes;
// a re-detection (new features) rebuilds the basis (allocates, as the detection itself does).
//
// Why a smoothing TPS: ~100 scattered features, no grid to choose (a B-spline lattice would need
// a knot spacing that the features' density varies under), the least bending surface through
// them, and at n = 100 its (n + 6)^2 system costs ~0.1 ms. Its polynomial part is quadratic,
// not the usual affine, and is not smoothed: a uniform or linearly varying motion (breathing's
// gradient) and a bowl (brain shift's sag, deeper in the middle) are reproduced without error.
// With the affine part, smoothing flattened a 10 mm sag: 1.15 mm RMS on held-out points after
// cortex-1h-compressed's shift, 0.052 mm with the quadratic (tests/vision/long_tracking_test).
// Measured against the mean displacement and the affine limit (large smoothing) on held-out
// material points: tests/vision/deformation_field_test.cpp, docs/ros2.md.

#include <Eigen/Dense>
#include <cstdint>
#include <opencv2/core.hpp>
#include <span>
#include <vector>

#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"

namespace pulsetrack::vision {

struct FieldConfig {
  bool enabled = true;
  double spacing_mm = 1.0;    // the grid's
  double margin_mm = 2.0;     // the grid reaches this far beyond the reference features
  double smoothing = 1000.0;  // TPS lambda (mm^2): 0 interpolates, large tends to the affine fit
  double huber_k = 3.0;       // residuals beyond k x the median residual are down-weighted
  int max_grid_points = 16384;
  // Confidence: 1 within one typical feature spacing of an ok feature, falling linearly to 0 at
  // `reach` spacings; beyond it a grid point is invalid (NaN in the point cloud).
  double reach = 3.0;
};
// The config's own check (the daemon's and the tools' readers call it): names the key.
Result<void> checkFieldConfig(const FieldConfig& c);

struct FieldQuery {
  cv::Vec3d position{0, 0, 0};      // mm, {C}: where the material point is now
  cv::Vec3d displacement{0, 0, 0};  // mm, since the reference pair
  double confidence = 0.0;          // as the grid's
};

class DeformationField {
 public:
  DeformationField(const FieldConfig& config, int max_features);

  // One pair's tracked features, as TrackingSession::process() returned them (`detected`: the
  // pair (re)detected; `detections`: the session's count, 1 at a fresh detection, which starts
  // a new signal). Returns whether the field holds for this pair (>= 6 ok features: the
  // spline's quadratic part needs them).
  bool update(std::span<const Feature> features, bool detected, uint32_t detections) noexcept;
  void reset() noexcept;

  [[nodiscard]] bool valid() const noexcept { return valid_; }
  // The grid, row-major (rows along e2, cols along e1), each a material point.
  [[nodiscard]] int cols() const noexcept { return cols_; }
  [[nodiscard]] int rows() const noexcept { return rows_; }
  [[nodiscard]] int points() const noexcept { return cols_ * rows_; }
  // Grid point k: rest position (reference pair) and displacement now, mm in {C}; confidence.
  [[nodiscard]] cv::Vec3d rest(int k) const noexcept {
    return {rest_(k, 0), rest_(k, 1), rest_(k, 2)};
  }
  [[nodiscard]] cv::Vec3d displacement(int k) const noexcept {
    return {disp_(k, 0), disp_(k, 1), disp_(k, 2)};
  }
  [[nodiscard]] double confidence(int k) const noexcept { return conf_[k]; }

  // Where the material point that was at `reference_mm` (in the reference pair, {C}) is now.
  // O(features); no allocation. Invalid field, or a point beyond the features' reach
  // (confidence 0): no displacement, the point where it was.
  [[nodiscard]] FieldQuery at(const cv::Vec3d& reference_mm) const noexcept;
  // The inverse: the reference position of the material point that is at `now_mm` in this pair
  // (a fixed-point iteration, exact to ~1e-9 mm for sub-mm motions). Invalid field: `now_mm`.
  [[nodiscard]] cv::Vec3d reference(const cv::Vec3d& now_mm) const noexcept;

  // Prediction (MotionPredictor's weights applied to the field): keep `history_s` of the
  // spline's solutions (allocated here, at most max_rate_hz of them per second); record() after
  // each valid update() at the pair's time; predict() fills `out` (points() x 3, mm) with the
  // grid's displacement at t + horizon, from the weights of that horizon:
  //   W(t + h) = W(t) + sum_j w_j (W(t - j step) - W(t - (j + 1) step)),  grid = basis x W.
  // False (and `out` untouched) while the history since the last re-detection is too short.
  void enablePrediction(double history_s, double max_rate_hz);
  void record(double t_s) noexcept;
  bool predict(std::span<const double> weights, double step_s, Eigen::MatrixXd& out) noexcept;

  // The surface frame: origin, e1, e2, normal ({C}).
  [[nodiscard]] const cv::Vec3d& origin() const noexcept { return origin_; }
  [[nodiscard]] const cv::Vec3d& axisS() const noexcept { return e1_; }
  [[nodiscard]] const cv::Vec3d& axisT() const noexcept { return e2_; }
  [[nodiscard]] const cv::Vec3d& normal() const noexcept { return nrm_; }
  [[nodiscard]] double spacing() const noexcept { return config_.spacing_mm; }
  // This pair: ok features used, of them down-weighted as outliers, factorizations done.
  [[nodiscard]] int used() const noexcept { return used_; }
  [[nodiscard]] int downweighted() const noexcept { return downweighted_; }
  [[nodiscard]] int factorizations() const noexcept { return factorizations_; }
  // The signal's number (bumped at each fresh detection): a consumer's grid indices hold within.
  [[nodiscard]] uint32_t signal() const noexcept { return signal_; }
  // The grid was clipped to max_grid_points (the features span more): its extent in mm.
  [[nodiscard]] bool clipped() const noexcept { return clipped_; }

 private:
  struct Node {
    int id = 0;
    size_t fidx = 0;           // the feature's index in this pair's span
    cv::Vec2d c{0, 0};         // plane coordinates of the reference position
    cv::Vec3d delta{0, 0, 0};  // added to point - point0
  };
  void start(std::span<const Feature> features);
  void rebuild(std::span<const Feature> features);  // new node set (allocates)
  void setNodes(std::vector<Node> next);            // the system's and the grid's basis
  [[nodiscard]] cv::Vec2d plane(const cv::Vec3d& p) const noexcept;
  [[nodiscard]] cv::Vec3d evaluate(const cv::Vec2d& c) const noexcept;
  void solve(std::span<const Feature> features) noexcept;
  void confidences() noexcept;

  FieldConfig config_;
  size_t max_features_;
  bool started_ = false, valid_ = false, clipped_ = false;
  uint32_t signal_ = 0, last_detections_ = 0;
  cv::Vec3d origin_{0, 0, 0}, e1_{1, 0, 0}, e2_{0, 1, 0}, nrm_{0, 0, -1};
  std::vector<Node> nodes_;
  std::vector<uint8_t> ok_, prev_ok_;
  std::vector<double> weight_, prev_weight_, scratch_;
  // The TPS system (n + 3) and its factorization; W: the solution (weights, affine) per axis.
  Eigen::MatrixXd base_, a_;
  Eigen::PartialPivLU<Eigen::MatrixXd> lu_;
  Eigen::MatrixXd y_, w_;
  bool factored_ = false;
  // The grid: basis (points x (n + 3)), rest positions, displacement, confidence.
  int cols_ = 0, rows_ = 0;
  double s0_ = 0, t0_ = 0;
  Eigen::MatrixXd g_, rest_, disp_;
  std::vector<double> conf_, nearest_;
  double typical_ = 1.0;  // the ok features' median nearest-neighbour spacing (mm)
  // The solutions' history for prediction: a ring of (t, W), cleared when the basis changes.
  [[nodiscard]] bool solutionAt(double t, Eigen::MatrixXd& w) const noexcept;
  std::vector<double> hist_t_;
  std::vector<Eigen::MatrixXd> hist_w_;
  size_t hist_head_ = 0, hist_size_ = 0;
  Eigen::MatrixXd w_pred_, w_a_, w_b_;
  int used_ = 0, downweighted_ = 0, factorizations_ = 0;
};

}  // namespace pulsetrack::vision
