// libFuzzer: the daemon's TOML config (daemon/config: pulsetrackd and --check-config).
// Input: the file's text.

#include "fuzz_file.hpp"
#include "pulsetrack/daemon/config.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path name = "fuzz-pulsetrackd.toml";
  auto config =
      pulsetrack::daemon::parseDaemonConfig(pulsetrack::fuzz::inputText(data, size), name);
  if (!config) pulsetrack::fuzz::requireNamed(config.error().message, name);
  return 0;
}
