#pragma once
// A command sample from the DDS command topic, checked field by field before the daemon acts on
// it: what the pipeline's command thread runs, and what fuzz/fuzz_command feeds with every field
// a remote participant controls (strings absent, unterminated lengths, any integers and doubles).

#include <string>

#include "pulsetrack/vision/stereo_rig.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"
#include "pulsetrack_msgs.h"

namespace pulsetrack::daemon {

enum class CommandKind { kStart, kStop, kRedetect, kSetRoi, kRecordStart, kRecordStop, kRefused };

struct CheckedCommand {
  CommandKind kind = CommandKind::kRefused;
  vision::Roi roi;        // kSetRoi
  double depth_mm = 0.0;  // kSetRoi
  std::string refusal;    // kRefused: "command <id> '<printable>' refused: <why>"
};

// `rig_id` and `ros_namespace` are this daemon's; `rig` the calibration the ROI is checked
// against (vision::TrackingSession::checkRoi).
[[nodiscard]] CheckedCommand checkCommand(const pulsetrack_msgs_msg_dds__Command_& c,
                                          const std::string& rig_id,
                                          const std::string& ros_namespace,
                                          const vision::StereoRig& rig);

// A Targets sample (rt/.../targets), every field a remote participant controls: "" when it can
// be followed (for this rig or any, a set number, frame 0 or 1, at most `max_points` finite
// points within 100 m), else "targets set <id> refused: <why>".
[[nodiscard]] std::string checkTargets(const pulsetrack_msgs_msg_dds__Targets_& t,
                                       const std::string& rig_id, size_t max_points);

}  // namespace pulsetrack::daemon
