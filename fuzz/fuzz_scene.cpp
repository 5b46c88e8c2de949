// libFuzzer: the scene TOML reader (sim/scene: `pulsetrack simulate`, gate_eval, the daemon's
// simulated rig). Input: the file's text.

#include "fuzz_file.hpp"
#include "pulsetrack/sim/scene.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path name = "fuzz-scene.toml";
  auto scene = pulsetrack::sim::parseScene(pulsetrack::fuzz::inputText(data, size), name);
  if (!scene) pulsetrack::fuzz::requireNamed(scene.error().message, name);
  return 0;
}
