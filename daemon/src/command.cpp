#include "pulsetrack/daemon/command.hpp"

#include <fmt/format.h>

#include <cmath>

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
  } else if (what == "record_start") {
    out.kind = CommandKind::kRecordStart;
  } else if (what == "record_stop") {
    out.kind = CommandKind::kRecordStop;
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
    why = "unknown command (start, stop, redetect, set_roi, record_start, record_stop)";
  }
  if (!why.empty()) {
    out.kind = CommandKind::kRefused;
    out.refusal = fmt::format("command {} '{}' refused: {}", c.request_id, printable(what), why);
  }
  return out;
}

std::string checkTargets(const pulsetrack_msgs_msg_dds__Targets_& t, const std::string& rig_id,
                         size_t max_points) {
  const std::string rig = t.rig_id != nullptr ? t.rig_id : "";
  std::string why;
  if (!rig.empty() && rig != rig_id)
    why = fmt::format("addressed to rig '{}', this is '{}'", printable(rig), rig_id);
  else if (t.set_id == 0)
    why = "set_id 0 (a set needs a number, echoed in its answers)";
  else if (t.frame > 1)
    why = fmt::format("frame {} (0: reference, 1: latest)", t.frame);
  else if (t.points._length > max_points)
    why = fmt::format("{} points, at most {}", t.points._length, max_points);
  else if (t.points._length > 0 && t.points._buffer == nullptr)
    why = "no points buffer";
  for (uint32_t i = 0; i < t.points._length && why.empty(); ++i) {
    const geometry_msgs_msg_dds__Point_& p = t.points._buffer[i];
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z) || std::abs(p.x) > 100 ||
        std::abs(p.y) > 100 || std::abs(p.z) > 100)
      why = fmt::format("point {} is not a finite position within 100 m", i);
  }
  return why.empty() ? "" : fmt::format("targets set {} refused: {}", t.set_id, why);
}

}  // namespace pulsetrack::daemon
