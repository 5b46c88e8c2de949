#pragma once
// The paper's stereo feature tracker (sections 2.B-2.C), with the design's accuracy fixes:
//
// initialize() (may allocate; runs at start and on re-detection):
//   left ROI -> specular mask (threshold, dilated by the template size) -> "darker than its
//   neighbourhood" mask (vessels) -> Harris corners, taken every grid cell's strongest first,
//   then every cell's second, ... until the ceiling of features that pass the gates is met
//   (the paper lowers the sensitivity until the ceiling of corners is met) -> stereo match in the
//   search box built from the ROI pair and the depth tolerance (NCC, quadratic peak, then an affine
//   refinement for the two views' different foreshortening) -> gates (incl. sheen) ->
//   triangulation.
// track() (per frame: no allocation, no lock, no exception):
//   each camera: NCC around the last position against the frame-0 template, quadratic peak,
//   translation refinement on 23x23 against the frame-0 patch (no drift) -> gates (NCC, NMI,
//   epipolar, distance to a parabolic surface fitted to the cloud) -> LM triangulation.
// refreshStereo() (per frame, after the result is out): some features' stereo match again in
//   the current pair, averaged into a per-feature correction (the first pair's noise out).
// A rejected feature keeps its id and its reason, and comes back when it passes again.

#include <array>
#include <cstdint>
#include <opencv2/core.hpp>
#include <span>
#include <string>
#include <vector>

#include "pulsetrack/vision/affine_refiner.hpp"
#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/ncc.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::vision {

enum class FeatureStatus : uint8_t {
  kOk,
  kOccluded,         // NCC or NMI below the gate: something covers it (instrument, glint)
  kLost,             // no peak inside the search window, or the refinement left the image
  kOutlierEpipolar,  // left and right no longer on one epipolar line
  kOutlierSurface,   // too far from the parabolic surface through the cloud
  kOutlierTriangulation,
};
const char* toString(FeatureStatus s) noexcept;

// The gate that rejected a feature or candidate (the status says what it means for the feature,
// this says which test spoke). The values are the DDS/ROS 2 Feature.msg REASON_* constants.
enum class Gate : uint8_t {
  kNone = 0,       // passed every gate
  kNcc,            // NCC below min_ncc
  kNccDrop,        // NCC below the feature's own running level by more than max_ncc_drop
  kNmi,            // NMI with the first pair's patch below min_nmi
  kGlint,          // a pixel over specular_threshold in the patch or its margin
  kSheen,          // brighter in one view than the local gain ratio allows (max_sheen)
  kNoPeak,         // the NCC maximum on the search window's border: no peak inside
  kNotConverged,   // the sub-pixel refinement did not converge, or left the peak
  kImageBorder,    // the patch leaves the image
  kEpipolar,       // farther than max_epipolar_px from the epipolar line
  kSurface,        // farther from the fitted parabola than max_surface_mm / the MAD limit
  kTriangulation,  // the rays do not meet in front of the cameras
  kStereoNcc,      // the left-right match's NCC below min_stereo_ncc
  kLeftRight,      // the right patch, matched back in the left image, lands farther than
                   // max_left_right_px from the left point (a depth edge, a repeated pattern)
  kMotion,         // its disparity changed by more than max_motion_px beyond what its
                   // neighbours' motion predicts (one view's match slid off the tissue)
  kDepthEdge,      // a textured corner block of the template does not match where the
                   // whole does (min_block_ncc): a nearer surface fills part of it
};
const char* toString(Gate g) noexcept;
// A set of gates (bit 1 << value): every gate a match failed, not only the first.
constexpr uint16_t gateBit(Gate g) noexcept {
  return static_cast<uint16_t>(1U << static_cast<unsigned>(g));
}
// "ok", or the status and the gate: "occluded:glint".
std::string statusText(FeatureStatus s, Gate g);

enum class Detector : uint8_t {
  kHarris,     // the paper's: Harris corners on tissue (vessels)
  kDarkBlobs,  // small dark blobs, centred (the validation plate's conical holes)
};

struct TrackerConfig {
  Detector detector = Detector::kHarris;
  double blob_radius_px = 3.0;      // kDarkBlobs: the blobs' radius in the image
  double blob_min_contrast = 20.0;  // kDarkBlobs: grey levels below the local mean
  int max_features = 100;
  int grid_cols = 5;
  int grid_rows = 5;
  double harris_k = 0.04;
  // Weakest corner taken, fraction of the strongest response. 1e-4: the corners are taken in
  // cell round-robin order until the ceiling passes, so weak ones are reached only where the
  // strong ones failed (teddy: 50 accepted at 1e-3, 73 at 1e-4; cortex scenes unchanged).
  double sensitivity_min = 1e-4;
  // After all of those (spaced and dense), corners min_distance_px apart down to this: reached
  // only where the others did not fill the ceiling (the Hamlyn heart: 60 -> 85 candidates and
  // 28 -> 33 features at its first pair; gate_eval unchanged. 1e-5 for all tiers instead took
  // teddy from 97 of 100 right to 95 of 99).
  double faint_sensitivity_min = 1e-6;
  int min_distance_px = 12;
  // Last of all (after the faint corners), points that are not corners at Harris's scale but
  // textured over the whole template in both directions: local maxima of the smaller eigenvalue
  // of the template's structure tensor, down to textured_sensitivity of the strongest, spaced
  // dense_distance_px, anywhere in the ROI (their templates may reach out of it; the corners
  // keep a margin inside). Reached only where the corners do not fill the ceiling: blurred SD
  // video (the Hamlyn heart's pair 1: 85 -> 180 candidates, with the fitted stereo NCC 41 -> 96
  // features; real-texture-sd 37 features at 0.137 mm -> 51 at 0.150 mm 3D RMS, >= 50 ok in
  // 0 -> 93 % of the pairs). The renders and photographs fill the ceiling before: gate_eval
  // unchanged.
  bool textured_points = true;
  double textured_sensitivity = 1e-3;
  // Where the corners min_distance_px apart do not fill the ceiling past the gates, those
  // between them down to this spacing are matched after all of them (teddy: 72 accepted at
  // 93 % from the 155 spaced ones, 100 at 95 % with these; cortex scenes fill from the spaced
  // ones: a denser set everywhere gathered the features where the vessels are densest, under
  // cortex-hard's instrument, and >= 50 ok fell from 80.5 % to 72.5 % of its pairs).
  int dense_distance_px = 8;
  double min_isotropy = 0.25;  // smaller / larger eigenvalue of the template's structure tensor
  // Grey level from which a pixel is (part of) a glint. Chosen by gate_eval: at 215 the gate
  // rejected 57 % of the right matches of cortex-hard's detection (bright tissue under a 1.3
  // gain) and 43 % on the photographs (white surfaces), catching 3 % of the wrong ones; at 250
  // (a glint's core saturates) it rejects 0-16 % of the right ones, and the sheen around a
  // glint is left to the sheen, NCC-drop and stereo NCC gates, which measure it.
  int specular_threshold = 250;
  int specular_dilate_px = 13;  // the template's half size plus the sheen around a glint
  int specular_margin_px = 6;   // the same margin around a match, in either camera
  // Tracking: a pixel over specular_threshold is a glint only when it is brighter by more than
  // this than the patch's brightest pixel at detection scaled by the patch's gain change since
  // (the mean's ratio). A camera whose gain drifts up 30 % saturates bright tissue: that is not
  // a glint and did not move the match (cortex-hard: the gate rejected 7 % of right video
  // matches, most of them so).
  double glint_excess = 15.0;
  // Tracking: a glint (as above) over part of a feature's 23x23 video patch is left out of the
  // match instead of hiding the feature (ShiftMask): its pixels at specular_threshold and
  // glint_grow_px around them, then the pixels brighter than the template by more than
  // glint_sheen_sigmas robust deviations of the match's residual (the sheen, of no fixed size),
  // the match refined again without them. While at most this fraction of the patch is left
  // out; more, and the feature is hidden as before. 0: a glint always hides the feature.
  // tests/vision/affine_refiner_test.cpp: a glint 5-9 px from the centre moves a match 0.42 px
  // RMS counted, 0.016 px left out; cortex-1h-compressed: of the first 100 features 71 ok at
  // the end (64 hidden by glints), 2 retired under a glint (16); cortex-hard unchanged.
  double max_glint_fraction = 0.5;
  int glint_grow_px = 5;
  double glint_sheen_sigmas = 3.0;
  int dark_window_px = 21;  // "darker than the neighbourhood" window
  int dark_delta = 2;       // grey levels below the local mean
  int video_search_px = 8;  // +- window around the last position
  // The video match's translation refinement: at most this many Gauss-Newton steps to settle
  // (a step under 2e-3 px), else the match is not_converged. 20 on every scene cost cortex-hard
  // 0.0365 -> 0.0383 mm of 3D RMS (gate_eval): the slow settlers there are the worse matches.
  int video_refine_iterations = 10;
  double min_ncc = 0.75;
  // A feature's video NCC is steady while it is seen (0.95-0.99 on tissue); a drop below its
  // own running level by more than this is an occlusion starting (an instrument's edge), even
  // above min_ncc.
  double max_ncc_drop = 0.08;
  // The stereo match after the affine refinement: the two views of a feature in sheen (below
  // the glint threshold, but different per view) agree less than tissue does.
  double min_stereo_ncc = 0.94;
  // ... fitted to the data (fit_sigmas, 1 - NCC as the value) where it rejects over a quarter of
  // a first detection's first round of matches, never below this; kept for the re-detections
  // that fill. The Hamlyn heart: 30 % under 0.94 (median 0.955) -> 0.88. The scenes the gate was
  // chosen on stay under a quarter (cortex-hard 22 %, teddy 23 %, cones 25 %): unchanged.
  // Equal to min_stereo_ncc: never fitted.
  double min_stereo_ncc_bound = 0.88;
  // The stereo match (detection and refresh) models an intensity ramp across the patch as well
  // as gain and bias (AffineTemplate's project-out: a 1.5 grey/px ramp in one view moves the
  // match 0.158 px unmodelled, 0.012 px modelled). Off: on the scenes it did not pay. cortex-hard
  // 3D RMS 0.0363 -> 0.0350 mm but pairs with >= 50 ok 75.0 -> 73.5 %, cortex-60s 0.0276 ->
  // 0.0273 mm, static glossy cortex 0.027 -> 0.029 mm (worst feature 0.051 -> 0.064): the
  // sheen there is a lobe, not a ramp, and the ramp-free NCC lets more of it past the gates.
  bool stereo_ramp = false;
  // A patch's brightness (with specular_margin_px around it) may differ between the views by at
  // most this fraction beyond the cameras' local gain ratio: more is view-dependent shine
  // (sheen), which moves the stereo match.
  double max_sheen = 0.02;
  // Left-right consistency at detection: the right patch matched back in the left image (the
  // same search box, reversed) must land within this of the left point.
  double max_left_right_px = 1.0;
  // Tracking: a feature's change of disparity since the epoch may differ from the mean of its
  // reacquire_neighbours nearest ok features' by at most this (px). The tissue moves smoothly:
  // neighbours 5-10 mm apart change depth together; one view's match sliding onto an
  // instrument's edge or into sheen does not.
  double max_motion_px = 0.5;
  // Detection: each textured 8x8 corner block of the template must correlate with the right
  // view at the match at least this well (a depth edge's other surface does not).
  double min_block_ncc = 0.5;
  double min_nmi = 0.25;
  double max_epipolar_px = 1.0;
  // Detection: a match's signed distance from its epipolar line may differ from the median of
  // its nearest features' by at most this (px). A real rig's calibration leaves each pixel's
  // line off by up to a few tenths of a pixel, but smoothly over the image, so neighbours share
  // the offset; a wrong match on similar texture (0.26-0.38 px off on cortex-60s, 0.14-0.27 mm
  // of depth for good) does not share it.
  double max_epipolar_spread_px = 0.15;
  // Detection: the two neighbour gates (max_sheen, max_epipolar_spread_px) were chosen on
  // rendered and photographed scenes. Where one of them rejects more than a quarter of a
  // detection round's matches, the images are not like those (the Hamlyn heart's rectified
  // pair: the rig's own vertical offset varies by 0.4-0.5 px over the ROI, and moist tissue
  // shines differently per view everywhere), and that gate's threshold becomes fit_sigmas
  // robust standard deviations (1.4826 x the median absolute value) of the round's own values:
  // never below the configured threshold, never above the bound. fittedGates() says what was
  // used. 0: the thresholds are fixed.
  double fit_sigmas = 3.0;
  double max_sheen_bound = 0.06;
  double max_epipolar_spread_bound_px = 0.6;
  double max_surface_mm = 2.0;      // distance to the fitted parabola
  double surface_mad_factor = 6.0;  // ... and at most this many MADs
  // Sub-pixel refinement after the NCC peak: affine for the stereo match (the two views
  // foreshorten the surface differently), translation for video matching (one camera's view
  // of a patch barely changes shape). Off: the paper's quadratic NCC peak alone.
  bool refinement = true;
  // Detection: where the stereo match's affine refinement does not settle (blurred SD video: a
  // third of the Hamlyn heart's matches), the match is refined in translation instead, and kept
  // only where the affine-refined features do not fill the ceiling: such features are dropped
  // first over it, and they neither count towards the ceiling nor judge their neighbours in
  // the sheen and epipolar-spread gates. The renders and photographs the gates were chosen on
  // fill it, and keep their figures (bench/gate_eval); the heart's pair 1: 33 -> 41 features.
  // The translation match leaves the foreshortening's bias in (real-texture-sd: 32 features at
  // 0.131 mm -> 37 at 0.137 mm 3D RMS). Off: the affine refinement's verdict stands.
  bool stereo_translation_fallback = true;
  // Re-detection is due when fewer than this fraction of the features found at the last
  // detection are ok (needsRedetection(); the caller runs redetect() off the per-frame path).
  double redetect_fraction = 0.5;
  // Re-detection fills: it keeps every feature (ok or hidden, under its id) and adds new ones
  // only farther than this from all of them, up to max_features. A feature not ok for longer
  // than retire_after_pairs is retired at the next re-detection (which it then triggers), so
  // that its region can be filled.
  int fill_distance_px = 30;
  // Detection matches as many corners as the ceiling, and more while fewer than this fraction
  // of the ceiling pass the gates (cortex-hard: 41 of 100 without it, 100 with it).
  double min_fill = 1.0;
  int retire_after_pairs = 300;
  // A feature that is not ok is searched for again from where its neighbours' motion puts it:
  // the mean image motion of its this many nearest ok features (in the reference pair), added
  // to its own reference position.
  int reacquire_neighbours = 6;
  // The neighbours' motion taken as an affine function of their positions (not their mean) where
  // they surround the feature: a sag's bowl and a turn are not blamed on the feature.
  bool affine_prediction = true;
  // ... and searched within this many px of there (the prediction is good to a pixel: 0.3 px
  // RMS on cortex-hard; a smaller window also keeps 30 hidden features cheap).
  int reacquire_search_px = 3;
  // Evaluation only (bench/gate_eval): every gate is evaluated on every match (otherwise the
  // tracker stops at the first that fails: no left-right search for a rejected candidate, no
  // triangulation of an occluded feature per pair), and the Harris maxima the specular mask
  // removed are matched too and reported among candidates() with the glint gate (never tracked).
  bool evaluate_gates = false;
  // Stereo refresh (refreshStereo()): features whose stereo match is measured again per call.
  // The first frame's stereo match carries that pair's sensor noise for good (0.1-0.2 px of
  // disparity on weak texture: 0.06-0.12 mm of depth); matching again in later pairs, whose noise
  // is fresh, and averaging takes it out. 0: off.
  int stereo_refresh = 25;
  // The average runs over at most this many matches per feature, then forgets slowly (the
  // surface's shape in the two views changes over minutes of brain shift).
  int stereo_refresh_window = 64;
  // Recent templates (refreshStereo(), after the result is out): per call, this many features
  // (round robin) that the frame-0 templates found in both views take their look in this pair
  // as their recent template; where the frame-0 template later finds nothing or scores below
  // min_ncc, the recent one is searched (tissue that deforms: the beating heart). 0: off.
  int template_refresh = 25;
  // Stereo confirmation: a feature whose first stereo_confirm_tries stereo refresh matches
  // (converged, no glint near; not the translation-refined ones) pass the stereo NCC gate in
  // fewer than this share was let in by its first pair alone (an NCC just over the gate, sheen
  // that one view has): its next pairs' views, the first pair's but for the noise, do not bear
  // it out. It is hidden as outlier_epipolar:stereo_ncc and retired by the next re-detection
  // (which it asks for stereo_confirm_tries pairs later, so that those unconfirmed meanwhile go
  // in one), its place filled but not with its own corner. real-texture-hard: 3D RMS 0.354 ->
  // 0.254 mm (its worst features 0.3-1.0 mm off in depth: first stereo NCC 0.944-0.952, the
  // next pairs' under 0.94 in 10 to 12 of 12); real-texture-sd 0.150 -> 0.142 mm; the Hamlyn
  // heart, cortex-60s, cortex-hard and the compression unchanged. 0: off.
  double min_stereo_confirmed = 0.25;
  int stereo_confirm_tries = 12;
  // Where the first detection fitted the stereo NCC gate (blurred video, unlike the renders and
  // photographs the tracking gates were chosen on), tracking takes these bounds instead of
  // max_motion_px, max_ncc_drop and video_search_px: the Hamlyn heart's disparity changes by
  // more than 0.5 px beyond its neighbours' over a beat, its NCC swings by more than 0.08, and it
  // moves up to 17 px a pair (ok per pair median 31.5 -> 47, >= 50 ok in 28.7 -> 44.3 % of the
  // pairs; docs/gates.md). Its video refinement settles slowly: the patches change shape over a
  // beat and a translation's Gauss-Newton steps shrink slowly on blurred video; of the heart's
  // not_converged refinements at 10 steps, half settle within 1.5 px by 20 (ok per pair median
  // 46.5 -> 66, >= 50 ok in 39 -> 92 % of the pairs). Off: the configured ones always.
  bool fit_tracking_gates = true;
  double max_motion_bound_px = 1.0;
  double max_ncc_drop_bound = 0.15;
  int video_search_bound_px = 12;
  int video_refine_iterations_bound = 20;
};

// The stereo refresh in three parts, so that its matching can run on a thread of its own
// (pulsetrackd's refresh stage, off the features' path): StereoTracker::prepareRefresh() (after
// the pair's result is out, on the tracking thread) takes the recent templates and copies what the
// stereo match needs into a RefreshJob - each chosen feature's state and a window of either view
// around it, so the pair's images may be reused at once; measureRefresh() matches the job on any
// thread and touches no tracker; StereoTracker::applyRefresh() (on the tracking thread, before a
// later pair) folds the matches into the features that are still the same ones.
// StereoTracker::refreshStereo() is the three in a row. Both are sized once (allocation-free
// after construction).
struct RefreshJob {
  struct Item {
    size_t index = 0;  // in features()
    int id = -1;
    cv::Vec2d left, right, right_track;
    cv::Matx22d warp = cv::Matx22d::eye();  // its stereo warp
    double view_gain = 1.0;
    std::array<cv::Point, 2> origin{};  // each window's top-left corner in its image
    std::array<cv::Size, 2> size{};     // each window (clipped by the image's border)
  };
  RefreshJob() = default;
  explicit RefreshJob(const TrackerConfig& config);  // room for config.stereo_refresh features
  // Feature k's window in camera `cam` (0 left, 1 right): a header over `pixels`.
  [[nodiscard]] cv::Mat window(size_t k, int cam) const noexcept;

  std::vector<Item> items;      // the first `count` are this job's
  std::vector<uint8_t> pixels;  // per item, the left and then the right window, side x side
  int side = 0;
  size_t count = 0;
  // The gates as the tracker had them at prepareRefresh().
  double min_ncc = 0.0, max_sheen = 0.0;
  // A glint near: its pixels (grown by glint_grow_px) left out of the match, when at most
  // max_glint_fraction of the template is; 0: such features are not matched.
  double max_glint_fraction = 0.0;
  int glint_grow_px = 0;
  int specular_margin_px = 0, specular_threshold = 255;
  bool dark_blobs = false, ramp = false;
};

struct RefreshOutcome {
  struct Match {
    size_t index = 0;
    int id = -1;
    cv::Vec2d right_track, centre;  // the track and the stereo match, in the job's pair
    cv::Matx22d warp = cv::Matx22d::eye();
    bool passed = false;  // passed every gate: averaged into the feature's stereo offset
    bool ncc_ok = false;  // its stereo NCC passed the gate (the stereo confirmation's verdict)
    // Every gate but the distance from the corrected track (within kConsensusFarPx): a vote in
    // the feature's consensus (StereoTracker::applyRefresh()).
    bool agrees = false;
    // Refined with a glint near left out (AffineMask; its sheen gate over the pixels kept): not
    // a stereo confirmation try (the first pair's match had no glint near).
    bool masked = false;
  };
  RefreshOutcome() = default;
  explicit RefreshOutcome(const TrackerConfig& config);
  // The first `count`: every converged match without a glint near (those that passed the
  // gates are averaged in, the others only count for the stereo confirmation).
  std::vector<Match> matches;
  size_t count = 0;
  // measureRefresh()'s scratch.
  std::vector<size_t> chosen;
  std::vector<double> left_mean, ratio;
  AffineTemplate affine;
  AffineMask mask;
  ShiftTemplate shift;
};

// Matches a job's features in their windows as the first pair's match was (the affine
// refinement from where they are, gated for sheen and glints). No allocation, lock or exception.
void measureRefresh(const RefreshJob& job, RefreshOutcome& out) noexcept;

struct Roi {
  cv::Rect left;
  cv::Rect right;
};

// The neighbour gates' thresholds at the last detection: the configured ones, or fitted to the
// data (TrackerConfig::fit_sigmas).
struct FittedGates {
  double min_stereo_ncc = 0.0;  // used
  double max_sheen = 0.0;       // used
  double max_epipolar_spread_px = 0.0;
  double configured_stereo_ncc = 0.0;  // TrackerConfig's
  double configured_sheen = 0.0;
  double configured_epipolar_spread_px = 0.0;
  bool stereo_ncc_fitted = false;
  bool sheen_fitted = false;
  bool epipolar_spread_fitted = false;
  // Detection (TrackerConfig::stereo_translation_fallback): matches whose affine stereo
  // refinement did not settle, and the features among them refined in translation instead.
  int stereo_unsettled = 0;
  int stereo_translation = 0;
  // Tracking (TrackerConfig::fit_tracking_gates): the gates the video matches meet, widened to
  // their bounds where the stereo NCC was fitted (the images are blurred video).
  double max_motion_px = 0.0;
  double max_ncc_drop = 0.0;
  int video_search_px = 0;
  int video_refine_iterations = 0;
  double configured_motion_px = 0.0;
  double configured_ncc_drop = 0.0;
  int configured_search_px = 0;
  int configured_refine_iterations = 0;
  bool tracking_fitted = false;
  // "sheen 2.0 %, epipolar spread 0.15 px (as configured)", or with "fitted to these images"
  // and the configured value beside each fitted one.
  [[nodiscard]] std::string summary() const;
};

struct Feature {
  int id = 0;
  FeatureStatus status = FeatureStatus::kOk;
  Gate gate = Gate::kNone;  // why, when not ok
  uint16_t failed = 0;      // gateBit() of every gate this pair's match failed
  // The match the gates judged in this pair (left, right as reported): for a feature that is
  // not ok, left/right stay where it was last seen or predicted.
  cv::Vec2d judged_left, judged_right;
  cv::Vec2d left;  // current pixel positions
  cv::Vec2d right;
  cv::Vec3d point;   // current 3D position in {C}, mm
  cv::Vec3d point0;  // at the first frame
  double ncc = 0.0;  // lower of the two cameras' video NCC (stereo NCC at frame 0)
  double nmi = 0.0;
  double epipolar_px = 0.0;
};

// One candidate of the initial stereo match, for `pulsetrack match`.
struct StereoCandidate {
  cv::Vec2d left, right;
  double ncc = 0, nmi = 0, epipolar_px = 0;
  cv::Vec3d point;
  FeatureStatus status = FeatureStatus::kOk;
  Gate gate = Gate::kNone;
  uint16_t failed = 0;  // gateBit() of every gate it failed (the first is `gate`)
};

class StereoTracker {
 public:
  StereoTracker(const StereoRig& rig, const TrackerConfig& config);
  [[nodiscard]] const StereoRig& rig() const noexcept { return rig_; }
  // The id the next new feature gets; a tracker that takes over from another (a new working
  // scale) continues its ids, so a fresh detection's features are new ids.
  [[nodiscard]] int nextId() const noexcept { return next_id_; }
  void continueIds(int next_id) noexcept { next_id_ = next_id; }

  // Detects and stereo-matches features in the first pair. Returns how many are ok. Fails on
  // an ROI outside the image or images that are not 8-bit grey of the rig's size.
  Result<int> initialize(const cv::Mat& left, const cv::Mat& right, const Roi& roi,
                         double depth_tolerance_mm);
  // Detects again in the current pair with the last ROI and depth tolerance, filling: the
  // features there are keep their ids (hidden ones too, they are searched for every pair); those
  // not ok for more than retire_after_pairs and the unconfirmed ones (min_stereo_confirmed) are
  // retired; new features go only where none are
  // (fill_distance_px), take new ids (never reused), and their reference position (point0) is
  // where they are now. Returns how many features the tracker has (ok or hidden).
  Result<int> redetect(const cv::Mat& left, const cv::Mat& right);
  // Features retired by the stereo confirmation (min_stereo_confirmed) since the tracker was
  // made.
  [[nodiscard]] int unconfirmedCount() const noexcept { return unconfirmed_count_; }
  [[nodiscard]] bool needsRedetection() const noexcept {
    return (detected_ok_ > 0 && okCount() < config_.redetect_fraction * detected_ok_) ||
           retirable_ > 0;
  }
  // The candidates of the last initialize(), rejected ones included.
  [[nodiscard]] const std::vector<StereoCandidate>& candidates() const { return candidates_; }
  // The neighbour gates' thresholds the last detection used.
  [[nodiscard]] const FittedGates& fittedGates() const noexcept { return gates_; }

  // Per frame: the real-time path.
  void track(const cv::Mat& left, const cv::Mat& right) noexcept;
  // refreshStereo() in parts (RefreshJob above): the job for this pair, and a job's matches
  // folded in (those whose feature has been re-detected since are left out). Neither allocates,
  // locks or throws. applyRefresh() returns how many matches were taken.
  void prepareRefresh(const cv::Mat& left, const cv::Mat& right, RefreshJob& job) noexcept;
  int applyRefresh(const RefreshOutcome& outcome) noexcept;
  // After track() has been published (it adds no latency): matches up to
  // config.stereo_refresh features (round robin, ok ones) between this left and right image
  // again, with the affine refinement, and folds each into the feature's running stereo
  // correction; track() applies it from the next pair on, to the position and to the reference
  // point0 alike (displacements stay consistent). Nothing after a detection until track() has
  // run (that pair's match is in already). No allocation, lock or exception. Returns how many
  // matches were taken. prepareRefresh(), measureRefresh() and applyRefresh() in a row.
  int refreshStereo(const cv::Mat& left, const cv::Mat& right) noexcept;

  [[nodiscard]] std::span<const Feature> features() const {
    return {features_.data(), features_.size()};
  }
  [[nodiscard]] int okCount() const noexcept;

  // The stereo refresh's consensus (State::votes): this many recent votes, re-seated when at
  // least kConsensusMin agree within kConsensusSpreadPx (their median absolute deviation) on an
  // offset kConsensusMovePx or more from the feature's. A vote is at most kConsensusFarPx from
  // the corrected track (further is another texture's optimum, not this one's).
  static constexpr int kConsensus = 8, kConsensusMin = 5;
  static constexpr double kConsensusSpreadPx = 0.2, kConsensusMovePx = 0.35, kConsensusFarPx = 2.0;

 private:
  struct State;
  // One vote in s's consensus (a match's offset from the track and its stereo warp); true when
  // it re-seated s's stereo offset (and warp).
  static bool reseat(State& s, const cv::Vec2d& vote, const cv::Matx22d& warp) noexcept;
  struct State {
    NccTemplate ncc[2];
    ShiftTemplate shift[2];
    NmiTemplate nmi[2];                // the frame-0 templates, for NMI
    double ncc_level[2] = {0.0, 0.0};  // running NCC while ok; 0 before the first frame
    // The right camera's video track (the reported right position adds the stereo correction).
    cv::Vec2d right_track;
    cv::Vec2d left0, right0;            // the first pair's match
    cv::Vec2d stereo_offset{0.0, 0.0};  // mean (stereo match - right_track)
    int stereo_samples = 1;             // the first pair's match counts as one
    // The last kConsensus refresh matches that passed every gate but the distance from the
    // corrected track (stereo match - right_track): where they agree with each other and not
    // with the offset, the first pair's match was off and the offset is re-seated there.
    std::array<cv::Vec2d, kConsensus> votes{};
    int vote_count = 0, vote_next = 0;
    // The stereo confirmation (min_stereo_confirmed): of its first stereo_confirm_tries stereo
    // refresh matches, how many passed the stereo NCC gate; unconfirmed: too few did (hidden,
    // retired at the next detection).
    int confirmed = 0, confirm_tries = 0;
    bool unconfirmed = false;
    cv::Matx22d stereo_warp = cv::Matx22d::eye();  // right offset per left offset (affine)
    // Detection: the stereo match was refined in translation (the affine one did not settle).
    bool stereo_translation = false;
    // Per camera, at detection: the brightest pixel and the mean of the patch with its glint
    // margin (the tracking glint gate tells a glint from gain-brightened tissue by them).
    std::array<double, 2> max0{255.0, 255.0};
    std::array<double, 2> mean0{0.0, 0.0};
    // Right / left brightness here: the nearest features' median at detection, in the first
    // detection's terms (a re-detection's divided by the gains' drift since).
    double view_gain = 1.0;
    // The rig's signed epipolar offset here (px): the nearest features' median at detection.
    // Tracking gates a match's offset against it (max_epipolar_px).
    double rig_offset = 0.0;
    // Where the feature would have been in the first detection's pair (its own position then,
    // or for a later one, its position less its neighbours' motion since): the common epoch
    // the neighbours' motion is measured from.
    cv::Vec2d epoch_left, epoch_right;
    bool seen = true;  // ok in the last pair: tracked from there; else predicted
    // Its image motion over the last pair, per camera (left, right track), while ok in both
    // pairs: the next search starts there (constant velocity), else zero.
    std::array<cv::Vec2d, 2> velocity{cv::Vec2d(0.0, 0.0), cv::Vec2d(0.0, 0.0)};
    int not_ok_pairs = 0;  // pairs since it was last ok
    // Per camera: this pair's match came from the frame-0 template (not the recent one).
    std::array<bool, 2> anchored{true, true};
    // The feature's look in a recent pair where the frame-0 templates found it in both views
    // (refreshTemplates()), per camera, searched where the frame-0 template finds nothing.
    bool recent = false;
    std::array<NccTemplate, 2> recent_ncc;
    std::array<ShiftTemplate, 2> recent_shift;
    std::array<cv::Vec2d, 2> recent_offset{};  // the position less the NCC template's centre
  };
  // Detection: fresh (initialize) or filling around the features there are (redetect).
  Result<int> detect(const cv::Mat& left, const cv::Mat& right, const Roi& roi,
                     double depth_tolerance_mm, bool fill);
  // Where feature i should be now from its nearest ok features (among the first `among`) and
  // their motion since the epoch; false when none is ok. `spread_px`: the RMS of their motions
  // about that mean (how far to trust it). With config.affine_prediction, their motion as an
  // affine function of their epoch positions where they surround the feature.
  bool predict(size_t i, cv::Vec2d& left, cv::Vec2d& right_track, size_t among,
               double& spread_px) const noexcept;
  // Feature i's nearest ok features at the epoch (config.reacquire_neighbours, nearest first;
  // among the first `among`): how many.
  static constexpr int kMaxNeighbours = 16;
  using NeighbourList = std::array<size_t, kMaxNeighbours>;
  int nearestOk(size_t i, size_t among, NeighbourList& idx) const noexcept;
  bool predict(size_t i, cv::Vec2d& left, cv::Vec2d& right_track, size_t among) const noexcept {
    double spread_px = 0.0;
    return predict(i, left, right_track, among, spread_px);
  }
  // `radius`: the search window's half size (smaller when a hidden feature's position is
  // predicted); `reacquiring`: the right camera is searched only when the left found it.
  // The search starts at the last position plus the feature's velocity.
  void trackOne(size_t i, const cv::Mat& left, const cv::Mat& right, int radius,
                bool reacquiring) noexcept;
  bool searchCamera(const cv::Mat& img, const NccTemplate& t, const cv::Vec2d& last, cv::Vec2d& pos,
                    double& ncc, int radius) noexcept;
  // One template pair near `last`: refinement from there, else NCC search and refinement.
  // With `mask`, the refinement leaves its pixels out (a glint).
  Gate locate(const cv::Mat& img, const NccTemplate& t, const ShiftTemplate& shift,
              const cv::Vec2d& last, cv::Vec2d& pos, double& ncc, int radius,
              const ShiftMask* mask) noexcept;
  // A glint near camera `cam`'s patch at `at`: a pixel over specular_threshold within
  // specular_margin_px that the patch's gain change since detection does not explain.
  [[nodiscard]] bool glintOver(const cv::Mat& img, const cv::Vec2d& at, const State& s,
                               int cam) const noexcept;
  // refreshStereo()'s first part: config.template_refresh features' recent templates.
  void refreshTemplates(const cv::Mat& left, const cv::Mat& right) noexcept;
  // Matches camera `cam`'s frame-0 template near `at` and moves `at` to the match. Returns the
  // gate that failed (kNone: found; kGlint: found, but a glint is on it).
  Gate trackCamera(int cam, const cv::Mat& img, cv::Vec2d& at, State& s, double& ncc, double& nmi,
                   int radius) noexcept;
  void motionGate() noexcept;
  void surfaceGate() noexcept;
  // The search radius the buffers are sized for, and the tracking gates for this detection.
  [[nodiscard]] int maxSearchPx() const noexcept;
  void setTrackingGates() noexcept;
  // Candidate positions in ROI coordinates (sub-pixel for blobs). Harris: the first `spaced`
  // are min_distance_px apart, the rest fill between them down to dense_distance_px.
  [[nodiscard]] std::vector<cv::Point2d> detectHarris(const cv::Mat& img, size_t& spaced,
                                                      std::vector<cv::Point2d>* masked) const;
  [[nodiscard]] std::vector<cv::Point2d> detectDarkBlobs(const cv::Mat& img) const;

  StereoRig rig_;
  TrackerConfig config_;
  std::vector<Feature> features_;
  std::vector<State> states_;
  std::vector<StereoCandidate> candidates_;
  std::vector<float> scores_;      // sized once: (2R+1)^2
  std::vector<uint8_t> scratch_;   // a padded copy of a window near the image border
  std::vector<double> residuals_;  // surface gate, sized to max_features
  RefreshJob refresh_job_;         // refreshStereo()'s, sized once
  RefreshOutcome refresh_outcome_;
  ShiftMask glint_mask_;  // trackCamera()'s, for the feature being matched
  int retirable_ = 0;     // features past retire_after_pairs
  int unconfirmed_count_ = 0;
  size_t refresh_next_ = 0;
  size_t template_next_ = 0;  // refreshTemplates()'s round robin
  bool tracked_ = false;      // track() ran since the last detection
  Roi roi_;
  double depth_tolerance_mm_ = 0.0;
  int next_id_ = 0;
  int detected_ok_ = 0;
  FittedGates gates_;
};

}  // namespace pulsetrack::vision
