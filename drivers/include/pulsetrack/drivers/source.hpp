#pragma once
// The camera-source interface the daemon's capture stage drives, and the two sources that need
// no hardware: the simulator live on a software trigger, and replay of a recording. The V4L2
// and libcamera drivers implement the same interface (hardware issue).

#include <atomic>
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
  uint64_t frames = 0;            // pairs handed over
  uint64_t missing_triggers = 0;  // trigger periods with a frame from neither camera
  uint64_t unpaired = 0;          // frames whose partner from the other camera never came
  uint64_t dropped = 0;           // gaps in a camera's own frame counter (its driver dropped)
  uint64_t overruns = 0;          // whole pairs not taken: a newer one was ready (newest wins)
};

// Counters a source updates on its capture thread and health reads on another.
class SharedCounters {
 public:
  void store(const SourceCounters& c) {
    frames_.store(c.frames, std::memory_order_relaxed);
    missing_.store(c.missing_triggers, std::memory_order_relaxed);
    unpaired_.store(c.unpaired, std::memory_order_relaxed);
    dropped_.store(c.dropped, std::memory_order_relaxed);
    overruns_.store(c.overruns, std::memory_order_relaxed);
  }
  [[nodiscard]] SourceCounters load() const {
    return {frames_.load(std::memory_order_relaxed), missing_.load(std::memory_order_relaxed),
            unpaired_.load(std::memory_order_relaxed), dropped_.load(std::memory_order_relaxed),
            overruns_.load(std::memory_order_relaxed)};
  }

 private:
  std::atomic<uint64_t> frames_{0}, missing_{0}, unpaired_{0}, dropped_{0}, overruns_{0};
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
  // Safe to call from any thread.
  [[nodiscard]] virtual SourceCounters counters() const = 0;
  // One line for health: "software 30 Hz", "recorded", "hardware ..." with its state.
  [[nodiscard]] virtual std::string triggerState() const = 0;
};

// Faults the simulated rig (and a recording replayed at a rate, as a live camera) can be told to
// show, so that the daemon's counting, health and recovery can be watched (a demo for the
// technician, the tests, the soak benchmark). 0 disables each.
struct SimFaults {
  int missing_trigger_every = 0;  // every Nth pulse never fires (neither camera exposes)
  int left_drop_every = 0;        // the left driver drops every Nth frame (a gap in its counter)
  int right_miss_every = 0;       // the right camera misses every Nth pulse (no gap, no frame)
  // The cameras go away (next() says kFault, as a driver whose device vanished) for `outage_s`,
  // at outage_every_s, 2 * outage_every_s, ... after start, then come back. The trigger goes on
  // firing meanwhile: its pulses are missing triggers.
  double outage_every_s = 0;
  double outage_s = 0;
};
// What an injected outage says (lastFault()).
inline constexpr const char* kInjectedOutage =
    "the cameras are gone (injected fault: source.faults.outage_s)";

// The simulator live: a software trigger at `fps` (absolute deadlines on CLOCK_MONOTONIC).
// Each camera's frames go through the FramePairer as a driver's would; a pair whose trigger
// passed while the previous pair was still rendering is not taken (newest wins: an overrun).
std::unique_ptr<CameraSource> makeSimSource(const sim::SceneSpec& scene,
                                            const vision::StereoRig& rig, double fps, bool loop,
                                            const SimFaults& faults = {});

struct ReplayOptions {
  enum class Pace {
    kRecorded,  // the recorded timestamps
    kFast,      // as fast as possible
    kRate,      // at `fps`, restamped with each pair's trigger time, as a live camera stamps
                // its exposure
  } pace = Pace::kRecorded;
  double fps = 30.0;
  bool loop = false;
  bool preload = false;  // decode every frame into memory first (no disk or zstd per frame)
};

// A recording, replayed. At Pace::kRate it can show missing triggers and outages (`faults`).
vision::Result<std::unique_ptr<CameraSource>> makeReplaySource(
    const std::filesystem::path& recording, const ReplayOptions& options,
    const SimFaults& faults = {});

}  // namespace pulsetrack::drivers
