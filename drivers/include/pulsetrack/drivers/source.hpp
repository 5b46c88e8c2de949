#pragma once
// The camera-source interface the daemon's capture stage drives, and the two sources that need
// no hardware: the simulator live on a software trigger, and replay of a recording. The V4L2
// and libcamera drivers implement the same interface (hardware issue).

#include <chrono>
#include <cstdint>
#include <memory>
#include <opencv2/core.hpp>
#include <string>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::drivers {

// One frame pair. The images are the caller's preallocated buffers (filled in place).
struct StereoFrame {
  cv::Mat left, right;
  uint64_t trigger_seq = 0;  // the trigger's sequence number; a gap is a missing trigger
  int64_t t_left_ns = 0;     // exposure times, CLOCK_MONOTONIC (replay: as recorded)
  int64_t t_right_ns = 0;
};

enum class Next { kFrame, kTimeout, kEnd, kFault };

struct SourceCounters {
  uint64_t frames = 0;
  uint64_t missing_triggers = 0;  // sequence gaps (sim: triggers that fired while rendering)
};

class CameraSource {
 public:
  virtual ~CameraSource() = default;
  [[nodiscard]] virtual std::string name() const = 0;
  [[nodiscard]] virtual const vision::StereoRig& rig() const = 0;
  virtual vision::Result<void> start() = 0;
  // The next pair into `frame` (images sized by the caller to the rig's image size).
  virtual Next next(StereoFrame& frame, std::chrono::milliseconds timeout) = 0;
  virtual void stop() = 0;
  [[nodiscard]] virtual std::string lastFault() const = 0;
  [[nodiscard]] virtual SourceCounters counters() const = 0;
};

// The simulator live: a software trigger at `fps` (absolute deadlines on CLOCK_MONOTONIC);
// a trigger that passes while the previous pair is still rendering is counted as missing.
std::unique_ptr<CameraSource> makeSimSource(const sim::SceneSpec& scene,
                                            const vision::StereoRig& rig, double fps, bool loop);

struct ReplayOptions {
  enum class Pace {
    kRecorded,  // the recorded timestamps
    kFast,      // as fast as possible
    kRate,      // at `fps`, restamped with the time each pair is handed over, as a live camera
  } pace = Pace::kRecorded;
  double fps = 30.0;
  bool loop = false;
  bool preload = false;  // decode every frame into memory first (no disk or zstd per frame)
};

// A recording, replayed.
vision::Result<std::unique_ptr<CameraSource>> makeReplaySource(
    const std::filesystem::path& recording, const ReplayOptions& options);

}  // namespace pulsetrack::drivers
