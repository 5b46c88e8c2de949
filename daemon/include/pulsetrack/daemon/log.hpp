#pragma once
// pulsetrackd's logging: one spdlog logger per component ("config", "source", "pipeline",
// "dds", "clock", "recorder", "systemd"), all to one sink: the journal when systemd started the
// daemon (JOURNAL_STREAM set: priorities and the component as SYSLOG_IDENTIFIER-style field
// survive), stderr otherwise. Never called on the per-frame path.

#include <spdlog/spdlog.h>

namespace pulsetrack::daemon::log {

// Sets the sink; call once at start. `force_stderr`: tests and --check-config.
void setup(bool force_stderr = false);
// The component's logger (created on first use, with the sink chosen by setup()).
spdlog::logger& get(const char* component);

}  // namespace pulsetrack::daemon::log
