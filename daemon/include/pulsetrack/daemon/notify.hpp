#pragma once
// systemd's notify protocol through libsystemd (sd_notify): READY=1 after the first tracked
// pair, WATCHDOG=1 only while every stage beats on time, STATUS= one line. Without
// NOTIFY_SOCKET (not started by systemd) every call is a no-op.

#include <chrono>
#include <span>
#include <string>

#include "pulsetrack/rt/heartbeat.hpp"

namespace pulsetrack::daemon {

class Notifier {
 public:
  Notifier();
  void ready() const;
  void status(const std::string& line) const;
  void stopping() const;
  // The interval to ping at (half of WatchdogSec), zero when the watchdog is off.
  [[nodiscard]] std::chrono::microseconds watchdogInterval() const { return interval_; }
  // Pings the watchdog when every heartbeat is at most `max_age` old; returns whether it did.
  bool pingIfHealthy(std::span<const rt::Heartbeat* const> stages,
                     std::chrono::nanoseconds max_age) const;

 private:
  std::chrono::microseconds interval_{0};
};

}  // namespace pulsetrack::daemon
