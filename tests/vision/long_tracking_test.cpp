// Hours-long tracking (issue 17, part 3): the TrackingSession and the dense field over a long
// case with 10 mm of sag and a 4 degree turn, an instrument crossing again and again, the light
// and the gains drifting (config/scenes/cortex-1h.toml; the suite runs its 3-minute compression,
// cortex-1h-compressed.toml; PULSETRACK_LONG_SCENE=config/scenes/cortex-1h.toml runs the hour).
//
// Against the simulator's truth (sim/include/pulsetrack/sim/session_truth.hpp, written apart from
// the session):
// - identity: every time a feature comes back (ok after not ok), its left pixel is where its
//   own material point is now (a feature that came back on other tissue is an identity lost);
// - drift: the mean displacement against the continuous truth and the dense field at held-out
//   material points (not features), at the start and at the end;
// - re-detections add features without a jump in the published signal;
// - the ok set's floor, and the time per pair over the run (printed, per tenth of the run).

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <iomanip>
#include <iostream>
#include <map>
#include <set>

#include "pulsetrack/analysis/plot.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/sim/session_truth.hpp"
#include "pulsetrack/vision/deformation_field.hpp"
#include "pulsetrack/vision/tracking_session.hpp"
#include "sim/cortex_roi.hpp"

namespace pulsetrack::vision {
namespace {

// One panel of the run's figure: over time in minutes, from zero up.
void panel(analysis::Axes& a, std::string title, std::string ylabel,
           std::vector<analysis::LineSeries> lines) {
  a.title = std::move(title);
  a.xlabel = "time (min)";
  a.ylabel = std::move(ylabel);
  a.lines = std::move(lines);
  a.ymin = 0.0;
}

std::string sceneFile() {
  if (const char* e = std::getenv("PULSETRACK_LONG_SCENE")) return e;
  return std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-1h-compressed.toml";
}

// One tenth of the run.
struct Window {
  double t0 = 0, t1 = 0;
  double mean_e2 = 0;  // mean displacement error^2, per axis
  long mean_n = 0;
  // Held-out material points, 3D, per field (the default smoothing first).
  std::array<double, 3> field_e2{}, field_max{};
  std::array<long, 3> field_n{};
  double fixed_e2 = 0;        // the signal against the first detection's material points, per axis
  double fixed_field_e2 = 0;  // the field's mean over those points against theirs, per axis
  long fixed_field_n = 0;
  double feat_e2 = 0;  // ok features' displacement error^2, 3D
  long feat_n = 0;
  double px_e2 = 0;  // ok features' left pixel against their material point's projection
  long px_n = 0;
  int min_ok = 1 << 30;
  int max_total = 0;
  std::vector<double> us;  // time per pair (process + field + afterPublish), microseconds
  [[nodiscard]] double meanRms() const {
    return std::sqrt(mean_e2 / static_cast<double>(std::max(1L, mean_n)));
  }
  [[nodiscard]] double fieldRms(size_t k = 0) const {
    return std::sqrt(field_e2[k] / static_cast<double>(std::max(1L, field_n[k])));
  }
  [[nodiscard]] double pxRms() const {
    return std::sqrt(px_e2 / static_cast<double>(std::max(1L, px_n)));
  }
  [[nodiscard]] double fixedFieldRms() const {
    return std::sqrt(fixed_field_e2 / static_cast<double>(std::max(1L, fixed_field_n)));
  }
  [[nodiscard]] double fixedRms() const {
    return std::sqrt(fixed_e2 / static_cast<double>(std::max(1L, mean_n)));
  }
  [[nodiscard]] double featRms() const {
    return std::sqrt(feat_e2 / static_cast<double>(std::max(1L, feat_n)));
  }
  [[nodiscard]] double medianUs() {
    if (us.empty()) return 0.0;
    std::nth_element(us.begin(), us.begin() + static_cast<long>(us.size() / 2), us.end());
    return us[us.size() / 2];
  }
};

TEST(TrackingSession, HoursLongTrackingKeepsIdsAndStaysDriftFree) {
  const std::string file = sceneFile();
  auto spec = sim::loadScene(file);
  ASSERT_TRUE(spec) << spec.error().message;
  auto rig = vision::loadRig(spec->rig_path);
  ASSERT_TRUE(rig) << rig.error().message;
  sim::StereoSimulator s(*spec, *rig);
  const sim::CortexScene& scene = *s.cortex();
  SessionConfig config;
  config.roi = test::cortexRoi(s, 19.0);
  // The tracker's defaults. (Retiring hidden features after 10 s, the default's 300 pairs at
  // 30 Hz, instead of 60 s at these 5 fps, kept more features ok, 35 instead of 30 at the
  // floor, but made the field worse, 0.087 instead of 0.052 mm at the end: each re-detection's
  // new features take their reference from the field, in the gaps.)
  TrackingSession session(s.rig(), config);
  // The default field, and two smaller smoothings (the 10 mm sag is a deep bowl).
  const std::array<double, 3> smoothing{FieldConfig{}.smoothing, 100.0, 10.0};
  std::vector<DeformationField> fields;
  for (double lambda : smoothing) {
    FieldConfig fc;
    fc.smoothing = lambda;
    fields.emplace_back(fc, config.tracker.max_features);
  }
  DeformationField& field = fields.front();
  std::vector<cv::Vec2d> first_set;  // the first detection's material points
  std::vector<cv::Vec3d> first_p0;   // ... and their reference positions
  sim::SessionTruth truth(s);
  std::vector<sim::HeldOutPoint> held;

  const int frames = s.frameCount();
  std::vector<Window> windows(10);
  for (size_t w = 0; w < windows.size(); ++w) {
    windows[w].t0 = s.frameTime(static_cast<int>(w * frames / windows.size()));
    windows[w].t1 = s.frameTime(static_cast<int>((w + 1) * frames / windows.size()) - 1);
  }
  std::map<int, bool> was_ok;  // id -> ok in the last pair it was reported
  int returns = 0, identity_lost = 0, off_1px = 0, redetections = 0, pairs = 0, floor_ok = 1 << 30;
  double worst_return_px = 0.0, worst_step = 0.0, floor_t = 0.0;
  int max_total = 0, max_id = 0;
  std::set<int> first_ids;
  std::map<int, std::pair<std::string, bool>> went_out;  // id: the gate, not ok since
  cv::Vec3d prev_meas(0, 0, 0), prev_truth(0, 0, 0);
  // Per pair, for the figure: time (min), signal error (mm, 3D), ok, total, time per pair (ms);
  // per fifth pair: the field's held-out RMS (mm).
  std::vector<double> ts, sig_err, oks, totals, ms, tf, field_rms;
  cv::Mat l, r;
  for (int i = 0; i < frames; ++i) {
    if (s.dropped(i)) continue;
    s.render(i, l, r);
    const double t = s.frameTime(i);
    const auto t_ns = static_cast<int64_t>(std::llround(t * 1e9));
    const auto c0 = std::chrono::steady_clock::now();
    const PairResult& pr = session.process(l, r, static_cast<uint64_t>(i), t_ns);
    const bool field_ok = field.update(pr.features, pr.detected, pr.deformation.detections);
    session.afterPublish(l, r);
    const auto c1 = std::chrono::steady_clock::now();
    std::array<bool, 3> valid{field_ok, false, false};
    for (size_t k = 1; k < fields.size(); ++k)
      valid[k] = fields[k].update(pr.features, pr.detected, pr.deformation.detections);
    ASSERT_EQ(pr.state, SessionState::kTracking) << "pair " << i << ": " << session.reason();
    ASSERT_TRUE(pr.deformation.valid) << "pair " << i;
    ASSERT_TRUE(truth.update(pr, t)) << "pair " << i;
    ++pairs;
    Window& w = windows[std::min(
        windows.size() - 1, static_cast<size_t>(i) * windows.size() / static_cast<size_t>(frames))];
    w.us.push_back(std::chrono::duration<double, std::micro>(c1 - c0).count());
    const Deformation& d = pr.deformation;
    if (pr.detected && i > 0) ++redetections;
    ts.push_back(t / 60.0);
    sig_err.push_back(cv::norm(d.displacement - truth.displacement()));
    oks.push_back(d.ok);
    totals.push_back(d.total);
    ms.push_back(w.us.back() / 1e3);
    if (i == 0) {
      for (const Feature& f : pr.features) first_ids.insert(f.id);
      held = sim::heldOutPoints(s, config.roi.left, t, pr.features);
      for (const Feature& f : pr.features)
        if (const sim::MaterialTruth* tr = truth.find(f.id)) {
          first_set.push_back(tr->uv);
          first_p0.push_back(scene.position(tr->uv[0], tr->uv[1], t));
        }
    }
    // The gate that took each of the first detection's features out of view, the last time.
    for (const Feature& f : pr.features) {
      if (!first_ids.contains(f.id)) continue;
      auto& [why, since_ok] = went_out[f.id];
      if (f.status == FeatureStatus::kOk) {
        since_ok = false;
      } else if (!since_ok) {
        why = statusText(f.status, f.gate);
        since_ok = true;
      }
    }
    cv::Vec3d fixed(0, 0, 0);
    for (const cv::Vec2d& uv : first_set)
      fixed += scene.position(uv[0], uv[1], t) - scene.position(uv[0], uv[1], s.frameTime(0));
    fixed /= static_cast<double>(std::max<size_t>(1, first_set.size()));
    w.fixed_e2 += (d.displacement - fixed).dot(d.displacement - fixed) / 3.0;
    if (field_ok && i % 5 == 0) {  // the same mean from the field: every point, hidden or not
      // Over the points it answers for (beyond the features' reach it says so: confidence 0).
      cv::Vec3d fm(0, 0, 0), tm(0, 0, 0);
      int answered = 0;
      for (size_t k = 0; k < first_p0.size(); ++k) {
        const FieldQuery q = field.at(first_p0[k]);
        if (q.confidence <= 0.0) continue;
        fm += q.displacement;
        tm += scene.position(first_set[k][0], first_set[k][1], t) - first_p0[k];
        ++answered;
      }
      if (answered > 0) {
        const cv::Vec3d e2 = (fm - tm) / answered;
        w.fixed_field_e2 += e2.dot(e2) / 3.0;
        ++w.fixed_field_n;
      }
    }

    // The mean displacement, and its step against the true step (a re-detection must not jump).
    const cv::Vec3d e = d.displacement - truth.displacement();
    w.mean_e2 += e.dot(e) / 3.0;
    ++w.mean_n;
    if (pairs > 1) {
      worst_step = std::max(
          worst_step, cv::norm((d.displacement - prev_meas) - (truth.displacement() - prev_truth)));
    }
    prev_meas = d.displacement;
    prev_truth = truth.displacement();
    if (d.ok < floor_ok && i > 0) {
      floor_ok = d.ok;
      floor_t = t;
    }
    w.min_ok = std::min(w.min_ok, d.ok);
    w.max_total = std::max(w.max_total, d.total);
    max_total = std::max(max_total, d.total);

    // Each feature: its own displacement against its material point's, and identity on return.
    for (const Feature& f : pr.features) {
      max_id = std::max(max_id, f.id);
      const bool ok = f.status == FeatureStatus::kOk;
      const auto prev = was_ok.find(f.id);
      const bool returned = ok && prev != was_ok.end() && !prev->second;
      was_ok[f.id] = ok;
      const sim::MaterialTruth* tr = truth.find(f.id);
      if (!ok || tr == nullptr) continue;
      const auto td = truth.featureDisplacements().find(f.id);
      if (td != truth.featureDisplacements().end()) {
        const cv::Vec3d fe = (f.point - f.point0) - td->second;
        w.feat_e2 += fe.dot(fe);
        ++w.feat_n;
      }
      const cv::Vec2d at = s.rig().projectLeft(scene.position(tr->uv[0], tr->uv[1], t));
      const double px = cv::norm(f.left - at);
      w.px_e2 += px * px;
      ++w.px_n;
      if (returned) {
        ++returns;
        worst_return_px = std::max(worst_return_px, px);
        if (px > 1.0) ++off_1px;
        if (px > 3.0) ++identity_lost;
      }
    }

    // The dense field at the held-out material points: where is the point that was at P now?
    for (size_t k = 0; k < fields.size() && i % 5 == 0; ++k) {
      if (!valid[k]) continue;
      double e2 = 0.0;
      int ne = 0;
      for (const sim::HeldOutPoint& h : held) {
        const FieldQuery q = fields[k].at(h.p0);
        if (q.confidence <= 0.0) continue;
        const double fe = cv::norm(q.position - scene.position(h.uv[0], h.uv[1], t));
        w.field_e2[k] += fe * fe;
        w.field_max[k] = std::max(w.field_max[k], fe);
        ++w.field_n[k];
        e2 += fe * fe;
        ++ne;
      }
      if (k == 0 && ne > 0) {
        tf.push_back(t / 60.0);
        field_rms.push_back(std::sqrt(e2 / ne));
      }
    }
  }

  std::cout << spec->name << ": " << pairs << " pairs over " << s.frameTime(frames - 1) << " s, "
            << redetections << " re-detection(s), " << max_id + 1 << " feature ids in all, "
            << held.size() << " held-out material points\n";
  std::cout << "   window (s)   | signal RMS/axis | vs first set (field's) | field RMS (max) | "
               "field 100, 10 | features RMS (px) | min ok | total | median time/pair\n";
  for (Window& w : windows) {
    std::cout << "  " << std::fixed << std::setprecision(0) << std::setw(5) << w.t0 << "-"
              << std::setw(5) << w.t1 << "   | " << std::setprecision(4) << std::setw(9)
              << w.meanRms() << " mm    | " << w.fixedRms() << " (" << w.fixedFieldRms()
              << ") mm | " << w.fieldRms() << " (" << w.field_max[0] << ") | " << w.fieldRms(1)
              << ", " << w.fieldRms(2) << " | " << w.featRms() << " (" << w.pxRms() << ")"
              << " mm  | " << std::setw(6) << w.min_ok << " | " << std::setw(5) << w.max_total
              << " | " << std::setprecision(2) << w.medianUs() / 1e3 << " ms\n";
  }
  std::cout << std::defaultfloat << std::setprecision(6);
  Window& a = windows.front();
  Window& z = windows.back();
  const double true_shift = cv::norm(truth.displacement());
  std::cout << "drift: mean displacement error RMS " << a.meanRms() << " mm at the start, "
            << z.meanRms() << " at the end (against the first detection's material points "
            << a.fixedRms() << " -> " << z.fixedRms() << "; the field's mean over them "
            << a.fixedFieldRms() << " -> " << z.fixedFieldRms() << "); the field " << a.fieldRms()
            << " -> " << z.fieldRms() << " mm (max " << z.field_max[0]
            << "), while the surface moved " << true_shift << " mm\n";
  std::cout << "identity: " << returns << " returns of a hidden feature, " << identity_lost
            << " on other tissue (> 3 px, a quarter template, from its own material point), "
            << off_1px << " more than 1 px off; worst " << worst_return_px << " px\n";
  std::cout << "floor: at least " << floor_ok
            << " features ok in every pair (the fewest at t = " << floor_t
            << " s); worst step error " << worst_step << " mm\n";
  std::cout << "time per pair (process, field, refresh): " << a.medianUs() / 1e3
            << " ms median in the first tenth, " << z.medianUs() / 1e3 << " ms in the last\n";

  // The first detection's features at the end: ok, held by a gate (which), or retired (and the
  // gate that took them out of view for the last time: what a change would have to mend).
  int first_ok = 0;
  std::map<std::string, int> first_held, first_retired;
  std::set<int> present;
  for (const Feature& f : session.last().features) {
    present.insert(f.id);
    if (!first_ids.contains(f.id)) continue;
    if (f.status == FeatureStatus::kOk)
      ++first_ok;
    else
      ++first_held[statusText(f.status, f.gate)];
  }
  for (const auto& [id, out] : went_out)
    if (!present.contains(id)) ++first_retired[out.first];
  const auto counts = [](const std::map<std::string, int>& m) {
    std::string text;
    for (const auto& [why, count] : m)
      text += (text.empty() ? "" : ", ") + why + " " + std::to_string(count);
    return text;
  };
  std::cout << "of the first detection's " << first_ids.size() << " features, " << first_ok
            << " are ok at the end under their ids; held: " << counts(first_held)
            << "; retired, by the gate that last took them out of view: " << counts(first_retired)
            << "\n";

  // The figure: errors, the feature count and the time per pair over the run.
  analysis::Figure fig(1400, 1100, 3, 1, spec->name + ": hours-long tracking against the truth");
  panel(fig.at(0, 0), "error (3D)", "mm",
        {{ts, sig_err, {180, 90, 30}, "mean displacement vs its truth", 1},
         {tf, field_rms, {40, 40, 200}, "field, held-out points (RMS)", 2}});
  panel(fig.at(1, 0), "features", "count",
        {{ts, oks, {40, 140, 40}, "ok", 1},
         {ts, totals, {120, 120, 120}, "tracked (ok or hidden)", 1}});
  panel(fig.at(2, 0), "time per pair (track, deformation, field, stereo refresh; 2 cores shared)",
        "ms", {{ts, ms, {30, 30, 30}, "per pair", 1}});
  const std::string png = spec->name + "-long-tracking.png";
  ASSERT_TRUE(fig.save(png)) << png;
  std::cout << "figure: " << std::filesystem::absolute(png).string() << "\n";

  EXPECT_GT(true_shift, 5.0);  // the case did shift the brain
  EXPECT_GT(returns, 100);     // the instrument did hide features, again and again
  EXPECT_LE(identity_lost, returns / 100);
  EXPECT_LE(z.meanRms(), 0.03);  // the increment rule's random walk: 0.12
  EXPECT_LE(z.fieldRms(), 0.1);
  EXPECT_LE(z.fixedFieldRms(), 0.03);  // fixed material points over the whole run, from the field
  EXPECT_LE(worst_step, 0.05);
  EXPECT_GE(floor_ok, 25);  // measured 38 (the hour: 51)
  // The first detection's features that last: 72 of 100 on the compression (64 when a glint
  // hid a feature instead of being left out of its match, 16 of them retired under one; 50 when
  // the motion gate and re-acquisition took the neighbours' mean motion, which a sag's bowl and
  // a turn make wrong for a feature on one side of them; issue 34 asks for 80).
  EXPECT_GE(first_ok, 67);
  EXPECT_LE(max_total, config.tracker.max_features);  // what a pair costs is bounded
}

}  // namespace
}  // namespace pulsetrack::vision
