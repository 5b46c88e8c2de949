#include "pulsetrack/drivers/pairing.hpp"

#include <algorithm>
#include <cmath>

namespace pulsetrack::drivers {

FramePairer::FramePairer(const PairerConfig& config) : config_(config) {
  if (config_.tolerance_ns <= 0) config_.tolerance_ns = config_.period_ns / 4;
}

CameraStamp& FramePairer::front(int cam) {
  const auto c = static_cast<size_t>(cam);
  return ring_[c][static_cast<size_t>(head_[c])];
}

void FramePairer::release(int cam, PairEvents& ev) {
  const auto c = static_cast<size_t>(cam);
  const CameraStamp& s = front(cam);
  if (ev.n_released < PairEvents::kMaxReleased)
    ev.released[static_cast<size_t>(ev.n_released++)] = s.slot;
  released_up_to_ns_ = std::max(released_up_to_ns_, s.t_ns);
  ++counters_.unpaired;
  ++unpaired_since_pair_;
  head_[c] = (head_[c] + 1) % kDepth;
  --count_[c];
}

PairEvents FramePairer::offer(int cam, const CameraStamp& stamp) {
  PairEvents ev;
  const auto c = static_cast<size_t>(cam & 1);
  if (have_seq_[c] && stamp.seq > last_seq_[c] + 1)
    counters_.dropped[c] += stamp.seq - last_seq_[c] - 1;
  have_seq_[c] = true;
  last_seq_[c] = stamp.seq;

  // Older than a frame already paired or given up: its partner is gone.
  if (stamp.t_ns < released_up_to_ns_ - config_.tolerance_ns) {
    ++counters_.out_of_order;
    ++counters_.unpaired;
    ev.released[static_cast<size_t>(ev.n_released++)] = stamp.slot;
    return ev;
  }
  if (count_[c] == kDepth) release(static_cast<int>(c), ev);  // its partner is long overdue
  ring_[c][static_cast<size_t>((head_[c] + count_[c]) % kDepth)] = stamp;
  ++count_[c];

  while (count_[0] > 0 && count_[1] > 0) {
    const CameraStamp l = front(0), r = front(1);
    const int64_t d = l.t_ns - r.t_ns;
    if (d < -config_.tolerance_ns) {
      release(0, ev);  // the right camera has no frame of this trigger
      continue;
    }
    if (d > config_.tolerance_ns) {
      release(1, ev);
      continue;
    }
    head_[0] = (head_[0] + 1) % kDepth;
    head_[1] = (head_[1] + 1) % kDepth;
    --count_[0];
    --count_[1];
    const int64_t t = l.t_ns + (r.t_ns - l.t_ns) / 2;
    if (have_pair_) {
      const double periods =
          static_cast<double>(t - last_pair_t_ns_) / static_cast<double>(config_.period_ns);
      const auto steps = static_cast<uint64_t>(std::max(1.0, std::round(periods)));
      // Trigger periods between the two pairs: each gave an unpaired frame or nothing at all.
      if (steps - 1 > unpaired_since_pair_)
        counters_.missing_triggers += steps - 1 - unpaired_since_pair_;
      last_trigger_ += steps;
    }
    have_pair_ = true;
    last_pair_t_ns_ = t;
    released_up_to_ns_ = std::max({released_up_to_ns_, l.t_ns, r.t_ns});
    unpaired_since_pair_ = 0;
    ++counters_.pairs;
    ev.paired = true;
    ev.left = l;
    ev.right = r;
    ev.trigger_seq = last_trigger_;
    break;  // a new frame completes at most one pair
  }
  return ev;
}

PairEvents FramePairer::reset() {
  PairEvents ev;
  for (int cam = 0; cam < 2; ++cam) {
    while (count_[static_cast<size_t>(cam)] > 0) {
      release(cam, ev);
      --counters_.unpaired;  // a restart, not a fault
    }
  }
  have_seq_ = {};
  have_pair_ = false;
  last_trigger_ = 0;
  released_up_to_ns_ = kNever;
  unpaired_since_pair_ = 0;
  return ev;
}

}  // namespace pulsetrack::drivers
