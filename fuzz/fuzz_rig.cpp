// libFuzzer: the rig YAML reader (vision::loadRig), as every program that loads a rig meets it,
// including a recording's own rig.yaml. Input: the file's bytes. A clear error is a pass; a
// crash, a sanitizer report, a leak or an allocation past libFuzzer's -rss_limit_mb is a finding.

#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include "pulsetrack/vision/stereo_rig.hpp"

namespace {
const std::filesystem::path& scratch() {
  static const std::filesystem::path p =
      std::filesystem::temp_directory_path() / ("fuzz_rig." + std::to_string(::getpid()) + ".yaml");
  return p;
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  {
    std::ofstream out(scratch(), std::ios::binary | std::ios::trunc);
    out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
  }
  auto rig = pulsetrack::vision::loadRig(scratch());
  if (rig) {
    // What passed must be usable: every later stage relies on validateRig's promises.
    const cv::Vec3d p(0.0, 0.0, 300.0);
    (void)rig->projectLeft(p);
    (void)rig->projectRight(p);
    (void)rig->backProjectRight(cv::Vec2d(rig->right.cx(), rig->right.cy()));
  } else if (rig.error().message.find(scratch().string()) == std::string::npos) {
    std::fprintf(stderr, "error does not name the file: %s\n", rig.error().message.c_str());
    __builtin_trap();
  }
  return 0;
}
