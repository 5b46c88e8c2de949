#pragma once
// What every two-camera source does with its cameras' frames (sim, V4L2, libcamera): offer them
// to the FramePairer, number a completed pair (the trigger box's pulse when there is one),
// stamp it, and keep the counters health reads. Buffer slots carry their camera:
// slot = camera * kSlotsPerCamera + the camera's buffer index.

#include <fmt/format.h>

#include <string>

#include "pulsetrack/drivers/pairing.hpp"
#include "pulsetrack/drivers/source.hpp"
#include "pulsetrack/drivers/trigger_box.hpp"

namespace pulsetrack::drivers {

class PairedFrames {
 public:
  static constexpr int kSlotsPerCamera = 1000;
  static int slot(int camera, int index) { return camera * kSlotsPerCamera + index; }
  static int camera(int slot) { return slot / kSlotsPerCamera; }
  static int index(int slot) { return slot % kSlotsPerCamera; }

  PairedFrames(int64_t period_ns, const TriggerBox* trigger)
      : period_ns_(period_ns), trigger_(trigger), pairer_({period_ns, 0}) {}

  PairEvents offer(int camera, const CameraStamp& stamp) { return pairer_.offer(camera, stamp); }
  PairEvents reset() { return pairer_.reset(); }

  // A completed pair into `frame`'s numbers and stamps (the images are the caller's).
  void emit(const PairEvents& ev, StereoFrame& frame) {
    frame.trigger_seq = ev.trigger_seq;
    if (trigger_ != nullptr) {
      if (const auto seq = trigger_->pulseNear(ev.left.t_ns, period_ns_ / 4))
        frame.trigger_seq = *seq;
    }
    frame.t_left_ns = ev.left.t_ns;
    frame.t_right_ns = ev.right.t_ns;
    ++frames_;
    publish();
  }
  // A pair the consumer did not take: a newer one was ready (newest wins).
  void overrun() {
    ++overruns_;
    publish();
  }

  [[nodiscard]] SourceCounters counters() const { return shared_.load(); }  // any thread
  // Health's trigger line for hardware cameras.
  [[nodiscard]] std::string triggerState(double fps) const {
    if (trigger_ != nullptr) return trigger_->state();
    return fmt::format(
        "free-running at {:g} Hz: no trigger box, the two cameras are only software-synchronized "
        "(pairs matched by timestamp)",
        fps);
  }

 private:
  void publish() {
    const PairerCounters& p = pairer_.counters();
    shared_.store(
        {frames_, p.missing_triggers, p.unpaired, p.dropped[0] + p.dropped[1], overruns_});
  }

  int64_t period_ns_;
  const TriggerBox* trigger_;
  FramePairer pairer_;
  uint64_t frames_ = 0, overruns_ = 0;
  SharedCounters shared_;
};

}  // namespace pulsetrack::drivers
