#include "pulsetrack/record/live_recorder.hpp"

#include <atomic_queue/atomic_queue.h>

#include <chrono>

namespace pulsetrack::record {

// Slot numbers: free ones (writer -> capture) and filled ones (capture -> writer). A slot number
// hands over the slot's images, so the hand-over must be release/acquire: AtomicQueueB2 (a state
// byte per element, stored with release and loaded with acquire). AtomicQueueB's SPSC pop loads
// the element relaxed, which orders nothing else: ThreadSanitizer (preset tsan) reported the
// writer thread reading images the capture thread had just copied in.
struct LiveRecorder::Queues {
  using Q = atomic_queue::AtomicQueueB2<uint32_t, std::allocator<uint32_t>, false, false, true>;
  explicit Queues(unsigned n) : free(n), filled(n) {}
  Q free, filled;
};

vision::Result<std::unique_ptr<LiveRecorder>> LiveRecorder::start(const LiveRecorderOptions& o,
                                                                  const vision::StereoRig& rig) {
  if (o.slots < 2) return vision::fail("recorder: at least 2 slots");
  auto w = Writer::create(o.dir, o.manifest, rig, o.zstd_level);
  if (!w) return std::unexpected(w.error());
  return std::unique_ptr<LiveRecorder>(
      new LiveRecorder(std::move(*w), o, cv::Size(o.manifest.width, o.manifest.height)));
}

LiveRecorder::LiveRecorder(Writer writer, const LiveRecorderOptions& o, cv::Size size)
    : writer_(std::move(writer)),
      dir_(o.dir),
      sync_every_(o.sync_every),
      left_(static_cast<size_t>(o.slots)),
      right_(static_cast<size_t>(o.slots)),
      meta_(static_cast<size_t>(o.slots)),
      queues_(std::make_unique<Queues>(static_cast<unsigned>(o.slots))) {
  for (size_t i = 0; i < left_.size(); ++i) {
    left_[i].create(size, CV_8UC1);
    right_[i].create(size, CV_8UC1);
    queues_->free.push(static_cast<uint32_t>(i));
  }
  thread_ = std::thread([this] { run(); });
}

LiveRecorder::~LiveRecorder() { stop(); }

bool LiveRecorder::offer(const FrameMeta& meta, const cv::Mat& left,
                         const cv::Mat& right) noexcept {
  uint32_t slot = 0;
  if (failed_.load(std::memory_order_acquire) || !running_.load(std::memory_order_relaxed))
    return false;
  if (!queues_->free.try_pop(slot)) {
    thinned_.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
  // Same size and type as the slots (the rig's): copyTo does not reallocate.
  left.copyTo(left_[slot]);
  right.copyTo(right_[slot]);
  meta_[slot] = meta;
  queues_->filled.push(slot);
  return true;
}

void LiveRecorder::run() {
  uint32_t slot = 0;
  uint64_t since_sync = 0;
  for (;;) {
    if (!queues_->filled.try_pop(slot)) {
      if (!running_.load(std::memory_order_acquire)) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
      continue;
    }
    if (!failed_.load(std::memory_order_relaxed)) {
      auto ok = writer_.write(meta_[slot], left_[slot], right_[slot]);
      if (!ok) {
        error_ = ok.error().message;
        failed_.store(true, std::memory_order_release);
      } else {
        written_.store(writer_.framesWritten(), std::memory_order_relaxed);
        bytes_.store(writer_.bytesWritten(), std::memory_order_relaxed);
        if (++since_sync >= static_cast<uint64_t>(sync_every_)) {
          (void)writer_.sync();
          since_sync = 0;
        }
      }
    }
    queues_->free.push(slot);
  }
  (void)writer_.close();
}

void LiveRecorder::stop() {
  if (!running_.exchange(false)) return;
  if (thread_.joinable()) thread_.join();
}

RecorderStatus LiveRecorder::status() const {
  RecorderStatus s;
  s.written = written_.load(std::memory_order_relaxed);
  s.thinned = thinned_.load(std::memory_order_relaxed);
  s.bytes = bytes_.load(std::memory_order_relaxed);
  s.stopped = failed_.load(std::memory_order_acquire) || !running_.load(std::memory_order_relaxed);
  if (failed_.load(std::memory_order_acquire)) s.error = error_;
  return s;
}

}  // namespace pulsetrack::record
