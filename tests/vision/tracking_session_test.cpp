// The TrackingSession's deformation against the simulator's ground truth on cortex-60s: the
// signal a robot acts on (displacement and velocity at the published delay), its continuity when
// the instrument hides features and at a re-detection, its stated noise; and the session's
// policy (stop, start, ROI changes, redetect).
//
// The truth: for each feature, its material point (the surface point under its pixel when it was
// detected) moved by the scene's true motion; the true deformation is the session's rule applied
// to those true displacements (session_truth.hpp, an independent implementation). So the
// error is the measurement's, not the definition's. Also printed: the error against the mean
// of a fixed set of material points (the first detection's), which the continuity trades for
// having no jumps.

#include "pulsetrack/vision/tracking_session.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <map>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/persistence.hpp>
#include <opencv2/imgproc.hpp>
#include <set>

#include "pulsetrack/sim/paper_rig.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/sim/session_truth.hpp"
#include "pulsetrack/vision/deformation_field.hpp"
#include "sim/cortex_roi.hpp"

namespace pulsetrack::vision {
namespace {

const std::string kScene = std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-60s.toml";

Roi roiFor(const sim::StereoSimulator& s, double r) { return test::cortexRoi(s, r); }

// One pair as the session returned it, for the fields evaluated afterwards.
struct Recorded {
  double t = 0;
  std::vector<Feature> features;
  bool detected = false;
  uint32_t detections = 0;
  cv::Vec3d mean_displacement{0, 0, 0};
  cv::Vec3d true_displacement{0, 0, 0};  // the continuous truth (the test's own)
  Prediction prediction;
};

// The dense field against held-out material points: a grid of left pixels over the whole ROI
// (edges and corners included) at the first pair, each the surface point under it, none within
// 1 mm of a feature; the robot's question for each, "where is the material point that was at P in
// the reference pair now?" (DeformationField::at), against the scene's true position. Errors are
// 3D (mm). Also the baselines a robot would have without the field: every point moved by the
// session's mean displacement, and the limit of huge smoothing (the spline's quadratic part alone).
struct FieldScore {
  double rms = 0, max = 0, rms_edge = 0;
  int points = 0, pairs = 0, below_confidence = 0;
};

FieldScore scoreField(const std::vector<Recorded>& pairs, const sim::StereoSimulator& s,
                      const Roi& roi, const FieldConfig* config, int max_features) {
  const sim::CortexScene& scene = *s.cortex();
  const std::vector<sim::HeldOutPoint> held =
      sim::heldOutPoints(s, roi.left, pairs.front().t, pairs.front().features);
  DeformationField field(config != nullptr ? *config : FieldConfig{}, max_features);
  FieldScore sc;
  double s2 = 0, s2e = 0;
  int ne = 0;
  for (const Recorded& rec : pairs) {
    if (config != nullptr && !field.update(rec.features, rec.detected, rec.detections)) continue;
    ++sc.pairs;
    for (const sim::HeldOutPoint& h : held) {
      const cv::Vec3d truth = scene.position(h.uv[0], h.uv[1], rec.t);
      cv::Vec3d est = h.p0 + rec.mean_displacement;
      if (config != nullptr) {
        const FieldQuery q = field.at(h.p0);
        if (q.confidence <= 0.0) {
          ++sc.below_confidence;
          continue;
        }
        est = q.position;
      }
      const double e = cv::norm(est - truth);
      s2 += e * e;
      sc.max = std::max(sc.max, e);
      ++sc.points;
      if (h.edge) {
        s2e += e * e;
        ++ne;
      }
    }
  }
  sc.rms = std::sqrt(s2 / std::max(1, sc.points));
  sc.rms_edge = std::sqrt(s2e / std::max(1, ne));
  return sc;
}

TEST(TrackingSession, DeformationFollowsTheTruthThroughAnInstrumentAndARedetection) {
  auto spec = sim::loadScene(kScene);
  ASSERT_TRUE(spec) << spec.error().message;
  sim::StereoSimulator s(*spec, *vision::loadRig(spec->rig_path));
  const sim::CortexScene& scene = *s.cortex();
  SessionConfig config;
  config.roi = roiFor(s, 19.0);
  TrackingSession session(s.rig(), config);
  // 18-31 s: the instrument crosses at 20-24 s; a re-detection is asked for at 27 s.
  const int first = 180, last = 310, redetect_at = 270;
  sim::SessionTruth truth(s);
  std::set<int> prev_ok_ids;
  int changes = 0;  // pairs whose ok set differs from the last pair's
  std::vector<double> err_d, err_v, sigma_d, sigma_v;
  double worst_jump = 0.0, fixed_set_err2 = 0.0;
  int redetections_seen = 0, pairs = 0, fixed_set_n = 0;
  std::vector<cv::Vec2d> first_set;  // the first detection's material points
  std::vector<Recorded> recorded;
  double t_first = 0.0;
  cv::Vec3d prev_meas(0, 0, 0), prev_truth(0, 0, 0);
  bool have_prev = false;
  cv::Mat l, r;
  for (int i = first; i < last; ++i) {
    if (s.dropped(i)) continue;
    s.render(i, l, r);
    const double t = s.frameTime(i);
    if (i == redetect_at) session.requestRedetect();
    const auto t_ns = static_cast<int64_t>(std::llround(t * 1e9));
    const PairResult& pr = session.process(l, r, static_cast<uint64_t>(i), t_ns);
    ASSERT_EQ(pr.state, SessionState::kTracking) << "pair " << i << ": " << session.reason();
    ++pairs;
    const Deformation& d = pr.deformation;
    if (pr.detected && i != first) ++redetections_seen;
    ASSERT_TRUE(d.valid) << "pair " << i;
    ASSERT_TRUE(truth.update(pr, t)) << "pair " << i;
    const cv::Vec3d true_out = truth.displacement();
    std::set<int> ok_ids;
    for (const Feature& f : pr.features)
      if (f.status == FeatureStatus::kOk) ok_ids.insert(f.id);
    if (pairs > 1 && ok_ids != prev_ok_ids) ++changes;
    prev_ok_ids = std::move(ok_ids);
    // The true velocity at the published delay (central difference, 1 ms), over the features
    // the signal is made of.
    cv::Vec3d true_vel(0, 0, 0);
    int nv = 0;
    for (const auto& [id, unused] : truth.featureDisplacements()) {
      const sim::MaterialTruth* tr = truth.find(id);
      const double tv = t - d.velocity_delay_s;
      true_vel += (scene.position(tr->uv[0], tr->uv[1], tv + 1e-3) -
                   scene.position(tr->uv[0], tr->uv[1], tv - 1e-3)) /
                  2e-3;
      ++nv;
    }
    if (i == first) {
      t_first = t;
      for (const Feature& f : pr.features)
        if (const sim::MaterialTruth* tr = truth.find(f.id)) first_set.push_back(tr->uv);
    }
    // Errors: displacement, velocity at the published delay; the step against the true step.
    err_d.push_back(cv::norm(d.displacement - true_out) / std::sqrt(3.0));
    if (d.velocity_delay_s > 0.0 && nv > 0) {
      err_v.push_back(cv::norm(d.velocity - true_vel / nv) / std::sqrt(3.0));
      sigma_v.push_back(d.velocity_sigma_mm_s);
    }
    sigma_d.push_back(d.displacement_sigma_mm);
    if (have_prev) {
      const double jump = cv::norm((d.displacement - prev_meas) - (true_out - prev_truth));
      worst_jump = std::max(worst_jump, jump);
    }
    prev_meas = d.displacement;
    prev_truth = true_out;
    have_prev = true;
    cv::Vec3d fixed(0, 0, 0);
    for (const cv::Vec2d& uv : first_set)
      fixed += scene.position(uv[0], uv[1], t) - scene.position(uv[0], uv[1], t_first);
    if (!first_set.empty()) {
      fixed /= static_cast<double>(first_set.size());
      fixed_set_err2 += (d.displacement - fixed).dot(d.displacement - fixed) / 3.0;
      ++fixed_set_n;
    }
    recorded.push_back({t, std::vector<Feature>(pr.features.begin(), pr.features.end()),
                        pr.detected, d.detections, d.displacement, true_out, d.prediction});
    session.afterPublish(l, r);
  }
  const auto rms = [](const std::vector<double>& v) {
    double s2 = 0;
    for (double x : v) s2 += x * x;
    return v.empty() ? 0.0 : std::sqrt(s2 / static_cast<double>(v.size()));
  };
  const auto mean = [](const std::vector<double>& v) {
    double s1 = 0;
    for (double x : v) s1 += x;
    return v.empty() ? 0.0 : s1 / static_cast<double>(v.size());
  };
  const double max_d = *std::max_element(err_d.begin(), err_d.end());
  std::cout << "cortex-60s 18-31 s, " << pairs << " pairs, " << changes
            << " changes of the ok set, " << redetections_seen << " re-detection(s): displacement "
            << "error RMS " << rms(err_d) << " mm per axis (max " << max_d
            << "), stated sigma mean " << mean(sigma_d) << " mm; velocity error RMS " << rms(err_v)
            << " mm/s per axis at the published delay "
            << session.last().deformation.velocity_delay_s * 1e3 << " ms, stated sigma mean "
            << mean(sigma_v) << " mm/s; worst step error " << worst_jump
            << " mm; against the first detection's fixed point set: RMS "
            << std::sqrt(fixed_set_err2 / std::max(1, fixed_set_n)) << " mm\n";
  EXPECT_EQ(redetections_seen, 1);
  EXPECT_GT(changes, 5);  // the instrument did hide features
  EXPECT_LE(rms(err_d), 0.02);
  EXPECT_LE(rms(err_v), 0.2);
  EXPECT_LE(worst_jump, 0.05);
  // The stated noise is the right size: the displacement's pair-to-pair noise, not its bias.
  EXPECT_GT(mean(sigma_d), 0.0005);
  EXPECT_LT(mean(sigma_d), 0.02);
  EXPECT_GT(mean(sigma_v), 0.005);
  EXPECT_LT(mean(sigma_v), 0.4);

  // The prediction through the real tracker (10 fps, so 100 and 200 ms land on later pairs):
  // relative RMS against holding, on the continuous truth, once the predictor has warmed up
  // (from 24 s). The predictor's own figures on long cases: motion_predictor_test.cpp.
  for (size_t k : {size_t{1}, size_t{2}}) {
    double em = 0, eh = 0;
    int n = 0;
    for (size_t i = 0; i < recorded.size(); ++i) {
      const Recorded& a = recorded[i];
      if (a.t < 24.0 || a.prediction.horizons <= static_cast<int>(k)) continue;
      const double h = a.prediction.horizon_s[k];
      for (size_t j = i + 1; j < recorded.size(); ++j) {
        if (std::abs(recorded[j].t - (a.t + h)) > 1e-6) continue;
        const cv::Vec3d later = recorded[j].true_displacement;
        const cv::Vec3d pm = a.prediction.displacement[k] - later;
        const cv::Vec3d ph = a.mean_displacement - later;
        em += pm.dot(pm);
        eh += ph.dot(ph);
        ++n;
      }
    }
    const double rel = std::sqrt(em / std::max(eh, 1e-30));
    std::cout << "prediction at " << recorded.back().prediction.horizon_s[k] * 1e3
              << " ms through the tracker (10 fps): relative RMS " << rel << " over " << n
              << " pairs (RMS " << std::sqrt(em / std::max(1, n) / 3.0) << " mm per axis, holding "
              << std::sqrt(eh / std::max(1, n) / 3.0) << ")\n";
    EXPECT_GT(n, 40);
    EXPECT_LT(rel, k == 1 ? 0.4 : 0.6);
  }

  // The dense field on held-out material points, its smoothing measured (the default is the
  // docs/ros2.md), against the mean displacement and the limit of huge smoothing.
  const FieldScore mean_only = scoreField(recorded, s, config.roi, nullptr, 100);
  std::cout << "held-out material points, 3D error over " << mean_only.pairs
            << " pairs: the mean displacement everywhere: RMS " << mean_only.rms << " mm, max "
            << mean_only.max << " (edge RMS " << mean_only.rms_edge << ")\n";
  FieldScore chosen;
  for (double lambda : {0.1, 1.0, 10.0, 100.0, 300.0, 1000.0, 3000.0, 1e6}) {
    FieldConfig fc;
    fc.smoothing = lambda;
    const FieldScore f = scoreField(recorded, s, config.roi, &fc, 100);
    std::cout << "  TPS smoothing " << lambda
              << (lambda == FieldConfig{}.smoothing ? " (default)" : "")
              << (lambda >= 1e6 ? " (the quadratic limit)" : "") << ": RMS " << f.rms << " mm, max "
              << f.max << ", edge RMS " << f.rms_edge << "; " << f.points << " points scored, "
              << f.below_confidence << " beyond the field's reach\n";
    if (lambda == FieldConfig{}.smoothing) chosen = f;
  }
  EXPECT_EQ(chosen.pairs, pairs);
  EXPECT_GT(chosen.points, 100 * pairs);
  EXPECT_LE(chosen.rms, 0.02);  // the issue's aim: 0.05
  EXPECT_LE(chosen.max, 0.1);
  EXPECT_LT(chosen.rms, 0.3 * mean_only.rms);  // the field knows what the mean cannot
}

TEST(TrackingSession, StopStartAndRoiChangesRestartTheSignalAndSayWhy) {
  auto spec = sim::loadScene(kScene);
  ASSERT_TRUE(spec) << spec.error().message;
  spec->supersample = 1;
  sim::StereoSimulator s(*spec, *vision::loadRig(spec->rig_path));
  SessionConfig config;
  config.roi = roiFor(s, 19.0);
  TrackingSession session(s.rig(), config);
  cv::Mat l, r;
  const auto pair = [&](int i) -> const PairResult& {
    s.render(i, l, r);
    const PairResult& pr =
        session.process(l, r, static_cast<uint64_t>(i), static_cast<int64_t>(i) * 100'000'000);
    session.afterPublish(l, r);
    return pr;
  };
  EXPECT_TRUE(pair(0).detected);
  EXPECT_EQ(session.last().deformation.detections, 1U);
  EXPECT_FALSE(session.last().deformation.continuous);  // a new signal starts
  EXPECT_TRUE(session.reason().empty());
  EXPECT_TRUE(pair(1).deformation.continuous);
  session.stop();
  EXPECT_EQ(pair(2).state, SessionState::kStopped);
  EXPECT_FALSE(session.last().deformation.valid);
  EXPECT_NE(session.reason().find("stopped"), std::string::npos);
  session.start();
  EXPECT_TRUE(pair(3).detected);
  EXPECT_FALSE(session.last().deformation.continuous);
  EXPECT_DOUBLE_EQ(cv::norm(session.last().deformation.displacement), 0.0);
  // A bad ROI: named, nothing tracked, no detection attempted; a good one recovers.
  session.setRoi({{-5, 10, 100, 100}, {10, 10, 100, 100}}, 20.0);
  EXPECT_EQ(pair(4).state, SessionState::kNoFeatures);
  EXPECT_NE(session.reason().find("left ROI -5,10 100x100: not inside the"), std::string::npos)
      << session.reason();
  session.setRoi(config.roi, 0.0);
  EXPECT_EQ(pair(5).state, SessionState::kNoFeatures);
  EXPECT_NE(session.reason().find("depth tolerance"), std::string::npos) << session.reason();
  session.setRoi(config.roi, 20.0);
  EXPECT_TRUE(pair(6).detected);
  EXPECT_EQ(session.last().state, SessionState::kTracking);
  // A re-detection keeps the signal continuous and counts.
  session.requestRedetect();
  EXPECT_TRUE(pair(7).detected);
  EXPECT_TRUE(session.last().deformation.continuous);
  EXPECT_EQ(session.last().deformation.detections, 2U);
  EXPECT_TRUE(pair(8).deformation.continuous);
  // A left ROI only (the daemon's set_roi with the right one all zero): the right ROI and the
  // depth tolerance are found in the pair, and cover the one the scene's depth gives.
  session.setRoi({config.roi.left, {}}, 0.0);
  EXPECT_TRUE(pair(9).detected) << session.reason();
  EXPECT_EQ(session.last().state, SessionState::kTracking);
  EXPECT_EQ(session.rangeSerial(), 1U);
  const StereoRange& found = session.stereoRange();
  EXPECT_GT((found.right & config.roi.right).area(), config.roi.right.area() / 2)
      << found.summary();
  const double z = s.cortex()->position(0.0, 0.0, 0.0)[2];  // the scene's own depth
  EXPECT_NEAR(found.depth_mm, z, 0.05 * z) << found.summary();
  EXPECT_GE(session.tracker().okCount(), 50);
}

}  // namespace
}  // namespace pulsetrack::vision

namespace pulsetrack::vision {
namespace {

// The right ROI derived from a left one (the console's ROI drawing): every point the left ROI sees
// between depth - tol and depth + tol lands inside it, by OpenCV's own undistortPoints and
// projectPoints on the rig file (nothing of the rig code under test), and it is not much larger.
// The working scale: only 0 (auto), 1 and 0.5 are taken; another is refused as a bad ROI is
// (nothing tracked, the reason names it). The half-size rig projects a point where the full one
// does, halved about the pixels' centres ((x + 0.5) / 2 - 0.5).
TEST(TrackingSession, AScaleOtherThanAutoOneOrHalfIsRefusedAndTheHalfRigProjectsHalved) {
  const StereoRig rig = sim::paperRig();
  SessionConfig c;
  c.roi = {{560, 380, 260, 220}, {540, 370, 260, 220}};
  c.scale = 0.7;
  TrackingSession session(rig, c);
  cv::Mat img(rig.left.imageSize(), CV_8UC1, cv::Scalar(128));
  (void)session.process(img, img, 0, 0);
  EXPECT_EQ(session.last().state, SessionState::kNoFeatures);
  EXPECT_EQ(session.reason(), "scale 0.7: must be 0 (chosen at the first detection), 1 or 0.5");
  EXPECT_EQ(session.detectionAttempts(), 0);
  const StereoRig half = TrackingSession::scaledRig(rig, 0.5);
  EXPECT_EQ(half.left.imageSize(), cv::Size(680, 512));
  const cv::Vec3d p(12.0, -7.0, 450.0);
  for (const auto& [full_cam, half_cam] :
       {std::pair{&rig.left, &half.left}, std::pair{&rig.right, &half.right}}) {
    const cv::Vec3d pc = full_cam == &rig.left ? p : rig.r * p + rig.t;
    const cv::Vec2d a = full_cam->project(pc), b = half_cam->project(pc);
    EXPECT_NEAR(b[0], (a[0] + 0.5) / 2 - 0.5, 1e-9);
    EXPECT_NEAR(b[1], (a[1] + 0.5) / 2 - 0.5, 1e-9);
  }
}

// A fresh detection (start(), a new ROI) gives new ids whatever the working scale: the tracker
// made for a scale continues the ids of the one before (the daemon's subscribers tell a new
// feature set by them).
TEST(TrackingSession, AFreshDetectionAtAnotherScaleGivesNewIds) {
  sim::SceneSpec spec;
  spec.kind = sim::SceneKind::kCortex;
  spec.supersample = 1;
  sim::StereoSimulator s(spec, sim::paperRig());
  cv::Mat left, right;
  s.render(0, left, right);
  SessionConfig c;
  c.roi = {{560, 380, 260, 220}, {540, 370, 260, 220}};
  c.scale = 0.5;
  TrackingSession session(s.rig(), c);
  const PairResult& first = session.process(left, right, 0, 0);
  ASSERT_EQ(first.state, SessionState::kTracking) << session.reason();
  ASSERT_FALSE(first.features.empty());
  int max_id = -1;
  for (const Feature& f : first.features) max_id = std::max(max_id, f.id);
  session.start();
  const PairResult& again = session.process(left, right, 1, 100'000'000);
  ASSERT_EQ(again.state, SessionState::kTracking) << session.reason();
  ASSERT_TRUE(again.detected);
  for (const Feature& f : again.features) EXPECT_GT(f.id, max_id);
}

TEST(TrackingSession, TheRightRoiForALeftOneHoldsWhatTheLeftSeesAtThoseDepths) {
  const std::string path = std::string(PULSETRACK_SOURCE_DIR) + "/config/rigs/paper-rig.yaml";
  auto rig = loadRig(path);
  ASSERT_TRUE(rig) << rig.error().message;
  cv::FileStorage fs(path, cv::FileStorage::READ);
  cv::Mat m1, d1, m2, d2, rot, t, rvec;
  fs["M1"] >> m1;
  fs["D1"] >> d1;
  fs["M2"] >> m2;
  fs["D2"] >> d2;
  fs["R"] >> rot;
  fs["T"] >> t;
  cv::Rodrigues(rot, rvec);
  for (const cv::Rect& left :
       {cv::Rect(483, 339, 400, 340), cv::Rect(10, 10, 300, 200), cv::Rect(900, 700, 400, 300)}) {
    const double depth = 450.0, tol = 20.0;
    const cv::Rect right = TrackingSession::rightRoiFor(*rig, left, depth, tol);
    ASSERT_FALSE(right.empty()) << left;
    std::vector<cv::Point2d> px;
    for (int i = 0; i <= 20; ++i)
      for (int j = 0; j <= 20; ++j)
        px.emplace_back(left.x + left.width * i / 20.0, left.y + left.height * j / 20.0);
    std::vector<cv::Point2d> norm;
    cv::undistortPoints(px, norm, m1, d1);
    std::vector<cv::Point3d> pts;
    for (const double z : {depth - tol, depth, depth + tol})
      for (const cv::Point2d& n : norm) pts.emplace_back(n.x * z, n.y * z, z);
    std::vector<cv::Point2d> pr;
    cv::projectPoints(pts, rvec, t, m2, d2, pr);
    double x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
    int outside = 0, in_image = 0;
    for (const cv::Point2d& q : pr) {
      if (q.x < 0 || q.y < 0 || q.x >= 1360 || q.y >= 1024) continue;  // off the right image
      ++in_image;
      x0 = std::min(x0, q.x);
      y0 = std::min(y0, q.y);
      x1 = std::max(x1, q.x);
      y1 = std::max(y1, q.y);
      if (!right.contains(cv::Point(static_cast<int>(q.x), static_cast<int>(q.y)))) ++outside;
    }
    ASSERT_GT(in_image, 100) << left;
    EXPECT_EQ(outside, 0) << left << " -> " << right;
    // Tight: within 3 px of the hull's box on each side the image's edge did not cut (where it
    // did, the samples stop short of the edge by up to a grid step).
    if (right.x > 0) {
      EXPECT_LE(x0 - right.x, 3.0) << right;
    }
    if (right.y > 0) {
      EXPECT_LE(y0 - right.y, 3.0) << right;
    }
    if (right.br().x < 1360) {
      EXPECT_LE(right.x + right.width - x1, 3.0) << right;
    }
    if (right.br().y < 1024) {
      EXPECT_LE(right.y + right.height - y1, 3.0) << right;
    }
  }
  // Not in front of the camera, or a nonsense ROI: nothing.
  EXPECT_TRUE(TrackingSession::rightRoiFor(*rig, {483, 339, 400, 340}, 10.0, 20.0).empty());
  EXPECT_TRUE(TrackingSession::rightRoiFor(*rig, {483, 339, 0, 340}, 450.0, 20.0).empty());
}

}  // namespace
}  // namespace pulsetrack::vision
