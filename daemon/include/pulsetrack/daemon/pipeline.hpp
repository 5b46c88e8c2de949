#pragma once
// pulsetrackd's pipeline: capture, track and publish stages on their own threads, joined by
// triple buffers of preallocated items (rt/latest_slot.hpp: the newest frame wins, drops are
// counted), each stage beating a heartbeat and filling a latency histogram.
//
//   capture: source.next() into a frame slot          -> frames_   (drop when track is slow)
//   track:   vision::TrackingSession (detection, retries, re-detection, the deformation), its
//            result copied into a preallocated slot                -> results_ (drop)
//   publish: converts each result to DDS features and deformation (stamped on the system clock)
//            and sends them; then hands the result to the field stage   -> field_results_ (drop)
//   refresh: at normal priority, on the latest job it can take: the tracker's stereo refresh
//            (vision::measureRefresh: some features' stereo match again, on windows the track
//            stage copied after the result went out); its matches return through
//            refresh_outcomes_ and the track stage folds them in before its next pair. A slow
//            refresh skips pairs (counted on health) and never delays the next pair's tracking.
//   field:   at normal priority, on the latest result it can take: the dense deformation field
//            (vision::DeformationField, with its per-grid prediction) as a sensor_msgs/PointCloud2
//            and the robot's targets' answers. Off the features' path: a slow field skips pairs
//            (counted on health) and never delays the next features sample.
//   health:  the health sample, systemd STATUS and the watchdog ping from health() called by the
//            main thread, which also re-measures the system clock.
//   preview: at [preview] rate_hz the capture stage copies a pair into a preallocated slot
//            (PreviewTap: a memcpy, after the pair went to the track stage); this stage, at normal
//            priority, scales and JPEG-encodes it and sends sensor_msgs/CompressedImage on
//            rt/.../{left,right}/image/compressed (the console's and rqt_image_view's view).
//
// The recorder is started and stopped at run time (config, or the record_start/record_stop
// commands): the capture stage reads it through an atomic pointer and an epoch (no lock on the
// real-time path); the command and health threads share its owner under a mutex.

#include <array>
#include <atomic>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "pulsetrack/daemon/config.hpp"
#include "pulsetrack/daemon/notify.hpp"
#include "pulsetrack/daemon/preview.hpp"
#include "pulsetrack/dds/dds.hpp"
#include "pulsetrack/drivers/source.hpp"
#include "pulsetrack/record/live_recorder.hpp"
#include "pulsetrack/rt/heartbeat.hpp"
#include "pulsetrack/rt/latency_histogram.hpp"
#include "pulsetrack/rt/latest_slot.hpp"
#include "pulsetrack/rt/system_clock.hpp"
#include "pulsetrack/vision/tracking_session.hpp"

namespace pulsetrack::daemon {

struct Frame {
  drivers::StereoFrame pair;
  int64_t captured_ns = 0;  // monotonic, when the source handed it over
};

struct TrackResult {
  uint64_t trigger_seq = 0;
  int64_t t_ns = 0;  // the pair's exposure (monotonic)
  int64_t captured_ns = 0;
  int64_t tracked_ns = 0;
  std::vector<vision::Feature> features;  // capacity reserved at start
  vision::Deformation deformation;
  bool detected = false;  // the features are new
};

// The session's reason for not tracking, for health: fixed, so that copying it allocates nothing.
struct TrackingText {
  std::array<char, 512> text{};
  size_t size = 0;
  vision::SessionState state = vision::SessionState::kNoFeatures;
};

// A robot's Targets set, handed from the command thread to the publish stage.
inline constexpr size_t kMaxTargets = 256;
struct TargetSet {
  uint32_t set_id = 0;
  uint8_t frame = 0;              // Targets.msg FRAME_REFERENCE 0, FRAME_LATEST 1
  std::vector<cv::Vec3d> points;  // mm, capacity kMaxTargets reserved at start
};

// A recording's folder name: RIG-YYYYmmdd-HHMMSS (UTC).
std::string recordingName(const std::string& rig_id);

enum class State : uint8_t { kStarting = 0, kOk = 1, kDegraded = 2, kFault = 3 };
const char* toString(State s);

class Pipeline {
 public:
  Pipeline(const DaemonConfig& config, std::unique_ptr<drivers::CameraSource> source,
           const dds::Participant& participant);
  ~Pipeline();
  Pipeline(const Pipeline&) = delete;
  Pipeline& operator=(const Pipeline&) = delete;

  // Creates the DDS writers and starts the threads. Thread-policy problems are returned as
  // warnings (said once by the caller), not errors.
  vision::Result<std::vector<std::string>> start();
  void stop();

  // Called periodically by the main thread: publishes health, updates STATUS, pings the
  // watchdog while every stage is on time. Returns the state it published.
  State health(const Notifier& notifier);
  // The stamps' clock (tests compare it with their own reading of CLOCK_REALTIME).
  [[nodiscard]] const rt::SystemClock& clock() const { return clock_; }

  [[nodiscard]] bool trackedOnce() const { return processed_.load() > 0; }
  [[nodiscard]] uint64_t tracked() const { return tracked_.load(); }
  // Test hook: stall the track stage (the watchdog must notice).
  void stallTrackFor(std::chrono::milliseconds d) { stall_ms_.store(d.count()); }
  // The stages off the features' path.
  enum class OffPath : uint8_t { kField, kRefresh, kPreview };
  static constexpr std::array<const char*, 3> kOffPathNames{"field", "refresh", "preview"};
  // Test hook: such a stage takes this much longer per pair (it must delay no features).
  void slowStageBy(OffPath stage, std::chrono::milliseconds d) {
    slow_ms_[static_cast<size_t>(stage)].store(d.count());
  }
  // The field stage: clouds sent, and results it skipped (a newer one came before it was free).
  [[nodiscard]] uint64_t fieldsSent() const { return fields_sent_.load(); }
  [[nodiscard]] uint64_t fieldSkips() const { return field_results_.drops(); }

  // The capture cycle (the paper's), from the command topic or `pulsetrack ctl`: stop (frames
  // are captured, not tracked), start (tracking resumes with a fresh detection), redetect,
  // set_roi. A command that cannot be applied is refused with a reason, reported on health.
  // Called from the command thread; hands over to the track stage without a lock.
  // Returns "" when accepted, else the reason.
  std::string command(const pulsetrack_msgs_msg_dds__Command_& c);
  // A robot's Targets set (rt/.../targets): checked here, followed by the publish stage from the
  // next pair (answers on rt/.../targets_tracked). Counted with the commands; "" or the reason.
  std::string targets(const pulsetrack_msgs_msg_dds__Targets_& t);
  [[nodiscard]] uint64_t commandsRefused() const { return commands_refused_.load(); }
  [[nodiscard]] uint64_t commandsAccepted() const { return commands_accepted_.load(); }
  // Times the source went away (a fault, or no pair for 1 s or three trigger periods).
  [[nodiscard]] uint64_t sourceFaults() const { return source_faults_.load(); }

  // The recorder ([recorder] dir, a new RIG-YYYYmmdd-HHMMSS folder each time): every captured
  // pair from now on, off the real-time path. "" when started, else why not (already recording,
  // the folder cannot be made). Any thread but the stages'.
  std::string startRecording();
  // Stops it and says what it recorded ("" when it was not recording). Waits (bounded) until the
  // capture stage has let go of it.
  std::string stopRecording();
  // Previews sent (each a left and a right image).
  [[nodiscard]] uint64_t previewsSent() const { return previews_sent_.load(); }

 private:
  void captureLoop();
  void trackLoop();
  void publishLoop();
  void fieldLoop();
  void refreshLoop();
  // The track stage, after a result went out: the pair's refresh job to the refresh stage.
  void handOverRefresh(vision::TrackingSession& session, const Frame& f);
  void previewLoop();
  // The test hook's stall, if any (slowStageBy).
  void slowDown(OffPath stage) const;
  // A stage off the path, on its own thread: its name and [realtime] off_path (normal priority,
  // its CPU); a CPU it cannot have is said once in the log.
  void offPathPolicy(const char* name) const;
  // The stereo refresh runs as a stage of its own (else the tracker has none to run).
  [[nodiscard]] bool refreshing() const {
    return config_.tracker.stereo_refresh > 0 && config_.tracker.refinement;
  }
  void commandLoop();

  DaemonConfig config_;
  std::unique_ptr<drivers::CameraSource> source_;
  // The recorder: owned under recorder_mutex_ (command and health threads), read by the capture
  // stage through recorder_live_; capture_epoch_ counts the capture's loop turns, so that
  // stopRecording knows when the stage has let go of it.
  std::mutex recorder_mutex_;
  std::unique_ptr<record::LiveRecorder> recorder_;
  std::atomic<record::LiveRecorder*> recorder_live_{nullptr};
  std::atomic<uint64_t> capture_epoch_{0};
  std::atomic<bool> capture_running_{false};
  std::string last_recording_;      // under recorder_mutex_: what the last recording did
  uint64_t recorded_ = UINT64_MAX;  // capture thread: the trigger number of the recording's frame 0
  std::atomic<uint64_t> recording_gen_{0};  // recordings started
  uint64_t recording_of_ = 0;               // capture thread: recorded_'s recording
  const dds::Participant& participant_;
  dds::Writer features_writer_, deformation_writer_, health_writer_, field_writer_, targets_writer_;
  dds::Writer image_writers_[2];           // the preview: left, right
  rt::LatestSlot<TargetSet> target_sets_;  // command thread -> field stage
  rt::LatestSlot<Frame> frames_;
  rt::LatestSlot<TrackResult> results_;
  std::atomic<uint64_t> frames_seq_{0}, results_seq_{0};  // wake-ups (futex, no lock)
  std::atomic<uint64_t> consumed_{0};  // pairs done with (published or not tracked): lossless
  uint64_t handed_ = 0;                // capture thread: pairs handed to the track stage
  rt::Heartbeat capture_beat_, track_beat_, publish_beat_;
  rt::LatencyHistogram capture_lat_, track_lat_, publish_lat_;
  rt::LatencyHistogram handover_lat_;  // handed over -> the track stage has it (in track_lat_)
  std::unique_ptr<PreviewTap> preview_tap_;  // capture -> preview ([preview] enabled)
  rt::LatencyHistogram preview_lat_;         // scale, encode and send (both images)
  std::atomic<uint64_t> previews_sent_{0};
  std::thread preview_;
  rt::LatestSlot<TrackResult> field_results_;  // publish -> field stage ([field] enabled)
  std::atomic<uint64_t> field_seq_{0};
  rt::LatencyHistogram field_lat_;  // pair handed over -> its field (and targets) sent
  std::atomic<uint64_t> fields_sent_{0};
  std::array<std::atomic<int64_t>, 3> slow_ms_{};  // slowStageBy(), per OffPath
  std::thread field_;
  // The stereo refresh's stage (tracker.stereo_refresh > 0): track -> refresh -> track.
  struct RefreshHandOff {
    vision::RefreshJob job;
    int64_t captured_ns = 0;
  };
  rt::LatestSlot<RefreshHandOff> refresh_jobs_;
  rt::LatestSlot<vision::RefreshOutcome> refresh_outcomes_;
  std::atomic<uint64_t> refresh_seq_{0};   // jobs handed over (and stop()'s wake-up)
  std::atomic<uint64_t> refresh_done_{0};  // jobs measured (and stop()'s wake-up)
  std::atomic<uint64_t> refreshes_{0};     // jobs measured, for health
  rt::LatencyHistogram refresh_lat_;       // pair handed over -> its refresh measured
  std::thread refresh_;
  std::atomic<uint64_t> tracked_{0}, processed_{0}, deadline_misses_{0};
  rt::SystemClock clock_;
  rt::LatestSlot<TrackingText> tracking_text_;  // track -> health, on a change
  TrackingText last_tracking_;                  // health thread's copy
  std::atomic<bool> running_{false};
  std::atomic<int64_t> stall_ms_{0};
  struct RoiRequest {
    vision::Roi roi;
    double depth_mm = 0;
  };
  rt::LatestSlot<RoiRequest> roi_requests_;
  std::atomic<bool> paused_{false}, redetect_requested_{false};
  std::atomic<uint64_t> commands_refused_{0}, commands_accepted_{0};
  rt::LatestSlot<std::string> command_errors_;  // the last refusal, for health
  std::string last_refusal_;                    // health thread's copy
  std::thread command_;
  std::atomic<int> ok_features_{0}, total_features_{0};
  std::atomic<int64_t> last_frame_ns_{0};
  int64_t quiet_after_ns_ =
      1'000'000'000;  // no pair for this long: the source is quiet (an outage)
  std::atomic<uint64_t> source_faults_{0}, source_recoveries_{0};  // capture -> health
  std::atomic<int64_t> source_outage_ns_{0};                       // the last outage's length
  std::atomic<uint64_t> outage_lost_{0};  // pulses lost in outages (said as outages, not losses)
  uint64_t outages_said_ = 0, recoveries_said_ = 0, recorder_faults_said_ = 0;  // health thread
  int recorder_segment_said_ = 1;
  rt::LatestSlot<std::string> source_errors_;  // capture -> health, on a fault's edge
  std::string last_source_error_;              // health thread's copy
  std::thread capture_, track_, publish_;
  struct LossWindow {  // health thread: the source's counters at the window's start
    int64_t t_ns = 0;
    uint64_t lost = 0, frames = 0;
    uint64_t lost_in = 0, pairs_in = 0;  // in the last complete window
  } loss_window_;
  int64_t started_ns_ = 0;
  bool said_ready_ = false;
};

}  // namespace pulsetrack::daemon
