#include "pulsetrack/daemon/log.hpp"

#include <spdlog/pattern_formatter.h>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/sinks/systemd_sink.h>

#include <cstdlib>
#include <memory>
#include <mutex>

namespace pulsetrack::daemon::log {

namespace {

std::mutex g_mutex;
spdlog::sink_ptr g_sink;

spdlog::sink_ptr sink() {
  if (!g_sink) {
    auto s = std::make_shared<spdlog::sinks::stderr_sink_mt>();
    s->set_pattern("pulsetrackd[%n] %l: %v");
    g_sink = s;
  }
  return g_sink;
}

}  // namespace

void setup(bool force_stderr) {
  const std::lock_guard lock(g_mutex);
  if (!force_stderr && std::getenv("JOURNAL_STREAM") != nullptr) {
    // The journal keeps the priority and the identifier; the component goes in the message
    // (formatted, with no end-of-line: the journal has its own records).
    auto s = std::make_shared<spdlog::sinks::systemd_sink_mt>("pulsetrackd", true);
    s->set_formatter(std::make_unique<spdlog::pattern_formatter>(
        "[%n] %v", spdlog::pattern_time_type::local, std::string()));
    g_sink = s;
  } else {
    g_sink.reset();
    (void)sink();
  }
  spdlog::drop_all();
}

spdlog::logger& get(const char* component) {
  const std::lock_guard lock(g_mutex);
  if (auto l = spdlog::get(component)) return *l;
  auto l = std::make_shared<spdlog::logger>(component, sink());
  l->set_level(spdlog::level::info);
  l->flush_on(spdlog::level::info);
  spdlog::register_logger(l);
  return *l;
}

}  // namespace pulsetrack::daemon::log
