#pragma once
// TrackingSession: the StereoTracker and the policy around it, one pair at a time. Knows no DDS,
// threads, clocks or files: pulsetrackd's track stage, `pulsetrack track`, `pulsetrack analyze`
// and the tests all drive it, so the offline signal is the live one, bit for bit.
//
// Policy:
// - detect in the first pair after construction, start() or setRoi(); a detection that finds
//   nothing says why (reason()) and is tried again at most once per retry_interval_s of pair
//   time (detection allocates; between attempts a pair costs nothing and allocates nothing);
//   an ROI that cannot work (outside the image, smaller than two templates) is refused by
//   checkRoi() and never detected in;
// - track every pair; re-detect (redetect(): it fills, new ids only where no feature is,
//   continuity kept) when the tracker asks
//   (too few features ok) or on requestRedetect(); stop() pauses until start();
// - afterPublish(): the tracker's stereo refresh, once the pair's result is out.
//
// The deformation: the mean displacement of the signal's features from their reference
// positions (point0, which the stereo refresh corrects with the positions). A feature that is ok
// counts with its own displacement; one that is hidden (an instrument, a glint) with its own
// displacement when it was last seen plus the motion since of its nearest features then
// (tracker.reacquire_neighbours of them; each neighbour's motion is the difference of two of its
// own displacements, which are measured against the first pair's templates: nothing integrates),
// until it is seen again and its own measurement takes over. While none of those neighbours is ok
// it is carried on by the mean increment of the features ok in both pairs. So an error lives
// only while a feature is hidden and nothing accumulates over hours of instruments coming and
// going. (The rule before, a step of the common features' mean increment whenever the ok set
// changed, was a random walk: 0.12 mm per axis after 3 minutes of cortex-1h-compressed; carrying
// hidden features on by the mean increment alone, 0.019.) A re-detection's new feature enters
// at the set's mean displacement (its own is zero there), a retired one leaves with the offset
// taking up the change of the mean: neither steps the signal. Velocity: the slope of a causal
// least-squares line through the displacement over the last velocity_window_s, published with
// its group delay (the window's mean age). Noise: the features' pair-to-pair scatter about the
// mean increment, as a standard error of the mean (smoothed over ~20 pairs). Prediction: the
// displacement at t + each configured horizon (MotionPredictor, restarted with the signal).

#include <array>
#include <cstdint>
#include <opencv2/core.hpp>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/motion_predictor.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"
#include "pulsetrack/vision/stereo_search.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"

namespace pulsetrack::vision {

struct SessionConfig {
  TrackerConfig tracker;
  // roi.right empty: the right ROI and the depth tolerance are found in the pair at detection
  // (findStereoRange over `search`'s depth range); depth_tolerance_mm is then not used. Both
  // empty: the left ROI too (findStereoRoi: the largest well-textured region free of highlights).
  Roi roi;
  double depth_tolerance_mm = 20.0;
  StereoSearchConfig search;
  double retry_interval_s = 1.0;    // between detection attempts that found nothing
  double velocity_window_s = 0.25;  // the velocity's least-squares window
  PredictionConfig prediction;      // the displacement at t + horizon (MotionPredictor)
  // The scale the tracker works at. Its templates (15x15, 23x23), windows and spacings are
  // fixed in pixels, chosen on images whose detail is a few pixels across (the paper's
  // 1360x1024, SD endoscope video); video whose detail is twice as wide (SD upscaled to 720x576,
  // a soft 1080p endoscope) gives those templates too little of it. 1: the images as they are;
  // 0.5: at half size (2x2 means; the rig's intrinsics with them); 0: chosen at the first
  // detection: at 1, and where that does not fill 90 % of the feature ceiling and half the size
  // stays at least auto_scale_min_width px wide, at 1/2 too; 1/2 is kept when it detects at
  // least 1.25 times as many features. Positions are reported in the images' pixels either way.
  // Other values are refused (checkScale).
  double scale = 0.0;
  int auto_scale_min_width = 320;
};

struct Deformation {
  bool valid = false;               // at least one feature ok in this pair
  cv::Vec3d centroid{0, 0, 0};      // mm, mean position of the ok features
  cv::Vec3d displacement{0, 0, 0};  // mm
  cv::Vec3d velocity{0, 0, 0};      // mm/s, of velocity_delay_s before the pair
  double velocity_delay_s = 0.0;
  double displacement_sigma_mm = 0.0;  // 1 sigma, RMS over the axes
  double velocity_sigma_mm_s = 0.0;
  int ok = 0;
  int total = 0;
  uint32_t detections = 0;  // feature sets so far in this signal (1 + re-detections)
  bool continuous = true;   // false: the signal (re)started here
  // The displacement predicted at the configured horizons (prediction.enabled), with its
  // expected error; the predictor's weights, so that the field is predicted the same way.
  Prediction prediction;
  std::array<std::array<double, kMaxOrder>, kMaxHorizons> prediction_weights{};
  int prediction_order = 0;
  double prediction_step_s = 0.0;
};

enum class SessionState : uint8_t {
  kTracking,    // features tracked in this pair
  kNoFeatures,  // no detection has succeeded (reason() says why); retried
  kStopped,     // stop(): pairs are not tracked
};
const char* toString(SessionState s) noexcept;

struct PairResult {
  uint64_t frame = 0;
  int64_t t_ns = 0;
  SessionState state = SessionState::kNoFeatures;
  bool detected = false;  // the features were (re)detected in this pair: new ids
  Deformation deformation;
  std::span<const Feature> features;  // valid until the next process()
};

class TrackingSession {
 public:
  TrackingSession(const StereoRig& rig, const SessionConfig& config);

  // Whether an ROI pair can be tracked in the rig's images: inside them, at least two templates
  // on each side, a positive depth tolerance. The error names the ROI and what is wrong. An
  // empty right ROI passes, whatever the tolerance (both are found in the pair).
  static Result<void> checkRoi(const StereoRig& rig, const Roi& roi, double depth_tolerance_mm);
  // The right ROI that sees what `left` sees at depth_mm +- tolerance_mm (along the left
  // camera's axis): the left ROI's edge, back-projected to both depths and projected into the
  // right camera (both cameras' distortion included), bounded and clamped to the right image.
  // An empty rect when none of it lands in the image or the depths are not in front.
  static cv::Rect rightRoiFor(const StereoRig& rig, const cv::Rect& left, double depth_mm,
                              double tolerance_mm);

  // Between pairs, on the session's thread. setRoi() and start() detect afresh in the next pair
  // (a new signal); an ROI that fails checkRoi() is kept out (the reason says why) until a good
  // one comes. requestRedetect() re-detects in the next pair and keeps the signal continuous.
  void setRoi(const Roi& roi, double depth_tolerance_mm);
  void start();
  void stop();
  void requestRedetect() { redetect_requested_ = true; }

  // One pair: detect or track, re-detect when due, and the deformation. Allocates only when it
  // detects (at most once per retry interval while detection finds nothing).
  const PairResult& process(const cv::Mat& left, const cv::Mat& right, uint64_t frame,
                            int64_t t_ns);
  // After the pair's result has been handed on: the stereo refresh (no allocation). The same
  // pair as the last process().
  void afterPublish(const cv::Mat& left, const cv::Mat& right) noexcept;
  // The same in parts, for a stage of its own (RefreshJob in stereo_tracker.hpp): the job of the
  // last process()'s pair (the recent templates are taken now), and a job's matches folded in
  // before a later pair. measureRefresh() runs between them on any thread.
  void prepareRefresh(const cv::Mat& left, const cv::Mat& right, RefreshJob& job) noexcept;
  int applyRefresh(const RefreshOutcome& outcome) noexcept;

  // Why nothing is tracked ("" while tracking): valid until the next call; no allocation.
  [[nodiscard]] std::string_view reason() const noexcept { return {reason_.data(), reason_len_}; }
  // Bumped whenever reason() changes, so that a reader can copy it only on a change.
  [[nodiscard]] uint64_t reasonSerial() const noexcept { return reason_serial_; }
  [[nodiscard]] const PairResult& last() const noexcept { return result_; }
  [[nodiscard]] const StereoTracker& tracker() const noexcept { return tracker_; }
  [[nodiscard]] int redetections() const noexcept { return redetections_; }
  [[nodiscard]] int detectionAttempts() const noexcept { return attempts_; }
  // Where the left ROI's surface was found (a left ROI only): valid after a detection that
  // searched, range_serial() bumped each time.
  [[nodiscard]] const StereoRange& stereoRange() const noexcept { return range_; }
  [[nodiscard]] uint64_t rangeSerial() const noexcept { return range_serial_; }
  // The scale the tracker works at (SessionConfig::scale; chosen at the first detection when
  // auto), and a line that says it ("" at 1).
  [[nodiscard]] double scale() const noexcept { return scale_; }
  [[nodiscard]] std::string scaleSummary() const;
  // The rig at a resampled image size: focal lengths and principal points follow the pixels'
  // centres ((c + 0.5) s - 0.5), distortion and extrinsics stay.
  static StereoRig scaledRig(const StereoRig& rig, double scale);
  // SessionConfig::scale: 0 (auto), 1 or 0.5; the error says so.
  static Result<void> checkScale(double scale);

 private:
  void setReason(std::string_view text) noexcept;
  void resetSignal() noexcept;
  void markReference() noexcept;  // every feature's displacement so far is the reference
  void deformation(int64_t t_ns) noexcept;
  bool detect(const cv::Mat& left, const cv::Mat& right, bool redetection);
  // The first detection: at the configured scale, or (auto) at the better of 1 and 1/2.
  bool detectFirst(const cv::Mat& left, const cv::Mat& right);
  void setScale(double scale, int next_id);  // a new tracker at that scale
  // The pair at the working scale (the images themselves at 1; else resampled into work_*_).
  void toWork(const cv::Mat& left, const cv::Mat& right);
  [[nodiscard]] const cv::Mat& workLeft(const cv::Mat& left) const noexcept {
    return scale_ == 1.0 ? left : work_l_;
  }
  [[nodiscard]] const cv::Mat& workRight(const cv::Mat& right) const noexcept {
    return scale_ == 1.0 ? right : work_r_;
  }
  [[nodiscard]] cv::Vec2d toImage(const cv::Vec2d& p) const noexcept {
    return {(p[0] + 0.5) / scale_ - 0.5, (p[1] + 0.5) / scale_ - 0.5};
  }
  [[nodiscard]] cv::Rect roiToWork(const cv::Rect& r) const noexcept;
  void rangeToImage() noexcept;  // range_'s pixels from the working scale to the images'
  std::span<const Feature> features() noexcept;  // the tracker's, in the images' pixels

  StereoTracker tracker_;
  StereoRig rig_;
  SessionConfig config_;
  // The working scale (1, or SessionConfig::scale, or auto's choice) and the pair there; out_
  // holds the features in the images' pixels.
  double scale_ = 1.0;
  cv::Mat work_l_, work_r_;
  std::vector<Feature> out_;
  PairResult result_;
  bool initialized_ = false, stopped_ = false, roi_ok_ = true, redetect_requested_ = false;
  bool have_attempt_ = false;
  int64_t last_attempt_ns_ = 0;
  int attempts_ = 0, redetections_ = 0;
  StereoRange range_;
  uint64_t range_serial_ = 0;
  uint32_t detections_ = 0;
  std::array<char, 512> reason_{};
  size_t reason_len_ = 0;
  uint64_t reason_serial_ = 0;
  // The displacement, per feature (by index; ids_ names them, members_ are in the signal): ok
  // in the last pair with a valid deformation, its own displacement when it was last ok, its
  // estimate since the signal's start (dhat_: its own plus birth_ while ok, carried on by the
  // others' mean increment while hidden). Scratch for re-detections (sized once).
  std::vector<uint8_t> prev_ok_, scratch_ok_;
  std::vector<cv::Vec3d> prev_d_, dhat_, birth_, scratch_d_;
  std::vector<int> ids_;
  size_t members_ = 0;
  // A hidden feature's nearest features when it was last seen (their index, -1: none) and their
  // own displacements then; neighbours_ per feature. Scratch for re-detections.
  size_t neighbours_ = 6;
  std::vector<int> nb_idx_, scratch_nb_idx_, old_to_new_;
  std::vector<cv::Vec3d> nb_d_, scratch_nb_d_;
  void hideFrom(size_t i, size_t n) noexcept;  // feature i was ok in the last pair, not now
  bool have_output_ = false;
  cv::Vec3d offset_{0, 0, 0}, output_{0, 0, 0};
  double noise_var_ = 0.0;  // smoothed variance of one feature's displacement increment
  bool have_noise_ = false;
  // The velocity's window: (t in s from the signal's start, displacement), a ring.
  struct Sample {
    double t;
    cv::Vec3d d;
  };
  std::vector<Sample> ring_;
  size_t ring_head_ = 0, ring_size_ = 0;
  int64_t t0_ns_ = 0;
  MotionPredictor predictor_;
};

}  // namespace pulsetrack::vision
