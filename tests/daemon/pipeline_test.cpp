// The pipeline in process, with a camera source that stalls and comes back (a fault, then
// silence, then frames): health goes degraded naming the fault and the silence, the stages keep
// beating (no watchdog restart for a camera problem), and tracking resumes.

#include "pulsetrack/daemon/pipeline.hpp"

#include <gtest/gtest.h>

#include <array>
#include <climits>
#include <cmath>
#include <ctime>
#include <thread>

#include "drivers/fake_v4l2.hpp"
#include "pulsetrack/daemon/command.hpp"
#include "pulsetrack/sim/paper_rig.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "test_util.hpp"

namespace pulsetrack::daemon {
namespace {

// Frames of a real render, then a fault and `stall` of silence, then frames again.
class StallingSource final : public drivers::CameraSource {
 public:
  StallingSource(std::vector<std::pair<cv::Mat, cv::Mat>> frames, vision::StereoRig rig,
                 int stall_after, std::chrono::milliseconds stall)
      : frames_(std::move(frames)),
        rig_(std::move(rig)),
        stall_after_(stall_after),
        stall_(stall) {}
  std::string name() const override { return "stalling test source"; }
  const vision::StereoRig& rig() const override { return rig_; }
  vision::Result<void> start() override { return {}; }
  drivers::Next next(drivers::StereoFrame& f, std::chrono::milliseconds timeout) override {
    if (n_ == static_cast<uint64_t>(stall_after_) && stall_end_ns_ == 0) {
      stall_end_ns_ = rt::monotonicNs() + std::chrono::nanoseconds(stall_).count();
      return drivers::Next::kFault;  // the device went away
    }
    if (stall_end_ns_ != 0 && rt::monotonicNs() < stall_end_ns_) {
      std::this_thread::sleep_for(timeout);
      return drivers::Next::kTimeout;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));  // 20 Hz
    const auto& p = frames_[n_.load() % frames_.size()];
    p.first.copyTo(f.left);
    p.second.copyTo(f.right);
    f.trigger_seq = n_++;
    f.t_left_ns = f.t_right_ns = rt::monotonicNs();  // the exposure
    // The same instant on the system clock, read by the test's own call.
    timespec real{};
    clock_gettime(CLOCK_REALTIME, &real);
    exposure_realtime_[f.trigger_seq % exposure_realtime_.size()] =
        int64_t{real.tv_sec} * 1'000'000'000 + real.tv_nsec;
    return drivers::Next::kFrame;
  }
  void stop() override {}
  std::string lastFault() const override { return "/dev/video0: ENODEV (unplugged)"; }
  drivers::SourceCounters counters() const override { return {n_.load(), 0, 0, 0}; }
  std::string triggerState() const override { return "test"; }
  // CLOCK_REALTIME read right after the exposure's monotonic stamp of frame `seq`.
  [[nodiscard]] int64_t exposureRealtime(uint64_t seq) const {
    return exposure_realtime_[seq % exposure_realtime_.size()];
  }

 private:
  std::array<std::atomic<int64_t>, 4096> exposure_realtime_{};
  std::vector<std::pair<cv::Mat, cv::Mat>> frames_;
  vision::StereoRig rig_;
  int stall_after_;
  std::chrono::milliseconds stall_;
  std::atomic<uint64_t> n_{0};
  int64_t stall_end_ns_ = 0;
};

// The first `n` pairs of the 60 s cortex case (supersample 1) and its rig.
struct RenderedCortex {
  vision::StereoRig rig;
  std::vector<std::pair<cv::Mat, cv::Mat>> frames;
};
vision::Result<RenderedCortex> renderCortex(int n) {
  auto spec = sim::loadScene(std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-60s.toml");
  if (!spec) return std::unexpected(spec.error());
  auto rig = vision::loadRig(spec->rig_path);
  if (!rig) return std::unexpected(rig.error());
  spec->supersample = 1;
  sim::StereoSimulator s(*spec, *rig);
  RenderedCortex r{*rig, std::vector<std::pair<cv::Mat, cv::Mat>>(static_cast<size_t>(n))};
  for (size_t i = 0; i < r.frames.size(); ++i)
    s.render(static_cast<int>(i), r.frames[i].first, r.frames[i].second);
  return r;
}

// A pipeline config for the tests: 20 Hz, no real-time policy, no memory lock.
DaemonConfig testConfig(const std::string& rig_id) {
  DaemonConfig config;
  config.rig_id = rig_id;
  config.fps = 20;
  config.lock_memory = false;
  config.capture = config.track = config.publish = {0, -1};
  // The dense field off: these tests judge the stages' heartbeats (1 s), and under qemu-aarch64
  // the field's set-up at the first pair (its bases, ~10 ms natively) took the publish stage
  // past it ("starting fault ok ..."). The field through the daemon: output_e2e_test.
  config.field.enabled = false;
  // The preview off for the same reason: its normal-priority thread shares the cores with the
  // stages here (no real-time policy). The preview through the daemon: ros2_output_test.
  config.preview.enabled = false;
  return config;
}

TEST(Pipeline, ASourceThatStallsAndComesBackIsDegradedThenOk) {
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto scene = renderCortex(4);
  ASSERT_TRUE(scene) << scene.error().message;
  const auto& [rig, frames] = *scene;

  DaemonConfig config = testConfig("rig-stall");
  auto p = dds::Participant::create(78);
  ASSERT_TRUE(p) << p.error().message;
  auto health = dds::Reader::create(*p, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                                    dds::Profile::kTransientLocal);
  ASSERT_TRUE(health);
  Pipeline pipeline(
      config, std::make_unique<StallingSource>(frames, rig, 40, std::chrono::milliseconds(2500)),
      *p);
  auto started = pipeline.start();
  ASSERT_TRUE(started) << started.error().message;
  const Notifier notifier;  // no NOTIFY_SOCKET: no-op
  std::vector<State> states;
  std::string degraded_text;
  pulsetrack_msgs_msg_dds__Health_ h{};
  uint64_t tracked_before = 0;
  for (int k = 0; k < 70; ++k) {  // 7 s
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    const State st = pipeline.health(notifier);
    // Judged from the first ok on: the stall comes after it. A start under qemu next to another
    // emulated test may take a stage past its 1 s heartbeat at the first pair ("starting fault
    // ok ..."); that is the start's verdict, not the stall's (the start: StampsAreTheExposure...).
    if (states.empty() && st != State::kOk) continue;
    if (states.empty() || states.back() != st) states.push_back(st);
    while (health->takeOne(&h, std::chrono::milliseconds(0))) {
      if (h.state == static_cast<uint8_t>(State::kDegraded)) degraded_text = h.last_error;
    }
    if (st == State::kDegraded) tracked_before = pipeline.tracked();
  }
  pipeline.stop();
  std::string seq;
  for (State st : states) seq += std::string(toString(st)) + " ";
  std::cout << "states: " << seq << "\ndegraded: " << degraded_text << "\n";
  // ok -> degraded (the stall) -> ok (frames again, tracked), never a fault.
  ASSERT_GE(states.size(), 3U) << seq;
  EXPECT_EQ(states.back(), State::kOk) << seq;
  EXPECT_NE(std::find(states.begin(), states.end(), State::kDegraded), states.end()) << seq;
  EXPECT_EQ(std::find(states.begin(), states.end(), State::kFault), states.end()) << seq;
  EXPECT_NE(degraded_text.find("no frame from the source for"), std::string::npos) << degraded_text;
  EXPECT_NE(degraded_text.find("ENODEV"), std::string::npos) << degraded_text;
  EXPECT_GT(pipeline.tracked(), tracked_before);  // tracking resumed
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
}

// The V4L2 source on the kernel emulation, the simulator's images in its buffers: a camera
// unplugged mid-stream makes health degraded naming the device, plugged back the daemon
// tracks again; the pairs stay whole.
TEST(Pipeline, AV4l2CameraUnpluggedAndPluggedBackIsReportedThenTrackedAgain) {
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto scene = renderCortex(4);
  ASSERT_TRUE(scene) << scene.error().message;
  const auto& [rig, frames] = *scene;
  test::FakeV4l2 io;
  io.period_ns = 50'000'000;  // 20 Hz
  const cv::Size size = rig.left.imageSize();
  for (const char* dev : {"/dev/video0", "/dev/video1"}) {
    auto& d = io.add(dev);
    d.width = size.width;
    d.height = size.height;
    const bool left = std::string(dev) == "/dev/video0";
    d.paint = [&frames, left, size](uint64_t k, uint8_t* data, uint32_t bpl) {
      const cv::Mat& img = left ? frames[k % 4].first : frames[k % 4].second;
      for (int y = 0; y < size.height; ++y)
        std::memcpy(data + static_cast<size_t>(y) * bpl, img.ptr(y),
                    static_cast<size_t>(size.width));
    };
  }
  drivers::V4l2StereoConfig vc;
  for (auto* c : {&vc.left, &vc.right}) {
    c->width = size.width;
    c->height = size.height;
  }
  vc.left.device = "/dev/video0";
  vc.right.device = "/dev/video1";
  vc.fps = 20;
  vc.reopen_ms = 200;
  DaemonConfig config = testConfig("rig-v4l2");
  auto p = dds::Participant::create(79);
  ASSERT_TRUE(p) << p.error().message;
  auto health = dds::Reader::create(*p, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                                    dds::Profile::kTransientLocal);
  ASSERT_TRUE(health);
  auto source = drivers::makeV4l2Source(io, vc, rig);
  ASSERT_TRUE(source->start());
  Pipeline pipeline(config, std::move(source), *p);
  ASSERT_TRUE(pipeline.start());
  const Notifier notifier;
  std::vector<State> states;
  std::string degraded_text, trigger_state;
  pulsetrack_msgs_msg_dds__Health_ h{};
  uint64_t tracked_unplugged = 0;
  for (int k = 0; k < 120; ++k) {  // 12 s
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    if (k == 40) io.unplug("/dev/video1");
    if (k == 70) {
      tracked_unplugged = pipeline.tracked();
      io.plug("/dev/video1");
    }
    const State st = pipeline.health(notifier);
    if (states.empty() || states.back() != st) states.push_back(st);
    while (health->takeOne(&h, std::chrono::milliseconds(0))) {
      if (h.state == static_cast<uint8_t>(State::kDegraded)) degraded_text = h.last_error;
      trigger_state = h.trigger_state;
    }
    if (k > 90 && st == State::kOk && pipeline.tracked() > tracked_unplugged + 20) break;
  }
  pipeline.stop();
  std::string seq;
  for (State st : states) seq += std::string(toString(st)) + " ";
  std::cout << "states: " << seq << "\ndegraded: " << degraded_text
            << "\ntrigger: " << trigger_state << "\n";
  EXPECT_EQ(states.back(), State::kOk) << seq;
  EXPECT_NE(std::find(states.begin(), states.end(), State::kDegraded), states.end()) << seq;
  EXPECT_NE(degraded_text.find("/dev/video1"), std::string::npos) << degraded_text;
  EXPECT_GT(pipeline.tracked(), tracked_unplugged + 20);  // tracking resumed
  EXPECT_NE(trigger_state.find("free-running"), std::string::npos) << trigger_state;
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
}

// Stamps: every features and deformation sample's header.stamp is its pair's exposure on the
// system clock, within 1 ms of CLOCK_REALTIME read at the exposure; health names the clock.
TEST(Pipeline, StampsAreTheExposureOnTheSystemClock) {
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto scene = renderCortex(4);
  ASSERT_TRUE(scene) << scene.error().message;
  const auto& [rig, frames] = *scene;
  DaemonConfig config = testConfig("rig-stamps");
  auto p = dds::Participant::create(84);
  ASSERT_TRUE(p) << p.error().message;
  auto features = dds::Reader::create(
      *p, dds::kFeaturesTopic, &pulsetrack_msgs_msg_dds__Features__desc, dds::Profile::kSensorData);
  auto deformation =
      dds::Reader::create(*p, dds::kDeformationTopic, &pulsetrack_msgs_msg_dds__Deformation__desc,
                          dds::Profile::kSensorData);
  auto health = dds::Reader::create(*p, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                                    dds::Profile::kTransientLocal);
  ASSERT_TRUE(features && deformation && health);
  auto owned =
      std::make_unique<StallingSource>(frames, rig, 1'000'000, std::chrono::milliseconds(0));
  const StallingSource* source = owned.get();
  Pipeline pipeline(config, std::move(owned), *p);
  ASSERT_TRUE(pipeline.start());
  const Notifier notifier;
  pulsetrack_msgs_msg_dds__Features_ f{};
  pulsetrack_msgs_msg_dds__Deformation_ d{};
  pulsetrack_msgs_msg_dds__Health_ h{};
  const auto ns = [](const builtin_interfaces_msg_dds__Time_& t) {
    return int64_t{t.sec} * 1'000'000'000 + t.nanosec;
  };
  int checked_f = 0, checked_d = 0, with_velocity = 0;
  double worst_ms = 0.0;
  std::string clock_state;
  for (int k = 0; k < 600 && (checked_f < 20 || checked_d < 20 || clock_state.empty()); ++k) {
    if (features->takeOne(&f, std::chrono::milliseconds(50))) {
      const double off_ms =
          static_cast<double>(ns(f.header.stamp) - source->exposureRealtime(f.frame)) * 1e-6;
      worst_ms = std::max(worst_ms, std::abs(off_ms));
      EXPECT_LT(std::abs(off_ms), 1.0) << "frame " << f.frame;
      ++checked_f;
    }
    while (deformation->takeOne(&d, std::chrono::milliseconds(0))) {
      EXPECT_LT(std::abs(ns(d.header.stamp) - source->exposureRealtime(d.frame)), 1'000'000);
      with_velocity += d.velocity_delay > 0.0 ? 1 : 0;  // not the signal's first sample
      ++checked_d;
    }
    if (k % 4 == 0) (void)pipeline.health(notifier);
    while (health->takeOne(&h, std::chrono::milliseconds(0))) clock_state = h.clock_state;
  }
  pipeline.stop();
  std::cout << checked_f << " features and " << checked_d
            << " deformation samples: stamp - CLOCK_REALTIME at the exposure, worst " << worst_ms
            << " ms; health: " << clock_state << "\n";
  EXPECT_GE(checked_f, 20);
  EXPECT_GE(checked_d, 20);
  EXPECT_GE(with_velocity, checked_d - 1);
  EXPECT_NE(clock_state.find("CLOCK_REALTIME"), std::string::npos) << clock_state;
  dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&d, &pulsetrack_msgs_msg_dds__Deformation__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
}

// A command sample's fields are a remote participant's: whatever they hold, the command is
// refused with a printable reason or is one the daemon can act on (fuzz/fuzz_command runs the
// same function on random samples; these are its findings and the cases around them).
TEST(CheckCommand, HostileFieldsAreRefusedPrintably) {
  const vision::StereoRig rig = sim::paperRig();
  pulsetrack_msgs_msg_dds__Command_ c{};
  const auto check = [&] { return checkCommand(c, "rig-a", "/or1", rig); };
  // Absent strings: no command.
  EXPECT_EQ(check().kind, CommandKind::kRefused);
  EXPECT_NE(check().refusal.find("unknown command"), std::string::npos);
  c.command = const_cast<char*>("start");
  EXPECT_EQ(check().kind, CommandKind::kStart);
  // Another rig's, with control characters and bytes above 127 in its id: quoted printably.
  char other[] = "rig\x1b[2J\xff\n";
  c.rig_id = other;
  auto refused = check();
  ASSERT_EQ(refused.kind, CommandKind::kRefused);
  for (const char ch : refused.refusal) EXPECT_TRUE(ch >= 32 && ch < 127) << refused.refusal;
  EXPECT_NE(refused.refusal.find("addressed to rig 'rig?[2J?"
                                 "?'"),
            std::string::npos)
      << refused.refusal;
  c.rig_id = nullptr;
  // ROIs whose corners overflow int (x + width past INT_MAX), negative sizes, NaN and huge
  // depths: refused, never accepted.
  c.command = const_cast<char*>("set_roi");
  const int good[4] = {400, 300, 400, 300};
  std::copy_n(good, 4, c.roi_left);
  std::copy_n(good, 4, c.roi_right);
  c.depth_tolerance_m = 0.02;
  ASSERT_EQ(check().kind, CommandKind::kSetRoi) << check().refusal;
  // A left ROI only (the right one all zero): the right ROI and the tolerance are found in the
  // next pair, so no depth is needed.
  std::fill_n(c.roi_right, 4, 0);
  c.depth_tolerance_m = 0.0;
  EXPECT_EQ(check().kind, CommandKind::kSetRoi) << check().refusal;
  EXPECT_EQ(check().roi.right, cv::Rect());
  std::copy_n(good, 4, c.roi_right);
  c.depth_tolerance_m = 0.02;
  for (const auto& bad :
       {std::array<int, 4>{INT_MAX, 0, INT_MAX, 300}, std::array<int, 4>{0, INT_MAX - 10, 400, 100},
        std::array<int, 4>{INT_MIN, INT_MIN, INT_MAX, INT_MAX},
        std::array<int, 4>{400, 300, -400, 300}}) {
    std::copy_n(bad.data(), 4, c.roi_left);
    EXPECT_EQ(check().kind, CommandKind::kRefused) << bad[0] << "," << bad[1];
  }
  std::copy_n(good, 4, c.roi_left);
  for (const double depth : {std::nan(""), 1e308, -0.02, 0.0, HUGE_VAL}) {
    c.depth_tolerance_m = depth;
    const auto r = check();
    EXPECT_EQ(r.kind, CommandKind::kRefused) << depth;
    EXPECT_NE(r.refusal.find("mm: must be in (0, 500]"), std::string::npos) << r.refusal;
  }
}

// The case: set_roi with a 40x40 ROI in the image's corner. Nothing is tracked there;
// health must not say ok, and must say why; a good ROI brings tracking back. An ROI outside the
// image is refused at the command with its reason.
TEST(Pipeline, AnRoiThatFindsNothingIsDegradedWithTheReasonOnHealth) {
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto scene = renderCortex(4);
  ASSERT_TRUE(scene) << scene.error().message;
  const auto& [rig, frames] = *scene;
  DaemonConfig config = testConfig("rig-roi");
  auto p = dds::Participant::create(85);
  ASSERT_TRUE(p) << p.error().message;
  auto health = dds::Reader::create(*p, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                                    dds::Profile::kTransientLocal);
  ASSERT_TRUE(health);
  Pipeline pipeline(
      config,
      std::make_unique<StallingSource>(frames, rig, 1'000'000, std::chrono::milliseconds(0)), *p);
  ASSERT_TRUE(pipeline.start());
  const Notifier notifier;
  pulsetrack_msgs_msg_dds__Health_ h{};
  const auto wait_for = [&](State want, int max_periods) {
    for (int k = 0; k < max_periods; ++k) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      if (pipeline.health(notifier) == want) {
        while (health->takeOne(&h, std::chrono::milliseconds(200))) {
          if (h.state == static_cast<uint8_t>(want)) return true;
        }
      }
    }
    return false;
  };
  ASSERT_TRUE(wait_for(State::kOk, 200));
  pulsetrack_msgs_msg_dds__Command_ c{};
  c.rig_id = const_cast<char*>("");
  c.request_id = 7;
  c.command = const_cast<char*>("set_roi");
  const int corner[4] = {10, 10, 40, 40};
  std::copy_n(corner, 4, c.roi_left);
  std::copy_n(corner, 4, c.roi_right);
  c.depth_tolerance_m = 0.02;
  EXPECT_EQ(pipeline.command(c), "");
  ASSERT_TRUE(wait_for(State::kDegraded, 200));
  const std::string tracking = h.tracking_state, last_error = h.last_error;
  std::cout << "health: " << tracking << " | " << last_error << "\n";
  EXPECT_NE(tracking.find("ROI 10,10 40x40"), std::string::npos) << tracking;
  EXPECT_NE(last_error.find("ROI 10,10 40x40"), std::string::npos) << last_error;
  // Outside the image: refused at once, with the reason.
  const int outside[4] = {1300, 1000, 100, 100};
  std::copy_n(outside, 4, c.roi_left);
  const std::string why = pipeline.command(c);
  EXPECT_NE(why.find("command 7 'set_roi' refused: left ROI 1300,1000 100x100: not inside"),
            std::string::npos)
      << why;
  // Another rig's command is refused, not obeyed.
  c.rig_id = const_cast<char*>("rig-other");
  c.command = const_cast<char*>("stop");
  EXPECT_NE(pipeline.command(c).find("addressed to rig 'rig-other'"), std::string::npos);
  // Back to the shipped ROI: tracking and ok again.
  c.rig_id = const_cast<char*>("rig-roi");
  c.command = const_cast<char*>("set_roi");
  const cv::Rect l = config.roi.left, r = config.roi.right;
  const int good_l[4] = {l.x, l.y, l.width, l.height}, good_r[4] = {r.x, r.y, r.width, r.height};
  std::copy_n(good_l, 4, c.roi_left);
  std::copy_n(good_r, 4, c.roi_right);
  EXPECT_EQ(pipeline.command(c), "");
  EXPECT_TRUE(wait_for(State::kOk, 200));
  pipeline.stop();
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
}

}  // namespace
}  // namespace pulsetrack::daemon
