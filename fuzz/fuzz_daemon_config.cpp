// libFuzzer: the daemon's TOML config (daemon/config: pulsetrackd and --check-config).
// Input: the file's text.

#include <string>

#include "pulsetrack/daemon/config.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  auto config = pulsetrack::daemon::parseDaemonConfig(text, "fuzz-pulsetrackd.toml");
  if (!config && config.error().message.find("fuzz-pulsetrackd.toml") == std::string::npos) {
    std::fprintf(stderr, "error does not name the file: %s\n", config.error().message.c_str());
    __builtin_trap();
  }
  return 0;
}
