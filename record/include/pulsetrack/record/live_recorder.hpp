#pragma once
// Lossless recording of the live stream, off the real-time path. The capture stage offers each
// pair; the pair is copied into one of a fixed set of preallocated slots (no allocation, no
// lock: two lock-free queues of slot numbers, atomic_queue) and a writer thread compresses and
// appends it with record::Writer. When every slot is taken (a slow disk) the pair is skipped and
// counted: the recording thins, capture never waits. A write that fails (disk full) stops the
// recording cleanly: the file ends with its last complete frame (Writer's guarantee), the
// error is kept for health, tracking goes on.

#include <atomic>
#include <filesystem>
#include <memory>
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
};

struct RecorderStatus {
  uint64_t written = 0;  // frames on disk
  uint64_t thinned = 0;  // pairs skipped because the disk was behind
  uint64_t bytes = 0;
  bool stopped = false;  // by a write error (or stop())
  std::string error;     // the write error, if any
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
  [[nodiscard]] const std::filesystem::path& dir() const { return dir_; }

 private:
  struct Queues;
  LiveRecorder(Writer writer, const LiveRecorderOptions& options, cv::Size size);
  void run();

  Writer writer_;
  std::filesystem::path dir_;
  int sync_every_;
  std::vector<cv::Mat> left_, right_;
  std::vector<FrameMeta> meta_;
  std::unique_ptr<Queues> queues_;
  std::atomic<bool> running_{true}, failed_{false};
  std::atomic<uint64_t> written_{0}, thinned_{0}, bytes_{0};
  std::string error_;  // set by the writer thread before failed_ (release)
  std::thread thread_;
};

}  // namespace pulsetrack::record
