#pragma once
// The system clock for stamps. The pipeline keeps CLOCK_MONOTONIC (latency, pairing: it never
// steps); what leaves the appliance is stamped on CLOCK_REALTIME, which ROS 2, tf2 and every
// other host on the OR network use. The offset between the two is measured at run time and
// re-measured periodically (off the real-time path): CLOCK_MONOTONIC is slewed with the system
// clock but never stepped, so the offset changes only when the system clock is stepped (NTP or
// PTP setting it, an operator's `date`), and such a step is counted and reported, not smeared.

#include <atomic>
#include <cstdint>
#include <string>

namespace pulsetrack::rt {

// CLOCK_REALTIME - CLOCK_MONOTONIC from the tightest of several bracketed reads.
struct ClockOffset {
  int64_t offset_ns = 0;
  int64_t uncertainty_ns = 0;  // half the tightest bracket
};
ClockOffset measureRealtimeOffset() noexcept;

// What the kernel says about the system clock's discipline (adjtimex, read only): NTP daemons
// (chrony, ntpd, systemd-timesyncd) clear STA_UNSYNC and set the error bounds while they keep
// the clock synchronized; a PTP setup (phc2sys) is reported the same way when it does so.
struct ClockSync {
  bool synchronized = false;
  int64_t max_error_us = 0;
  int64_t est_error_us = 0;
  std::string text;  // "synchronized (kernel NTP status), max error 12 ms" / "NOT synchronized ..."
};
ClockSync systemClockSync();

class SystemClock {
 public:
  SystemClock() { (void)remeasure(); }
  // Measures the offset again; returns the step (ns) when it moved by more than `step_ns` since
  // the last measurement (and counts it), else 0. Call from one thread at a time.
  int64_t remeasure(int64_t step_ns = 100'000) noexcept;
  // A monotonic time on the system clock (any thread, no lock).
  [[nodiscard]] int64_t toRealtime(int64_t monotonic_ns) const noexcept {
    return monotonic_ns + offset_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] int64_t offsetNs() const noexcept { return offset_.load(); }
  [[nodiscard]] uint64_t steps() const noexcept { return steps_.load(); }

 private:
  std::atomic<int64_t> offset_{0};
  std::atomic<uint64_t> steps_{0};
  bool measured_ = false;
};

}  // namespace pulsetrack::rt
