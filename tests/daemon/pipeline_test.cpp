// The pipeline in process, with a camera source that stalls and comes back (a fault, then
// silence, then frames): health goes degraded naming the fault and the silence, the stages keep
// beating (no watchdog restart for a camera problem), and tracking resumes.

#include "pulsetrack/daemon/pipeline.hpp"

#include <gtest/gtest.h>

#include <thread>

#include "drivers/fake_v4l2.hpp"
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
    f.t_left_ns = f.t_right_ns = rt::monotonicNs();
    return drivers::Next::kFrame;
  }
  void stop() override {}
  std::string lastFault() const override { return "/dev/video0: ENODEV (unplugged)"; }
  drivers::SourceCounters counters() const override { return {n_.load(), 0, 0, 0}; }
  std::string triggerState() const override { return "test"; }

 private:
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

TEST(Pipeline, ASourceThatStallsAndComesBackIsDegradedThenOk) {
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto scene = renderCortex(4);
  ASSERT_TRUE(scene) << scene.error().message;
  const auto& [rig, frames] = *scene;

  DaemonConfig config;
  config.rig_id = "rig-stall";
  config.fps = 20;
  config.lock_memory = false;
  config.capture = config.track = config.publish = {0, -1};
  auto p = dds::Participant::create(78);
  ASSERT_TRUE(p) << p.error().message;
  auto health = dds::Reader::create(*p, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                                    dds::Profile::kTransientLocal);
  ASSERT_TRUE(health);
  Pipeline pipeline(
      config, std::make_unique<StallingSource>(frames, rig, 20, std::chrono::milliseconds(2500)),
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
  // starting -> ok -> degraded (the stall) -> ok (frames again, tracked).
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
  DaemonConfig config;
  config.rig_id = "rig-v4l2";
  config.fps = 20;
  config.lock_memory = false;
  config.capture = config.track = config.publish = {0, -1};
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

}  // namespace
}  // namespace pulsetrack::daemon
