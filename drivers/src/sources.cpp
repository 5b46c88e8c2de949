#include <fmt/format.h>
#include <time.h>

#include "pulsetrack/drivers/source.hpp"
#include "pulsetrack/rt/heartbeat.hpp"

namespace pulsetrack::drivers {

namespace {

void sleepUntil(int64_t t_ns) {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(t_ns / 1'000'000'000);
  ts.tv_nsec = static_cast<long>(t_ns % 1'000'000'000);
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

class SimSource final : public CameraSource {
 public:
  SimSource(const sim::SceneSpec& scene, const vision::StereoRig& rig, double fps, bool loop)
      : sim_(scene, rig), period_ns_(static_cast<int64_t>(1e9 / fps)), loop_(loop) {}
  std::string name() const override { return "sim " + sim_.spec().name; }
  const vision::StereoRig& rig() const override { return sim_.rig(); }
  vision::Result<void> start() override {
    t0_ns_ = rt::monotonicNs();
    index_ = 0;
    return {};
  }
  Next next(StereoFrame& frame, std::chrono::milliseconds timeout) override {
    int64_t due = t0_ns_ + static_cast<int64_t>(index_) * period_ns_;
    const int64_t now = rt::monotonicNs();
    if (due > now + std::chrono::nanoseconds(timeout).count()) return Next::kTimeout;
    if (due < now - period_ns_) {
      // Rendering took longer than a period: those triggers fired with no frame.
      const auto late = static_cast<uint64_t>((now - due) / period_ns_);
      counters_.missing_triggers += late;
      index_ += late;
      due = t0_ns_ + static_cast<int64_t>(index_) * period_ns_;
    }
    const int count = sim_.frameCount();
    if (!loop_ && index_ >= static_cast<uint64_t>(count)) return Next::kEnd;
    sleepUntil(due);
    sim_.render(static_cast<int>(index_ % static_cast<uint64_t>(count)), frame.left, frame.right);
    frame.trigger_seq = index_;
    frame.t_left_ns = frame.t_right_ns = due;
    ++index_;
    ++counters_.frames;
    return Next::kFrame;
  }
  void stop() override {}
  std::string lastFault() const override { return {}; }
  SourceCounters counters() const override { return counters_; }

 private:
  sim::StereoSimulator sim_;
  int64_t period_ns_;
  bool loop_;
  int64_t t0_ns_ = 0;
  uint64_t index_ = 0;
  SourceCounters counters_;
};

class ReplaySource final : public CameraSource {
 public:
  ReplaySource(record::Reader reader, bool realtime, bool loop)
      : reader_(std::move(reader)), realtime_(realtime), loop_(loop) {}
  std::string name() const override { return "replay " + reader_.dir().string(); }
  const vision::StereoRig& rig() const override { return reader_.rig(); }
  vision::Result<void> start() override {
    index_ = 0;
    t0_ns_ = rt::monotonicNs();
    base_ns_ = reader_.size() > 0 ? reader_.meta(0).t_left_ns : 0;
    return {};
  }
  Next next(StereoFrame& frame, std::chrono::milliseconds timeout) override {
    if (index_ >= reader_.size()) {
      if (!loop_ || reader_.size() == 0) return Next::kEnd;
      start();
    }
    const record::FrameMeta& m = reader_.meta(index_);
    if (realtime_) {
      const int64_t due = t0_ns_ + (m.t_left_ns - base_ns_);
      if (due > rt::monotonicNs() + std::chrono::nanoseconds(timeout).count())
        return Next::kTimeout;
      sleepUntil(due);
    }
    if (auto ok = reader_.read(index_, frame.left, frame.right); !ok) {
      fault_ = ok.error().message;
      return Next::kFault;
    }
    if (counters_.frames > 0 && m.trigger_seq > last_seq_ + 1)
      counters_.missing_triggers += m.trigger_seq - last_seq_ - 1;
    last_seq_ = m.trigger_seq;
    frame.trigger_seq = m.trigger_seq;
    frame.t_left_ns = m.t_left_ns;
    frame.t_right_ns = m.t_right_ns;
    ++index_;
    ++counters_.frames;
    return Next::kFrame;
  }
  void stop() override {}
  std::string lastFault() const override { return fault_; }
  SourceCounters counters() const override { return counters_; }

 private:
  record::Reader reader_;
  bool realtime_, loop_;
  size_t index_ = 0;
  int64_t t0_ns_ = 0, base_ns_ = 0;
  uint64_t last_seq_ = 0;
  std::string fault_;
  SourceCounters counters_;
};

}  // namespace

std::unique_ptr<CameraSource> makeSimSource(const sim::SceneSpec& scene,
                                            const vision::StereoRig& rig, double fps, bool loop) {
  return std::make_unique<SimSource>(scene, rig, fps, loop);
}

vision::Result<std::unique_ptr<CameraSource>> makeReplaySource(
    const std::filesystem::path& recording, bool realtime, bool loop) {
  auto r = record::Reader::open(recording);
  if (!r) return std::unexpected(r.error());
  if (r->size() == 0)
    return vision::fail(
        fmt::format("{}: the recording holds no complete frame", recording.string()));
  return std::unique_ptr<CameraSource>(
      std::make_unique<ReplaySource>(std::move(*r), realtime, loop));
}

}  // namespace pulsetrack::drivers
