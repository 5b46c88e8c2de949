#pragma once
// Cameras through libcamera 0.0.3 (boards whose sensors have no plain V4L2 capture node, e.g.
// behind an ISP): two cameras, the raw stream in 8-bit grey (R8), requests re-queued as they
// complete, the frames' sensor timestamps (controls::SensorTimestamp, CLOCK_MONOTONIC) and
// sequence numbers paired by the same FramePairer as V4L2, behind the daemon's source interface.
// A camera that disconnects is a fault; it is set up again every `reopen_ms` until it returns.

#include <memory>
#include <string>
#include <vector>

#include "pulsetrack/drivers/source.hpp"

namespace pulsetrack::drivers {

struct LibcameraInfo {
  std::string id;
  std::string model;
};
// The cameras libcamera sees on this machine.
vision::Result<std::vector<LibcameraInfo>> listLibcameraCameras();

struct LibcameraStereoConfig {
  std::string left_id, right_id;  // libcamera ids (listLibcameraCameras)
  int width = 1360, height = 1024;
  double fps = 30.0;
  int buffers = 6;
  int reopen_ms = 500;
};

class TriggerBox;

std::unique_ptr<CameraSource> makeLibcameraSource(const LibcameraStereoConfig& config,
                                                  vision::StereoRig rig,
                                                  TriggerBox* trigger = nullptr);

}  // namespace pulsetrack::drivers
