// libFuzzer: the rig YAML reader (vision::loadRig), as every program that loads a rig meets it,
// including a recording's own rig.yaml. Input: the file's bytes. A clear error is a pass; a
// crash, a sanitizer report, a leak or an allocation past libFuzzer's -rss_limit_mb is a finding.

#include "fuzz_file.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = pulsetrack::fuzz::writeInput("rig.yaml", data, size);
  auto rig = pulsetrack::vision::loadRig(path);
  if (!rig) {
    pulsetrack::fuzz::requireNamed(rig.error().message, path);
    return 0;
  }
  // What passed must be usable: every later stage relies on validateRig's promises.
  const cv::Vec3d p(0.0, 0.0, 300.0);
  (void)rig->projectLeft(p);
  (void)rig->projectRight(p);
  (void)rig->backProjectRight(cv::Vec2d(rig->right.cx(), rig->right.cy()));
  return 0;
}
