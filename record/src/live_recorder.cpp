#include "pulsetrack/record/live_recorder.hpp"

#include <atomic_queue/atomic_queue.h>
#include <fmt/format.h>
#include <sys/statvfs.h>

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

namespace {

std::string megabytes(uint64_t bytes) { return fmt::format("{} MB", bytes / 1'000'000); }

}  // namespace

uint64_t freeBytes(const std::filesystem::path& path) {
  std::error_code ec;
  std::filesystem::path p = path;
  while (!p.empty() && !std::filesystem::exists(p, ec)) p = p.parent_path();
  struct statvfs st {};
  if (::statvfs(p.empty() ? "." : p.c_str(), &st) != 0) return UINT64_MAX;
  return static_cast<uint64_t>(st.f_bavail) * st.f_frsize;
}

vision::Result<std::unique_ptr<LiveRecorder>> LiveRecorder::start(const LiveRecorderOptions& o,
                                                                  const vision::StereoRig& rig) {
  if (o.slots < 2) return vision::fail("recorder: at least 2 slots");
  auto w = Writer::create(o.dir, o.manifest, rig, o.zstd_level);
  if (!w) return std::unexpected(w.error());
  return std::unique_ptr<LiveRecorder>(new LiveRecorder(std::move(*w), o, rig));
}

LiveRecorder::LiveRecorder(Writer writer, const LiveRecorderOptions& o,
                           const vision::StereoRig& rig)
    : writer_(std::move(writer)),
      options_(o),
      rig_(rig),
      left_(static_cast<size_t>(o.slots)),
      right_(static_cast<size_t>(o.slots)),
      meta_(static_cast<size_t>(o.slots)),
      queues_(std::make_unique<Queues>(static_cast<unsigned>(o.slots))),
      dir_(o.dir) {
  const cv::Size size(o.manifest.width, o.manifest.height);
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
  if (!running_.load(std::memory_order_relaxed)) return false;
  if (failed_.load(std::memory_order_acquire)) {
    unrecorded_.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
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

uint64_t LiveRecorder::freeNow() const {
  return options_.free_bytes ? options_.free_bytes(options_.dir) : freeBytes(options_.dir);
}

void LiveRecorder::fail(const std::string& why) {
  (void)writer_.close();  // the segment ends with its last complete frame
  written_before_ += writer_.framesWritten();
  bytes_before_ += writer_.bytesWritten();
  {
    const std::lock_guard lock(status_mutex_);
    error_ = why;
  }
  faults_.fetch_add(1, std::memory_order_relaxed);
  failed_.store(true, std::memory_order_release);
}

bool LiveRecorder::tryResume() {
  const uint64_t reserve = options_.min_free_bytes;
  const uint64_t margin = std::max<uint64_t>(reserve / 2, uint64_t{64} << 20);
  if (freeNow() < reserve + margin) return false;
  const int segment = segment_ + 1;
  std::filesystem::path dir = options_.dir;
  dir += fmt::format("-part{}", segment);
  auto w = Writer::create(dir, options_.manifest, rig_, options_.zstd_level);
  if (!w) {
    const std::lock_guard lock(status_mutex_);
    error_ = w.error().message;
    return false;
  }
  writer_ = std::move(*w);
  base_frame_ = UINT64_MAX;
  {
    const std::lock_guard lock(status_mutex_);
    error_.clear();
    dir_ = dir;
    segment_ = segment;
  }
  failed_.store(false, std::memory_order_release);
  return true;
}

void LiveRecorder::run() {
  uint32_t slot = 0;
  uint64_t since_sync = 0;
  auto next_check = std::chrono::steady_clock::now();
  for (;;) {
    if (failed_.load(std::memory_order_relaxed) && options_.resume_check_ms > 0 &&
        running_.load(std::memory_order_acquire) &&
        std::chrono::steady_clock::now() >= next_check) {
      next_check =
          std::chrono::steady_clock::now() + std::chrono::milliseconds(options_.resume_check_ms);
      (void)tryResume();
    }
    if (!queues_->filled.try_pop(slot)) {
      if (!running_.load(std::memory_order_acquire)) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
      continue;
    }
    if (!failed_.load(std::memory_order_relaxed)) {
      const uint64_t free = options_.min_free_bytes > 0 ? freeNow() : UINT64_MAX;
      if (free < options_.min_free_bytes) {
        fail(fmt::format(
            "{}: the disk is almost full: {} free, below the {} reserve "
            "([recorder] min_free_mb); recording resumes when {} are free",
            dir_.string(), megabytes(free), megabytes(options_.min_free_bytes),
            megabytes(options_.min_free_bytes +
                      std::max<uint64_t>(options_.min_free_bytes / 2, uint64_t{64} << 20))));
        next_check =
            std::chrono::steady_clock::now() + std::chrono::milliseconds(options_.resume_check_ms);
        queues_->free.push(slot);
        continue;
      }
      FrameMeta meta = meta_[slot];
      if (base_frame_ == UINT64_MAX) base_frame_ = meta.frame;  // a segment starts at frame 0
      meta.frame -= base_frame_;
      auto ok = writer_.write(meta, left_[slot], right_[slot]);
      if (!ok) {
        fail(ok.error().message);
        next_check =
            std::chrono::steady_clock::now() + std::chrono::milliseconds(options_.resume_check_ms);
      } else {
        written_.store(written_before_ + writer_.framesWritten(), std::memory_order_relaxed);
        bytes_.store(bytes_before_ + writer_.bytesWritten(), std::memory_order_relaxed);
        if (++since_sync >= static_cast<uint64_t>(options_.sync_every)) {
          (void)writer_.sync();
          since_sync = 0;
        }
      }
    }
    queues_->free.push(slot);
  }
  if (!failed_.load(std::memory_order_relaxed)) (void)writer_.close();
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
  s.faults = faults_.load(std::memory_order_relaxed);
  s.unrecorded = unrecorded_.load(std::memory_order_relaxed);
  const bool failed = failed_.load(std::memory_order_acquire);
  s.stopped = failed || !running_.load(std::memory_order_relaxed);
  const std::lock_guard lock(status_mutex_);
  if (failed) s.error = error_;
  s.segment = segment_;
  s.dir = dir_;
  return s;
}

}  // namespace pulsetrack::record
