#include "pulsetrack/vision/motion_predictor.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "ring_bracket.hpp"

namespace pulsetrack::vision {

Result<void> checkPredictionConfig(const PredictionConfig& c) {
  if (c.horizons_s.empty() || c.horizons_s.size() > static_cast<size_t>(kMaxHorizons))
    return fail(fmt::format("[prediction] horizons_ms: 1 to {} horizons, got {}", kMaxHorizons,
                            c.horizons_s.size()));
  for (double h : c.horizons_s) {
    if (!(h > 0.0 && h <= 2.0))
      return fail(fmt::format("[prediction] horizons_ms: {} ms is not in (0, 2000] ms", h * 1e3));
  }
  if (!(c.step_s >= 0.005 && c.step_s <= 0.5))
    return fail(fmt::format("[prediction] step_ms = {}: must be in [5, 500] ms", c.step_s * 1e3));
  if (c.order < 2 || c.order > kMaxOrder)
    return fail(fmt::format("[prediction] order = {}: must be in [2, {}]", c.order, kMaxOrder));
  if (!(c.memory_s >= 1.0 && c.memory_s <= 3600.0))
    return fail(fmt::format("[prediction] memory_s = {}: must be in [1, 3600] s", c.memory_s));
  if (!(c.error_memory_s >= 0.5 && c.error_memory_s <= 600.0))
    return fail(
        fmt::format("[prediction] error_memory_s = {}: must be in [0.5, 600] s", c.error_memory_s));
  if (!(c.max_rate_hz >= 1.0 && c.max_rate_hz <= 2000.0))
    return fail(fmt::format("[prediction] max_rate_hz = {}: must be in [1, 2000]", c.max_rate_hz));
  return {};
}

MotionPredictor::MotionPredictor(const PredictionConfig& config) : config_(config) {
  order_ = std::clamp(config_.order, 2, kMaxOrder);
  horizons_ = static_cast<int>(std::min(config_.horizons_s.size(), size_t{kMaxHorizons}));
  double h_max = 0.0;
  for (int k = 0; k < horizons_; ++k) h_max = std::max(h_max, config_.horizons_s[size_t(k)]);
  const double span = order_ * config_.step_s + h_max + 0.5;
  const auto cap = static_cast<size_t>(std::ceil(span * config_.max_rate_hz)) + 4;
  t_.assign(cap, 0.0);
  d_.assign(cap, cv::Vec3d(0, 0, 0));
  for (int k = 0; k < horizons_; ++k) {
    const auto kk = static_cast<size_t>(k);
    normal_[kk] = Mat::Zero(order_, order_);
    rhs_[kk] = Vec::Zero(order_);
    pending_[kk].assign(
        static_cast<size_t>(std::ceil(config_.horizons_s[kk] * config_.max_rate_hz)) + 4,
        Pending{});
  }
  reset();
}

void MotionPredictor::reset() noexcept {
  head_ = size_ = 0;
  last_t_ = 0.0;
  out_ = {};
  out_.horizons = horizons_;
  for (int k = 0; k < horizons_; ++k) {
    const auto kk = static_cast<size_t>(k);
    normal_[kk].setZero();
    rhs_[kk].setZero();
    w_[kk].fill(0.0);
    fitted_[kk] = 0;
    pending_head_[kk] = pending_size_[kk] = 0;
    mse_model_[kk] = mse_hold_[kk] = 0.0;
    scored_[kk] = 0;
    out_.horizon_s[kk] = config_.horizons_s[kk];
  }
}

double MotionPredictor::modelRms(int k) const noexcept {
  return std::sqrt(mse_model_[static_cast<size_t>(k)]);
}
double MotionPredictor::holdRms(int k) const noexcept {
  return std::sqrt(mse_hold_[static_cast<size_t>(k)]);
}

bool MotionPredictor::at(double t, cv::Vec3d& d) const noexcept {
  size_t a = 0, b = 0;
  double f = 0.0;
  if (!ringBracket(t_, head_, size_, t, a, b, f)) return false;
  d = a == b ? d_[b] : d_[a] + f * (d_[b] - d_[a]);
  return true;
}

bool MotionPredictor::lags(double t, std::array<cv::Vec3d, kMaxOrder>& x) const noexcept {
  cv::Vec3d prev;
  if (!at(t, prev)) return false;
  for (int j = 0; j < order_; ++j) {
    cv::Vec3d next;
    if (!at(t - (j + 1) * config_.step_s, next)) return false;
    x[static_cast<size_t>(j)] = prev - next;
    prev = next;
  }
  return true;
}

const Prediction& MotionPredictor::add(double t, const cv::Vec3d& d) noexcept {
  if (size_ > 0 && t < last_t_) reset();  // time went back: a new signal
  const double dt = size_ > 0 ? t - last_t_ : 0.0;
  if (size_ == 0 || dt > 0.0) {
    const size_t cap = t_.size();
    const size_t slot = (head_ + size_) % cap;
    t_[slot] = t;
    d_[slot] = d;
    if (size_ < cap)
      ++size_;
    else
      head_ = (head_ + 1) % cap;
    last_t_ = t;
  }
  std::array<cv::Vec3d, kMaxOrder> x{};
  const bool have_lags = lags(t, x);
  for (int k = 0; k < horizons_; ++k) {
    const auto kk = static_cast<size_t>(k);
    const double h = config_.horizons_s[kk];
    // Score the predictions now due, against the measured signal (interpolated).
    std::vector<Pending>& pend = pending_[kk];
    while (pending_size_[kk] > 0) {
      const Pending& p = pend[pending_head_[kk]];
      cv::Vec3d truth;
      if (p.t > t || !at(p.t, truth)) break;
      const double em = (p.model - truth).dot(p.model - truth);
      const double eh = (p.hold - truth).dot(p.hold - truth);
      const double a = scored_[kk] == 0
                           ? 1.0
                           : 1.0 - std::exp(-(p.t - last_scored_t_[kk]) / config_.error_memory_s);
      mse_model_[kk] += a * (em - mse_model_[kk]);
      mse_hold_[kk] += a * (eh - mse_hold_[kk]);
      ++scored_[kk];
      last_scored_t_[kk] = p.t;
      pending_head_[kk] = (pending_head_[kk] + 1) % pend.size();
      --pending_size_[kk];
    }
    // Learn from the sample h ago: its lags, and what followed.
    std::array<cv::Vec3d, kMaxOrder> xs{};
    cv::Vec3d ds;
    if (dt > 0.0 && lags(t - h, xs) && at(t - h, ds)) {
      const double lambda = std::exp(-dt / config_.memory_s);
      normal_[kk] *= lambda;
      rhs_[kk] *= lambda;
      const cv::Vec3d y = d - ds;
      for (int a = 0; a < 3; ++a) {
        Vec v(order_);
        for (int j = 0; j < order_; ++j) v[j] = xs[static_cast<size_t>(j)][a];
        normal_[kk].noalias() += v * v.transpose();
        rhs_[kk].noalias() += v * y[a];
      }
      ++fitted_[kk];
      if (fitted_[kk] >= order_) {
        Mat m = normal_[kk];
        const double ridge = 1e-6 * m.trace() / order_ + 1e-15;
        for (int j = 0; j < order_; ++j) m(j, j) += ridge;
        const Eigen::LLT<Mat> llt(m);
        if (llt.info() == Eigen::Success) {
          const Vec w = llt.solve(rhs_[kk]);
          for (int j = 0; j < order_; ++j) w_[kk][static_cast<size_t>(j)] = w[j];
        }
      }
    }
    // Predict, and keep it to be scored.
    cv::Vec3d model = d;
    if (have_lags && fitted_[kk] >= order_) {
      for (int j = 0; j < order_; ++j)
        model += w_[kk][static_cast<size_t>(j)] * x[static_cast<size_t>(j)];
    }
    if (dt > 0.0 || size_ == 1) {
      const size_t cap = pend.size();
      if (pending_size_[kk] == cap) {  // full: drop the oldest
        pending_head_[kk] = (pending_head_[kk] + 1) % cap;
        --pending_size_[kk];
      }
      pend[(pending_head_[kk] + pending_size_[kk]) % cap] = {t + h, model, d};
      ++pending_size_[kk];
    }
    const bool use = have_lags && fitted_[kk] >= 2 * order_ && scored_[kk] >= 10 &&
                     mse_model_[kk] < mse_hold_[kk];
    out_.displacement[kk] = use ? model : d;
    out_.model[kk] = use;
    out_.sigma_mm[kk] =
        scored_[kk] == 0 ? 0.0 : std::sqrt((use ? mse_model_[kk] : mse_hold_[kk]) / 3.0);
  }
  return out_;
}

}  // namespace pulsetrack::vision
