#include "pulsetrack/vision/deformation_field.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "ring_bracket.hpp"

namespace pulsetrack::vision {

namespace {

// The TPS kernel r^2 log r, from r^2.
inline double phi(double r2) noexcept { return r2 > 1e-300 ? 0.5 * r2 * std::log(r2) : 0.0; }

// The spline's polynomial part: quadratic in (s, t), not only affine, so that a bowl (the sag of
// brain shift: 10 mm in the centre, half at the rim) is in the null space and the smoothing does
// not flatten it (affine: 1.15 mm RMS on held-out points after cortex-1h-compressed's sag).
// Scaled by 30 mm so the terms are of order 1.
constexpr int kPoly = 6;
constexpr double kPolyScaleMm = 30.0;
inline void polyTerms(const cv::Vec2d& c, double* p) noexcept {
  const double u = c[0] / kPolyScaleMm, v = c[1] / kPolyScaleMm;
  p[0] = 1.0;
  p[1] = u;
  p[2] = v;
  p[3] = u * u;
  p[4] = u * v;
  p[5] = v * v;
}

constexpr double kMinScaleMm = 0.005;  // residual scale floor: a perfect fit flags nothing
constexpr int kIterations = 4;         // IRLS at most

}  // namespace

Result<void> checkFieldConfig(const FieldConfig& c) {
  if (!(c.spacing_mm >= 0.05 && c.spacing_mm <= 20.0))
    return fail(fmt::format("[field] spacing_mm = {}: must be in [0.05, 20] mm", c.spacing_mm));
  if (!(c.margin_mm >= 0.0 && c.margin_mm <= 50.0))
    return fail(fmt::format("[field] margin_mm = {}: must be in [0, 50] mm", c.margin_mm));
  if (!(c.smoothing > 0.0 && c.smoothing <= 1e6))
    return fail(
        fmt::format("[field] smoothing = {}: must be in (0, 1e6] mm^2 (0 would "
                    "interpolate every feature's noise and outliers)",
                    c.smoothing));
  if (!(c.huber_k >= 1.0 && c.huber_k <= 100.0))
    return fail(fmt::format("[field] huber_k = {}: must be in [1, 100]", c.huber_k));
  if (c.max_grid_points < 4 || c.max_grid_points > 1'000'000)
    return fail(
        fmt::format("[field] max_grid_points = {}: must be in [4, 1000000]", c.max_grid_points));
  if (!(c.reach >= 1.0 && c.reach <= 100.0))
    return fail(fmt::format("[field] reach = {}: must be in [1, 100] feature spacings", c.reach));
  return {};
}

DeformationField::DeformationField(const FieldConfig& config, int max_features)
    : config_(config), max_features_(static_cast<size_t>(std::max(1, max_features))) {
  nodes_.reserve(max_features_);
  ok_.assign(max_features_, 0);
  prev_ok_.assign(max_features_, 0);
  weight_.assign(max_features_, 1.0);
  prev_weight_.assign(max_features_, 1.0);
  scratch_.assign(max_features_, 0.0);
}

void DeformationField::reset() noexcept {
  started_ = valid_ = factored_ = false;
  nodes_.clear();
  last_detections_ = 0;
}

cv::Vec2d DeformationField::plane(const cv::Vec3d& p) const noexcept {
  const cv::Vec3d d = p - origin_;
  return {d.dot(e1_), d.dot(e2_)};
}

void DeformationField::start(std::span<const Feature> features) {
  // The surface frame from the reference positions of the ok features.
  cv::Vec3d c(0, 0, 0);
  int n = 0;
  for (const Feature& f : features) {
    if (f.status != FeatureStatus::kOk) continue;
    c += f.point0;
    ++n;
  }
  if (n < kPoly) return;
  c /= n;
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const Feature& f : features) {
    if (f.status != FeatureStatus::kOk) continue;
    const Eigen::Vector3d d(f.point0[0] - c[0], f.point0[1] - c[1], f.point0[2] - c[2]);
    cov += d * d.transpose();
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
  const Eigen::Vector3d nv = es.eigenvectors().col(0);  // the smallest spread: the normal
  cv::Vec3d nrm(nv[0], nv[1], nv[2]);
  if (nrm.dot(c) > 0) nrm = -nrm;  // towards the cameras (the origin of {C})
  cv::Vec3d e1 = cv::Vec3d(1, 0, 0) - nrm * nrm[0];
  if (cv::norm(e1) < 1e-6) e1 = cv::Vec3d(0, 1, 0) - nrm * nrm[1];
  e1 /= cv::norm(e1);
  origin_ = c;
  nrm_ = nrm;
  e1_ = e1;
  e2_ = nrm.cross(e1);
  ++signal_;
  started_ = true;
  nodes_.clear();
  valid_ = false;
  rebuild(features);
  // The grid over the features' extent (+ margin), at the spacing.
  double smin = 1e300, smax = -1e300, tmin = 1e300, tmax = -1e300;
  for (const Node& nd : nodes_) {
    smin = std::min(smin, nd.c[0]);
    smax = std::max(smax, nd.c[0]);
    tmin = std::min(tmin, nd.c[1]);
    tmax = std::max(tmax, nd.c[1]);
  }
  const double h = config_.spacing_mm, m = config_.margin_mm;
  s0_ = std::floor((smin - m) / h) * h;
  t0_ = std::floor((tmin - m) / h) * h;
  cols_ = static_cast<int>(std::ceil((smax + m - s0_) / h - 1e-9)) + 1;
  rows_ = static_cast<int>(std::ceil((tmax + m - t0_) / h - 1e-9)) + 1;
  clipped_ = false;
  while (static_cast<long>(cols_) * rows_ > config_.max_grid_points) {  // keep the middle
    clipped_ = true;
    if (cols_ >= rows_) {
      --cols_;
      s0_ += cols_ % 2 == 0 ? h : 0.0;
    } else {
      --rows_;
      t0_ += rows_ % 2 == 0 ? h : 0.0;
    }
  }
  // The rest surface: a spline of the reference heights over (s, t), the same nodes.
  const auto k = static_cast<Eigen::Index>(nodes_.size());
  Eigen::MatrixXd a = Eigen::MatrixXd::Zero(k + kPoly, k + kPoly);
  Eigen::VectorXd z = Eigen::VectorXd::Zero(k + kPoly);
  for (Eigen::Index i = 0; i < k; ++i)
    z[i] = (features[nodes_[static_cast<size_t>(i)].fidx].point0 - origin_).dot(nrm_);
  a.topLeftCorner(k, k) = base_.topLeftCorner(k, k);
  // The reference surface is a measured shape (0.8 mm gyri, ~3 mm of curvature over the field),
  // not a motion: nearly interpolated (1e-4 of the smoothing).
  for (Eigen::Index r = 0; r < k; ++r) a(r, r) += config_.smoothing * 1e-4;
  a.topRightCorner(k, kPoly) = base_.topRightCorner(k, kPoly);
  a.bottomLeftCorner(kPoly, k) = base_.bottomLeftCorner(kPoly, k);
  const Eigen::VectorXd hz = a.partialPivLu().solve(z);
  rest_.resize(static_cast<Eigen::Index>(cols_) * rows_, 3);
  for (int r = 0; r < rows_; ++r) {
    for (int q = 0; q < cols_; ++q) {
      const cv::Vec2d st(s0_ + q * h, t0_ + r * h);
      double pt[kPoly];
      polyTerms(st, pt);
      double zz = 0.0;
      for (int q2 = 0; q2 < kPoly; ++q2) zz += hz[k + q2] * pt[q2];
      for (Eigen::Index j = 0; j < k; ++j) {
        const cv::Vec2d d = st - nodes_[static_cast<size_t>(j)].c;
        zz += hz[j] * phi(d.dot(d));
      }
      const cv::Vec3d p = origin_ + st[0] * e1_ + st[1] * e2_ + zz * nrm_;
      const Eigen::Index idx = static_cast<Eigen::Index>(r) * cols_ + q;
      rest_(idx, 0) = p[0];
      rest_(idx, 1) = p[1];
      rest_(idx, 2) = p[2];
    }
  }
  disp_.setZero(rest_.rows(), 3);
  conf_.assign(static_cast<size_t>(rest_.rows()), 0.0);
  nearest_.assign(static_cast<size_t>(rest_.rows()), 0.0);
  rebuild(features);  // now with the grid's basis
}

void DeformationField::rebuild(std::span<const Feature> features) {
  // Match by id: a node keeps its reference. A new feature (a re-detection's) joins where this
  // pair's field maps its position back to the reference pair: the field is solved from the
  // known features first.
  std::vector<Node> next;
  next.reserve(max_features_);
  bool any_new = false;
  for (size_t i = 0; i < features.size() && next.size() < max_features_; ++i) {
    const Feature& f = features[i];
    const auto old =
        std::find_if(nodes_.begin(), nodes_.end(), [&](const Node& n) { return n.id == f.id; });
    if (old == nodes_.end()) {
      any_new = true;
      continue;
    }
    next.push_back(*old);
    next.back().fidx = i;
  }
  if (any_new && !next.empty() && valid_) {
    setNodes(std::move(next));
    solve(features);
    next = nodes_;
  }
  const bool solved = valid_ && !next.empty();
  for (size_t i = 0; i < features.size() && next.size() < max_features_; ++i) {
    const Feature& f = features[i];
    if (std::any_of(next.begin(), next.end(), [&](const Node& n) { return n.id == f.id; }))
      continue;
    Node nd;
    nd.id = f.id;
    nd.fidx = i;
    const cv::Vec3d ref = solved ? reference(f.point0) : f.point0;
    nd.c = plane(ref);
    nd.delta = f.point0 - ref;
    next.push_back(nd);
  }
  // In the features' order, so that the steady state's node i is feature i.
  std::sort(next.begin(), next.end(), [](const Node& a, const Node& b) { return a.fidx < b.fidx; });
  setNodes(std::move(next));
}

void DeformationField::setNodes(std::vector<Node> next) {
  nodes_ = std::move(next);
  const auto k = static_cast<Eigen::Index>(nodes_.size());
  base_.setZero(k + kPoly, k + kPoly);
  for (Eigen::Index i = 0; i < k; ++i) {
    const cv::Vec2d& ci = nodes_[static_cast<size_t>(i)].c;
    for (Eigen::Index j = 0; j < i; ++j) {
      const cv::Vec2d d = ci - nodes_[static_cast<size_t>(j)].c;
      base_(i, j) = base_(j, i) = phi(d.dot(d));
    }
    double pt[kPoly];
    polyTerms(ci, pt);
    for (int q = 0; q < kPoly; ++q) base_(i, k + q) = base_(k + q, i) = pt[q];
  }
  a_.resize(k + kPoly, k + kPoly);
  lu_ = Eigen::PartialPivLU<Eigen::MatrixXd>(k + kPoly);
  hist_head_ = hist_size_ = 0;  // a new basis: the solutions before it do not combine with it
  for (Eigen::MatrixXd& h : hist_w_) h.setZero(k + kPoly, 3);
  w_pred_.setZero(k + kPoly, 3);
  w_a_.setZero(k + kPoly, 3);
  w_b_.setZero(k + kPoly, 3);
  y_.setZero(k + kPoly, 3);
  w_.setZero(k + kPoly, 3);
  factored_ = false;
  std::fill(prev_ok_.begin(), prev_ok_.end(), 0);
  std::fill(weight_.begin(), weight_.end(), 1.0);
  if (rest_.rows() > 0) {
    const Eigen::Index m = rest_.rows();
    g_.resize(m, k + kPoly);
    for (int r = 0; r < rows_; ++r) {
      for (int q = 0; q < cols_; ++q) {
        const Eigen::Index idx = static_cast<Eigen::Index>(r) * cols_ + q;
        const cv::Vec2d st(s0_ + q * config_.spacing_mm, t0_ + r * config_.spacing_mm);
        for (Eigen::Index j = 0; j < k; ++j) {
          const cv::Vec2d d = st - nodes_[static_cast<size_t>(j)].c;
          g_(idx, j) = phi(d.dot(d));
        }
        double pt[kPoly];
        polyTerms(st, pt);
        for (int q2 = 0; q2 < kPoly; ++q2) g_(idx, k + q2) = pt[q2];
      }
    }
  }
}

cv::Vec3d DeformationField::evaluate(const cv::Vec2d& c) const noexcept {
  const auto k = static_cast<Eigen::Index>(nodes_.size());
  if (w_.rows() != k + kPoly) return {0, 0, 0};
  double pt[kPoly];
  polyTerms(c, pt);
  double d[3] = {0.0, 0.0, 0.0};
  for (int a = 0; a < 3; ++a)
    for (int q = 0; q < kPoly; ++q) d[a] += w_(k + q, a) * pt[q];
  for (Eigen::Index j = 0; j < k; ++j) {
    if (w_(j, 0) == 0.0 && w_(j, 1) == 0.0 && w_(j, 2) == 0.0) continue;
    const cv::Vec2d e = c - nodes_[static_cast<size_t>(j)].c;
    const double p = phi(e.dot(e));
    for (int a = 0; a < 3; ++a) d[a] += w_(j, a) * p;
  }
  return {d[0], d[1], d[2]};
}

void DeformationField::solve(std::span<const Feature> features) noexcept {
  const size_t n = nodes_.size();
  used_ = 0;
  for (size_t i = 0; i < n; ++i) {
    const Feature& f = features[nodes_[i].fidx];
    ok_[i] = f.status == FeatureStatus::kOk ? 1 : 0;
    used_ += ok_[i];
    const cv::Vec3d y = f.point - f.point0 + nodes_[i].delta;
    for (int a = 0; a < 3; ++a) y_(static_cast<Eigen::Index>(i), a) = ok_[i] != 0 ? y[a] : 0.0;
    if (ok_[i] == 0) weight_[i] = 1.0;  // an ok one starts from its last pair's weight
  }
  downweighted_ = 0;
  valid_ = used_ >= kPoly;
  if (!valid_) return;
  for (int it = 0; it < kIterations; ++it) {
    bool same = factored_;
    for (size_t i = 0; i < n && same; ++i)
      same = ok_[i] == prev_ok_[i] && (ok_[i] == 0 || weight_[i] == prev_weight_[i]);
    if (!same) {
      // Not ok: row and column i replaced by the identity (its weight is 0, it pulls on nothing).
      a_ = base_;
      for (size_t i = 0; i < n; ++i) {
        const auto ii = static_cast<Eigen::Index>(i);
        if (ok_[i] == 0) {
          a_.row(ii).setZero();
          a_.col(ii).setZero();
          a_(ii, ii) = 1.0;
        } else {
          a_(ii, ii) += config_.smoothing / weight_[i];
        }
      }
      lu_.compute(a_);
      ++factorizations_;
      factored_ = true;
      std::copy_n(ok_.begin(), n, prev_ok_.begin());
      std::copy_n(weight_.begin(), n, prev_weight_.begin());
    }
    w_.noalias() = lu_.solve(y_);
    // Residuals at the nodes: y - f(c_i) = (lambda / w_i) x_i.
    size_t m = 0;
    for (size_t i = 0; i < n; ++i) {
      if (ok_[i] == 0) continue;
      const auto ii = static_cast<Eigen::Index>(i);
      const double r = config_.smoothing / weight_[i] * w_.row(ii).norm();
      scratch_[m++] = r;
    }
    std::nth_element(scratch_.begin(), scratch_.begin() + static_cast<long>(m / 2),
                     scratch_.begin() + static_cast<long>(m));
    const double tau = config_.huber_k * std::max(scratch_[m / 2], kMinScaleMm);
    bool changed = false;
    downweighted_ = 0;
    for (size_t i = 0; i < n; ++i) {
      if (ok_[i] == 0) continue;
      const auto ii = static_cast<Eigen::Index>(i);
      // The residual had the weight's smoothing; the Huber weight from it.
      const double r = config_.smoothing / weight_[i] * w_.row(ii).norm();
      // (tau / r)^2: an outlier's pull falls with its distance (Huber's tau / r kept 0.5 mm
      // outliers at 1.9x the clean error in deformation_field_test; this, 1.1x).
      double wi = r <= tau ? 1.0 : (tau / r) * (tau / r);
      wi = std::max(wi, 1e-3);
      if (wi < 1.0) ++downweighted_;
      // Quantized, so that the iteration settles and an unchanged set keeps its factors.
      wi = std::ldexp(std::round(std::ldexp(wi, 6)), -6);
      wi = std::max(wi, 1.0 / 64);
      if (wi != weight_[i]) changed = true;
      weight_[i] = wi;
    }
    if (!changed) break;
  }
}

void DeformationField::confidences() noexcept {
  // The ok nodes' typical spacing (median nearest neighbour), then each grid point's nearest.
  const size_t n = nodes_.size();
  size_t m = 0;
  for (size_t i = 0; i < n; ++i) {
    if (ok_[i] == 0) continue;
    double best = 1e300;
    for (size_t j = 0; j < n; ++j) {
      if (j == i || ok_[j] == 0) continue;
      const cv::Vec2d d = nodes_[i].c - nodes_[j].c;
      best = std::min(best, d.dot(d));
    }
    scratch_[m++] = std::sqrt(best);
  }
  std::nth_element(scratch_.begin(), scratch_.begin() + static_cast<long>(m / 2),
                   scratch_.begin() + static_cast<long>(m));
  // The spacing: twice the median nearest-neighbour distance (a point between two features is
  // about one nearest-neighbour distance from each).
  typical_ = std::max(2.0 * scratch_[m / 2], 1e-3);
  const double reach = config_.reach;
  for (int r = 0; r < rows_; ++r) {
    for (int q = 0; q < cols_; ++q) {
      const size_t idx = static_cast<size_t>(r) * static_cast<size_t>(cols_) + q;
      const cv::Vec2d st(s0_ + q * config_.spacing_mm, t0_ + r * config_.spacing_mm);
      double best = 1e300;
      for (size_t j = 0; j < n; ++j) {
        if (ok_[j] == 0) continue;
        const cv::Vec2d d = st - nodes_[j].c;
        best = std::min(best, d.dot(d));
      }
      const double u = std::sqrt(best) / typical_;
      conf_[idx] = std::clamp(1.0 - (u - 1.0) / (reach - 1.0), 0.0, 1.0);
      if (reach <= 1.0) conf_[idx] = u <= 1.0 ? 1.0 : 0.0;
    }
  }
}

bool DeformationField::update(std::span<const Feature> features, bool detected,
                              uint32_t detections) noexcept {
  // A fresh detection (or one this consumer missed: the count went back) starts a new signal.
  if (!started_ || (detected && detections <= 1) || detections < last_detections_) {
    valid_ = false;
    nodes_.clear();
    rest_.resize(0, 3);
    start(features);
    if (!started_) return false;
  }
  last_detections_ = detections;
  bool same = features.size() == nodes_.size();
  for (size_t i = 0; i < features.size() && same; ++i)
    same = features[i].id == nodes_[i].id && nodes_[i].fidx == i;
  if (!same) rebuild(features);  // a re-detection: new features, retired ones
  const bool ok_changed = [&] {
    for (size_t i = 0; i < nodes_.size(); ++i)
      if ((features[nodes_[i].fidx].status == FeatureStatus::kOk) != (prev_ok_[i] != 0))
        return true;
    return !factored_;
  }();
  solve(features);
  if (!valid_) return false;
  if (ok_changed) confidences();
  for (int a = 0; a < 3; ++a) disp_.col(a).noalias() = g_ * w_.col(a);
  return true;
}

void DeformationField::enablePrediction(double history_s, double max_rate_hz) {
  const auto cap = static_cast<size_t>(std::ceil(history_s * max_rate_hz)) + 4;
  hist_t_.assign(cap, 0.0);
  hist_w_.assign(cap, Eigen::MatrixXd::Zero(w_.rows(), 3));
  hist_head_ = hist_size_ = 0;
}

void DeformationField::record(double t_s) noexcept {
  if (!valid_ || hist_t_.empty()) return;
  const size_t cap = hist_t_.size();
  if (hist_size_ > 0 && t_s <= hist_t_[(hist_head_ + hist_size_ - 1) % cap]) return;
  const size_t slot = (hist_head_ + hist_size_) % cap;
  hist_t_[slot] = t_s;
  hist_w_[slot] = w_;  // the same size since the last rebuild: no allocation
  if (hist_size_ < cap)
    ++hist_size_;
  else
    hist_head_ = (hist_head_ + 1) % cap;
}

bool DeformationField::solutionAt(double t, Eigen::MatrixXd& w) const noexcept {
  size_t a = 0, b = 0;
  double f = 0.0;
  if (!ringBracket(hist_t_, hist_head_, hist_size_, t, a, b, f)) return false;
  if (a == b)
    w = hist_w_[b];
  else
    w = (1.0 - f) * hist_w_[a] + f * hist_w_[b];
  return true;
}

bool DeformationField::predict(std::span<const double> weights, double step_s,
                               Eigen::MatrixXd& out) noexcept {
  if (!valid_ || hist_size_ == 0) return false;
  const double t = hist_t_[(hist_head_ + hist_size_ - 1) % hist_t_.size()];
  if (!solutionAt(t, w_a_)) return false;
  w_pred_ = w_;
  for (size_t j = 0; j < weights.size(); ++j) {
    if (!solutionAt(t - static_cast<double>(j + 1) * step_s, w_b_)) return false;
    w_pred_ += weights[j] * (w_a_ - w_b_);
    w_a_.swap(w_b_);
  }
  if (out.rows() != g_.rows() || out.cols() != 3) return false;  // the caller sizes it
  for (int a = 0; a < 3; ++a) out.col(a).noalias() = g_ * w_pred_.col(a);
  return true;
}

cv::Vec3d DeformationField::reference(const cv::Vec3d& now_mm) const noexcept {
  if (!valid_) return now_mm;
  // A fixed point: converges at the displacement's gradient (0.2 in a deep sag).
  cv::Vec3d ref = now_mm;
  for (int it = 0; it < 30; ++it) {
    const cv::Vec3d nref = now_mm - evaluate(plane(ref));
    const double step = cv::norm(nref - ref);
    ref = nref;
    if (step < 1e-9) break;
  }
  return ref;
}

FieldQuery DeformationField::at(const cv::Vec3d& reference_mm) const noexcept {
  FieldQuery q;
  q.position = reference_mm;
  if (!valid_) return q;
  const cv::Vec2d c = plane(reference_mm);
  q.displacement = evaluate(c);
  q.position = reference_mm + q.displacement;
  double best = 1e300;
  for (size_t j = 0; j < nodes_.size(); ++j) {
    if (ok_[j] == 0) continue;
    const cv::Vec2d d = c - nodes_[j].c;
    best = std::min(best, d.dot(d));
  }
  const double u = std::sqrt(best) / typical_;
  q.confidence = std::clamp(1.0 - (u - 1.0) / (config_.reach - 1.0), 0.0, 1.0);
  if (q.confidence <= 0.0) {  // beyond the features' reach: no answer, the point stays
    q.displacement = cv::Vec3d(0, 0, 0);
    q.position = reference_mm;
  }
  return q;
}

}  // namespace pulsetrack::vision
