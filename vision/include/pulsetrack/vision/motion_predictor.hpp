#pragma once
// MotionPredictor: where the surface will be when the robot's command lands (latency
// compensation), per pair, causal, at the horizons the config names.
//
// The model: the displacement's future increment is a linear function of its recent increments,
//   d(t + h) - d(t) = sum_j w_j (d(t - j s) - d(t - (j + 1) s)),   j = 0 .. order - 1,
// the lags s apart read from the pairs by linear interpolation (any frame rate, dropped pairs).
// A sum of sinusoids (breathing and its harmonics, cardiac, vasomotor) obeys such a recursion
// exactly, with weights that depend on the frequencies only, not on the amplitudes or the
// direction: so one set of weights per horizon, fitted on the three axes of the mean
// displacement, also predicts every point of the dense field. The weights: exponentially
// weighted least squares (memory_s) with a small ridge, solved every pair, so they follow a
// breathing rate or amplitude that changes.
//
// The guard: every prediction is scored when its time comes, against the measured signal, and so
// is holding the last value; the published prediction is the model's while its recent error
// (error_memory_s) is below holding's, else the last value (never worse than holding, lately).
// The expected error published with it: that recent error, 1 sigma per axis.
//
// Per pair: no allocation, no lock, no exception (buffers sized at construction).

#include <Eigen/Dense>
#include <array>
#include <opencv2/core.hpp>
#include <span>
#include <vector>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::vision {

inline constexpr int kMaxHorizons = 4;
inline constexpr int kMaxOrder = 32;

struct PredictionConfig {
  bool enabled = true;
  std::vector<double> horizons_s{0.05, 0.1, 0.2};
  double step_s = 0.05;         // the lags' spacing
  int order = 16;               // lags: the history used is order x step_s
  double memory_s = 20.0;       // the fit's forgetting time constant
  double error_memory_s = 5.0;  // the error estimates' (and the guard's)
  double max_rate_hz = 500.0;   // the history's capacity: pairs per second at most
};
// The config's own check: names the key ([prediction] ...).
Result<void> checkPredictionConfig(const PredictionConfig& c);

struct Prediction {
  int horizons = 0;
  std::array<double, kMaxHorizons> horizon_s{};
  std::array<cv::Vec3d, kMaxHorizons> displacement{};  // mm, predicted at t + horizon
  std::array<double, kMaxHorizons> sigma_mm{};  // expected error, 1 sigma per axis (0: unknown yet)
  std::array<bool, kMaxHorizons> model{};       // false: the last value (the model not better)
};

class MotionPredictor {
 public:
  explicit MotionPredictor(const PredictionConfig& config);
  void reset() noexcept;  // a new signal: forget the history and the fit
  // The signal at t (s): learns from it, scores the predictions now due, predicts.
  const Prediction& add(double t, const cv::Vec3d& d_mm) noexcept;
  [[nodiscard]] const Prediction& last() const noexcept { return out_; }
  // Horizon k's weights (order of them): what predict(), and the field's prediction, apply.
  [[nodiscard]] std::span<const double> weights(int k) const noexcept {
    return {w_[static_cast<size_t>(k)].data(), static_cast<size_t>(order_)};
  }
  [[nodiscard]] int order() const noexcept { return order_; }
  [[nodiscard]] double step() const noexcept { return config_.step_s; }
  // The recent RMS errors (3D, mm) of the model and of holding, horizon k.
  [[nodiscard]] double modelRms(int k) const noexcept;
  [[nodiscard]] double holdRms(int k) const noexcept;

 private:
  bool at(double t, cv::Vec3d& d) const noexcept;  // interpolated from the history
  bool lags(double t, std::array<cv::Vec3d, kMaxOrder>& x) const noexcept;

  PredictionConfig config_;
  int order_ = 16, horizons_ = 0;
  // The history: (t, d) of the pairs, oldest first in a ring.
  std::vector<double> t_;
  std::vector<cv::Vec3d> d_;
  size_t head_ = 0, size_ = 0;
  double last_t_ = 0.0;
  // Per horizon: the fit's normal equations and weights, the pending predictions, the errors.
  using Mat = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kMaxOrder, kMaxOrder>;
  using Vec = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxOrder, 1>;
  std::array<Mat, kMaxHorizons> normal_;
  std::array<Vec, kMaxHorizons> rhs_;
  std::array<std::array<double, kMaxOrder>, kMaxHorizons> w_{};
  std::array<int, kMaxHorizons> fitted_{};  // training samples so far
  struct Pending {
    double t = 0;  // when it is due
    cv::Vec3d model, hold;
  };
  std::array<std::vector<Pending>, kMaxHorizons> pending_;
  std::array<size_t, kMaxHorizons> pending_head_{}, pending_size_{};
  std::array<double, kMaxHorizons> mse_model_{}, mse_hold_{};
  std::array<int, kMaxHorizons> scored_{};
  std::array<double, kMaxHorizons> last_scored_t_{};
  Prediction out_;
};

}  // namespace pulsetrack::vision
