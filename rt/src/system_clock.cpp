#include "pulsetrack/rt/system_clock.hpp"

#include <sys/timex.h>
#include <time.h>

#include <cstdlib>
#include <limits>

namespace pulsetrack::rt {

namespace {

int64_t nowNs(clockid_t id) noexcept {
  timespec ts{};
  clock_gettime(id, &ts);
  return int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

}  // namespace

ClockOffset measureRealtimeOffset() noexcept {
  ClockOffset best{0, std::numeric_limits<int64_t>::max()};
  for (int i = 0; i < 7; ++i) {
    const int64_t m0 = nowNs(CLOCK_MONOTONIC);
    const int64_t r = nowNs(CLOCK_REALTIME);
    const int64_t m1 = nowNs(CLOCK_MONOTONIC);
    const int64_t half = (m1 - m0) / 2;
    if (half < best.uncertainty_ns) best = {r - (m0 + half), half};
  }
  return best;
}

ClockSync systemClockSync() {
  timex tx{};
  tx.modes = 0;  // read only
  const int state = adjtimex(&tx);
  ClockSync s;
  if (state < 0) {
    s.text = "status unknown (adjtimex failed)";
    return s;
  }
  s.synchronized = state != TIME_ERROR && (tx.status & STA_UNSYNC) == 0;
  s.max_error_us = tx.maxerror;
  s.est_error_us = tx.esterror;
  const auto ms = [](int64_t us) { return std::to_string((us + 500) / 1000) + " ms"; };
  s.text = s.synchronized
               ? "synchronized (kernel NTP status), max error " + ms(s.max_error_us) +
                     ", estimated " + ms(s.est_error_us)
               : "NOT synchronized (no NTP/PTP discipline reported by the kernel: the stamps may "
                 "differ from other hosts' clocks)";
  return s;
}

int64_t SystemClock::remeasure(int64_t step_ns) noexcept {
  const ClockOffset o = measureRealtimeOffset();
  const int64_t old = offset_.exchange(o.offset_ns, std::memory_order_relaxed);
  if (!measured_) {
    measured_ = true;
    return 0;
  }
  const int64_t step = o.offset_ns - old;
  if (std::llabs(step) <= step_ns) return 0;
  steps_.fetch_add(1);
  return step;
}

}  // namespace pulsetrack::rt
