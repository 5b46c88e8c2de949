// The tracker on real in-vivo tissue (issue 32): the Hamlyn Centre's beating heart (da Vinci,
// rectified, 360x288), read from ../shared/data (the test says so and skips when it is absent).

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "hamlyn.hpp"
#include "pulsetrack/vision/stereo_search.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"
#include "pulsetrack/vision/tracking_session.hpp"
#include "test_util.hpp"

namespace pulsetrack::vision {
namespace {

// Pair 1 with its right ROI and depth tolerance from the stereo search on the left ROI (as
// `track` finds them).
class RealTissueOnTheHeart : public hamlyn::PairOne {
 protected:
  void SetUp() override {
    PairOne::SetUp();
    if (IsSkipped() || HasFailure()) return;
    auto found = findStereoRange(pair_.rig, pair_.left, pair_.right, hamlyn::kRoi);
    ASSERT_TRUE(found) << found.error().message;
    found_ = *found;
    roi_ = {hamlyn::kRoi, found_.right};
  }
  // Detects on pair 1 at that ROI: the ok count, or -1 (a failure) when it cannot.
  int detect(StereoTracker& tracker) const {
    auto n = tracker.initialize(pair_.left, pair_.right, roi_, found_.tolerance_mm);
    EXPECT_TRUE(n) << n.error().message;
    return n ? *n : -1;
  }
  StereoRange found_;
  Roi roi_;
};

// The neighbour gates (sheen, epipolar spread) were chosen on renders and photographs. On the
// heart they rejected most matches: the rig's own vertical offset varies by 0.4-0.5 px over the
// ROI against a 0.15 px gate, and the moist surface shines differently per view everywhere.
// Fitted to the pair's own values they keep what the other gates accept, within their bounds.
TEST_F(RealTissueOnTheHeart, NeighbourGatesFitToTheBeatingHeart) {
  const StereoRig* rig = &pair_.rig;
  TrackerConfig fixed;
  fixed.fit_sigmas = 0.0;
  StereoTracker as_configured(*rig, fixed);
  const int ok_fixed = detect(as_configured);
  EXPECT_FALSE(as_configured.fittedGates().sheen_fitted);
  EXPECT_FALSE(as_configured.fittedGates().epipolar_spread_fitted);
  EXPECT_EQ(as_configured.fittedGates().max_epipolar_spread_px, fixed.max_epipolar_spread_px);

  StereoTracker fitting(*rig, TrackerConfig{});
  const int ok_fit = detect(fitting);
  const FittedGates& g = fitting.fittedGates();
  std::cout << "hamlyn pair 1: " << ok_fixed << " ok with the configured gates, " << ok_fit
            << " fitted: " << g.summary() << "\n";
  EXPECT_TRUE(g.epipolar_spread_fitted);
  EXPECT_GT(g.max_epipolar_spread_px, fixed.max_epipolar_spread_px);
  EXPECT_LE(g.max_epipolar_spread_px, fixed.max_epipolar_spread_bound_px);
  EXPECT_GE(g.max_sheen, fixed.max_sheen);
  EXPECT_LE(g.max_sheen, fixed.max_sheen_bound);
  EXPECT_NE(g.summary().find("fitted to these images"), std::string::npos) << g.summary();
  EXPECT_GE(ok_fit, 2 * ok_fixed);
  EXPECT_GE(ok_fit, 20);
  // What the fitted gates let in is still on the rig's geometry: every ok match within the
  // absolute epipolar gate and on the rows the stereo search measured (+-1 px).
  int ok = 0;
  for (const Feature& f : fitting.features()) {
    if (f.status != FeatureStatus::kOk) continue;
    ++ok;
    EXPECT_LE(f.epipolar_px, TrackerConfig{}.max_epipolar_px) << "feature " << f.id;
    EXPECT_NEAR(rig->epipolarOffset(f.left, f.right), found_.vertical_px, 1.0)
        << "feature " << f.id;
  }
  EXPECT_EQ(ok, ok_fit);
}

// The heart's 360x288 video is blurred: the stereo match's affine refinement does not settle on
// a third of pair 1's matches (28 of 85). Refined in translation instead, as many of them as the
// other gates accept are taken, because the affine-refined ones do not fill the ceiling (on
// renders and photographs they do, and the fallback changes nothing there: bench/gate_eval).
TEST_F(RealTissueOnTheHeart, UnsettledStereoMatchesAreRefinedInTranslationWhereFewPass) {
  TrackerConfig affine_only;
  affine_only.stereo_translation_fallback = false;
  StereoTracker strict(pair_.rig, affine_only);
  const int n_strict = detect(strict);
  EXPECT_EQ(strict.fittedGates().stereo_translation, 0);
  StereoTracker fallback(pair_.rig, TrackerConfig{});
  const int n = detect(fallback);
  const FittedGates& g = fallback.fittedGates();
  std::cout << "hamlyn pair 1: " << n_strict << " ok with the affine refinement only, " << n
            << " with the translation fallback: " << g.summary() << "\n";
  EXPECT_GT(g.stereo_unsettled, 20);
  EXPECT_GE(g.stereo_translation, 5);
  EXPECT_GE(n, n_strict + 5);
  EXPECT_NE(g.summary().find("refined in translation"), std::string::npos) << g.summary();
  // Still on the rig's rows (the stereo search's measured offset, +-1 px).
  for (const Feature& f : fallback.features()) {
    if (f.status != FeatureStatus::kOk) continue;
    EXPECT_NEAR(pair_.rig.epipolarOffset(f.left, f.right), found_.vertical_px, 1.0)
        << "feature " << f.id;
  }
}

// Issue 32's first acceptance figure: >= 80 features at the first detection of the heart from a
// left ROI. Its 200x180 ROI held 85 Harris corners (spaced 12 px, 17 px inside the ROI), and a
// third of the matches scored under the stereo NCC gate chosen on renders (0.94). Points textured
// over the whole template (spaced 8 px, their templates reaching out of the ROI) are matched
// after the corners, and the stereo NCC threshold is fitted to the first round's own scores.
TEST_F(RealTissueOnTheHeart, TexturedPointsAndAFittedStereoNccFillTheCeiling) {
  TrackerConfig before;
  before.textured_points = false;
  before.min_stereo_ncc_bound = before.min_stereo_ncc;  // never fitted
  StereoTracker corners(pair_.rig, before);
  const int n_before = detect(corners);
  EXPECT_FALSE(corners.fittedGates().stereo_ncc_fitted);
  StereoTracker now(pair_.rig, TrackerConfig{});
  const int n = detect(now);
  const FittedGates& g = now.fittedGates();
  std::cout << "hamlyn pair 1: " << n_before << " ok from corners at the configured stereo NCC, "
            << n << " with textured points and the fitted threshold (" << now.candidates().size()
            << " candidates): " << g.summary() << "\n";
  EXPECT_LE(n_before, 50);  // measured 41
  EXPECT_GE(n, 80);         // measured 96
  EXPECT_TRUE(g.stereo_ncc_fitted);
  EXPECT_LT(g.min_stereo_ncc, TrackerConfig{}.min_stereo_ncc);
  EXPECT_GE(g.min_stereo_ncc, TrackerConfig{}.min_stereo_ncc_bound);
  EXPECT_NE(g.summary().find("stereo NCC 0.88 (fitted"), std::string::npos) << g.summary();
  // ... and tracking takes the bounds of its gates for such images.
  EXPECT_TRUE(g.tracking_fitted);
  EXPECT_EQ(g.max_motion_px, TrackerConfig{}.max_motion_bound_px);
  EXPECT_EQ(g.max_ncc_drop, TrackerConfig{}.max_ncc_drop_bound);
  EXPECT_EQ(g.video_search_px, TrackerConfig{}.video_search_bound_px);
  EXPECT_EQ(g.video_refine_iterations, TrackerConfig{}.video_refine_iterations_bound);
  EXPECT_NE(g.summary().find("tracking: motion 1.00 px, NCC drop 0.15, search +-12 px, "
                             "refinement 20 steps"),
            std::string::npos)
      << g.summary();
  // Every feature inside the left ROI, above the fitted threshold, and on the rig's rows.
  for (const Feature& f : now.features()) {
    if (f.status != FeatureStatus::kOk) continue;
    EXPECT_TRUE(hamlyn::kRoi.contains(cv::Point(int(f.left[0]), int(f.left[1]))))
        << "feature " << f.id;
    EXPECT_GE(f.ncc, g.min_stereo_ncc) << "feature " << f.id;
    EXPECT_NEAR(pair_.rig.epipolarOffset(f.left, f.right), found_.vertical_px, 1.0)
        << "feature " << f.id;
  }
}

// The heart's ok features per pair and the ok matches' vertical disparities over all 300 pairs,
// as `pulsetrack track --fps 25 --roi-left 120,60,200,180` and the daemon run them (the session:
// detection, re-detection, tracking, and after each result the stereo and template refreshes).
// `upscale` 2: every pair (and the rig, the ROI) at twice its size (bicubic), the heart as an SD
// camera's 720x576 frame that holds the 360x288 one's detail would show it; `scale` the
// session's (0: auto).
struct HeartRun {
  std::vector<int> ok_per_pair;
  std::vector<double> vertical;
  int median = 0;
  double scale = 1.0;  // the session's working scale
  double fifty = 0.0;  // the share of pairs with >= 50 ok
};
HeartRun runHeart(const StereoRig& rig, const TrackerConfig& tracker, int upscale = 1,
                  double scale = 0.0) {
  SessionConfig sc;
  sc.roi.left = cv::Rect(hamlyn::kRoi.x * upscale, hamlyn::kRoi.y * upscale,
                         hamlyn::kRoi.width * upscale, hamlyn::kRoi.height * upscale);
  sc.tracker = tracker;
  sc.scale = scale;
  TrackingSession session(upscale == 1 ? rig : TrackingSession::scaledRig(rig, upscale), sc);
  constexpr int kPairs = 300;
  HeartRun run;
  for (int k = 1; k <= kPairs; ++k) {
    cv::Mat left, right;
    hamlyn::readPair(k, left, right);
    if (left.empty() || right.empty()) {
      ADD_FAILURE() << "cannot read pair " << k;
      return run;
    }
    if (upscale != 1) {
      cv::resize(left, left, {}, upscale, upscale, cv::INTER_CUBIC);
      cv::resize(right, right, {}, upscale, upscale, cv::INTER_CUBIC);
    }
    const PairResult& r = session.process(left, right, static_cast<uint64_t>(k),
                                          static_cast<int64_t>(k) * 40'000'000);
    int ok = 0;
    for (const Feature& f : r.features) {
      if (f.status != FeatureStatus::kOk) continue;
      ++ok;
      run.vertical.push_back(std::abs(f.left[1] - f.right[1]));
    }
    run.ok_per_pair.push_back(ok);
    session.afterPublish(left, right);
  }
  std::vector<int> sorted = run.ok_per_pair;
  std::sort(sorted.begin(), sorted.end());
  run.median = sorted[sorted.size() / 2];
  run.scale = session.scale();
  run.fifty = static_cast<double>(
                  std::count_if(sorted.begin(), sorted.end(), [](int n) { return n >= 50; })) /
              static_cast<double>(sorted.size());
  return run;
}

// Before: 0 ok from pair 17 on, for good (a fill re-detection with nothing ok kept the lost
// features' stale positions, found nothing, and re-detection was never due again; tracking lost
// the heart's faster phases to the search window and the rectified rows' 0.6 px offset to the
// epipolar gate). The beating heart changes its look over a beat: where a feature's frame-0
// template finds nothing, its look in a recent pair where the frame-0 templates did find it in
// both views holds it (template_refresh).
TEST(RealTissue, TheBeatingHeartIsTrackedThroughTheWholeSequence) {
  PULSETRACK_SKIP_WITHOUT_DATA(hamlyn::dir());
  auto rig = loadRig(hamlyn::dir() / "rig.yaml");
  ASSERT_TRUE(rig) << rig.error().message;
  TrackerConfig frame0_only;
  frame0_only.template_refresh = 0;
  const HeartRun off = runHeart(*rig, frame0_only);
  TrackerConfig renders_gates;
  renders_gates.fit_tracking_gates = false;
  const HeartRun fixed = runHeart(*rig, renders_gates);
  HeartRun on = runHeart(*rig, TrackerConfig{});
  ASSERT_EQ(on.ok_per_pair.size(), 300U);
  const auto none = std::count(on.ok_per_pair.begin(), on.ok_per_pair.end(), 0);
  ASSERT_FALSE(on.vertical.empty());
  std::nth_element(on.vertical.begin(),
                   on.vertical.begin() + static_cast<long>(on.vertical.size() / 2),
                   on.vertical.end());
  const double vertical_median = on.vertical[on.vertical.size() / 2];
  const auto fifty =
      std::count_if(on.ok_per_pair.begin(), on.ok_per_pair.end(), [](int n) { return n >= 50; });
  const double fifty_share =
      static_cast<double>(fifty) / static_cast<double>(on.ok_per_pair.size());
  std::cout << "hamlyn, 300 pairs: " << on.ok_per_pair.front()
            << " ok at the first pair, ok per pair median " << on.median
            << " (frame-0 templates only: " << off.median
            << "; the renders' tracking gates: " << fixed.median << "), pairs with >= 50 ok "
            << 100.0 * fifty_share << " %, pairs with none " << none
            << "; ok matches' vertical disparity median " << vertical_median << " px\n";
  EXPECT_EQ(none, 0);
  // The acceptance: >= 80 at the first detection (measured 96; 41 before the textured
  // points and the fitted stereo NCC, 33 before the translation fallback) and >= 50 ok in 80 %
  // of the pairs (measured 92 %, median 66; 39 % and 46.5 with the video refinement's 10 steps,
  // 32 with the renders' tracking gates, 19 before the textured points).
  EXPECT_GE(on.ok_per_pair.front(), 80);
  EXPECT_GE(fifty_share, 0.80);
  EXPECT_GE(on.median, 60);
  EXPECT_GE(on.median, fixed.median + 20);
  EXPECT_GE(on.median, off.median);
  EXPECT_LE(vertical_median, 1.0);
}

// Issue 32's item 3 (scale): the tracker's templates and windows are fixed in pixels. The same
// heart at twice the size (a 720x576 frame with the 360x288 one's detail) gave them a quarter of
// the detail: 40 features at the first detection, 25 ok per pair at the median, >= 50 ok in 7 %
// of the pairs, 45 re-detections. The session tries half the size where the first detection
// does not fill the ceiling and keeps it (it detects 97): the native figures come back.
TEST(RealTissue, TheHeartAtTwiceItsSizeIsTrackedAtHalfScale) {
  PULSETRACK_SKIP_WITHOUT_DATA(hamlyn::dir());
  auto rig = loadRig(hamlyn::dir() / "rig.yaml");
  ASSERT_TRUE(rig) << rig.error().message;
  HeartRun native_scale = runHeart(*rig, TrackerConfig{}, 2, 1.0);
  HeartRun chosen = runHeart(*rig, TrackerConfig{}, 2, 0.0);
  ASSERT_EQ(chosen.ok_per_pair.size(), 300U);
  ASSERT_FALSE(chosen.vertical.empty());
  std::nth_element(chosen.vertical.begin(),
                   chosen.vertical.begin() + static_cast<long>(chosen.vertical.size() / 2),
                   chosen.vertical.end());
  const double vertical = chosen.vertical[chosen.vertical.size() / 2];
  std::cout << "hamlyn at 720x576: at scale 1 " << native_scale.ok_per_pair.front()
            << " at the first pair, median " << native_scale.median << ", >= 50 ok in "
            << 100.0 * native_scale.fifty << " %; auto (scale " << chosen.scale << ") "
            << chosen.ok_per_pair.front() << ", median " << chosen.median << ", >= 50 ok in "
            << 100.0 * chosen.fifty << " %, vertical disparity median " << vertical
            << " px of the 720x576 images\n";
  EXPECT_EQ(native_scale.scale, 1.0);
  EXPECT_EQ(chosen.scale, 0.5);
  EXPECT_GE(chosen.ok_per_pair.front(), 80);
  EXPECT_GE(chosen.fifty, 0.80);
  EXPECT_GE(chosen.median, native_scale.median + 20);
  // In the images' pixels: twice the native run's 0.53 px (the rig's rows off by 0.6 px).
  EXPECT_GT(vertical, 0.7);
  EXPECT_LT(vertical, 1.5);
}

}  // namespace
}  // namespace pulsetrack::vision
