#pragma once
// The cameras' preview hand-off: the capture stage offers each pair; at most every `period_ns`
// one is copied into a preallocated slot (the newest wins) for the preview stage, which scales,
// encodes and sends it off the real-time path. offer() allocates nothing, locks nothing and
// throws nothing (tests/vision/tracker_realtime_test.cpp proves it).

#include <atomic>
#include <cstdint>

#include "pulsetrack/drivers/source.hpp"
#include "pulsetrack/rt/latency_histogram.hpp"
#include "pulsetrack/rt/latest_slot.hpp"

namespace pulsetrack::daemon {

// A pair for the preview stage (full size, preallocated).
struct PreviewFrame {
  cv::Mat left, right;
  uint64_t trigger_seq = 0;
  int64_t t_left_ns = 0, t_right_ns = 0;
};

class PreviewTap {
 public:
  // Slots of `size` (8-bit, one channel) allocated here; period_ns <= 0: never taken.
  PreviewTap(cv::Size size, int64_t period_ns);

  // The capture stage: copies the pair when the next copy is due by its exposure stamp (one per
  // period on average, never two within 0.9 periods); `now_ns` (monotonic, when the source
  // handed it over) times the copy. True when it did.
  bool offer(const drivers::StereoFrame& pair, int64_t now_ns) noexcept;
  // The preview stage: the newest copy, or nullptr; valid until the next take().
  const PreviewFrame* take() noexcept { return slots_.take(); }
  // Bumped after each copy (wait on it with std::atomic::wait).
  std::atomic<uint64_t>& sequence() noexcept { return seq_; }
  // Copies the preview stage never took (a newer one came while it was busy).
  [[nodiscard]] uint64_t drops() const noexcept { return slots_.drops(); }
  // The copies' time in the capture stage.
  [[nodiscard]] const rt::LatencyHistogram& copyLatency() const noexcept { return copy_lat_; }

 private:
  rt::LatestSlot<PreviewFrame> slots_;
  int64_t period_ns_ = 0, next_ns_ = 0;  // next_ns_: when the next copy is due
  bool any_ = false;
  std::atomic<uint64_t> seq_{0};
  rt::LatencyHistogram copy_lat_;
};

}  // namespace pulsetrack::daemon
