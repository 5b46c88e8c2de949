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
  ReplaySource(record::Reader reader, const ReplayOptions& o) : reader_(std::move(reader)), o_(o) {}
  vision::Result<void> preload() {
    frames_.resize(reader_.size());
    for (size_t i = 0; i < reader_.size(); ++i) {
      if (auto ok = reader_.read(i, frames_[i].first, frames_[i].second); !ok) return ok;
    }
    return {};
  }
  std::string name() const override { return "replay " + reader_.dir().string(); }
  const vision::StereoRig& rig() const override { return reader_.rig(); }
  vision::Result<void> start() override {
    index_ = 0;
    t0_ns_ = rt::monotonicNs();
    base_ns_ = reader_.meta(0).t_left_ns;
    return {};
  }
  Next next(StereoFrame& frame, std::chrono::milliseconds timeout) override {
    if (index_ >= reader_.size()) {
      if (!o_.loop) return Next::kEnd;
      loops_ += reader_.meta(reader_.size() - 1).trigger_seq + 1;  // the sequence goes on
      index_ = 0;
      t0_ns_ = rt::monotonicNs();
    }
    const record::FrameMeta& m = reader_.meta(index_);
    int64_t due = 0;
    using P = ReplayOptions::Pace;
    if (o_.pace == P::kRecorded) due = t0_ns_ + (m.t_left_ns - base_ns_);
    if (o_.pace == P::kRate) {
      due = t0_rate_ns_ == 0
                ? (t0_rate_ns_ = rt::monotonicNs())
                : t0_rate_ns_ + static_cast<int64_t>(static_cast<double>(handed_) * 1e9 / o_.fps);
    }
    if (due > rt::monotonicNs() + std::chrono::nanoseconds(timeout).count()) return Next::kTimeout;
    if (due > 0) sleepUntil(due);
    if (o_.preload) {
      frames_[index_].first.copyTo(frame.left);
      frames_[index_].second.copyTo(frame.right);
    } else if (auto ok = reader_.read(index_, frame.left, frame.right); !ok) {
      fault_ = ok.error().message;
      return Next::kFault;
    }
    if (counters_.frames > 0 && index_ > 0 && m.trigger_seq > last_seq_ + 1)
      counters_.missing_triggers += m.trigger_seq - last_seq_ - 1;
    last_seq_ = m.trigger_seq;
    if (o_.pace == P::kRate) {
      frame.trigger_seq = handed_;
      frame.t_left_ns = frame.t_right_ns = rt::monotonicNs();
    } else {
      frame.trigger_seq = m.trigger_seq + loops_;
      frame.t_left_ns = m.t_left_ns;
      frame.t_right_ns = m.t_right_ns;
    }
    ++index_;
    ++handed_;
    ++counters_.frames;
    return Next::kFrame;
  }
  void stop() override {}
  std::string lastFault() const override { return fault_; }
  SourceCounters counters() const override { return counters_; }

 private:
  record::Reader reader_;
  ReplayOptions o_;
  std::vector<std::pair<cv::Mat, cv::Mat>> frames_;
  size_t index_ = 0;
  uint64_t loops_ = 0, handed_ = 0;
  int64_t t0_ns_ = 0, base_ns_ = 0, t0_rate_ns_ = 0;
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
    const std::filesystem::path& recording, const ReplayOptions& options) {
  auto r = record::Reader::open(recording);
  if (!r) return std::unexpected(r.error());
  if (r->size() == 0)
    return vision::fail(
        fmt::format("{}: the recording holds no complete frame", recording.string()));
  if (!(options.fps > 0.0)) return vision::fail("replay: the rate must be positive");
  auto src = std::make_unique<ReplaySource>(std::move(*r), options);
  if (options.preload) {
    if (auto ok = src->preload(); !ok) return std::unexpected(ok.error());
  }
  return std::unique_ptr<CameraSource>(std::move(src));
}

}  // namespace pulsetrack::drivers
