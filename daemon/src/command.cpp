#include "pulsetrack/daemon/command.hpp"

#include <fmt/format.h>

#include "pulsetrack/vision/tracking_session.hpp"

namespace pulsetrack::daemon {

namespace {
// What a participant sent, quoted in a refusal: short and printable ASCII only (the refusal goes
// out on the health topic: it is not an echo of control characters or invalid UTF-8).
std::string printable(const std::string& s) {
  std::string out;
  for (const char ch : s.substr(0, 32)) out += (ch >= 32 && ch < 127) ? ch : '?';
  return out;
}
}  // namespace

CheckedCommand checkCommand(const pulsetrack_msgs_msg_dds__Command_& c, const std::string& rig_id,
                            const std::string& ros_namespace, const vision::StereoRig& rig) {
  const std::string what = c.command != nullptr ? c.command : "";
  const std::string addressed = c.rig_id != nullptr ? c.rig_id : "";
  CheckedCommand out;
  std::string why;
  if (!addressed.empty() && addressed != rig_id) {
    why = fmt::format("addressed to rig '{}', this is '{}' (namespace '{}')", printable(addressed),
                      rig_id, ros_namespace);
  } else if (what == "start") {
    out.kind = CommandKind::kStart;
  } else if (what == "stop") {
    out.kind = CommandKind::kStop;
  } else if (what == "redetect") {
    out.kind = CommandKind::kRedetect;
  } else if (what == "set_roi") {
    const cv::Rect l(c.roi_left[0], c.roi_left[1], c.roi_left[2], c.roi_left[3]);
    const cv::Rect r(c.roi_right[0], c.roi_right[1], c.roi_right[2], c.roi_right[3]);
    // Metres on the wire; checkRoi refuses a depth that is not in (0, 500] mm (NaN included).
    const double depth_mm = c.depth_tolerance_m * 1e3;
    if (auto ok = vision::TrackingSession::checkRoi(rig, {l, r}, depth_mm); !ok) {
      why = ok.error().message;
    } else {
      out.kind = CommandKind::kSetRoi;
      out.roi = {l, r};
      out.depth_mm = depth_mm;
    }
  } else {
    why = "unknown command (start, stop, redetect, set_roi)";
  }
  if (!why.empty()) {
    out.kind = CommandKind::kRefused;
    out.refusal = fmt::format("command {} '{}' refused: {}", c.request_id, printable(what), why);
  }
  return out;
}

}  // namespace pulsetrack::daemon
