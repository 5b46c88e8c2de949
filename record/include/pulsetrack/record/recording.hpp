#pragma once
// The pulsetrack recording format, version 1 (docs/recording-format.md): one folder holding
// the rig calibration, a manifest, the stereo frames (lossless, zstd) with their timestamps and
// trigger sequence numbers, a per-frame table for people, and for simulated recordings the
// scene and its ground truth. Written by the simulator and the daemon's recorder, read by the
// replay driver and every offline tool.
//
// Crash safety: frames are appended as self-checking records (CRC-32 of header and payload),
// so a recording cut by power loss or a full disk reads back up to its last complete frame.

#include <cstdint>
#include <filesystem>
#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::record {

using vision::Result;

inline constexpr int kFormatVersion = 1;

struct FrameMeta {
  uint64_t frame = 0;        // trigger pulse index since the recording started; gaps = not recorded
  uint64_t trigger_seq = 0;  // the trigger source's own sequence number
  int64_t t_left_ns = 0;     // exposure timestamps, CLOCK_MONOTONIC-like ns (sim: scene time)
  int64_t t_right_ns = 0;
  uint32_t flags = 0;  // reserved, 0
};

struct Manifest {
  int version = kFormatVersion;
  std::string source;  // "sim:<scene name>", "v4l2:<devices>", "replay:<folder>", ...
  std::string rig_id;  // the rig's name, also the DDS key
  int width = 0;
  int height = 0;
  std::string pixel_format = "gray8";
  double nominal_fps = 0.0;
  std::string created;  // ISO 8601 UTC
};

class Writer {
 public:
  // Creates `dir` (which must not exist or be empty) with manifest.toml, rig.yaml, frames.ptv
  // and frames.csv. `zstd_level` 1 is fast enough for live use; 0 stores raw frames.
  static Result<Writer> create(const std::filesystem::path& dir, const Manifest& manifest,
                               const vision::StereoRig& rig, int zstd_level = 1);
  Writer(Writer&&) noexcept;
  Writer& operator=(Writer&&) noexcept;
  ~Writer();

  // Appends one stereo frame (8-bit grey, the manifest's size). A failed write (disk full)
  // leaves the file ending in the last complete frame and returns the error.
  Result<void> write(const FrameMeta& meta, const cv::Mat& left, const cv::Mat& right);
  // Flushes to the device (fdatasync); the recorder calls it every few frames.
  Result<void> sync();
  Result<void> close();

  [[nodiscard]] uint64_t framesWritten() const;
  [[nodiscard]] uint64_t bytesWritten() const;
  [[nodiscard]] const std::filesystem::path& dir() const;

 private:
  struct Impl;
  explicit Writer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

class Reader {
 public:
  // Opens a recording and indexes its frames (record headers only). A recording whose last
  // record is incomplete or fails its CRC opens with the complete frames; truncation() says
  // what was cut.
  static Result<Reader> open(const std::filesystem::path& dir);
  Reader(Reader&&) noexcept;
  Reader& operator=(Reader&&) noexcept;
  ~Reader();

  [[nodiscard]] const Manifest& manifest() const;
  [[nodiscard]] const vision::StereoRig& rig() const;
  [[nodiscard]] size_t size() const;
  [[nodiscard]] const FrameMeta& meta(size_t index) const;
  [[nodiscard]] const std::optional<std::string>& truncation() const;
  // Records out of order (a frame index that does not increase or is past 2^31-1, a left stamp
  // going back): read in file order, each named here (the first 8) for the tools to print.
  [[nodiscard]] const std::vector<std::string>& warnings() const;
  [[nodiscard]] const std::filesystem::path& dir() const;

  // Decodes frame `index` into left/right (reallocated only if their size or type differ).
  Result<void> read(size_t index, cv::Mat& left, cv::Mat& right);

 private:
  struct Impl;
  explicit Reader(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace pulsetrack::record
