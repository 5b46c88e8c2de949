// libFuzzer: the scene TOML reader (sim/scene: `pulsetrack simulate`, gate_eval, the daemon's
// simulated rig). Input: the file's text.

#include <string>

#include "pulsetrack/sim/scene.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  auto scene = pulsetrack::sim::parseScene(text, "fuzz-scene.toml");
  if (!scene && scene.error().message.find("fuzz-scene.toml") == std::string::npos) {
    std::fprintf(stderr, "error does not name the file: %s\n", scene.error().message.c_str());
    __builtin_trap();
  }
  return 0;
}
