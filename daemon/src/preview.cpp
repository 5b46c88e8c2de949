#include "pulsetrack/daemon/preview.hpp"

#include <algorithm>

#include "pulsetrack/rt/heartbeat.hpp"

namespace pulsetrack::daemon {

PreviewTap::PreviewTap(cv::Size size, int64_t period_ns) : period_ns_(period_ns) {
  if (period_ns_ <= 0) return;
  for (PreviewFrame& p : slots_.slots()) {
    p.left.create(size, CV_8UC1);
    p.right.create(size, CV_8UC1);
  }
}

bool PreviewTap::offer(const drivers::StereoFrame& pair, int64_t now_ns) noexcept {
  // On a schedule of the exposures (what a viewer sees), with a twentieth of a period's slack:
  // 30 fps pairs (33.3 ms apart, stamps rounded) give 5 Hz, every 6th pair, not every 7th. A late
  // copy (a pair missing when one was due) pushes the schedule on, so that two copies are never
  // less than 0.9 periods apart.
  const int64_t t = pair.t_left_ns;
  const int64_t slack = period_ns_ / 20;
  if (period_ns_ <= 0 || (any_ && t < next_ns_ - slack)) return false;
  PreviewFrame& p = slots_.back();
  if (pair.left.size() != p.left.size() || pair.left.type() != CV_8UC1 ||
      pair.right.size() != p.right.size() || pair.right.type() != CV_8UC1)
    return false;  // never a reallocation here
  next_ns_ = any_ ? std::max(next_ns_ + period_ns_, t + period_ns_ - slack) : t + period_ns_;
  any_ = true;
  pair.left.copyTo(p.left);  // the same size and type: a memcpy into the preallocated image
  pair.right.copyTo(p.right);
  p.trigger_seq = pair.trigger_seq;
  p.t_left_ns = pair.t_left_ns;
  p.t_right_ns = pair.t_right_ns;
  slots_.publish();
  copy_lat_.record(static_cast<uint64_t>(rt::monotonicNs() - now_ns));
  seq_.fetch_add(1, std::memory_order_release);
  seq_.notify_one();
  return true;
}

}  // namespace pulsetrack::daemon
