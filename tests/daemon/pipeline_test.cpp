// The pipeline in process, with a camera source that stalls and comes back (a fault, then
// silence, then frames): health goes degraded naming the fault and the silence, the stages keep
// beating (no watchdog restart for a camera problem), and tracking resumes.

#include "pulsetrack/daemon/pipeline.hpp"

#include <gtest/gtest.h>

#include <thread>

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

TEST(Pipeline, ASourceThatStallsAndComesBackIsDegradedThenOk) {
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto spec = sim::loadScene(std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-60s.toml");
  ASSERT_TRUE(spec);
  auto rig = vision::loadRig(spec->rig_path);
  ASSERT_TRUE(rig);
  spec->supersample = 1;
  sim::StereoSimulator s(*spec, *rig);
  std::vector<std::pair<cv::Mat, cv::Mat>> frames(4);
  for (int i = 0; i < 4; ++i)
    s.render(i, frames[static_cast<size_t>(i)].first, frames[static_cast<size_t>(i)].second);

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
      config, std::make_unique<StallingSource>(frames, *rig, 20, std::chrono::milliseconds(2500)),
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

}  // namespace
}  // namespace pulsetrack::daemon
