#pragma once
// Pairing the two cameras' frames of one trigger pulse.
//
// Each camera delivers its frames with its own sequence counter (V4L2: v4l2_buffer.sequence;
// a gap is a frame the camera or its driver dropped) and an exposure timestamp on
// CLOCK_MONOTONIC. Hardware-triggered cameras expose within microseconds of each other while
// the trigger period is milliseconds, so two frames are a pair exactly when their timestamps
// lie within `tolerance_ns`. A frame whose partner never comes is released as unpaired; it is
// never paired with a neighbouring trigger's frame. Pairs are numbered in trigger periods from
// the first pair, so a trigger that produced a frame in neither camera shows as a gap in the
// numbers and is counted as a missing trigger.
//
// No allocation, no lock: a fixed ring of kDepth pending frames per camera. One thread offers
// (the capture stage).

#include <array>
#include <cstddef>
#include <cstdint>

namespace pulsetrack::drivers {

struct PairerConfig {
  int64_t period_ns = 33'333'333;  // the trigger's nominal period
  int64_t tolerance_ns = 0;        // 0: a quarter of the period
};

struct CameraStamp {
  uint64_t seq = 0;  // the camera's own frame counter
  int64_t t_ns = 0;  // exposure time, CLOCK_MONOTONIC
  int slot = -1;     // the caller's buffer holding the frame
};

struct PairEvents {
  static constexpr int kMaxReleased = 9;
  bool paired = false;
  CameraStamp left, right;   // when paired
  uint64_t trigger_seq = 0;  // when paired: trigger periods since the first pair
  // Buffers of unpaired frames, to be given back by the caller (oldest first).
  std::array<int, kMaxReleased> released{};
  int n_released = 0;
};

struct PairerCounters {
  uint64_t pairs = 0;
  uint64_t unpaired = 0;              // frames released without a partner
  std::array<uint64_t, 2> dropped{};  // per camera: gaps in its own sequence counter
  uint64_t missing_triggers = 0;      // trigger periods with a frame from neither camera
  uint64_t out_of_order = 0;          // a frame older than one already released or paired
};

class FramePairer {
 public:
  static constexpr int kDepth = 4;
  static constexpr int64_t kNever = INT64_MIN / 2;

  explicit FramePairer(const PairerConfig& config);

  // A frame from camera `cam` (0 left, 1 right). Returns the pair it completes, if any, and the
  // buffers of frames that can no longer be paired.
  PairEvents offer(int cam, const CameraStamp& stamp);

  [[nodiscard]] const PairerCounters& counters() const { return counters_; }
  [[nodiscard]] int pending(int cam) const { return count_[static_cast<size_t>(cam)]; }

  // Forget the pending frames (their buffers are listed) and the numbering: after a restart.
  PairEvents reset();

 private:
  void release(int cam, PairEvents& ev);
  CameraStamp& front(int cam);

  PairerConfig config_;
  std::array<std::array<CameraStamp, kDepth>, 2> ring_{};
  std::array<int, 2> head_{}, count_{};
  std::array<bool, 2> have_seq_{};
  std::array<uint64_t, 2> last_seq_{};
  bool have_pair_ = false;
  uint64_t last_trigger_ = 0;
  int64_t last_pair_t_ns_ = 0;
  int64_t released_up_to_ns_ = kNever;  // newest timestamp released or paired
  uint64_t unpaired_since_pair_ = 0;
  PairerCounters counters_;
};

}  // namespace pulsetrack::drivers
