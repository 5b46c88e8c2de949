#pragma once
// Stereo video files, in and out (docs/video.md), through OpenCV's FFmpeg backend:
// - in: two files (left, right) or one file with both views side by side or top and bottom, any
//   codec FFmpeg decodes; each frame's time from the container (its presentation time stamp),
//   its frame number from that time and the stream's rate, so a frame the camera or the encoder
//   dropped leaves a gap in the numbers, as a missing trigger does in a recording;
// - out: lossless FFV1 in Matroska, 8-bit grey, bit-exact (two files or one side by side), with
//   a frames.csv beside it that keeps each frame's recording number and exposure times (a video
//   has a constant rate; the recording's gaps and stamps are in the CSV).

#include <cstdint>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::record {

enum class VideoLayout { kTwoFiles, kSideBySide, kTopBottom };
// "two", "sbs" (side-by-side, left view on the left), "tb" (top-bottom, left view on top).
vision::Result<VideoLayout> parseVideoLayout(const std::string& text);

struct VideoFrame {
  uint64_t frame = 0;  // from the time stamp: round((t - t_first) * rate); gaps = dropped frames
  int64_t t_ns = 0;    // the container's time stamp of this frame (both files': the left one's)
};

class StereoVideoReader {
 public:
  // Two files (kTwoFiles: `right` is the right view's file) or one file split in two.
  static vision::Result<StereoVideoReader> open(const std::string& left, const std::string& right,
                                                VideoLayout layout);
  StereoVideoReader(StereoVideoReader&&) noexcept;
  StereoVideoReader& operator=(StereoVideoReader&&) noexcept;
  ~StereoVideoReader();
  // The next pair in grey (false at the end). Frames of one file that the other lacks are
  // skipped and counted (unpaired); a frame that cannot be decoded ends the file with a warning.
  vision::Result<bool> next(cv::Mat& left, cv::Mat& right, VideoFrame& meta);
  [[nodiscard]] double rate() const;        // frames per second, the stream's
  [[nodiscard]] cv::Size viewSize() const;  // one view's size
  [[nodiscard]] uint64_t missing() const;   // frames the time stamps say are not there
  [[nodiscard]] uint64_t unpaired() const;  // frames one file had and the other not
  [[nodiscard]] const std::vector<std::string>& warnings() const;  // the gaps, said once each
  [[nodiscard]] std::string name() const;  // "left.mkv + right.mkv" or "both.mkv (sbs)"

 private:
  struct Impl;
  explicit StereoVideoReader(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// A recording (or any pairs) to lossless FFV1/Matroska: kTwoFiles writes OUT-left.mkv and
// OUT-right.mkv (OUT without its .mkv), the others one OUT.mkv; and OUT-frames.csv
// (video_frame,frame,trigger_seq,t_left_ns,t_right_ns).
class StereoVideoWriter {
 public:
  static vision::Result<StereoVideoWriter> open(const std::string& out, VideoLayout layout,
                                                cv::Size view, double rate);
  StereoVideoWriter(StereoVideoWriter&&) noexcept;
  StereoVideoWriter& operator=(StereoVideoWriter&&) noexcept;
  ~StereoVideoWriter();
  vision::Result<void> write(const cv::Mat& left, const cv::Mat& right, const FrameMeta& meta);
  // Closes the files; the paths written.
  vision::Result<std::vector<std::string>> finish();

 private:
  struct Impl;
  explicit StereoVideoWriter(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace pulsetrack::record
