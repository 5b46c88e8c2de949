// libFuzzer: a DDS command sample as a remote participant may write it: every field it controls
// (rig id and command strings, absent or not, the request id, both ROIs' integers, the depth
// tolerance's double), checked by daemon::checkCommand against the paper's rig, as the daemon's
// command thread does before it acts; and a Targets sample (rig id, set id, frame, points) by
// daemon::checkTargets.

#include <fuzzer/FuzzedDataProvider.h>

#include <cmath>
#include <string>
#include <vector>

#include "pulsetrack/daemon/command.hpp"
#include "pulsetrack/sim/paper_rig.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace pulsetrack;
  static const vision::StereoRig rig = sim::paperRig();
  FuzzedDataProvider in(data, size);
  std::string rig_id = in.ConsumeRandomLengthString(64);
  std::string command = in.ConsumeRandomLengthString(64);
  const bool has_rig = in.ConsumeBool(), has_command = in.ConsumeBool();
  pulsetrack_msgs_msg_dds__Command_ c{};
  c.rig_id = has_rig ? rig_id.data() : nullptr;
  c.command = has_command ? command.data() : nullptr;
  c.request_id = in.ConsumeIntegral<uint32_t>();
  for (int& v : c.roi_left) v = in.ConsumeIntegral<int32_t>();
  for (int& v : c.roi_right) v = in.ConsumeIntegral<int32_t>();
  c.depth_tolerance_m = in.ConsumeFloatingPoint<double>();
  const auto checked = daemon::checkCommand(c, "rig-a", "/or1", rig);
  if (checked.kind == daemon::CommandKind::kRefused) {
    // The refusal goes out on the health topic: printable ASCII only, whatever was sent.
    if (checked.refusal.find("refused") == std::string::npos) __builtin_trap();
    for (const char ch : checked.refusal)
      if (ch < 32 || ch >= 127) __builtin_trap();
  } else if (checked.kind == daemon::CommandKind::kSetRoi) {
    // What is accepted lies inside the image.
    const cv::Size s = rig.left.imageSize();
    for (const cv::Rect& r : {checked.roi.left, checked.roi.right}) {
      if (r.x < 0 || r.y < 0 || r.width <= 0 || r.height <= 0 ||
          static_cast<int64_t>(r.x) + r.width > s.width ||
          static_cast<int64_t>(r.y) + r.height > s.height)
        __builtin_trap();
    }
  }
  // A Targets set from the rest of the input.
  pulsetrack_msgs_msg_dds__Targets_ t{};
  t.rig_id = has_rig ? rig_id.data() : nullptr;
  t.set_id = in.ConsumeIntegral<uint32_t>();
  t.frame = in.ConsumeIntegral<uint8_t>();
  std::vector<geometry_msgs_msg_dds__Point_> points(in.ConsumeIntegralInRange<size_t>(0, 300));
  for (auto& p : points) {
    p.x = in.ConsumeFloatingPoint<double>();
    p.y = in.ConsumeFloatingPoint<double>();
    p.z = in.ConsumeFloatingPoint<double>();
  }
  t.points._buffer = points.data();
  t.points._length = static_cast<uint32_t>(points.size());
  const std::string why = daemon::checkTargets(t, "rig-a", 256);
  if (why.empty()) {
    // What is accepted: at most 256 finite points within 100 m, a set number, frame 0 or 1.
    if (points.size() > 256 || t.set_id == 0 || t.frame > 1) __builtin_trap();
    for (const auto& p : points)
      if (!(std::abs(p.x) <= 100 && std::abs(p.y) <= 100 && std::abs(p.z) <= 100)) __builtin_trap();
  } else {
    for (const char ch : why)
      if (ch < 32 || ch >= 127) __builtin_trap();
  }
  return 0;
}
