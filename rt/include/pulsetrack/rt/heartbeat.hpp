#pragma once
// A stage's heartbeat: the stage stores the monotonic time at every iteration (one relaxed
// store, no allocation); the health thread asks whether every stage beat recently. The systemd
// watchdog is pinged only while all of them are on time.

#include <atomic>
#include <chrono>
#include <cstdint>

namespace pulsetrack::rt {

inline int64_t monotonicNs() noexcept {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

class Heartbeat {
 public:
  void beat(int64_t now_ns = monotonicNs()) noexcept {
    last_ns_.store(now_ns, std::memory_order_relaxed);
  }
  // True when the last beat is at most `max_age_ns` old (false before the first beat).
  [[nodiscard]] bool alive(int64_t now_ns, int64_t max_age_ns) const noexcept {
    const int64_t last = last_ns_.load(std::memory_order_relaxed);
    return last != 0 && now_ns - last <= max_age_ns;
  }

 private:
  std::atomic<int64_t> last_ns_{0};
};

}  // namespace pulsetrack::rt
