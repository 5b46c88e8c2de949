#include "pulsetrack/daemon/pipeline.hpp"

#include <fmt/format.h>

#include <array>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <thread>

#include "pulsetrack/daemon/command.hpp"
#include "pulsetrack/daemon/log.hpp"
#include "pulsetrack/rt/thread_policy.hpp"

namespace pulsetrack::daemon {

const char* toString(State s) {
  switch (s) {
    case State::kStarting:
      return "starting";
    case State::kOk:
      return "ok";
    case State::kDegraded:
      return "degraded";
    case State::kFault:
      return "fault";
  }
  return "unknown";
}

namespace {

constexpr const char* kFrameId = "pulsetrack_left_camera";
// The field's cloud: 7 channels, then 3 per prediction horizon (dx_<ms>ms, dy_.., dz_..).
constexpr size_t kCloudFloats = 7;
constexpr size_t kCloudMaxFloats = kCloudFloats + 3 * vision::kMaxHorizons;
constexpr std::array<const char*, kCloudFloats> kCloudFieldNames = {"x",  "y",  "z",         "dx",
                                                                    "dy", "dz", "confidence"};

geometry_msgs_msg_dds__Point_ point(const cv::Vec3d& mm) {
  return {mm[0] * 1e-3, mm[1] * 1e-3, mm[2] * 1e-3};
}
geometry_msgs_msg_dds__Vector3_ vec(const cv::Vec3d& mm) {
  return {mm[0] * 1e-3, mm[1] * 1e-3, mm[2] * 1e-3};
}

// Waits until `seq` differs from `seen` (futex, no lock) or `running` goes false.
bool waitFor(std::atomic<uint64_t>& seq, uint64_t& seen, const std::atomic<bool>& running) {
  while (running.load(std::memory_order_relaxed)) {
    const uint64_t now = seq.load(std::memory_order_acquire);
    if (now != seen) {
      seen = now;
      return true;
    }
    seq.wait(now, std::memory_order_acquire);
  }
  return false;
}

}  // namespace

std::string recordingName(const std::string& rig_id) {
  const std::time_t now = std::time(nullptr);
  std::tm utc{};
  gmtime_r(&now, &utc);
  std::array<char, 32> stamp{};
  std::strftime(stamp.data(), stamp.size(), "%Y%m%d-%H%M%S", &utc);
  return rig_id + "-" + stamp.data();
}

Pipeline::Pipeline(const DaemonConfig& config, std::unique_ptr<drivers::CameraSource> source,
                   const dds::Participant& participant)
    : config_(config), source_(std::move(source)), participant_(participant) {
  quiet_after_ns_ = std::max<int64_t>(1'000'000'000, static_cast<int64_t>(3e9 / config_.fps));
  const cv::Size size = source_->rig().left.imageSize();
  for (Frame& f : frames_.slots()) {
    f.pair.left.create(size, CV_8UC1);
    f.pair.right.create(size, CV_8UC1);
  }
  if (config_.preview.enabled) {
    preview_tap_ =
        std::make_unique<PreviewTap>(size, static_cast<int64_t>(1e9 / config_.preview.rate_hz));
  }
  for (TrackResult& r : results_.slots())
    r.features.reserve(static_cast<size_t>(config_.tracker.max_features));
  for (TrackResult& r : field_results_.slots())
    r.features.reserve(static_cast<size_t>(config_.tracker.max_features));
  for (TargetSet& t : target_sets_.slots()) t.points.reserve(kMaxTargets);
  if (refreshing()) {
    for (RefreshHandOff& j : refresh_jobs_.slots()) j.job = vision::RefreshJob(config_.tracker);
    for (vision::RefreshOutcome& o : refresh_outcomes_.slots())
      o = vision::RefreshOutcome(config_.tracker);
  }
}

Pipeline::~Pipeline() { stop(); }

vision::Result<std::vector<std::string>> Pipeline::start() {
  const dds::Topics& topics = config_.topics;
  auto fw =
      dds::Writer::create(participant_, topics.features.c_str(),
                          &pulsetrack_msgs_msg_dds__Features__desc, dds::Profile::kSensorData);
  if (!fw) return std::unexpected(fw.error());
  auto dw =
      dds::Writer::create(participant_, topics.deformation.c_str(),
                          &pulsetrack_msgs_msg_dds__Deformation__desc, dds::Profile::kSensorData);
  if (!dw) return std::unexpected(dw.error());
  auto hw =
      dds::Writer::create(participant_, topics.health.c_str(),
                          &pulsetrack_msgs_msg_dds__Health__desc, dds::Profile::kTransientLocal);
  if (!hw) return std::unexpected(hw.error());
  features_writer_ = std::move(*fw);
  deformation_writer_ = std::move(*dw);
  health_writer_ = std::move(*hw);
  if (config_.field.enabled) {
    auto ffw =
        dds::Writer::create(participant_, topics.field.c_str(),
                            &sensor_msgs_msg_dds__PointCloud2__desc, dds::Profile::kSensorData);
    if (!ffw) return std::unexpected(ffw.error());
    field_writer_ = std::move(*ffw);
    auto tw = dds::Writer::create(participant_, topics.targets_tracked.c_str(),
                                  &pulsetrack_msgs_msg_dds__TrackedTargets__desc,
                                  dds::Profile::kSensorData);
    if (!tw) return std::unexpected(tw.error());
    targets_writer_ = std::move(*tw);
  }
  if (config_.preview.enabled) {
    for (int k = 0; k < 2; ++k) {
      auto iw = dds::Writer::create(
          participant_, (k == 0 ? topics.image_left : topics.image_right).c_str(),
          &sensor_msgs_msg_dds__CompressedImage__desc, dds::Profile::kSensorData);
      if (!iw) return std::unexpected(iw.error());
      image_writers_[k] = std::move(*iw);
    }
    // The JPEG codec's one-time set-up (OpenCV's imgcodecs registers its codecs, GDAL's among
    // them) here, before the stages run, not at the first preview next to them.
    std::vector<uchar> jpeg;
    if (!cv::imencode(".jpg", cv::Mat(8, 8, CV_8UC1, cv::Scalar(0)), jpeg))
      return vision::fail(
          "the preview: OpenCV cannot encode JPEG here (set [preview] enabled = false)");
  }
  if (auto ok = source_->start(); !ok) return std::unexpected(ok.error());
  std::vector<std::string> warnings;
  if (config_.lock_memory) {
    if (std::string w = rt::lockMemory(); !w.empty()) warnings.push_back(w);
  }
  running_ = true;
  started_ns_ = rt::monotonicNs();
  std::atomic<int> set_up{0};
  std::vector<std::string> thread_warnings(3);
  const auto with_policy = [&](int k, const char* name, const rt::ThreadPolicy& p, auto loop) {
    return std::thread([this, k, name, p, loop, &set_up, &thread_warnings] {
      thread_warnings[static_cast<size_t>(k)] = rt::applyThreadPolicy(name, p);
      set_up.fetch_add(1);
      set_up.notify_all();
      (this->*loop)();
    });
  };
  capture_ = with_policy(0, "pt-capture", config_.capture, &Pipeline::captureLoop);
  track_ = with_policy(1, "pt-track", config_.track, &Pipeline::trackLoop);
  publish_ = with_policy(2, "pt-publish", config_.publish, &Pipeline::publishLoop);
  for (int v = set_up.load(); v < 3; v = set_up.load()) set_up.wait(v);
  command_ = std::thread([this] { commandLoop(); });
  if (config_.field.enabled) {  // normal priority, as the preview: off the features' path
    field_ = std::thread([this] {
      offPathPolicy("pt-field");
      fieldLoop();
    });
  }
  if (refreshing()) {  // normal priority, as the field: off the features' path
    refresh_ = std::thread([this] {
      offPathPolicy("pt-refresh");
      refreshLoop();
    });
  }
  if (config_.preview.enabled) {  // normal priority: it must never take a core from the stages
    preview_ = std::thread([this] {
      offPathPolicy("pt-preview");
      previewLoop();
    });
  }
  for (std::string& w : thread_warnings) {
    if (!w.empty()) warnings.push_back(std::move(w));
  }
  return warnings;
}

void Pipeline::stop() {
  if (!running_.exchange(false)) return;
  frames_seq_.fetch_add(1);
  frames_seq_.notify_all();
  results_seq_.fetch_add(1);
  results_seq_.notify_all();
  field_seq_.fetch_add(1);
  field_seq_.notify_all();
  refresh_seq_.fetch_add(1);
  refresh_seq_.notify_all();
  refresh_done_.fetch_add(1);
  refresh_done_.notify_all();
  consumed_.fetch_add(1);
  consumed_.notify_all();
  if (preview_tap_) {
    preview_tap_->sequence().fetch_add(1);
    preview_tap_->sequence().notify_all();
  }
  for (std::thread* t : {&capture_, &track_, &publish_, &field_, &refresh_, &command_, &preview_}) {
    if (t->joinable()) t->join();
  }
  source_->stop();
}

void Pipeline::captureLoop() {
  bool faulted = false;  // the source said so (a fault, or its end)
  bool out = false;      // an outage: a fault, or quiet for longer than quiet_after_ns_
  int64_t out_since = 0;
  uint64_t lost_at_outage = 0;
  capture_running_.store(true);
  while (running_.load(std::memory_order_relaxed)) {
    // The recorder is let go of at the end of each turn (stopRecording waits for that).
    capture_epoch_.fetch_add(1, std::memory_order_acq_rel);
    capture_epoch_.notify_all();
    Frame& f = frames_.back();
    const drivers::Next n = source_->next(f.pair, std::chrono::milliseconds(100));
    const int64_t now = rt::monotonicNs();
    capture_beat_.beat(now);
    if (n == drivers::Next::kFrame) {
      if (out) {  // the source is back: the outage is over (health says so, with its length)
        // The outage's pulses, counted by the source as missing now that a pair came: the
        // outage was said already, health's loss window leaves them out.
        const drivers::SourceCounters c = source_->counters();
        outage_lost_.fetch_add(c.missing_triggers + c.unpaired - lost_at_outage,
                               std::memory_order_relaxed);
        source_outage_ns_.store(now - out_since, std::memory_order_relaxed);
        source_recoveries_.fetch_add(1, std::memory_order_release);
        out = false;
      }
      f.captured_ns = now;
      capture_lat_.record(static_cast<uint64_t>(std::max<int64_t>(0, now - f.pair.t_left_ns)));
      frames_.publish();
      // The slot just published is read by the track stage only, and written again by this
      // stage only after two more publishes: the recorder and the preview copy it now, off the
      // pair's latency.
      if (record::LiveRecorder* rec = recorder_live_.load(std::memory_order_acquire)) {
        // A copy into a free slot, or a counted skip: never a wait.
        // A new recording (its generation is stored before its pointer): its frame 0.
        if (const uint64_t gen = recording_gen_.load(std::memory_order_acquire);
            gen != recording_of_) {
          recording_of_ = gen;
          recorded_ = f.pair.trigger_seq;
        }
        (void)rec->offer({f.pair.trigger_seq - recorded_, f.pair.trigger_seq, f.pair.t_left_ns,
                          f.pair.t_right_ns, 0},
                         f.pair.left, f.pair.right);
      }
      if (preview_tap_) (void)preview_tap_->offer(f.pair, now);
      last_frame_ns_.store(now, std::memory_order_relaxed);
      faulted = false;
      ++handed_;
      if (config_.lossless) {  // replay: wait until the pair is through (none replaced)
        frames_seq_.fetch_add(1, std::memory_order_release);
        frames_seq_.notify_one();
        for (uint64_t c = consumed_.load(); c < handed_ && running_.load(); c = consumed_.load())
          consumed_.wait(c);
      }
    } else {
      const bool fault = n == drivers::Next::kFault || n == drivers::Next::kEnd;
      if (fault && !faulted) {  // said once per fault, on its edge (the health thread reports it)
        source_errors_.back() =
            n == drivers::Next::kEnd ? "the source ended" : source_->lastFault();
        source_errors_.publish();
        faulted = true;
      }
      const int64_t last = last_frame_ns_.load(std::memory_order_relaxed);
      const bool quiet = last != 0 && now - last > quiet_after_ns_;
      if (!out && (fault || quiet) && last != 0) {  // an outage starts (counted once)
        out = true;
        out_since = fault ? now : last;
        const drivers::SourceCounters c = source_->counters();
        lost_at_outage = c.missing_triggers + c.unpaired;
        source_faults_.fetch_add(1, std::memory_order_release);
      }
      if (fault) std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    frames_seq_.fetch_add(1, std::memory_order_release);
    frames_seq_.notify_one();
  }
  capture_running_.store(false);
  capture_epoch_.fetch_add(1, std::memory_order_acq_rel);
  capture_epoch_.notify_all();
}

void Pipeline::previewLoop() {
  const int scale = config_.preview.scale;
  const std::vector<int> params = {cv::IMWRITE_JPEG_QUALITY, config_.preview.jpeg_quality};
  cv::Mat small[2];
  std::vector<uchar> jpeg[2];
  std::string format = "mono8; jpeg compressed mono8";  // image_transport's compressed format
  std::string frame_ids[2] = {"pulsetrack_left_camera", "pulsetrack_right_camera"};
  uint64_t seen = 0;
  while (running_.load(std::memory_order_relaxed)) {
    if (!waitFor(preview_tap_->sequence(), seen, running_)) break;
    const PreviewFrame* p = preview_tap_->take();
    if (p == nullptr) continue;
    const int64_t t0 = rt::monotonicNs();
    slowDown(OffPath::kPreview);  // the test hook
    bool ok = true;
    for (int k = 0; k < 2; ++k) {
      const cv::Mat& full = k == 0 ? p->left : p->right;
      if (scale > 1)
        cv::resize(full, small[k], cv::Size(full.cols / scale, full.rows / scale), 0, 0,
                   cv::INTER_AREA);
      else
        small[k] = full;
      ok = ok && cv::imencode(".jpg", small[k], jpeg[k], params);
    }
    if (!ok) {
      log::get("preview").error("cannot encode the preview as JPEG; preview stopped");
      return;
    }
    for (int k = 0; k < 2; ++k) {
      sensor_msgs_msg_dds__CompressedImage_ m{};
      m.header.frame_id = frame_ids[k].data();
      m.header.stamp = dds::stamp(clock_.toRealtime(k == 0 ? p->t_left_ns : p->t_right_ns));
      m.format = format.data();
      m.data._buffer = jpeg[k].data();
      m.data._length = m.data._maximum = static_cast<uint32_t>(jpeg[k].size());
      m.data._release = false;
      (void)image_writers_[k].write(&m);
    }
    previews_sent_.fetch_add(1);
    preview_lat_.record(static_cast<uint64_t>(rt::monotonicNs() - t0));
  }
}

std::string Pipeline::startRecording() {
  const std::lock_guard lock(recorder_mutex_);
  if (recorder_) return fmt::format("already recording to {}", recorder_->status().dir.string());
  // A second recording in the same second gets its own folder (RIG-STAMP.2, ...).
  const std::filesystem::path base = config_.record_dir / recordingName(config_.rig_id);
  std::filesystem::path dir = base;
  std::error_code ec;
  for (int n = 2; std::filesystem::exists(dir, ec) && n < 1000; ++n)
    dir = base.string() + "." + std::to_string(n);
  record::LiveRecorderOptions o;
  o.dir = dir;
  o.slots = config_.record_slots;
  o.min_free_bytes = static_cast<uint64_t>(config_.record_min_free_mb) * 1'000'000;
  o.resume_check_ms = config_.record_resume ? 2000 : 0;
  o.manifest.source = "pulsetrackd " + source_->name();
  o.manifest.rig_id = config_.rig_id;
  o.manifest.width = source_->rig().left.imageSize().width;
  o.manifest.height = source_->rig().left.imageSize().height;
  o.manifest.nominal_fps = config_.fps;
  auto r = record::LiveRecorder::start(o, source_->rig());
  if (!r) return r.error().message;
  recorder_ = std::move(*r);
  recorder_segment_said_ = 1;
  recorder_faults_said_ = 0;
  recording_gen_.fetch_add(1, std::memory_order_release);
  recorder_live_.store(recorder_.get(), std::memory_order_release);
  log::get("recorder").info("recording to {}", dir.string());
  return "";
}

std::string Pipeline::stopRecording() {
  const std::lock_guard lock(recorder_mutex_);
  if (!recorder_) return "";
  recorder_live_.store(nullptr, std::memory_order_release);
  // The capture stage may hold the old pointer until the end of its turn (at most one source
  // call: 100 ms); two epochs later it has let go. Bounded: a stage stuck for 5 s is a fault the
  // watchdog handles, and the recorder is then kept (leaked) rather than freed under it.
  const uint64_t e0 = capture_epoch_.load(std::memory_order_acquire);
  const int64_t until = rt::monotonicNs() + 5'000'000'000;
  while (capture_running_.load() && capture_epoch_.load(std::memory_order_acquire) < e0 + 2) {
    if (rt::monotonicNs() > until) {
      log::get("recorder").error("the capture stage did not let go of the recorder in 5 s");
      (void)recorder_.release();
      return "the capture stage did not let go of the recorder";
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  recorder_->stop();
  const record::RecorderStatus st = recorder_->status();
  last_recording_ = fmt::format(
      "stopped: {} frames in {} segments to {} ({} skipped: disk behind; {} disk faults, {} pairs "
      "not recorded){}{}",
      st.written, st.segment, st.dir.string(), st.thinned, st.faults, st.unrecorded,
      st.error.empty() ? "" : "; ", st.error);
  recorder_.reset();
  log::get("recorder").info("recorded {}", last_recording_);
  return last_recording_;
}

void Pipeline::trackLoop() {
  vision::SessionConfig sc;
  sc.tracker = config_.tracker;
  sc.roi = config_.roi;
  sc.depth_tolerance_mm = config_.depth_tolerance_mm;
  sc.retry_interval_s = config_.retry_interval_s;
  sc.velocity_window_s = config_.velocity_window_s;
  sc.prediction = config_.prediction;
  sc.scale = config_.tracker_scale;
  vision::TrackingSession session(source_->rig(), sc);
  uint64_t seen = 0, reason_seen = UINT64_MAX;
  bool stopped = false;
  auto last_state = static_cast<vision::SessionState>(0xff);
  const auto deadline_ns = static_cast<int64_t>(config_.deadline_ms * 1e6);
  while (running_.load(std::memory_order_relaxed)) {
    track_beat_.beat();
    // The capture stage bumps the sequence after every source call (a frame or a 100 ms
    // timeout), so this stage beats while the source is quiet and sleeps on a futex otherwise.
    if (!waitFor(frames_seq_, seen, running_)) break;
    Frame* f = frames_.take();
    // Without a result the publish stage is still woken, so that it beats too.
    const auto wake_publish = [this] {
      results_seq_.fetch_add(1, std::memory_order_release);
      results_seq_.notify_one();
    };
    if (f == nullptr) {
      wake_publish();
      continue;
    }
    handover_lat_.record(
        static_cast<uint64_t>(std::max<int64_t>(0, rt::monotonicNs() - f->captured_ns)));
    if (const int64_t stall = stall_ms_.exchange(0); stall > 0)
      std::this_thread::sleep_for(std::chrono::milliseconds(stall));
    // Commands, between pairs (the command thread checked them).
    if (const RoiRequest* req = roi_requests_.take()) session.setRoi(req->roi, req->depth_mm);
    if (const bool pause = paused_.load(); pause != stopped) {
      stopped = pause;
      if (pause)
        session.stop();
      else
        session.start();
    }
    if (redetect_requested_.exchange(false)) session.requestRedetect();
    // The refresh stage's newest matches, from an earlier pair, folded in before this one.
    if (const vision::RefreshOutcome* o = refreshing() ? refresh_outcomes_.take() : nullptr)
      (void)session.applyRefresh(*o);
    const vision::PairResult& pr =
        session.process(f->pair.left, f->pair.right, f->pair.trigger_seq, f->pair.t_left_ns);
    processed_.fetch_add(1);
    if (session.reasonSerial() != reason_seen || pr.state != last_state) {
      reason_seen = session.reasonSerial();
      last_state = pr.state;
      TrackingText& t = tracking_text_.back();
      const std::string_view why = session.reason();
      t.size = std::min(why.size(), t.text.size());
      std::copy_n(why.data(), t.size, t.text.data());
      t.state = pr.state;
      tracking_text_.publish();
    }
    if (pr.state != vision::SessionState::kTracking) {  // nothing to publish (health says why)
      ok_features_.store(0);
      total_features_.store(0);
      consumed_.fetch_add(1);
      consumed_.notify_one();
      wake_publish();
      continue;
    }
    TrackResult& r = results_.back();
    const int64_t done = rt::monotonicNs();
    r.features.assign(pr.features.begin(), pr.features.end());  // within the reserved capacity
    r.deformation = pr.deformation;
    r.detected = pr.detected;
    r.trigger_seq = f->pair.trigger_seq;
    r.t_ns = f->pair.t_left_ns;
    r.captured_ns = f->captured_ns;
    r.tracked_ns = done;
    track_lat_.record(static_cast<uint64_t>(done - f->captured_ns));
    if (done - f->captured_ns > deadline_ns) deadline_misses_.fetch_add(1);
    ok_features_.store(pr.deformation.ok);
    total_features_.store(static_cast<int>(r.features.size()));
    results_.publish();
    tracked_.fetch_add(1);
    results_seq_.fetch_add(1, std::memory_order_release);
    results_seq_.notify_one();
    // The pair's result is on its way: now the recent templates are taken, and the windows that
    // the refresh stage matches again are copied (a fixed number per pair: a bounded copy).
    if (refreshing()) handOverRefresh(session, *f);
  }
}

void Pipeline::handOverRefresh(vision::TrackingSession& session, const Frame& f) {
  RefreshHandOff& j = refresh_jobs_.back();
  session.prepareRefresh(f.pair.left, f.pair.right, j.job);
  if (j.job.count == 0) return;
  j.captured_ns = f.captured_ns;
  refresh_jobs_.publish();
  const uint64_t job = refresh_seq_.fetch_add(1, std::memory_order_release) + 1;
  refresh_seq_.notify_one();
  if (!config_.lossless) return;
  // A replay: the matches are in before the next pair, as `pulsetrack track` has them.
  for (uint64_t d = refresh_done_.load(); d < job && running_.load(); d = refresh_done_.load())
    refresh_done_.wait(d);
  if (const vision::RefreshOutcome* o = refresh_outcomes_.take()) (void)session.applyRefresh(*o);
}

// The refresh stage: the stereo refresh's matching, on the latest job it can take.
void Pipeline::refreshLoop() {
  uint64_t seen = 0;
  while (running_.load(std::memory_order_relaxed)) {
    if (!waitFor(refresh_seq_, seen, running_)) break;
    const RefreshHandOff* j = refresh_jobs_.take();
    if (j == nullptr) continue;
    slowDown(OffPath::kRefresh);
    vision::measureRefresh(j->job, refresh_outcomes_.back());
    refresh_outcomes_.publish();
    refresh_lat_.record(static_cast<uint64_t>(rt::monotonicNs() - j->captured_ns));
    refreshes_.fetch_add(1, std::memory_order_relaxed);
    refresh_done_.fetch_add(1, std::memory_order_release);
    refresh_done_.notify_one();
  }
}

void Pipeline::offPathPolicy(const char* name) const {
  if (const std::string w = rt::applyThreadPolicy(name, config_.off_path); !w.empty())
    log::get("pipeline").warn("{}: {}", name, w);
}

void Pipeline::slowDown(OffPath stage) const {
  if (const int64_t ms = slow_ms_[static_cast<size_t>(stage)].load(); ms > 0)
    std::this_thread::sleep_for(std::chrono::milliseconds(ms));
}

void Pipeline::publishLoop() {
  std::vector<pulsetrack_msgs_msg_dds__Feature_> list(
      static_cast<size_t>(config_.tracker.max_features));
  pulsetrack_msgs_msg_dds__Features_ fs{};
  fs.header.frame_id = const_cast<char*>(kFrameId);
  fs.rig_id = config_.rig_id.data();
  fs.features._buffer = list.data();
  fs.features._maximum = static_cast<uint32_t>(list.size());
  fs.features._release = false;
  pulsetrack_msgs_msg_dds__Deformation_ d{};
  d.header.frame_id = const_cast<char*>(kFrameId);
  d.rig_id = config_.rig_id.data();
  std::array<double, vision::kMaxHorizons> p_horizon{}, p_sigma{};
  std::array<geometry_msgs_msg_dds__Vector3_, vision::kMaxHorizons> p_disp{};
  std::array<bool, vision::kMaxHorizons> p_model{};
  d.prediction_horizon = {vision::kMaxHorizons, 0, p_horizon.data(), false};
  d.predicted_displacement = {vision::kMaxHorizons, 0, p_disp.data(), false};
  d.prediction_sigma = {vision::kMaxHorizons, 0, p_sigma.data(), false};
  d.predicted_by_model = {vision::kMaxHorizons, 0, p_model.data(), false};
  uint64_t seen = 0;
  while (running_.load(std::memory_order_relaxed)) {
    publish_beat_.beat();
    if (!waitFor(results_seq_, seen, running_)) break;
    TrackResult* r = results_.take();
    if (r == nullptr) continue;
    // Stamps: the pair's exposure on the system clock.
    const auto stamp = dds::stamp(clock_.toRealtime(r->t_ns));
    const size_t n = std::min(r->features.size(), list.size());
    for (size_t i = 0; i < n; ++i) {
      const vision::Feature& f = r->features[i];
      list[i].id = f.id;
      list[i].status = static_cast<uint8_t>(f.status);
      list[i].reason = static_cast<uint8_t>(f.gate);
      list[i].position = point(f.point);
      list[i].displacement = vec(f.point - f.point0);
      list[i].ncc = static_cast<float>(f.ncc);
      list[i].nmi = static_cast<float>(f.nmi);
      list[i].left_x = static_cast<float>(f.left[0]);
      list[i].left_y = static_cast<float>(f.left[1]);
      list[i].right_x = static_cast<float>(f.right[0]);
      list[i].right_y = static_cast<float>(f.right[1]);
    }
    fs.features._length = static_cast<uint32_t>(n);
    fs.frame = r->trigger_seq;
    fs.header.stamp = stamp;
    (void)features_writer_.write(&fs);
    const vision::Deformation& def = r->deformation;
    if (def.valid) {
      d.frame = r->trigger_seq;
      d.header.stamp = stamp;
      d.centroid = point(def.centroid);
      d.displacement = vec(def.displacement);
      d.velocity = vec(def.velocity);
      d.velocity_delay = def.velocity_delay_s;
      d.displacement_sigma = def.displacement_sigma_mm * 1e-3;
      d.velocity_sigma = def.velocity_sigma_mm_s * 1e-3;
      d.features_ok = static_cast<uint32_t>(def.ok);
      d.features_total = static_cast<uint32_t>(def.total);
      d.detections = def.detections;
      d.continuous = def.continuous;
      const vision::Prediction& pr = def.prediction;
      const auto np = static_cast<uint32_t>(config_.prediction.enabled ? pr.horizons : 0);
      for (uint32_t k = 0; k < np; ++k) {
        p_horizon[k] = pr.horizon_s[k];
        p_disp[k] = vec(pr.displacement[k]);
        p_sigma[k] = pr.sigma_mm[k] * 1e-3;
        p_model[k] = pr.model[k];
      }
      d.prediction_horizon._length = d.predicted_displacement._length = d.prediction_sigma._length =
          d.predicted_by_model._length = np;
      (void)deformation_writer_.write(&d);
    }
    publish_lat_.record(static_cast<uint64_t>(rt::monotonicNs() - r->tracked_ns));
    if (config_.field.enabled) {
      // The field stage's copy (within the reserved capacity); it takes the latest it can.
      TrackResult& fr = field_results_.back();
      fr.features.assign(r->features.begin(), r->features.end());
      fr.deformation = r->deformation;
      fr.detected = r->detected;
      fr.trigger_seq = r->trigger_seq;
      fr.t_ns = r->t_ns;
      fr.captured_ns = r->captured_ns;
      fr.tracked_ns = r->tracked_ns;
      field_results_.publish();
      field_seq_.fetch_add(1, std::memory_order_release);
      field_seq_.notify_one();
      continue;  // done with once the field stage is (a lossless replay waits for it)
    }
    consumed_.fetch_add(1);
    consumed_.notify_one();
  }
}

// The field stage: the dense field and the targets' answers, on the latest result it can take.
void Pipeline::fieldLoop() {
  // The field's cloud: x y z (where each grid point is now), dx dy dz (since the signal's first
  // pair), m, and confidence; float32 little-endian, organized as the grid (rows x cols).
  std::unique_ptr<vision::DeformationField> field;
  std::vector<uint8_t> cloud_data;
  std::array<sensor_msgs_msg_dds__PointField_, kCloudMaxFloats> cloud_fields{};
  std::vector<std::string> cloud_names;  // the fields' names (their storage)
  std::array<Eigen::MatrixXd, vision::kMaxHorizons> predicted_grid;
  const int horizons = config_.prediction.enabled
                           ? static_cast<int>(std::min<size_t>(config_.prediction.horizons_s.size(),
                                                               vision::kMaxHorizons))
                           : 0;
  const size_t floats = kCloudFloats + 3 * static_cast<size_t>(horizons);
  const auto cloud_step = static_cast<uint32_t>(floats * sizeof(float));
  sensor_msgs_msg_dds__PointCloud2_ cloud{};
  // (The stage runs only with [field] enabled.)
  field = std::make_unique<vision::DeformationField>(config_.field, config_.tracker.max_features);
  if (horizons > 0) {
    field->enablePrediction(config_.prediction.order * config_.prediction.step_s + 0.1,
                            std::max(config_.prediction.max_rate_hz, 2.0 * config_.fps));
  }
  cloud_data.assign(static_cast<size_t>(config_.field.max_grid_points) * cloud_step, 0);
  cloud_names.reserve(floats);
  for (const char* n : kCloudFieldNames) cloud_names.emplace_back(n);
  for (int k = 0; k < horizons; ++k) {
    const long ms = std::lround(config_.prediction.horizons_s[static_cast<size_t>(k)] * 1e3);
    for (const char* axis : {"dx", "dy", "dz"})
      cloud_names.push_back(fmt::format("{}_{}ms", axis, ms));
  }
  for (size_t i = 0; i < floats; ++i) {
    cloud_fields[i].name = cloud_names[i].data();
    cloud_fields[i].offset = static_cast<uint32_t>(i * sizeof(float));
    cloud_fields[i].datatype = 7;  // sensor_msgs/PointField FLOAT32
    cloud_fields[i].count = 1;
  }
  cloud.header.frame_id = const_cast<char*>(kFrameId);
  cloud.fields._buffer = cloud_fields.data();
  cloud.fields._length = cloud.fields._maximum = static_cast<uint32_t>(floats);
  cloud.fields._release = false;
  cloud.is_bigendian = std::endian::native == std::endian::big;
  cloud.point_step = cloud_step;
  cloud.data._buffer = cloud_data.data();
  cloud.data._maximum = static_cast<uint32_t>(cloud_data.size());
  cloud.data._release = false;
  // The robot's targets: their references (mm, in the field's reference pair), the last answers.
  std::vector<cv::Vec3d> target_refs, target_last;
  target_refs.reserve(kMaxTargets);
  target_last.reserve(kMaxTargets);
  uint32_t target_set = 0, target_signal = 0;
  bool target_answered = false;
  std::vector<geometry_msgs_msg_dds__Point_> tt_ref(kMaxTargets), tt_pos(kMaxTargets);
  std::vector<geometry_msgs_msg_dds__Vector3_> tt_disp(kMaxTargets);
  std::vector<float> tt_conf(kMaxTargets);
  pulsetrack_msgs_msg_dds__TrackedTargets_ tt{};
  tt.header.frame_id = const_cast<char*>(kFrameId);
  tt.rig_id = config_.rig_id.data();
  tt.reference = {kMaxTargets, 0, tt_ref.data(), false};
  tt.position = {kMaxTargets, 0, tt_pos.data(), false};
  tt.displacement = {kMaxTargets, 0, tt_disp.data(), false};
  tt.confidence = {kMaxTargets, 0, tt_conf.data(), false};
  uint64_t seen = 0;
  while (running_.load(std::memory_order_relaxed)) {
    if (!waitFor(field_seq_, seen, running_)) break;
    TrackResult* r = field_results_.take();
    if (r == nullptr) continue;
    const vision::Deformation& def = r->deformation;
    const auto stamp = dds::stamp(clock_.toRealtime(r->t_ns));
    slowDown(OffPath::kField);  // the test hook
    if (field->update(r->features, r->detected, def.detections)) {
      const int m = std::min(field->points(), config_.field.max_grid_points);
      // The grid predicted at each horizon with the mean's weights, when the mean's model is in
      // use (else, as for the mean, the field as it is).
      field->record(static_cast<double>(r->t_ns) * 1e-9);
      std::array<bool, vision::kMaxHorizons> predicted{};
      for (int h = 0; h < horizons && h < def.prediction.horizons; ++h) {
        const auto hh = static_cast<size_t>(h);
        Eigen::MatrixXd& g = predicted_grid[hh];
        if (g.rows() != field->points()) g.setZero(field->points(), 3);  // a new grid only
        predicted[hh] =
            def.prediction.model[hh] && field->predict({def.prediction_weights[hh].data(),
                                                        static_cast<size_t>(def.prediction_order)},
                                                       def.prediction_step_s, g);
      }
      bool dense = true;
      for (int k = 0; k < m; ++k) {
        const double conf = field->confidence(k);
        std::array<float, kCloudMaxFloats> v{};
        if (conf > 0.0) {
          const cv::Vec3d disp = field->displacement(k), at = field->rest(k) + disp;
          v[0] = static_cast<float>(at[0] * 1e-3);
          v[1] = static_cast<float>(at[1] * 1e-3);
          v[2] = static_cast<float>(at[2] * 1e-3);
          for (int a = 0; a < 3; ++a)
            v[3 + static_cast<size_t>(a)] = static_cast<float>(disp[a] * 1e-3);
          v[6] = static_cast<float>(conf);
          for (int h = 0; h < horizons; ++h) {
            const auto hh = static_cast<size_t>(h);
            for (int a = 0; a < 3; ++a) {
              const double p = predicted[hh] ? predicted_grid[hh](k, a) : disp[a];
              v[kCloudFloats + 3 * hh + static_cast<size_t>(a)] = static_cast<float>(p * 1e-3);
            }
          }
        } else {
          v.fill(std::numeric_limits<float>::quiet_NaN());  // ROS's invalid point
          v[6] = 0.0F;
          dense = false;
        }
        std::memcpy(cloud_data.data() + static_cast<size_t>(k) * cloud_step, v.data(), cloud_step);
      }
      cloud.header.stamp = stamp;
      cloud.width = static_cast<uint32_t>(field->cols());
      cloud.height = static_cast<uint32_t>(m / std::max(1, field->cols()));
      cloud.row_step = cloud.width * cloud_step;
      cloud.data._length = cloud.row_step * cloud.height;
      cloud.is_dense = dense;
      (void)field_writer_.write(&cloud);
      // The robot's targets: a new set (mapped back to the reference when given as it is now),
      // a new signal (each target goes on from where it was last), then this pair's answers.
      if (const TargetSet* set = target_sets_.take()) {
        target_set = set->set_id;
        target_refs.clear();
        for (const cv::Vec3d& p : set->points)
          target_refs.push_back(set->frame == 1 ? field->reference(p) : p);
        target_signal = field->signal();
        target_answered = false;
      }
      if (field->signal() != target_signal) {
        if (target_answered) target_refs.assign(target_last.begin(), target_last.end());
        target_signal = field->signal();
      }
      if (target_set != 0 && !target_refs.empty()) {
        target_last.clear();
        for (size_t k = 0; k < target_refs.size(); ++k) {
          const vision::FieldQuery q = field->at(target_refs[k]);
          target_last.push_back(q.position);
          tt_ref[k] = point(target_refs[k]);
          tt_pos[k] = point(q.position);
          tt_disp[k] = vec(q.displacement);
          tt_conf[k] = static_cast<float>(q.confidence);
        }
        target_answered = true;
        const auto answers = static_cast<uint32_t>(target_refs.size());
        tt.reference._length = tt.position._length = tt.displacement._length =
            tt.confidence._length = answers;
        tt.header.stamp = stamp;
        tt.frame = r->trigger_seq;
        tt.set_id = target_set;
        tt.signal = field->signal();
        (void)targets_writer_.write(&tt);
      }
      fields_sent_.fetch_add(1);
    }
    field_lat_.record(static_cast<uint64_t>(rt::monotonicNs() - r->captured_ns));
    consumed_.fetch_add(1);
    consumed_.notify_one();
  }
}

std::string Pipeline::command(const pulsetrack_msgs_msg_dds__Command_& c) {
  CheckedCommand cc = checkCommand(c, config_.rig_id, config_.ros_namespace, source_->rig());
  switch (cc.kind) {
    case CommandKind::kStart:
      paused_.store(false);
      break;
    case CommandKind::kStop:
      paused_.store(true);
      break;
    case CommandKind::kRedetect:
      redetect_requested_.store(true);
      break;
    case CommandKind::kSetRoi:
      roi_requests_.back() = {cc.roi, cc.depth_mm};
      roi_requests_.publish();
      break;
    case CommandKind::kRecordStart:
      if (config_.record_dir.empty()) {
        cc.refusal = fmt::format("command {} 'record_start' refused: no [recorder] dir configured",
                                 c.request_id);
      } else if (std::string why = startRecording(); !why.empty()) {
        cc.refusal = fmt::format("command {} 'record_start' refused: {}", c.request_id, why);
      }
      break;
    case CommandKind::kRecordStop:
      (void)stopRecording();
      break;
    case CommandKind::kRefused:
      break;
  }
  if (!cc.refusal.empty()) {
    commands_refused_.fetch_add(1);
    command_errors_.back() = cc.refusal;
    command_errors_.publish();
    log::get("command").warn("{}", cc.refusal);
  } else {
    commands_accepted_.fetch_add(1);
  }
  return cc.refusal;
}

void Pipeline::commandLoop() {
  auto reader =
      dds::Reader::create(participant_, config_.topics.command.c_str(),
                          &pulsetrack_msgs_msg_dds__Command__desc, dds::Profile::kCommand);
  if (!reader) {
    log::get("dds").error("commands will not be received: {}", reader.error().message);
    return;
  }
  // The robot's targets: reliable, volatile, so that any reliable writer matches (a ROS 2
  // publisher with rclcpp's QoS(1).reliable(), or transient_local too).
  std::optional<dds::Reader> targets;
  if (config_.field.enabled) {
    auto tr = dds::Reader::create(participant_, config_.topics.targets.c_str(),
                                  &pulsetrack_msgs_msg_dds__Targets__desc, dds::Profile::kCommand);
    if (!tr)
      log::get("dds").error("targets will not be received: {}", tr.error().message);
    else
      targets.emplace(std::move(*tr));
  }
  pulsetrack_msgs_msg_dds__Command_ c{};
  pulsetrack_msgs_msg_dds__Targets_ t{};
  // Commands wait (up to 50 ms); the targets are only looked at between them (no wait), so a
  // burst of commands is not slowed by an idle targets topic (a 50 ms wait per command made a
  // 2000-command test time out) and a set waits at most 50 ms.
  const auto wait = std::chrono::milliseconds(targets ? 50 : 100);
  while (running_.load()) {
    if (reader->takeOne(&c, wait)) (void)command(c);
    if (targets && targets->takeOne(&t, std::chrono::milliseconds(0))) (void)this->targets(t);
  }
  dds_sample_free(&c, &pulsetrack_msgs_msg_dds__Command__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&t, &pulsetrack_msgs_msg_dds__Targets__desc, DDS_FREE_CONTENTS);
}

std::string Pipeline::targets(const pulsetrack_msgs_msg_dds__Targets_& t) {
  if (std::string why = checkTargets(t, config_.rig_id, kMaxTargets); !why.empty()) {
    log::get("command").warn("{}", why);
    command_errors_.back() = why;
    command_errors_.publish();
    commands_refused_.fetch_add(1);
    return why;
  }
  TargetSet& set = target_sets_.back();
  set.set_id = t.set_id;
  set.frame = t.frame;
  set.points.clear();
  for (uint32_t i = 0; i < t.points._length; ++i) {
    const geometry_msgs_msg_dds__Point_& p = t.points._buffer[i];
    set.points.emplace_back(p.x * 1e3, p.y * 1e3, p.z * 1e3);
  }
  target_sets_.publish();
  commands_accepted_.fetch_add(1);
  log::get("command").info("targets set {}: {} points ({})", t.set_id, t.points._length,
                           t.frame == 1 ? "as they are now" : "in the reference pair");
  return "";
}

State Pipeline::health(const Notifier& notifier) {
  const int64_t now = rt::monotonicNs();
  // A stage is on time when it beat within the health period (at least 1 s: the sim source
  // renders slowly on this machine) .
  const int64_t max_age =
      std::max<int64_t>(1'000'000'000, int64_t{config_.health_period_ms} * 2'000'000);
  const rt::Heartbeat* stages[] = {&capture_beat_, &track_beat_, &publish_beat_};
  // The watchdog is pinged only when every stage is on time; that check is the stall verdict.
  const bool stalled = !notifier.pingIfHealthy(stages, std::chrono::nanoseconds(max_age));
  // The source is quiet when no pair came for 1 s or three trigger periods: degraded (the
  // stages still run and the watchdog is still fed; the device may come back).
  if (const std::string* e = source_errors_.take()) last_source_error_ = *e;
  const int64_t last_frame = last_frame_ns_.load(std::memory_order_relaxed);
  const bool quiet = last_frame != 0 && now - last_frame > quiet_after_ns_;
  // Outages (faults, or the source quiet): each said once in the journal, and its end.
  const uint64_t outages = source_faults_.load(std::memory_order_acquire);
  const uint64_t recoveries = source_recoveries_.load(std::memory_order_acquire);
  if (outages != outages_said_) {
    outages_said_ = outages;
    log::get("source").warn(
        "outage {}: {}", outages,
        last_source_error_.empty() ? "no frame from the source" : last_source_error_);
  }
  if (recoveries != recoveries_said_) {
    recoveries_said_ = recoveries;
    log::get("source").info(
        "frames again after an outage of {:.1f} s ({} outages so far)",
        static_cast<double>(source_outage_ns_.load(std::memory_order_relaxed)) * 1e-9, outages);
  }
  // Triggers that gave no pair (missing pulses, frames without a partner) over a window of
  // 20 trigger periods (at least 1 s): more than a fifth of them is degraded, said on health.
  const uint64_t outage_lost = outage_lost_.load();  // before the counters: never more than them
  const drivers::SourceCounters sc = source_->counters();
  const uint64_t lost = sc.missing_triggers + sc.unpaired - outage_lost;
  const auto window_ns = std::max<int64_t>(1'000'000'000, static_cast<int64_t>(20e9 / config_.fps));
  if (now - loss_window_.t_ns >= window_ns) {
    // (An outage's pulses are counted by the source and then by outage_lost_ a moment apart:
    // the difference may step back once.)
    loss_window_.lost_in = lost > loss_window_.lost ? lost - loss_window_.lost : 0;
    loss_window_.pairs_in = sc.frames - loss_window_.frames;
    loss_window_ = {now, lost, sc.frames, loss_window_.lost_in, loss_window_.pairs_in};
  }
  const uint64_t lost_now = loss_window_.lost_in, pairs_now = loss_window_.pairs_in;
  const bool losing = lost_now * 4 > pairs_now && lost_now > 0;
  // The stamps' clock: re-measured here, off the real-time path; a step is said, not smeared.
  if (const int64_t step = clock_.remeasure(); step != 0) {
    log::get("clock").warn(
        "the system clock was stepped by {:+.3f} ms: stamps follow it from now on ({} steps)",
        static_cast<double>(step) * 1e-6, clock_.steps());
  }
  const rt::ClockSync sync = rt::systemClockSync();
  if (const TrackingText* t = tracking_text_.take()) last_tracking_ = *t;
  const bool tracking = last_tracking_.state == vision::SessionState::kTracking;
  const std::string why_not(last_tracking_.text.data(), last_tracking_.size);
  State state = State::kOk;
  if (!trackedOnce())
    state = stalled && now - started_ns_ > 10 * max_age ? State::kFault : State::kStarting;
  else if (stalled)
    state = State::kFault;
  else if (quiet || losing || !tracking || ok_features_.load() < 3)
    state = State::kDegraded;
  if (trackedOnce() && !said_ready_) {
    notifier.ready();
    said_ready_ = true;
  }
  const double secs = static_cast<double>(now - started_ns_) * 1e-9;
  const double fps = secs > 0 ? static_cast<double>(tracked()) / secs : 0.0;
  const std::string line =
      fmt::format("{}: {} of {} features ok, {:.1f} fps, {} drops, track p99 {} us",
                  toString(state), ok_features_.load(), total_features_.load(), fps,
                  frames_.drops() + results_.drops(), track_lat_.percentileNs(0.99) / 1000);
  notifier.status(line);

  // With the field: its stage (pair handed over -> field sent); with the preview: its stage
  // (scale, encode, send) and the capture stage's copy for it.
  // With the refresh: its stage (pair handed over -> its matches measured).
  // The track stage's first part on its own: the pair handed over -> the track thread has it (the
  // wake-up of a sleeping thread on another core).
  pulsetrack_msgs_msg_dds__StageLatency_ st[8]{};
  std::array<const rt::LatencyHistogram*, 8> hist{&capture_lat_, &handover_lat_, &track_lat_,
                                                  &publish_lat_};
  std::array<const char*, 8> names{"capture", "handover", "track", "publish"};
  int nstages = 4;
  if (config_.field.enabled) {
    hist[static_cast<size_t>(nstages)] = &field_lat_;
    names[static_cast<size_t>(nstages++)] = "field";
  }
  if (refreshing()) {
    hist[static_cast<size_t>(nstages)] = &refresh_lat_;
    names[static_cast<size_t>(nstages++)] = "refresh";
  }
  if (preview_tap_) {
    hist[static_cast<size_t>(nstages)] = &preview_lat_;
    names[static_cast<size_t>(nstages++)] = "preview";
    hist[static_cast<size_t>(nstages)] = &preview_tap_->copyLatency();
    names[static_cast<size_t>(nstages++)] = "preview_copy";
  }
  for (int i = 0; i < nstages; ++i) {
    const rt::LatencyHistogram& lat = *hist[static_cast<size_t>(i)];
    st[i].stage = const_cast<char*>(names[static_cast<size_t>(i)]);
    st[i].p50_us = static_cast<uint32_t>(lat.percentileNs(0.5) / 1000);
    st[i].p99_us = static_cast<uint32_t>(lat.percentileNs(0.99) / 1000);
    st[i].max_us = static_cast<uint32_t>(lat.maxNs() / 1000);
  }
  pulsetrack_msgs_msg_dds__Health_ h{};
  h.header.frame_id = const_cast<char*>(kFrameId);
  h.header.stamp = dds::stamp(clock_.toRealtime(now));
  h.rig_id = config_.rig_id.data();
  h.state = static_cast<uint8_t>(state);
  std::string state_text = line;
  h.state_text = state_text.data();
  h.stages._buffer = st;
  h.stages._length = static_cast<uint32_t>(nstages);
  h.stages._maximum = static_cast<uint32_t>(nstages);
  h.stages._release = false;
  h.fps = static_cast<float>(fps);
  h.frames = tracked();
  h.drops = frames_.drops() + results_.drops() + sc.overruns;
  h.deadline_misses = deadline_misses_.load();
  h.missing_triggers = sc.missing_triggers;
  h.unpaired = sc.unpaired;
  h.source_faults = outages;
  h.commands_accepted = commands_accepted_.load();
  h.commands_refused = commands_refused_.load();
  std::string source_name = source_->name();
  h.source = source_name.data();
  std::string source_state = quiet ? "stalled" : paused_.load() ? "paused" : "running";
  h.source_state = source_state.data();
  std::string trigger_state = source_->triggerState();
  h.trigger_state = trigger_state.data();
  const std::lock_guard lock(recorder_mutex_);
  std::string recorder_state = last_recording_.empty() ? "off" : "off (" + last_recording_ + ")";
  if (recorder_ != nullptr) {
    const record::RecorderStatus rs = recorder_->status();
    h.recorder_faults = rs.faults;
    const std::string faults =
        rs.faults == 0
            ? ""
            : fmt::format("; {} disk faults, {} pairs not recorded", rs.faults, rs.unrecorded);
    recorder_state =
        rs.error.empty()
            ? fmt::format("recording {}: {} frames, {} skipped (disk behind){}", rs.dir.string(),
                          rs.written, rs.thinned, faults)
            : fmt::format("stopped after {} frames: {}{}", rs.written, rs.error, faults);
    if (rs.faults != recorder_faults_said_) {
      recorder_faults_said_ = rs.faults;
      log::get("recorder").warn("{}", recorder_state);
    }
    if (rs.segment != recorder_segment_said_) {
      recorder_segment_said_ = rs.segment;
      log::get("recorder").info("recording again, to {}", rs.dir.string());
    }
  }
  h.recorder_state = recorder_state.data();
  std::string tracking_state =
      tracking
          ? fmt::format("tracking {} of {} features", ok_features_.load(), total_features_.load())
          : fmt::format("{}: {}", vision::toString(last_tracking_.state), why_not);
  h.tracking_state = tracking_state.data();
  h.clock_synchronized = sync.synchronized;
  std::string clock_state = fmt::format("CLOCK_REALTIME {}; {} steps", sync.text, clock_.steps());
  h.clock_state = clock_state.data();
  h.security_state = const_cast<char*>(participant_.securityState().c_str());
  std::string output_state = fmt::format(
      "readers matched: features {}, deformation {}, health {}, field {}, targets_tracked {}",
      features_writer_.matchedReaders(), deformation_writer_.matchedReaders(),
      health_writer_.matchedReaders(),
      config_.field.enabled ? std::to_string(field_writer_.matchedReaders()) : "off",
      config_.field.enabled ? std::to_string(targets_writer_.matchedReaders()) : "off");
  // The stages off the features' path: what each did and what it skipped (each takes the latest
  // pair when free).
  if (config_.field.enabled) {
    output_state += fmt::format("; field stage: {} sent, {} pairs skipped", fields_sent_.load(),
                                field_results_.drops());
  }
  if (refreshing()) {
    // Pairs whose job it never took; matches replaced by newer ones before the track stage took
    // them (the track stage slower than the refresh).
    output_state +=
        fmt::format("; refresh stage: {} measured, {} pairs skipped, {} replaced",
                    refreshes_.load(), refresh_jobs_.drops(), refresh_outcomes_.drops());
  }
  if (preview_tap_) {
    output_state += fmt::format("; preview stage: {} sent, {} copies skipped",
                                previews_sent_.load(), preview_tap_->drops());
  }
  h.output_state = output_state.data();
  if (const std::string* refusal = command_errors_.take()) last_refusal_ = *refusal;
  std::string err =
      quiet    ? fmt::format("no frame from the source for {} ms{}", (now - last_frame) / 1'000'000,
                          last_source_error_.empty() ? "" : ": " + last_source_error_)
      : losing ? fmt::format(
                     "{} of the last {} triggers gave no frame pair (missing triggers {}, "
                     "unpaired frames {} in all)",
                     lost_now, lost_now + pairs_now, sc.missing_triggers, sc.unpaired)
      : !tracking && trackedOnce() ? tracking_state
      : !last_refusal_.empty()     ? last_refusal_
                                   : last_source_error_;
  h.last_error = err.data();
  const cv::Size size = source_->rig().left.imageSize();
  h.image_width = static_cast<uint32_t>(size.width);
  h.image_height = static_cast<uint32_t>(size.height);
  (void)health_writer_.write(&h);
  return state;
}

}  // namespace pulsetrack::daemon
