#include "pulsetrack/vision/tracking_session.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>
#include <opencv2/imgproc.hpp>

#include "pulsetrack/vision/affine_refiner.hpp"

namespace pulsetrack::vision {

namespace {

constexpr size_t kRing = 256;  // velocity window samples at most (0.25 s at 1 kHz)

std::string roiText(const cv::Rect& r) {
  return fmt::format("{},{} {}x{}", r.x, r.y, r.width, r.height);
}

}  // namespace

const char* toString(SessionState s) noexcept {
  switch (s) {
    case SessionState::kTracking:
      return "tracking";
    case SessionState::kNoFeatures:
      return "no features";
    case SessionState::kStopped:
      return "stopped";
  }
  return "unknown";
}

TrackingSession::TrackingSession(const StereoRig& rig, const SessionConfig& config)
    : tracker_(rig, config.tracker), rig_(rig), config_(config), predictor_(config.prediction) {
  const auto n = static_cast<size_t>(std::max(1, config_.tracker.max_features));
  prev_ok_.assign(n, 0);
  prev_d_.assign(n, cv::Vec3d(0, 0, 0));
  ids_.assign(n, -1);
  dhat_.assign(n, cv::Vec3d(0, 0, 0));
  birth_.assign(n, cv::Vec3d(0, 0, 0));
  scratch_ok_.assign(n, 0);
  scratch_d_.assign(3 * n, cv::Vec3d(0, 0, 0));
  neighbours_ = static_cast<size_t>(std::clamp(config_.tracker.reacquire_neighbours, 1, 16));
  nb_idx_.assign(n * neighbours_, -1);
  nb_d_.assign(n * neighbours_, cv::Vec3d(0, 0, 0));
  scratch_nb_idx_.assign(n * neighbours_, -1);
  scratch_nb_d_.assign(n * neighbours_, cv::Vec3d(0, 0, 0));
  old_to_new_.assign(n, -1);
  ring_.assign(kRing, Sample{0.0, {0, 0, 0}});
  out_.reserve(n);
  setRoi(config_.roi, config_.depth_tolerance_mm);
}

StereoRig TrackingSession::scaledRig(const StereoRig& rig, double scale) {
  StereoRig out = rig;
  for (CameraModel* cam : {&out.left, &out.right}) {
    const cv::Size from = cam->imageSize();
    cv::Matx33d k = cam->k();
    k(0, 0) *= scale;
    k(0, 1) *= scale;
    k(0, 2) = (k(0, 2) + 0.5) * scale - 0.5;
    k(1, 1) *= scale;
    k(1, 2) = (k(1, 2) + 0.5) * scale - 0.5;
    const cv::Size size(static_cast<int>(from.width * scale),
                        static_cast<int>(from.height * scale));
    *cam = CameraModel(k, cam->dist().data(), cam->numDistortion(), size);
  }
  return out;
}

Result<void> TrackingSession::checkScale(double scale) {
  if (scale == 0.0 || scale == 1.0 || scale == 0.5) return {};
  return fail(
      fmt::format("scale {:g}: must be 0 (chosen at the first detection), 1 or 0.5", scale));
}

void TrackingSession::setScale(double scale, int next_id) {
  scale_ = scale;
  tracker_ = StereoTracker(scale == 1.0 ? rig_ : scaledRig(rig_, scale), config_.tracker);
  tracker_.continueIds(next_id);
}

void TrackingSession::toWork(const cv::Mat& left, const cv::Mat& right) {
  if (scale_ == 1.0) return;
  // Half size: each pixel the mean of a 2x2 block (an odd last row or column left out), so a
  // pixel centre x of the half image is 2x + 0.5 of the full one. A plain loop: OpenCV's
  // INTER_AREA allocates its tables on every call.
  for (const auto& [from, to] : {std::pair{&left, &work_l_}, std::pair{&right, &work_r_}}) {
    to->create(from->rows / 2, from->cols / 2, CV_8UC1);
    for (int y = 0; y < to->rows; ++y) {
      const uint8_t* a = from->ptr<uint8_t>(2 * y);
      const uint8_t* b = from->ptr<uint8_t>(2 * y + 1);
      uint8_t* o = to->ptr<uint8_t>(y);
      for (int x = 0; x < to->cols; ++x) {
        o[x] = static_cast<uint8_t>((a[2 * x] + a[2 * x + 1] + b[2 * x] + b[2 * x + 1] + 2) / 4);
      }
    }
  }
}

cv::Rect TrackingSession::roiToWork(const cv::Rect& r) const noexcept {
  if (scale_ == 1.0 || r == cv::Rect()) return r;
  const int x0 = static_cast<int>(std::lround(r.x * scale_));
  const int y0 = static_cast<int>(std::lround(r.y * scale_));
  const int x1 = static_cast<int>(std::lround((r.x + r.width) * scale_));
  const int y1 = static_cast<int>(std::lround((r.y + r.height) * scale_));
  return {x0, y0, x1 - x0, y1 - y0};
}

void TrackingSession::rangeToImage() noexcept {
  if (scale_ == 1.0) return;
  const auto rect = [&](const cv::Rect& r) {
    if (r == cv::Rect()) return r;
    const int x0 = static_cast<int>(std::lround(r.x / scale_));
    const int y0 = static_cast<int>(std::lround(r.y / scale_));
    return cv::Rect(x0, y0, static_cast<int>(std::lround((r.x + r.width) / scale_)) - x0,
                    static_cast<int>(std::lround((r.y + r.height) / scale_)) - y0);
  };
  range_.left = rect(range_.left);
  range_.right = rect(range_.right);
  range_.right_outline =
      cv::Rect2d(range_.right_outline.x / scale_, range_.right_outline.y / scale_,
                 range_.right_outline.width / scale_, range_.right_outline.height / scale_);
  range_.disparity_lo_px /= scale_;
  range_.disparity_hi_px /= scale_;
  range_.vertical_px /= scale_;
  range_.vertical_spread_px /= scale_;
  if (range_.region) {
    range_.region->found = rect(range_.region->found);
    range_.region->roi = rect(range_.region->roi);
  }
}

std::span<const Feature> TrackingSession::features() noexcept {
  const std::span<const Feature> f = tracker_.features();
  if (scale_ == 1.0) return f;
  out_.assign(f.begin(), f.end());  // within the capacity reserved: no allocation
  for (Feature& x : out_) {
    x.left = toImage(x.left);
    x.right = toImage(x.right);
    x.judged_left = toImage(x.judged_left);
    x.judged_right = toImage(x.judged_right);
    x.epipolar_px /= scale_;
  }
  return out_;
}

std::string TrackingSession::scaleSummary() const {
  if (scale_ == 1.0) return "";
  return fmt::format(
      "tracked at {:g} of the images' size ({}x{} px; {}): positions reported in "
      "the images' pixels",
      scale_, tracker_.rig().left.imageSize().width, tracker_.rig().left.imageSize().height,
      config_.scale > 0.0 ? "as configured" : "chosen at the first detection: more features there");
}

bool TrackingSession::detectFirst(const cv::Mat& left, const cv::Mat& right) {
  const bool autoscale = !(config_.scale > 0.0);
  const int next_id = tracker_.nextId();  // a fresh detection's features are new ids
  setScale(autoscale ? 1.0 : config_.scale, next_id);
  toWork(left, right);
  const bool found = detect(workLeft(left), workRight(right), false);
  const int ceiling = std::max(1, config_.tracker.max_features);
  const int at_one = found ? tracker_.okCount() : 0;
  if (!autoscale || 10 * at_one >= 9 * ceiling || left.cols / 2 < config_.auto_scale_min_width)
    return found;
  // Half the size too: kept when it detects at least 1.25 times as many.
  StereoTracker kept = std::move(tracker_);
  const StereoRange kept_range = range_;
  const std::string kept_reason(reason());
  setScale(0.5, next_id);
  toWork(left, right);
  const bool half = detect(work_l_, work_r_, false);
  --attempts_;  // one attempt, at two scales
  if (half && 4 * tracker_.okCount() >= 5 * std::max(at_one, 1)) return true;
  tracker_ = std::move(kept);
  range_ = kept_range;
  scale_ = 1.0;
  setReason(kept_reason);
  return found;
}

Result<void> TrackingSession::checkRoi(const StereoRig& rig, const Roi& roi,
                                       double depth_tolerance_mm) {
  const cv::Size size = rig.left.imageSize();
  const cv::Rect frame(0, 0, size.width, size.height);
  constexpr int kMin = 2 * kAffineSide;
  if (roi.left == cv::Rect() && roi.right != cv::Rect())
    return fail(fmt::format("right ROI {} without a left ROI", roiText(roi.right)));
  for (const auto& [name, r] : {std::pair{"left", roi.left}, std::pair{"right", roi.right}}) {
    if (r == cv::Rect()) continue;  // found in the pair (the left one: findStereoRoi)
    if ((r & frame) != r || r.width <= 0 || r.height <= 0) {
      return fail(fmt::format("{} ROI {}: not inside the {}x{} image", name, roiText(r), size.width,
                              size.height));
    }
    if (r.width < kMin || r.height < kMin) {
      return fail(
          fmt::format("{} ROI {}: too small for {}x{} templates (at least {} px on each side)",
                      name, roiText(r), kAffineSide, kAffineSide, kMin));
    }
  }
  if (roi.right == cv::Rect()) return {};  // the tolerance is found with the right ROI
  if (!(depth_tolerance_mm > 0.0 && depth_tolerance_mm <= 500.0))
    return fail(fmt::format("depth tolerance {} mm: must be in (0, 500]", depth_tolerance_mm));
  return {};
}

cv::Rect TrackingSession::rightRoiFor(const StereoRig& rig, const cv::Rect& left, double depth_mm,
                                      double tolerance_mm) {
  const double near = depth_mm - tolerance_mm, far = depth_mm + tolerance_mm;
  if (!(near > 0.0) || !std::isfinite(far) || left.width <= 0 || left.height <= 0) return {};
  double x0 = INFINITY, y0 = INFINITY, x1 = -INFINITY, y1 = -INFINITY;
  constexpr int kPerSide = 8;  // distortion bends the edges: points along them, not corners only
  for (int k = 0; k <= kPerSide; ++k) {
    const double u = left.x + left.width * k / static_cast<double>(kPerSide);
    const double v = left.y + left.height * k / static_cast<double>(kPerSide);
    for (const cv::Vec2d& px : {cv::Vec2d(u, left.y), cv::Vec2d(u, left.y + left.height),
                                cv::Vec2d(left.x, v), cv::Vec2d(left.x + left.width, v)}) {
      const Ray ray = rig.backProjectLeft(px);
      if (!(ray.direction[2] > 0.0)) continue;
      for (const double z : {near, far}) {
        const double s = (z - ray.origin[2]) / ray.direction[2];
        const cv::Vec2d q = rig.projectRight(ray.origin + s * ray.direction);
        if (!std::isfinite(q[0]) || !std::isfinite(q[1])) continue;
        x0 = std::min(x0, q[0]);
        y0 = std::min(y0, q[1]);
        x1 = std::max(x1, q[0]);
        y1 = std::max(y1, q[1]);
      }
    }
  }
  if (!(x1 >= x0 && y1 >= y0)) return {};
  const cv::Size size = rig.right.imageSize();
  const cv::Rect box(cv::Point(static_cast<int>(std::floor(x0)), static_cast<int>(std::floor(y0))),
                     cv::Point(static_cast<int>(std::ceil(x1)), static_cast<int>(std::ceil(y1))));
  return box & cv::Rect(0, 0, size.width, size.height);
}

void TrackingSession::setReason(std::string_view text) noexcept {
  const size_t n = std::min(text.size(), reason_.size());
  if (n == reason_len_ && std::memcmp(reason_.data(), text.data(), n) == 0) return;
  std::memcpy(reason_.data(), text.data(), n);
  reason_len_ = n;
  ++reason_serial_;
}

void TrackingSession::setRoi(const Roi& roi, double depth_tolerance_mm) {
  config_.roi = roi;
  config_.depth_tolerance_mm = depth_tolerance_mm;
  initialized_ = false;
  have_attempt_ = false;
  auto ok = checkRoi(rig_, roi, depth_tolerance_mm);
  if (ok) ok = checkScale(config_.scale);  // a bad scale is refused as a bad ROI is
  roi_ok_ = ok.has_value();
  setReason(roi_ok_ ? "waiting for the first pair" : ok.error().message);
}

void TrackingSession::start() {
  stopped_ = false;
  initialized_ = false;
  have_attempt_ = false;
  if (roi_ok_) setReason("waiting for the first pair");
}

void TrackingSession::stop() {
  stopped_ = true;
  initialized_ = false;
}

void TrackingSession::resetSignal() noexcept {
  have_output_ = false;
  offset_ = output_ = cv::Vec3d(0, 0, 0);
  members_ = 0;
  ring_size_ = 0;
  detections_ = 0;
}

void TrackingSession::markReference() noexcept {
  const auto feats = tracker_.features();
  const size_t n = std::min(feats.size(), prev_ok_.size());
  if (!have_output_) {  // a fresh detection: every feature's displacement starts at zero here
    for (size_t i = 0; i < n; ++i) {
      ids_[i] = feats[i].id;
      prev_ok_[i] = feats[i].status == FeatureStatus::kOk ? 1 : 0;
      prev_d_[i] = feats[i].point - feats[i].point0;
      birth_[i] = -prev_d_[i];
      dhat_[i] = cv::Vec3d(0, 0, 0);
    }
    std::fill(nb_idx_.begin(), nb_idx_.end(), -1);
    members_ = n;
    return;
  }
  // A re-detection: the features kept (by id) keep their state; a new one enters at the set's
  // mean displacement (its own is zero: its reference is now), so that it adds no step; the
  // retired ones leave, and the offset takes up the change of the mean so nothing jumps.
  cv::Vec3d old_mean(0, 0, 0);
  std::fill(old_to_new_.begin(), old_to_new_.end(), -1);
  for (size_t i = 0; i < members_; ++i) old_mean += dhat_[i];
  if (members_ > 0) old_mean /= static_cast<double>(members_);
  cv::Vec3d* const prev_d = scratch_d_.data();
  cv::Vec3d* const dhat = prev_d + prev_ok_.size();
  cv::Vec3d* const birth = dhat + prev_ok_.size();
  cv::Vec3d new_mean(0, 0, 0);
  for (size_t j = 0; j < n; ++j) {
    const Feature& f = feats[j];
    const cv::Vec3d own = f.point - f.point0;
    const bool ok = f.status == FeatureStatus::kOk;
    size_t i = 0;
    while (i < members_ && ids_[i] != f.id) ++i;
    if (i < members_) old_to_new_[i] = static_cast<int>(j);
    if (i < members_) {
      std::copy_n(nb_idx_.begin() + static_cast<long>(i * neighbours_), neighbours_,
                  scratch_nb_idx_.begin() + static_cast<long>(j * neighbours_));
      std::copy_n(nb_d_.begin() + static_cast<long>(i * neighbours_), neighbours_,
                  scratch_nb_d_.begin() + static_cast<long>(j * neighbours_));
      birth[j] = birth_[i];
      dhat[j] = ok ? birth_[i] + own : dhat_[i];
      prev_d[j] = ok ? own : prev_d_[i];
    } else {
      birth[j] = old_mean - own;
      dhat[j] = old_mean;
      prev_d[j] = own;
      std::fill_n(scratch_nb_idx_.begin() + static_cast<long>(j * neighbours_), neighbours_, -1);
    }
    scratch_ok_[j] = ok ? 1 : 0;
    new_mean += dhat[j];
  }
  for (size_t j = 0; j < n; ++j) {
    ids_[j] = feats[j].id;
    prev_ok_[j] = scratch_ok_[j];
    prev_d_[j] = prev_d[j];
    dhat_[j] = dhat[j];
    birth_[j] = birth[j];
  }
  // The hidden features' neighbours, renumbered (a retired one drops out).
  for (size_t k = 0; k < n * neighbours_; ++k) {
    const int old = scratch_nb_idx_[k];
    nb_idx_[k] = old >= 0 ? old_to_new_[static_cast<size_t>(old)] : -1;
    nb_d_[k] = scratch_nb_d_[k];
  }
  members_ = n;
  if (n > 0) offset_ += old_mean - new_mean / static_cast<double>(n);
}

bool TrackingSession::detect(const cv::Mat& left, const cv::Mat& right, bool redetection) {
  ++attempts_;
  Roi roi{roiToWork(config_.roi.left), roiToWork(config_.roi.right)};
  double tolerance = config_.depth_tolerance_mm;
  if (!redetection && roi.right == cv::Rect()) {
    auto found =
        findStereoRoi(tracker_.rig(), left, right, roi.left, 2 * kAffineSide, config_.search);
    if (!found) {
      setReason(fmt::format("{}; detection is tried again every {:g} s", found.error().message,
                            config_.retry_interval_s));
      return false;
    }
    range_ = *found;
    rangeToImage();  // said in the images' pixels
    ++range_serial_;
    roi.left = found->left;
    roi.right = found->right;
    tolerance = found->tolerance_mm;
    if (auto usable = checkRoi(tracker_.rig(), roi, tolerance); !usable) {
      setReason(fmt::format("left ROI {}: {} ({})", roiText(roi.left), usable.error().message,
                            found->summary()));
      return false;
    }
  }
  auto ok = redetection ? tracker_.redetect(left, right)
                        : tracker_.initialize(left, right, roi, tolerance);
  if (ok && *ok > 0) {
    setReason("");
    return true;
  }
  if (!ok) {
    setReason(ok.error().message);
    return false;
  }
  // Nothing passed: say what the candidates met.
  const auto& cands = tracker_.candidates();
  std::map<std::string, int> by_gate;
  for (const StereoCandidate& c : cands) ++by_gate[statusText(c.status, c.gate)];
  std::string gates;
  for (const auto& [g, n] : by_gate)
    gates += fmt::format("{}{} {}", gates.empty() ? "" : ", ", n, g);
  const std::string where = fmt::format("ROI {} (right {})", roiText(roi.left), roiText(roi.right));
  setReason(cands.empty()
                ? fmt::format("{}: no corner found in the left ROI (no texture there, or too "
                              "small); detection is tried again every {:g} s",
                              where, config_.retry_interval_s)
                : fmt::format("{}: none of {} corners passed the gates ({}); detection is tried "
                              "again every {:g} s",
                              where, cands.size(), gates, config_.retry_interval_s));
  return false;
}

const PairResult& TrackingSession::process(const cv::Mat& left, const cv::Mat& right,
                                           uint64_t frame, int64_t t_ns) {
  result_.frame = frame;
  result_.t_ns = t_ns;
  result_.detected = false;
  result_.deformation.valid = false;
  result_.features = {};
  if (stopped_) {
    result_.state = SessionState::kStopped;
    setReason("stopped (start resumes)");
    return result_;
  }
  result_.state = SessionState::kNoFeatures;
  if (!roi_ok_) return result_;  // the reason names the ROI
  if (!initialized_) {
    const auto interval = static_cast<int64_t>(config_.retry_interval_s * 1e9);
    if (have_attempt_ && t_ns - last_attempt_ns_ < interval && t_ns >= last_attempt_ns_)
      return result_;
    have_attempt_ = true;
    last_attempt_ns_ = t_ns;
    redetect_requested_ = false;
    if (!detectFirst(left, right)) return result_;
    initialized_ = true;
    resetSignal();
    t0_ns_ = t_ns;
    detections_ = 1;
    result_.detected = true;
  } else {
    toWork(left, right);
    tracker_.track(workLeft(left), workRight(right));
    deformation(t_ns);
    if (redetect_requested_ || tracker_.needsRedetection()) {
      redetect_requested_ = false;
      // The new features' reference is where they are now: the signal goes on from the value
      // just measured with the old ones. With none ok there is nothing to fill around (the
      // hidden ones cannot be predicted: their positions are stale and would keep new corners
      // out of their regions): a fresh detection, its stereo search included, under new ids.
      if (detect(workLeft(left), workRight(right), tracker_.okCount() > 0)) {
        ++redetections_;
        ++detections_;
        result_.detected = true;
        markReference();
      } else {
        initialized_ = false;  // tried again (rate-limited) from the next pair
        have_attempt_ = true;
        last_attempt_ns_ = t_ns;
      }
    }
    result_.state = SessionState::kTracking;
    result_.features = features();
    result_.deformation.detections = detections_;
    return result_;
  }
  // A fresh detection: the signal starts at zero here.
  markReference();
  deformation(t_ns);
  result_.state = SessionState::kTracking;
  result_.features = features();
  result_.deformation.detections = detections_;
  return result_;
}

void TrackingSession::hideFrom(size_t i, size_t n) noexcept {
  // The nearest features that were ok in the last pair (insertion into a short list), with their
  // own displacements then, when feature i was last seen too.
  const auto feats = tracker_.features();
  const cv::Vec3d at = feats[i].point;
  int* const idx = nb_idx_.data() + i * neighbours_;
  cv::Vec3d* const snap = nb_d_.data() + i * neighbours_;
  std::array<double, 16> dist{};
  size_t m = 0;
  for (size_t j = 0; j < n; ++j) {
    if (j == i || prev_ok_[j] == 0) continue;
    const double d2 = (feats[j].point - at).dot(feats[j].point - at);
    if (m == neighbours_ && d2 >= dist[m - 1]) continue;
    size_t q = m < neighbours_ ? m++ : m - 1;
    while (q > 0 && dist[q - 1] > d2) {
      dist[q] = dist[q - 1];
      idx[q] = idx[q - 1];
      snap[q] = snap[q - 1];
      --q;
    }
    dist[q] = d2;
    idx[q] = static_cast<int>(j);
    snap[q] = prev_d_[j];
  }
  for (size_t q = m; q < neighbours_; ++q) idx[q] = -1;
}

void TrackingSession::deformation(int64_t t_ns) noexcept {
  Deformation& d = result_.deformation;
  const auto feats = tracker_.features();
  const size_t n = std::min({feats.size(), prev_ok_.size(), members_});
  cv::Vec3d sum_p(0, 0, 0), sum_inc(0, 0, 0);
  double sum_inc_sq = 0.0;
  int ok = 0, common = 0;
  bool changed = false;
  for (size_t i = 0; i < n; ++i) {
    const Feature& f = feats[i];
    const bool now = f.status == FeatureStatus::kOk;
    if (now != (prev_ok_[i] != 0)) changed = true;
    if (!now) continue;
    sum_p += f.point;
    ++ok;
    if (prev_ok_[i] != 0) {
      const cv::Vec3d inc = (f.point - f.point0) - prev_d_[i];
      sum_inc += inc;
      sum_inc_sq += inc.dot(inc);
      ++common;
    }
  }
  d.ok = ok;
  d.total = static_cast<int>(feats.size());
  d.valid = ok > 0;
  if (!d.valid) return;  // every feature keeps its estimate until one is seen again
  // Each feature's displacement: its own while ok; while hidden, its last one carried on by the
  // mean increment of the features ok in both pairs (so an error lives only while the feature is
  // hidden: when it comes back its own measurement replaces it, and nothing accumulates).
  const cv::Vec3d mean_inc = common > 0 ? cv::Vec3d(sum_inc / common) : cv::Vec3d(0, 0, 0);
  cv::Vec3d sum_hat(0, 0, 0);
  for (size_t i = 0; i < n; ++i) {
    const Feature& f = feats[i];
    if (f.status == FeatureStatus::kOk) {
      dhat_[i] = birth_[i] + (f.point - f.point0);
    } else {
      if (prev_ok_[i] != 0) hideFrom(i, n);
      // Its own displacement when last seen plus its neighbours' motion since (each theirs:
      // a difference of two of their own displacements, so nothing integrates); while none of
      // them is ok, carried on by the mean increment.
      cv::Vec3d moved(0, 0, 0);
      int seen = 0;
      for (size_t k = 0; k < neighbours_; ++k) {
        const int j = nb_idx_[i * neighbours_ + k];
        if (j < 0 || static_cast<size_t>(j) >= n) continue;
        const Feature& g = feats[static_cast<size_t>(j)];
        if (g.status != FeatureStatus::kOk) continue;
        moved += (g.point - g.point0) - nb_d_[i * neighbours_ + k];
        ++seen;
      }
      dhat_[i] = seen > 0 ? birth_[i] + prev_d_[i] + moved / seen : dhat_[i] + mean_inc;
    }
    sum_hat += dhat_[i];
  }
  const cv::Vec3d mean_d = sum_hat / static_cast<double>(std::max<size_t>(1, n));
  bool continuous = true;
  if (!have_output_) {
    offset_ = -mean_d;  // the signal starts at zero
    continuous = false;
  } else if (changed && common == 0) {
    continuous = false;  // nothing in common: the motion in between is unknown
  }
  have_output_ = true;
  output_ = mean_d + offset_;
  // Noise: one feature's increment scatters about the mean increment by sqrt(2) sigma_f per
  // axis (both pairs' noise); the mean of ok features has sigma_f / sqrt(ok).
  if (common >= 3) {
    const cv::Vec3d m = sum_inc / common;
    const double var_inc = std::max(0.0, (sum_inc_sq - common * m.dot(m)) / (3.0 * (common - 1)));
    noise_var_ = have_noise_ ? 0.95 * noise_var_ + 0.05 * var_inc : var_inc;
    have_noise_ = true;
  }
  const double sigma_d = std::sqrt(noise_var_ / 2.0 / ok);
  // Velocity: least-squares slope over the window, on the continuous signal.
  if (!continuous) ring_size_ = 0;
  const double t = static_cast<double>(t_ns - t0_ns_) * 1e-9;
  ring_[ring_head_] = {t, output_};
  ring_head_ = (ring_head_ + 1) % ring_.size();
  ring_size_ = std::min(ring_size_ + 1, ring_.size());
  double st = 0.0;
  cv::Vec3d sd(0, 0, 0);
  size_t m = 0;
  for (size_t k = 0; k < ring_size_; ++k) {
    const Sample& s = ring_[(ring_head_ + ring_.size() - 1 - k) % ring_.size()];
    if (k >= 2 && t - s.t > config_.velocity_window_s + 1e-9) break;
    st += s.t;
    sd += s.d;
    ++m;
  }
  d.velocity = cv::Vec3d(0, 0, 0);
  d.velocity_delay_s = 0.0;
  d.velocity_sigma_mm_s = 0.0;
  if (m >= 2) {
    const double tm = st / static_cast<double>(m);
    const cv::Vec3d dm = sd / static_cast<double>(m);
    double stt = 0.0;
    cv::Vec3d std_(0, 0, 0);
    for (size_t k = 0; k < m; ++k) {
      const Sample& s = ring_[(ring_head_ + ring_.size() - 1 - k) % ring_.size()];
      stt += (s.t - tm) * (s.t - tm);
      std_ += (s.t - tm) * (s.d - dm);
    }
    if (stt > 0.0) {
      d.velocity = std_ / stt;
      d.velocity_delay_s = t - tm;
      d.velocity_sigma_mm_s = sigma_d / std::sqrt(stt);
    }
  }
  d.centroid = sum_p / ok;
  d.displacement = output_;
  d.displacement_sigma_mm = sigma_d;
  d.continuous = continuous;
  if (config_.prediction.enabled) {
    if (!continuous) predictor_.reset();
    d.prediction = predictor_.add(t, output_);
    for (int k = 0; k < d.prediction.horizons; ++k) {
      const auto w = predictor_.weights(k);
      std::copy(w.begin(), w.end(), d.prediction_weights[static_cast<size_t>(k)].begin());
    }
    d.prediction_order = predictor_.order();
    d.prediction_step_s = predictor_.step();
  }
  for (size_t i = 0; i < n; ++i) {
    prev_ok_[i] = feats[i].status == FeatureStatus::kOk ? 1 : 0;
    if (prev_ok_[i] != 0) prev_d_[i] = feats[i].point - feats[i].point0;
  }
}

void TrackingSession::afterPublish(const cv::Mat& left, const cv::Mat& right) noexcept {
  // At a working scale other than 1, the pair process() just resampled (the same pair).
  if (initialized_ && !stopped_) tracker_.refreshStereo(workLeft(left), workRight(right));
}

void TrackingSession::prepareRefresh(const cv::Mat& left, const cv::Mat& right,
                                     RefreshJob& job) noexcept {
  job.count = 0;
  if (initialized_ && !stopped_) tracker_.prepareRefresh(workLeft(left), workRight(right), job);
}

int TrackingSession::applyRefresh(const RefreshOutcome& outcome) noexcept {
  return initialized_ && !stopped_ ? tracker_.applyRefresh(outcome) : 0;
}

}  // namespace pulsetrack::vision
