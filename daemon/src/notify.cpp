#include "pulsetrack/daemon/notify.hpp"

#include <systemd/sd-daemon.h>

namespace pulsetrack::daemon {

Notifier::Notifier() {
  uint64_t usec = 0;
  if (sd_watchdog_enabled(0, &usec) > 0) interval_ = std::chrono::microseconds(usec / 2);
}

void Notifier::ready() const { sd_notify(0, "READY=1"); }

void Notifier::status(const std::string& line) const { sd_notify(0, ("STATUS=" + line).c_str()); }

void Notifier::stopping() const { sd_notify(0, "STOPPING=1"); }

bool Notifier::pingIfHealthy(std::span<const rt::Heartbeat* const> stages,
                             std::chrono::nanoseconds max_age) const {
  const int64_t now = rt::monotonicNs();
  for (const rt::Heartbeat* h : stages) {
    if (!h->alive(now, max_age.count())) return false;
  }
  sd_notify(0, "WATCHDOG=1");
  return true;
}

}  // namespace pulsetrack::daemon
