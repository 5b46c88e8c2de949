#include "pulsetrack/rt/thread_policy.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>

#include <cerrno>
#include <cstring>
#include <string>

namespace pulsetrack::rt {

namespace {
std::string reason(const char* what, int err) {
  std::string s = std::string(what) + ": " + std::strerror(err);
  if (err == EPERM) s += " (needs CAP_SYS_NICE / CAP_IPC_LOCK or root; running without it)";
  return s;
}
}  // namespace

std::string applyThreadPolicy(const char* name, const ThreadPolicy& policy) {
  std::string out;
  char short_name[16] = {};
  std::strncpy(short_name, name, sizeof short_name - 1);
  pthread_setname_np(pthread_self(), short_name);
  if (policy.cpu >= 0) {
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(static_cast<size_t>(policy.cpu), &set);
    if (const int e = pthread_setaffinity_np(pthread_self(), sizeof set, &set); e != 0)
      out += reason(("affinity to CPU " + std::to_string(policy.cpu)).c_str(), e);
  }
  if (policy.fifo_priority > 0) {
    sched_param p{};
    p.sched_priority = policy.fifo_priority;
    if (const int e = pthread_setschedparam(pthread_self(), SCHED_FIFO, &p); e != 0) {
      if (!out.empty()) out += "; ";
      out += reason(("SCHED_FIFO priority " + std::to_string(policy.fifo_priority)).c_str(), e);
    }
  }
  return out;
}

std::string lockMemory() {
  if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0) return reason("mlockall", errno);
  return {};
}

}  // namespace pulsetrack::rt
