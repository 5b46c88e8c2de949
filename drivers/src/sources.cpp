#include <fmt/format.h>
#include <time.h>

#include <array>
#include <cmath>

#include "paired_frames.hpp"
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

// Within an injected outage, `since_start_ns` after the source started.
bool inOutage(const SimFaults& f, int64_t since_start_ns) {
  if (f.outage_every_s <= 0 || f.outage_s <= 0) return false;
  const double t = static_cast<double>(since_start_ns) * 1e-9;
  return t >= f.outage_every_s && std::fmod(t, f.outage_every_s) < f.outage_s;
}

bool every(int n, uint64_t k) {
  return n > 0 && k % static_cast<uint64_t>(n) == static_cast<uint64_t>(n - 1);
}

class SimSource final : public CameraSource {
 public:
  SimSource(const sim::SceneSpec& scene, const vision::StereoRig& rig, double fps, bool loop,
            const SimFaults& faults)
      : sim_(scene, rig),
        period_ns_(static_cast<int64_t>(1e9 / fps)),
        fps_(fps),
        loop_(loop),
        faults_(faults),
        pairs_(period_ns_, nullptr) {}
  std::string name() const override { return "sim " + sim_.spec().name; }
  const vision::StereoRig& rig() const override { return sim_.rig(); }
  vision::Result<void> start() override {
    t0_ns_ = rt::monotonicNs();
    index_ = 0;
    (void)pairs_.reset();
    return {};
  }
  Next next(StereoFrame& frame, std::chrono::milliseconds timeout) override {
    const int64_t until = rt::monotonicNs() + std::chrono::nanoseconds(timeout).count();
    const auto count = static_cast<uint64_t>(sim_.frameCount());
    for (;;) {
      int64_t due = t0_ns_ + static_cast<int64_t>(index_) * period_ns_;
      const int64_t now = rt::monotonicNs();
      outage_ = inOutage(faults_, now - t0_ns_);
      // The cameras are gone: their pulses pass with no frame. A pulse from before the outage
      // that a slow consumer has not taken yet is still gone through below (a late pair).
      if (outage_ && (due > now || inOutage(faults_, due - t0_ns_))) {
        while (due <= now && inOutage(faults_, due - t0_ns_))
          due = t0_ns_ + static_cast<int64_t>(++index_) * period_ns_;
        if (due > now) return Next::kFault;
        // A consumer slower than the outages' period (qemu): a pulse between two outages
        // exposed both cameras; it goes through below as a late pair (an overrun), not missing.
        continue;
      }
      if (due > until) return Next::kTimeout;
      if (!loop_ && index_ >= count) return Next::kEnd;
      if (inOutage(faults_, due - t0_ns_)) {
        if (due <= now) {  // a pulse of an outage that ended meanwhile
          ++index_;
        } else {
          sleepUntil(due);  // the outage starts with this pulse
        }
        continue;
      }
      // Rendering took longer than a period: the cameras exposed on every pulse, but a newer
      // pair is already due, so this one is not taken (newest wins, counted as an overrun).
      const bool late = due + period_ns_ <= now;
      if (!late) sleepUntil(due);
      const uint64_t k = index_++;
      if (every(faults_.missing_trigger_every, k)) continue;  // the pulse never fired
      const int slot = static_cast<int>(k % count);           // the scene frame it shows
      if (every(faults_.left_drop_every, k)) {
        ++seq_[0];  // the driver dropped it: a gap in the left counter
      } else {
        pairs_.offer(0, {seq_[0]++, due, slot});
      }
      if (every(faults_.right_miss_every, k)) continue;
      const PairEvents ev = pairs_.offer(1, {seq_[1]++, due, slot});
      if (!ev.paired) continue;
      if (late) {
        pairs_.overrun();
        continue;
      }
      sim_.render(ev.left.slot, frame.left, frame.right);
      pairs_.emit(ev, frame);
      return Next::kFrame;
    }
  }
  void stop() override {}
  std::string lastFault() const override { return outage_ ? kInjectedOutage : ""; }
  SourceCounters counters() const override { return pairs_.counters(); }
  std::string triggerState() const override { return fmt::format("software {:g} Hz", fps_); }

 private:
  sim::StereoSimulator sim_;
  int64_t period_ns_;
  double fps_;
  bool loop_;
  SimFaults faults_;
  PairedFrames pairs_;
  int64_t t0_ns_ = 0;
  uint64_t index_ = 0;
  bool outage_ = false;
  std::array<uint64_t, 2> seq_{};
};

class ReplaySource final : public CameraSource {
 public:
  ReplaySource(record::Reader reader, const ReplayOptions& o, const SimFaults& faults)
      : reader_(std::move(reader)), o_(o), faults_(faults) {}
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
    using P = ReplayOptions::Pace;
    if (o_.pace == P::kRate && t0_rate_ns_ != 0) {
      // Injected faults, as a live camera on a trigger shows them (pulses pass meanwhile).
      const int64_t until = rt::monotonicNs() + std::chrono::nanoseconds(timeout).count();
      for (;;) {
        const int64_t now = rt::monotonicNs();
        outage_ = inOutage(faults_, now - t0_rate_ns_);
        if (outage_) return Next::kFault;
        if (every(faults_.missing_trigger_every, handed_)) {
          skipPulses(1);
          continue;
        }
        const int64_t due = rateDue(handed_);
        if (!inOutage(faults_, due - t0_rate_ns_)) break;
        if (due <= now) {  // a pulse of an outage that ended meanwhile
          skipPulses(1);
          continue;
        }
        if (due > until) return Next::kTimeout;
        sleepUntil(due);  // the outage starts with this pulse
      }
    }
    if (index_ >= reader_.size()) {
      if (!o_.loop) return Next::kEnd;
      loops_ += reader_.meta(reader_.size() - 1).trigger_seq + 1;  // the sequence goes on
      index_ = 0;
      t0_ns_ = rt::monotonicNs();
    }
    const record::FrameMeta& m = reader_.meta(index_);
    int64_t due = 0;
    if (o_.pace == P::kRecorded) due = t0_ns_ + (m.t_left_ns - base_ns_);
    if (o_.pace == P::kRate) {
      due = t0_rate_ns_ == 0 ? (t0_rate_ns_ = rt::monotonicNs()) : rateDue(handed_);
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
    if (o_.pace != P::kRate && counters_.frames > 0 && index_ > 0 && m.trigger_seq > last_seq_ + 1)
      counters_.missing_triggers += m.trigger_seq - last_seq_ - 1;
    last_seq_ = m.trigger_seq;
    if (o_.pace == P::kRate) {
      // Stamped with the trigger's time (due), as a hardware-triggered camera stamps the
      // exposure, not the moment the copy ended: a slow first copy must not shorten the period.
      frame.trigger_seq = handed_;
      frame.t_left_ns = frame.t_right_ns = due;
    } else {
      frame.trigger_seq = m.trigger_seq + loops_;
      frame.t_left_ns = m.t_left_ns;
      frame.t_right_ns = m.t_right_ns;
    }
    ++index_;
    ++handed_;
    ++counters_.frames;
    shared_.store(counters_);
    return Next::kFrame;
  }
  void stop() override {}
  std::string lastFault() const override { return outage_ ? kInjectedOutage : fault_; }
  SourceCounters counters() const override { return shared_.load(); }
  std::string triggerState() const override {
    return o_.pace == ReplayOptions::Pace::kRate ? fmt::format("replay at {:g} Hz", o_.fps)
                                                 : "recorded";
  }

 private:
  [[nodiscard]] int64_t rateDue(uint64_t pulse) const {
    return t0_rate_ns_ + static_cast<int64_t>(static_cast<double>(pulse) * 1e9 / o_.fps);
  }
  // Pulses that gave no frame (at a rate): counted, and the recording moves on as time does.
  void skipPulses(uint64_t n) {
    handed_ += n;
    counters_.missing_triggers += n;
    index_ = o_.loop ? (index_ + n) % reader_.size() : std::min(index_ + n, reader_.size());
    shared_.store(counters_);
  }

  record::Reader reader_;
  ReplayOptions o_;
  SimFaults faults_;
  bool outage_ = false;
  std::vector<std::pair<cv::Mat, cv::Mat>> frames_;
  size_t index_ = 0;
  uint64_t loops_ = 0, handed_ = 0;
  int64_t t0_ns_ = 0, base_ns_ = 0, t0_rate_ns_ = 0;
  uint64_t last_seq_ = 0;
  std::string fault_;
  SourceCounters counters_;
  SharedCounters shared_;
};

}  // namespace

std::unique_ptr<CameraSource> makeSimSource(const sim::SceneSpec& scene,
                                            const vision::StereoRig& rig, double fps, bool loop,
                                            const SimFaults& faults) {
  return std::make_unique<SimSource>(scene, rig, fps, loop, faults);
}

vision::Result<std::unique_ptr<CameraSource>> makeReplaySource(
    const std::filesystem::path& recording, const ReplayOptions& options, const SimFaults& faults) {
  auto r = record::Reader::open(recording);
  if (!r) return std::unexpected(r.error());
  if (r->size() == 0)
    return vision::fail(
        fmt::format("{}: the recording holds no complete frame", recording.string()));
  if (!(options.fps > 0.0)) return vision::fail("replay: the rate must be positive");
  if (faults.left_drop_every + faults.right_miss_every > 0 ||
      ((faults.missing_trigger_every > 0 || faults.outage_every_s > 0) &&
       options.pace != ReplayOptions::Pace::kRate))
    return vision::fail(
        "replay: only missing triggers and outages can be injected, and only at a rate");
  auto src = std::make_unique<ReplaySource>(std::move(*r), options, faults);
  if (options.preload) {
    if (auto ok = src->preload(); !ok) return std::unexpected(ok.error());
  }
  return std::unique_ptr<CameraSource>(std::move(src));
}

}  // namespace pulsetrack::drivers
