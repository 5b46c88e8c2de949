#include "pulsetrack/record/video.hpp"

#include <fmt/format.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <optional>

namespace pulsetrack::record {

using vision::fail;

vision::Result<VideoLayout> parseVideoLayout(const std::string& text) {
  if (text == "two") return VideoLayout::kTwoFiles;
  if (text == "sbs") return VideoLayout::kSideBySide;
  if (text == "tb") return VideoLayout::kTopBottom;
  return fail(fmt::format("video layout '{}': expected two, sbs or tb", text));
}

namespace {

// One file: its frames in grey with their time stamps and numbers.
struct VideoStream {
  std::string path;
  cv::VideoCapture cap;
  double rate = 0;
  double t0_ms = 0;
  bool started = false;
  bool ended = false;
  std::optional<uint64_t> last;  // the previous frame's number
  cv::Mat bgr;

  static vision::Result<VideoStream> open(const std::string& path) {
    VideoStream s;
    s.path = path;
    if (!std::filesystem::is_regular_file(path)) return fail(fmt::format("{}: no such file", path));
    try {
      s.cap.open(path, cv::CAP_FFMPEG);
    } catch (const cv::Exception& e) {
      return fail(fmt::format("{}: cannot open as video: {}", path, e.err));
    }
    if (!s.cap.isOpened())
      return fail(fmt::format("{}: cannot open as video (OpenCV's FFmpeg backend)", path));
    s.rate = s.cap.get(cv::CAP_PROP_FPS);
    if (!(s.rate > 0.0 && s.rate < 100000.0))
      return fail(fmt::format("{}: the stream gives no frame rate", path));
    return s;
  }
  // The next frame (grey) and its number; false at the end.
  bool read(cv::Mat& grey, uint64_t& number, int64_t& t_ns, std::vector<std::string>& warnings) {
    if (ended) return false;
    bool ok = false;
    try {
      ok = cap.read(bgr);
    } catch (const cv::Exception& e) {
      warnings.push_back(fmt::format("{}: decoding stopped: {}", path, e.err));
    }
    if (!ok || bgr.empty()) {
      ended = true;
      return false;
    }
    const double t_ms = cap.get(cv::CAP_PROP_POS_MSEC);
    if (!started) {
      t0_ms = t_ms;
      started = true;
    }
    const double since = (t_ms - t0_ms) * 1e-3;
    number = static_cast<uint64_t>(std::llround(std::max(0.0, since) * rate));
    t_ns = static_cast<int64_t>(std::llround(t_ms * 1e6));
    if (last && number <= *last) number = *last + 1;  // a stamp that did not advance
    if (last && number > *last + 1) {
      warnings.push_back(fmt::format(
          "{}: {} frame(s) missing after frame {} (the time stamps "
          "jump from {:.3f} s to {:.3f} s at {:.3f} frames/s)",
          path, number - *last - 1, *last, static_cast<double>(*last) / rate, since, rate));
    }
    last = number;
    if (bgr.channels() == 3)
      cv::cvtColor(bgr, grey, cv::COLOR_BGR2GRAY);
    else if (bgr.channels() == 4)
      cv::cvtColor(bgr, grey, cv::COLOR_BGRA2GRAY);
    else
      bgr.copyTo(grey);
    return true;
  }
};

}  // namespace

struct StereoVideoReader::Impl {
  VideoLayout layout = VideoLayout::kTwoFiles;
  VideoStream a, b;  // b: the right file (two files only)
  cv::Size view;
  uint64_t missing = 0, unpaired = 0;
  std::optional<uint64_t> last_pair;
  std::vector<std::string> warnings;
  cv::Mat ga, gb;
};

StereoVideoReader::StereoVideoReader(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
StereoVideoReader::StereoVideoReader(StereoVideoReader&&) noexcept = default;
StereoVideoReader& StereoVideoReader::operator=(StereoVideoReader&&) noexcept = default;
StereoVideoReader::~StereoVideoReader() = default;

vision::Result<StereoVideoReader> StereoVideoReader::open(const std::string& left,
                                                          const std::string& right,
                                                          VideoLayout layout) {
  auto impl = std::make_unique<Impl>();
  impl->layout = layout;
  auto a = VideoStream::open(left);
  if (!a) return std::unexpected(a.error());
  impl->a = std::move(*a);
  const cv::Size whole(static_cast<int>(impl->a.cap.get(cv::CAP_PROP_FRAME_WIDTH)),
                       static_cast<int>(impl->a.cap.get(cv::CAP_PROP_FRAME_HEIGHT)));
  if (whole.width <= 0 || whole.height <= 0)
    return fail(fmt::format("{}: the stream gives no image size", left));
  if (layout == VideoLayout::kTwoFiles) {
    if (right.empty()) return fail(fmt::format("{}: two files, but no right view's file", left));
    auto b = VideoStream::open(right);
    if (!b) return std::unexpected(b.error());
    impl->b = std::move(*b);
    const cv::Size other(static_cast<int>(impl->b.cap.get(cv::CAP_PROP_FRAME_WIDTH)),
                         static_cast<int>(impl->b.cap.get(cv::CAP_PROP_FRAME_HEIGHT)));
    if (other != whole)
      return fail(fmt::format("{} is {}x{}, {} is {}x{}: the views must be the same size", left,
                              whole.width, whole.height, right, other.width, other.height));
    if (std::fabs(impl->a.rate - impl->b.rate) > 1e-3 * impl->a.rate)
      return fail(fmt::format("{} runs at {:.3f} frames/s, {} at {:.3f}: not one stereo stream",
                              left, impl->a.rate, right, impl->b.rate));
    impl->view = whole;
  } else if (layout == VideoLayout::kSideBySide) {
    if (whole.width % 2 != 0)
      return fail(
          fmt::format("{}: {} px wide: side by side needs an even width", left, whole.width));
    impl->view = {whole.width / 2, whole.height};
  } else {
    if (whole.height % 2 != 0)
      return fail(
          fmt::format("{}: {} px high: top and bottom needs an even height", left, whole.height));
    impl->view = {whole.width, whole.height / 2};
  }
  return StereoVideoReader(std::move(impl));
}

vision::Result<bool> StereoVideoReader::next(cv::Mat& left, cv::Mat& right, VideoFrame& meta) {
  Impl& i = *impl_;
  uint64_t na = 0, nb = 0;
  int64_t ta = 0, tb = 0;
  if (!i.a.read(i.ga, na, ta, i.warnings)) return false;
  if (i.ga.size() !=
      (i.layout == VideoLayout::kTwoFiles
           ? i.view
           : cv::Size(i.layout == VideoLayout::kSideBySide ? 2 * i.view.width : i.view.width,
                      i.layout == VideoLayout::kTopBottom ? 2 * i.view.height : i.view.height))) {
    return fail(fmt::format("{}: frame {} is {}x{}, the stream said otherwise", i.a.path, na,
                            i.ga.cols, i.ga.rows));
  }
  if (i.layout == VideoLayout::kTwoFiles) {
    // Pair by frame number: the file that is behind reads on (its extra frames unpaired).
    if (!i.b.read(i.gb, nb, tb, i.warnings)) return false;
    while (na != nb) {
      ++i.unpaired;
      if (na < nb) {
        if (!i.a.read(i.ga, na, ta, i.warnings)) return false;
      } else {
        if (!i.b.read(i.gb, nb, tb, i.warnings)) return false;
      }
    }
    i.ga.copyTo(left);
    i.gb.copyTo(right);
  } else if (i.layout == VideoLayout::kSideBySide) {
    i.ga(cv::Rect(0, 0, i.view.width, i.view.height)).copyTo(left);
    i.ga(cv::Rect(i.view.width, 0, i.view.width, i.view.height)).copyTo(right);
  } else {
    i.ga(cv::Rect(0, 0, i.view.width, i.view.height)).copyTo(left);
    i.ga(cv::Rect(0, i.view.height, i.view.width, i.view.height)).copyTo(right);
  }
  if (i.last_pair && na > *i.last_pair + 1) i.missing += na - *i.last_pair - 1;
  i.last_pair = na;
  meta.frame = na;
  meta.t_ns = ta;
  return true;
}

double StereoVideoReader::rate() const { return impl_->a.rate; }
cv::Size StereoVideoReader::viewSize() const { return impl_->view; }
uint64_t StereoVideoReader::missing() const { return impl_->missing; }
uint64_t StereoVideoReader::unpaired() const { return impl_->unpaired; }
const std::vector<std::string>& StereoVideoReader::warnings() const { return impl_->warnings; }
std::string StereoVideoReader::name() const {
  if (impl_->layout == VideoLayout::kTwoFiles) return impl_->a.path + " + " + impl_->b.path;
  return fmt::format("{} ({})", impl_->a.path,
                     impl_->layout == VideoLayout::kSideBySide ? "side by side" : "top-bottom");
}

// ----------------------------------------------------------------------------------------------

struct StereoVideoWriter::Impl {
  VideoLayout layout = VideoLayout::kTwoFiles;
  cv::Size view;
  std::vector<std::string> paths;
  cv::VideoWriter a, b;
  std::ofstream csv;
  uint64_t written = 0;
  cv::Mat both;
};

StereoVideoWriter::StereoVideoWriter(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
StereoVideoWriter::StereoVideoWriter(StereoVideoWriter&&) noexcept = default;
StereoVideoWriter& StereoVideoWriter::operator=(StereoVideoWriter&&) noexcept = default;
StereoVideoWriter::~StereoVideoWriter() = default;

vision::Result<StereoVideoWriter> StereoVideoWriter::open(const std::string& out,
                                                          VideoLayout layout, cv::Size view,
                                                          double rate) {
  auto impl = std::make_unique<Impl>();
  impl->layout = layout;
  impl->view = view;
  std::filesystem::path base(out);
  if (base.extension() == ".mkv") base.replace_extension();
  const int ffv1 = cv::VideoWriter::fourcc('F', 'F', 'V', '1');
  const auto openOne = [&](cv::VideoWriter& w, const std::string& path,
                           cv::Size size) -> vision::Result<void> {
    try {
      w.open(path, cv::CAP_FFMPEG, ffv1, rate, size, false);
    } catch (const cv::Exception& e) {
      return fail(fmt::format("{}: cannot write FFV1 video: {}", path, e.err));
    }
    if (!w.isOpened())
      return fail(fmt::format("{}: cannot write FFV1 video (OpenCV's FFmpeg backend)", path));
    impl->paths.push_back(path);
    return {};
  };
  if (layout == VideoLayout::kTwoFiles) {
    if (auto ok = openOne(impl->a, base.string() + "-left.mkv", view); !ok)
      return std::unexpected(ok.error());
    if (auto ok = openOne(impl->b, base.string() + "-right.mkv", view); !ok)
      return std::unexpected(ok.error());
  } else {
    const cv::Size whole = layout == VideoLayout::kSideBySide
                               ? cv::Size(2 * view.width, view.height)
                               : cv::Size(view.width, 2 * view.height);
    if (auto ok = openOne(impl->a, base.string() + ".mkv", whole); !ok)
      return std::unexpected(ok.error());
  }
  const std::string csv = base.string() + "-frames.csv";
  impl->csv.open(csv);
  if (!impl->csv) return fail(fmt::format("{}: cannot write", csv));
  impl->csv << "video_frame,frame,trigger_seq,t_left_ns,t_right_ns\n";
  impl->paths.push_back(csv);
  return StereoVideoWriter(std::move(impl));
}

vision::Result<void> StereoVideoWriter::write(const cv::Mat& left, const cv::Mat& right,
                                              const FrameMeta& meta) {
  Impl& i = *impl_;
  if (left.size() != i.view || right.size() != i.view || left.type() != CV_8UC1 ||
      right.type() != CV_8UC1)
    return fail(fmt::format("{}: frame {} is not two 8-bit grey {}x{} views", i.paths.front(),
                            meta.frame, i.view.width, i.view.height));
  if (i.layout == VideoLayout::kTwoFiles) {
    i.a.write(left);
    i.b.write(right);
  } else {
    if (i.layout == VideoLayout::kSideBySide)
      cv::hconcat(left, right, i.both);
    else
      cv::vconcat(left, right, i.both);
    i.a.write(i.both);
  }
  i.csv << fmt::format("{},{},{},{},{}\n", i.written++, meta.frame, meta.trigger_seq,
                       meta.t_left_ns, meta.t_right_ns);
  return {};
}

vision::Result<std::vector<std::string>> StereoVideoWriter::finish() {
  Impl& i = *impl_;
  i.a.release();
  i.b.release();
  i.csv.close();
  if (!i.csv) return fail(fmt::format("{}: write failed", i.paths.back()));
  return i.paths;
}

}  // namespace pulsetrack::record
