#pragma once
// Thread set-up from the daemon's config: SCHED_FIFO priority, CPU affinity, locked memory.
// Each returns an empty string on success and a one-line reason otherwise (typically EPERM for
// an ordinary user): the caller says so once and runs on.

#include <string>

namespace pulsetrack::rt {

struct ThreadPolicy {
  int fifo_priority = 0;  // 1..99 for SCHED_FIFO; 0 leaves the default scheduler
  int cpu = -1;           // pin to this CPU; -1 leaves the affinity alone
};

// Applies `policy` to the calling thread and names it (at most 15 characters are kept).
std::string applyThreadPolicy(const char* name, const ThreadPolicy& policy);

// mlockall(MCL_CURRENT | MCL_FUTURE): no page faults on the per-frame path.
std::string lockMemory();

}  // namespace pulsetrack::rt
