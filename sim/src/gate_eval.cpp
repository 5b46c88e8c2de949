#include "pulsetrack/sim/gate_eval.hpp"

#include <fmt/format.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <set>

#include "pulsetrack/sim/session_truth.hpp"
#include "pulsetrack/vision/affine_refiner.hpp"

namespace pulsetrack::sim {

using vision::FeatureStatus;
using vision::Gate;
using vision::gateBit;

namespace {

constexpr uint16_t kLostGates =
    gateBit(Gate::kNoPeak) | gateBit(Gate::kNotConverged) | gateBit(Gate::kImageBorder);
// Gates evaluated only on matches that passed the others (they need the accepted set).
constexpr uint16_t kLateGates = gateBit(Gate::kSheen) | gateBit(Gate::kSurface);

// Which gates a match was evaluated on, given what it failed.
bool evaluated(Gate g, uint16_t failed, bool tracking) {
  const uint16_t bit = gateBit(g);
  if (g == Gate::kNone) return false;
  if (tracking) {
    if (g == Gate::kStereoNcc || g == Gate::kSheen || g == Gate::kLeftRight ||
        g == Gate::kDepthEdge)
      return false;
    if ((failed & kLostGates) != 0) return (failed & bit) != 0;  // no match to judge further
    // The motion and surface gates judge the features that passed the others.
    if (g == Gate::kSurface || g == Gate::kMotion)
      return (failed & ~(gateBit(Gate::kSurface) | gateBit(Gate::kMotion))) == 0;
    return true;
  }
  if (g == Gate::kNccDrop || g == Gate::kMotion) return false;  // tracking only
  if ((failed & gateBit(Gate::kNoPeak)) != 0) return g == Gate::kNoPeak;
  if ((bit & (kLateGates | gateBit(Gate::kImageBorder))) != 0)
    return (failed & ~(kLateGates | gateBit(Gate::kImageBorder))) == 0;
  return true;
}

double rmsOf(const std::vector<double>& v) {
  double s = 0.0;
  for (double x : v) s += x * x;
  return v.empty() ? 0.0 : std::sqrt(s / static_cast<double>(v.size()));
}

}  // namespace

void GateTable::add(uint16_t failed, bool is_accepted, bool is_good, bool tracking) {
  ++matches;
  if (is_good) ++good;
  if (is_accepted) {
    ++accepted;
    if (is_good) ++accepted_good;
  }
  for (size_t g = 1; g < kGateCount; ++g) {
    const auto gate = static_cast<Gate>(g);
    if (!evaluated(gate, failed, tracking)) continue;
    const bool fails = (failed & gateBit(gate)) != 0;
    GateRates& r = gates[g];
    if (is_good) {
      ++r.good;
      if (fails) ++r.good_rejected;
    } else {
      ++r.bad;
      if (!fails) ++r.bad_passed;
    }
  }
}

std::string formatGateTable(const GateTable& t, const std::string& title) {
  const auto pct = [](long a, long b) {
    return b > 0 ? fmt::format("{:5.1f} % ({}/{})",
                               100.0 * static_cast<double>(a) / static_cast<double>(b), a, b)
                 : std::string("    -");
  };
  std::string out = fmt::format("{}\n  {:<14} {:>26} {:>26}\n", title, "gate",
                                "false reject (right ones)", "false accept (wrong ones)");
  for (size_t g = 1; g < kGateCount; ++g) {
    const GateRates& r = t.gates[g];
    if (r.good + r.bad == 0) continue;
    out += fmt::format("  {:<14} {:>26} {:>26}\n", vision::toString(static_cast<Gate>(g)),
                       pct(r.good_rejected, r.good), pct(r.bad_passed, r.bad));
  }
  out += fmt::format(
      "  matches {} (right {}, no truth {}); accepted {}, of them right {}; right ones "
      "accepted {}\n",
      t.matches, t.good, t.no_truth, t.accepted, pct(t.accepted_good, t.accepted),
      pct(t.accepted_good, t.good));
  return out;
}

// --- Photographs ---

vision::Result<PhotoPair> loadPhotoPair(const std::filesystem::path& dir,
                                        const std::string& disparity, double scale) {
  PhotoPair p;
  p.name = dir.filename().string();
  const auto read = [](const std::filesystem::path& f, int flags, cv::Mat& m) -> std::string {
    try {
      m = cv::imread(f.string(), flags);
    } catch (const cv::Exception& e) {
      return fmt::format("{}: cannot read image: {}", f.string(), e.err);
    }
    return m.empty() ? fmt::format("{}: missing or unreadable image", f.string()) : "";
  };
  cv::Mat disp8;
  for (const auto& [f, flags, m] : {std::tuple{dir / "left.png", cv::IMREAD_GRAYSCALE, &p.left},
                                    std::tuple{dir / "right.png", cv::IMREAD_GRAYSCALE, &p.right},
                                    std::tuple{dir / disparity, cv::IMREAD_UNCHANGED, &disp8}}) {
    if (std::string e = read(f, flags, *m); !e.empty()) return vision::fail(e);
  }
  if (p.right.size() != p.left.size() || disp8.size() != p.left.size() || disp8.type() != CV_8UC1) {
    return vision::fail(fmt::format("{}: left, right and {} (8-bit grey) must have one size",
                                    dir.string(), disparity));
  }
  disp8.convertTo(p.disparity, CV_32F, 1.0 / scale);
  return p;
}

vision::StereoRig rectifiedRig(cv::Size size, double f_px, double baseline_mm) {
  vision::StereoRig rig;
  const cv::Matx33d k(f_px, 0, (size.width - 1) / 2.0, 0, f_px, (size.height - 1) / 2.0, 0, 0, 1);
  const double dist[5] = {0, 0, 0, 0, 0};
  rig.left = vision::CameraModel(k, dist, 5, size);
  rig.right = vision::CameraModel(k, dist, 5, size);
  rig.r = cv::Matx33d::eye();
  rig.t = cv::Vec3d(-baseline_mm, 0, 0);
  return rig;
}

namespace {

// The truth says: disparity at the left point (nearest pixel), 0 unknown.
float truthAt(const PhotoPair& p, const cv::Vec2d& left) {
  const int x = static_cast<int>(std::lround(left[0])), y = static_cast<int>(std::lround(left[1]));
  if (x < 0 || y < 0 || x >= p.disparity.cols || y >= p.disparity.rows) return 0.0F;
  return p.disparity.at<float>(y, x);
}

// Row search: the x in [x0, x1] where `templ` (side 2 half + 1) best matches `img`'s row y
// (TM_CCOEFF_NORMED), with a quadratic peak; false when the range is empty.
bool rowPeak(const cv::Mat& img, const cv::Mat& templ, int y, int x0, int x1, double& x) {
  const int half = templ.cols / 2;
  if (x1 < x0) return false;
  cv::Mat res;
  cv::matchTemplate(img(cv::Rect(x0 - half, y - half, x1 - x0 + templ.cols, templ.rows)), templ,
                    res, cv::TM_CCOEFF_NORMED);
  cv::Point at;
  cv::minMaxLoc(res, nullptr, nullptr, nullptr, &at);
  x = x0 + at.x;
  if (at.x > 0 && at.x < res.cols - 1) {
    const double a = res.at<float>(0, at.x - 1), b = res.at<float>(0, at.x),
                 c = res.at<float>(0, at.x + 1);
    const double den = a - 2 * b + c;
    if (den < 0) x += 0.5 * (a - c) / den;
  }
  return true;
}

}  // namespace

PlainMatcherResult plainMatcher(const PhotoPair& p, const cv::Rect& roi, int dmin, int dmax,
                                int corners) {
  PlainMatcherResult out;
  constexpr int kHalf = 7;
  cv::Mat mask = cv::Mat::zeros(p.left.size(), CV_8UC1);
  mask(roi).setTo(255);
  std::vector<cv::Point2f> pts;
  cv::goodFeaturesToTrack(p.left, pts, corners, 0.01, 12, mask, 3, true, 0.04);
  out.candidates = static_cast<int>(pts.size());
  for (const cv::Point2f& q : pts) {
    const int x = static_cast<int>(std::lround(q.x)), y = static_cast<int>(std::lround(q.y));
    if (y - kHalf < 0 || y + kHalf >= p.left.rows || x - kHalf < 0 || x + kHalf >= p.left.cols)
      continue;
    const cv::Mat templ = p.left(cv::Rect(x - kHalf, y - kHalf, 2 * kHalf + 1, 2 * kHalf + 1));
    // Right x in [x - dmax, x - dmin]; then the left-right check: the right patch back along the
    // left row.
    double xr = 0, xl = 0;
    if (!rowPeak(p.right, templ, y, std::max(kHalf, x - dmax),
                 std::min(p.right.cols - 1 - kHalf, x - dmin), xr)) {
      continue;
    }
    const int xri = static_cast<int>(std::lround(xr));
    const cv::Mat back = p.right(cv::Rect(xri - kHalf, y - kHalf, 2 * kHalf + 1, 2 * kHalf + 1));
    if (!rowPeak(p.left, back, y, std::max(kHalf, xri + dmin),
                 std::min(p.left.cols - 1 - kHalf, xri + dmax), xl)) {
      continue;
    }
    if (std::abs(xl - x) > 1.0) continue;
    ++out.accepted;
    const float truth = truthAt(p, {double(x), double(y)});
    if (truth <= 0.0F) continue;
    ++out.judged;
    if (std::abs((x - xr) - truth) <= 1.0) ++out.accepted_good;
  }
  return out;
}

vision::Result<PhotoEvaluation> evaluatePhotoPair(const PhotoPair& p,
                                                  const vision::TrackerConfig& config, int dmin,
                                                  int dmax) {
  const vision::StereoRig rig = rectifiedRig(p.left.size());
  // The right ROI is the left one shifted by s px (depth K / s, K = f b); the tolerance makes
  // the search box reach disparities dmin..dmax (and 2 px beyond, the box's own margin).
  const double k = 500.0 * 20.0;
  // z - tol lands on dmax exactly; s rounded down keeps z + tol beyond dmin.
  const int s = std::max(1, static_cast<int>(std::floor(2.0 / (1.0 / dmin + 1.0 / dmax))));
  const double z = k / s;
  const double tol = z - k / dmax;
  const int margin = 7 + 8 + 3;
  const cv::Rect left_roi(margin + dmax, margin, p.left.cols - 2 * margin - dmax,
                          p.left.rows - 2 * margin);
  vision::Roi roi{left_roi, left_roi - cv::Point(s, 0)};
  vision::TrackerConfig c = config;
  c.evaluate_gates = true;
  vision::StereoTracker tracker(rig, c);
  auto ok = tracker.initialize(p.left, p.right, roi, tol);
  if (!ok) return std::unexpected(ok.error());
  PhotoEvaluation e;
  for (const vision::StereoCandidate& cand : tracker.candidates()) {
    const bool accepted = cand.status == FeatureStatus::kOk;
    const float truth = truthAt(p, cand.left);
    if (accepted) ++e.accepted;
    ++e.candidates;
    if (truth <= 0.0F) {
      ++e.table.no_truth;
      continue;
    }
    const bool good = std::abs((cand.left[0] - cand.right[0]) - truth) <= 1.0 &&
                      std::abs(cand.left[1] - cand.right[1]) <= 1.0;
    e.table.add(cand.failed, accepted, good, false);
    if (accepted) {
      ++e.accepted_judged;
      if (good) ++e.accepted_good;
    }
  }
  e.plain = plainMatcher(p, left_roi, dmin, dmax);
  return e;
}

// --- The simulated scene ---

vision::Result<SceneRun> runScene(StereoSimulator& sim, const SceneRunOptions& options) {
  const CortexScene* scene = sim.cortex();
  if (scene == nullptr) return vision::fail("gate evaluation: the scene must be a cortex scene");
  const vision::StereoRig& rig = sim.rig();
  vision::SessionConfig config;
  config.tracker = options.tracker;
  config.tracker.evaluate_gates = true;
  // The ROI: the bounding boxes of a circle of roi_radius_mm around the patch's centre.
  std::vector<cv::Point2f> pl, pr;
  for (int k = 0; k < 36; ++k) {
    const double a = k * CV_PI / 18;
    const cv::Vec3d p = scene->position(options.roi_radius_mm * std::cos(a),
                                        options.roi_radius_mm * std::sin(a), 0.0);
    const cv::Vec2d l = rig.projectLeft(p), r = rig.projectRight(p);
    pl.emplace_back(static_cast<float>(l[0]), static_cast<float>(l[1]));
    pr.emplace_back(static_cast<float>(r[0]), static_cast<float>(r[1]));
  }
  config.roi = {cv::boundingRect(pl), cv::boundingRect(pr)};
  vision::TrackingSession session(rig, config);
  const cv::Vec3d centre_l = cv::Vec3d(0, 0, 0);
  const cv::Vec3d centre_r = rig.rightCentre();
  const Instrument& in = scene->spec().instrument;
  const double ramp = (1.0 - in.hold_fraction) / 2.0 * in.duration_s;
  const double rest_from = in.start_s + ramp, rest_to = in.start_s + in.duration_s - ramp;
  const double gone = in.start_s + in.duration_s;
  SceneRun run;
  // Seen by both cameras at time t (the instrument hides it from neither).
  const auto seen = [&](const cv::Vec3d& p, double t) {
    return !scene->occluded(p, centre_l, t) && !scene->occluded(p, centre_r, t);
  };

  if (in.enabled) {
    const double mid = (rest_from + rest_to) / 2.0, r = options.roi_radius_mm;
    long inside = 0, covered = 0;
    for (double v = -r; v <= r; v += 0.25) {
      for (double u = -r; u <= r; u += 0.25) {
        if (u * u + v * v > r * r) continue;
        ++inside;
        if (!seen(scene->position(u, v, mid), mid)) ++covered;
      }
    }
    run.instrument_covers = static_cast<double>(covered) / static_cast<double>(inside);
    // The same over the left ROI, the box features are detected in (its corners lie outside
    // the circle), pixel by pixel in the left image.
    inside = covered = 0;
    const cv::Rect& box = config.roi.left;
    for (int y = box.y; y < box.y + box.height; y += 2) {
      for (int x = box.x; x < box.x + box.width; x += 2) {
        cv::Vec2d uv;
        if (!scene->materialAt(rig, cv::Vec2d(x, y), mid, uv)) continue;
        ++inside;
        if (!seen(scene->position(uv[0], uv[1], mid), mid)) ++covered;
      }
    }
    run.instrument_covers_box =
        inside > 0 ? static_cast<double>(covered) / static_cast<double>(inside) : 0.0;
  }
  struct Truth {
    cv::Vec2d uv;
    double t_ref = 0;
    bool found = false;
  };
  std::map<int, Truth> truth;
  std::ofstream samples;
  if (!options.samples_csv.empty()) {
    samples.open(options.samples_csv);
    if (!samples) return std::unexpected(vision::Error{"cannot write " + options.samples_csv});
    samples << "pair,t,id,ex_mm,ey_mm,ez_mm,elx_px,ely_px,erx_px,ery_px,gate,visible,clear\n";
  }
  std::set<int> ids;
  std::set<int> ok_before, hidden, back;
  std::vector<double> err3, errd;
  std::vector<double> ts;
  std::vector<cv::Vec3d> meas, tru;
  std::optional<SessionTruth> session_truth;
  if (sim.cortex() != nullptr) session_truth.emplace(sim);
  double track_s = 0.0, refresh_s = 0.0;
  long ok_sum = 0;
  int tracked_pairs = 0;
  const int n = options.pairs > 0 ? std::min(options.pairs, sim.frameCount()) : sim.frameCount();
  cv::Mat l, r;
  for (int i = 0; i < n; ++i) {
    if (sim.dropped(i)) continue;
    sim.render(i, l, r);
    const double t = sim.frameTime(i);
    const auto t0 = std::chrono::steady_clock::now();
    const vision::PairResult& res = session.process(l, r, static_cast<uint64_t>(i),
                                                    static_cast<int64_t>(std::llround(t * 1e9)));
    const auto t1 = std::chrono::steady_clock::now();
    session.afterPublish(l, r);
    const auto t2 = std::chrono::steady_clock::now();
    if (res.state != vision::SessionState::kTracking) {
      run.ok_per_pair.push_back(0);
      ++run.pairs;
      continue;
    }
    if (!res.detected) {
      track_s += std::chrono::duration<double>(t1 - t0).count();
      refresh_s += std::chrono::duration<double>(t2 - t1).count();
      ok_sum += res.deformation.ok;
      ++tracked_pairs;
    }
    const auto visible = [&](const cv::Vec3d& p) { return seen(p, t); };
    // Detection candidates.
    if (res.detected) {
      ++run.detections;
      std::vector<bool> right_match;
      for (const vision::StereoCandidate& c : session.tracker().candidates()) {
        cv::Vec2d uv;
        right_match.push_back(false);
        if (!scene->materialAt(rig, c.left, t, uv)) {
          ++run.detection.no_truth;
          continue;
        }
        const cv::Vec3d p = scene->position(uv[0], uv[1], t);
        const bool good = visible(p) && cv::norm(rig.projectRight(p) - c.right) <= options.right_px;
        right_match.back() = good;
        run.detection.add(c.failed, c.status == FeatureStatus::kOk, good, false);
      }
      if (run.detections == 1) {
        // Grid coverage of the first detection: a cell has texture when a corner in it has a
        // right match (a feature could be there).
        const cv::Rect& roi = config.roi.left;
        std::array<int, 25> any{}, okc{};
        const auto& cands = session.tracker().candidates();
        for (size_t k = 0; k < cands.size(); ++k) {
          const vision::StereoCandidate& c = cands[k];
          const int gx = std::clamp(int((c.left[0] - roi.x) * 5 / roi.width), 0, 4);
          const int gy = std::clamp(int((c.left[1] - roi.y) * 5 / roi.height), 0, 4);
          const auto cell = static_cast<size_t>(gy) * 5 + static_cast<size_t>(gx);
          if (right_match[k]) ++any[cell];
          if (c.status == FeatureStatus::kOk) ++okc[cell];
        }
        for (size_t k = 0; k < 25; ++k) {
          if (any[k] == 0) continue;
          ++run.textured_cells;
          if (okc[k] == 0) ++run.empty_textured_cells;
        }
      }
    }
    int ok = 0;
    for (const vision::Feature& f : res.features) {
      ids.insert(f.id);
      Truth& tr = truth[f.id];
      if (!tr.found && tr.t_ref == 0.0) {
        tr.found = scene->materialAt(rig, f.judged_left, t, tr.uv);
        tr.t_ref = t > 0.0 ? t : 1e-9;
      }
      const bool accepted = f.status == FeatureStatus::kOk;
      if (accepted) ++ok;
      if (!tr.found) {
        ++run.tracking.no_truth;
        continue;
      }
      const cv::Vec3d p = scene->position(tr.uv[0], tr.uv[1], t);
      if (!res.detected || tr.t_ref != t) {
        const bool good = visible(p) &&
                          cv::norm(rig.projectLeft(p) - f.judged_left) <= options.right_px &&
                          cv::norm(rig.projectRight(p) - f.judged_right) <= options.right_px;
        run.tracking.add(f.failed, accepted, good, true);
      }
      if (!accepted) {
        if (samples.is_open()) {
          // Not ok: why (the gate), whether it was visible, and whether its whole video patch
          // was (the corners of its patch in the left view, where the truth knows them).
          int clear = 1;
          constexpr double kVideoHalf = vision::kShiftHalf;
          for (const cv::Vec2d& off :
               {cv::Vec2d(-kVideoHalf, -kVideoHalf), cv::Vec2d(kVideoHalf, -kVideoHalf),
                cv::Vec2d(-kVideoHalf, kVideoHalf), cv::Vec2d(kVideoHalf, kVideoHalf)}) {
            cv::Vec2d uv;
            if (scene->materialAt(rig, rig.projectLeft(p) + off, t, uv) &&
                !visible(scene->position(uv[0], uv[1], t)))
              clear = 0;
          }
          samples << fmt::format("{},{:.4f},{},,,,,,,,{},{},{}\n", i, t, f.id,
                                 static_cast<int>(f.gate), visible(p) ? 1 : 0, clear);
        }
        continue;
      }
      const double e = cv::norm(f.point - p);
      if (samples.is_open()) {
        const cv::Vec3d d = f.point - p;
        const cv::Vec2d el = f.left - rig.projectLeft(p), er = f.right - rig.projectRight(p);
        samples << fmt::format(
            "{},{:.4f},{},{:.5f},{:.5f},{:.5f},{:.4f},{:.4f},{:.4f},{:.4f},0,1,1\n", i, t, f.id,
            d[0], d[1], d[2], el[0], el[1], er[0], er[1]);
      }
      err3.push_back(e);
      run.max_3d_mm = std::max(run.max_3d_mm, e);
      if (e > 0.5) ++run.above_half_mm;
    }
    if (i == 0 || run.pairs == 0) run.first_ok = ok;
    run.ok_per_pair.push_back(ok);
    ++run.pairs;
    // Re-acquisition bookkeeping.
    if (in.enabled) {
      for (const vision::Feature& f : res.features) {
        const bool is_ok = f.status == FeatureStatus::kOk;
        if (t < in.start_s && is_ok) ok_before.insert(f.id);
        if (t < in.start_s && !is_ok) ok_before.erase(f.id);
        if (t >= rest_from && t <= rest_to && !is_ok && ok_before.contains(f.id))
          hidden.insert(f.id);
        if (t > gone && t <= gone + 1.0 + 1e-9 && hidden.contains(f.id)) {
          if (is_ok)
            back.insert(f.id);
          else
            back.erase(f.id);  // back means ok at the last pair within the second
        }
      }
    }
    // The true mean displacement by the session's rule (session_truth.hpp).
    const vision::Deformation& d = res.deformation;
    if (d.valid && session_truth && session_truth->update(res, t)) {
      errd.push_back(cv::norm(d.displacement - session_truth->displacement()) / std::sqrt(3.0));
      ts.push_back(t);
      meas.push_back(d.displacement);
      tru.push_back(session_truth->displacement());
    }
  }
  run.distinct_ids = static_cast<int>(ids.size());
  run.rms_3d_mm = rmsOf(err3);
  run.ok_samples = static_cast<long>(err3.size());
  run.displacement_rms_mm = rmsOf(errd);
  run.hidden = static_cast<int>(hidden.size());
  run.back_within_1s = static_cast<int>(back.size());
  run.ms_per_pair_tracking = tracked_pairs > 0 ? 1e3 * track_s / tracked_pairs : 0.0;
  run.ms_per_pair_refresh = tracked_pairs > 0 ? 1e3 * refresh_s / tracked_pairs : 0.0;
  run.mean_ok = tracked_pairs > 0 ? static_cast<double>(ok_sum) / tracked_pairs : 0.0;
  // Amplitudes at the scene's breathing and cardiac frequencies: least squares on a constant,
  // a trend and the sines and cosines of every motion component and harmonic.
  std::vector<double> freqs;
  double f_breath = 0.0, f_card = 0.0;
  for (const Oscillation& o : scene->spec().oscillations) {
    if (!o.enabled) continue;
    freqs.push_back(o.frequency_hz);
    for (const Harmonic& h : o.harmonics) freqs.push_back(o.frequency_hz * h.multiple);
    if (o.name == "breathing") f_breath = o.frequency_hz;
    if (o.name == "cardiac") f_card = o.frequency_hz;
  }
  const auto amplitude = [&](const std::vector<cv::Vec3d>& y, double f) {
    const int cols = 2 + 2 * static_cast<int>(freqs.size());
    const int rows = static_cast<int>(y.size());
    if (rows <= cols || f <= 0.0) return 0.0;
    cv::Mat a(rows, cols, CV_64F), b(rows, 3, CV_64F);
    int target = -1;
    for (int k = 0; k < rows; ++k) {
      a.at<double>(k, 0) = 1.0;
      a.at<double>(k, 1) = ts[static_cast<size_t>(k)] - ts.front();
      for (size_t j = 0; j < freqs.size(); ++j) {
        const double w = 2 * CV_PI * freqs[j] * ts[static_cast<size_t>(k)];
        a.at<double>(k, 2 + 2 * static_cast<int>(j)) = std::sin(w);
        a.at<double>(k, 3 + 2 * static_cast<int>(j)) = std::cos(w);
      }
      for (int c = 0; c < 3; ++c) b.at<double>(k, c) = y[static_cast<size_t>(k)][c];
    }
    for (size_t j = 0; j < freqs.size(); ++j) {
      if (std::abs(freqs[j] - f) < 1e-9 && target < 0) target = 2 + 2 * static_cast<int>(j);
    }
    cv::Mat x;
    cv::solve(a, b, x, cv::DECOMP_SVD);
    double s2 = 0.0;
    for (int c = 0; c < 3; ++c) {
      s2 += x.at<double>(target, c) * x.at<double>(target, c) +
            x.at<double>(target + 1, c) * x.at<double>(target + 1, c);
    }
    return std::sqrt(s2);
  };
  const double mb = amplitude(meas, f_breath), tb = amplitude(tru, f_breath);
  const double mc = amplitude(meas, f_card), tc = amplitude(tru, f_card);
  run.breathing_error = tb > 0.0 ? std::abs(mb - tb) / tb : 0.0;
  run.cardiac_error = tc > 0.0 ? std::abs(mc - tc) / tc : 0.0;
  return run;
}

}  // namespace pulsetrack::sim
