#pragma once
// Lossless recording of the live stream, off the real-time path. The capture stage offers each
// pair; the pair is copied into one of a fixed set of preallocated slots (no allocation, no
// lock: two lock-free queues of slot numbers, atomic_queue) and a writer thread compresses and
// appends it with record::Writer. When every slot is taken (a slow disk) the pair is skipped and
// counted: the recording thins, capture never waits. A write that fails (disk full, a file-size
// limit) or free space below the reserve stops the recording cleanly: the file ends with its last
// complete frame (Writer's guarantee), the error is kept for health, tracking goes on. When the
// disk has room again (the reserve and a margin free: a technician deleted old cases), the
// recorder resumes by itself in a new segment, DIR-part2, DIR-part3..., each a complete recording
// whose frame numbers start at 0; the pairs offered while stopped are counted, not kept.

#include <atomic>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "pulsetrack/record/recording.hpp"

namespace pulsetrack::record {

struct LiveRecorderOptions {
  std::filesystem::path dir;  // must not exist or be empty
  Manifest manifest;
  int slots = 32;  // pairs that can wait for the disk
  int zstd_level = 1;
  int sync_every = 30;  // fdatasync every so many frames
  // Free space kept on the recording's file system (the journal and the system need it too):
  // below it the recording stops; it resumes once the reserve plus half of it (at least 64 MiB
  // more) is free, looked at every `resume_check_ms` (0: never resume).
  uint64_t min_free_bytes = 0;
  int resume_check_ms = 2000;
  // Free bytes on the file system holding `dir` (statvfs when empty; a test's seam).
  std::function<uint64_t(const std::filesystem::path&)> free_bytes;
};

// Free bytes for an unprivileged writer (statvfs f_bavail) on the file system holding `path`
// (or its nearest existing parent); UINT64_MAX when it cannot be asked.
uint64_t freeBytes(const std::filesystem::path& path);

struct RecorderStatus {
  uint64_t written = 0;  // frames on disk, every segment
  uint64_t thinned = 0;  // pairs skipped because the disk was behind
  uint64_t bytes = 0;
  bool stopped = false;       // by a write error or the reserve (or stop())
  std::string error;          // why it is stopped now, if by an error or the reserve
  uint64_t faults = 0;        // times the disk stopped the recording
  uint64_t unrecorded = 0;    // pairs offered while it was stopped
  int segment = 1;            // the segment written now (1: DIR itself)
  std::filesystem::path dir;  // the segment's folder
};

class LiveRecorder {
 public:
  static vision::Result<std::unique_ptr<LiveRecorder>> start(const LiveRecorderOptions& options,
                                                             const vision::StereoRig& rig);
  ~LiveRecorder();
  LiveRecorder(const LiveRecorder&) = delete;
  LiveRecorder& operator=(const LiveRecorder&) = delete;

  // The capture thread's call. False when the pair was not taken (no free slot, or stopped).
  bool offer(const FrameMeta& meta, const cv::Mat& left, const cv::Mat& right) noexcept;
  // Writes what is queued, closes the recording.
  void stop();
  [[nodiscard]] RecorderStatus status() const;  // any thread

 private:
  struct Queues;
  LiveRecorder(Writer writer, const LiveRecorderOptions& options, const vision::StereoRig& rig);
  void run();
  // Writer thread: stop the segment with `why`; try a new one when the disk has room.
  void fail(const std::string& why);
  bool tryResume();
  [[nodiscard]] uint64_t freeNow() const;

  Writer writer_;
  LiveRecorderOptions options_;
  vision::StereoRig rig_;
  std::vector<cv::Mat> left_, right_;
  std::vector<FrameMeta> meta_;
  std::unique_ptr<Queues> queues_;
  std::atomic<bool> running_{true}, failed_{false};
  std::atomic<uint64_t> written_{0}, thinned_{0}, bytes_{0}, faults_{0}, unrecorded_{0};
  uint64_t written_before_ = 0, bytes_before_ = 0;  // writer thread: closed segments' totals
  uint64_t base_frame_ = UINT64_MAX;  // writer thread: the segment's first frame number
  mutable std::mutex status_mutex_;   // error_, dir_, segment_: writer thread and status() only
  std::string error_;
  std::filesystem::path dir_;
  int segment_ = 1;
  std::thread thread_;
};

}  // namespace pulsetrack::record
