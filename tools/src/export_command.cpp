// pulsetrack export: a recording to lossless video (FFV1 in Matroska), to an image folder, and to
// an overlay video for talks and papers (the left view, the features by status, the ROI, the
// displacement plot running along).

#include <fmt/format.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <optional>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "pulsetrack/record/video.hpp"
#include "pulsetrack/tools/commands.hpp"

namespace pulsetrack::tools {

namespace {

struct ExportArgs {
  std::string input, video, layout = "two", images, overlay, track, deformation, roi;
  double window_s = 10.0;
  bool quiet = false;
};

cv::Scalar statusColour(const std::string& status) {
  if (status == "ok") return {0, 200, 0};
  if (status == "occluded") return {0, 190, 255};
  if (status == "lost") return {150, 150, 150};
  return {0, 0, 230};  // an outlier (BGR)
}

// The plot strip under the image: dx, dy, dz (mm) over the last `window` seconds.
void drawPlot(cv::Mat& strip, const std::vector<record::DeformationRow>& d, size_t upto,
              double window) {
  strip.setTo(cv::Scalar(255, 255, 255));
  if (d.empty() || upto == 0) return;
  const double t_end = d[upto - 1].t, t_begin = t_end - window;
  double lo = -0.05, hi = 0.05;
  for (size_t k = 0; k < upto; ++k) {
    if (d[k].t < t_begin) continue;
    lo = std::min({lo, d[k].dx, d[k].dy, d[k].dz});
    hi = std::max({hi, d[k].dx, d[k].dy, d[k].dz});
  }
  const double pad = 0.1 * (hi - lo);
  lo -= pad;
  hi += pad;
  const int left = 70, right = 10, top = 10, bottom = 30;
  const int w = strip.cols - left - right, h = strip.rows - top - bottom;
  const auto px = [&](double t, double v) {
    return cv::Point(left + static_cast<int>((t - t_begin) / window * w),
                     top + static_cast<int>((hi - v) / (hi - lo) * h));
  };
  cv::rectangle(strip, cv::Rect(left, top, w, h), cv::Scalar(180, 180, 180));
  if (lo < 0 && hi > 0) cv::line(strip, px(t_begin, 0), px(t_end, 0), cv::Scalar(210, 210, 210));
  const cv::Scalar colours[3] = {{40, 40, 220}, {40, 160, 40}, {220, 90, 30}};  // x red, y, z
  const char* names[3] = {"dx", "dy", "dz"};
  for (int a = 0; a < 3; ++a) {
    std::vector<cv::Point> line;
    for (size_t k = 0; k < upto; ++k) {
      if (d[k].t < t_begin) continue;
      const double v = a == 0 ? d[k].dx : a == 1 ? d[k].dy : d[k].dz;
      line.push_back(px(d[k].t, v));
    }
    if (line.size() > 1) cv::polylines(strip, line, false, colours[a], 2, cv::LINE_AA);
    cv::putText(strip, names[a], cv::Point(left + 10 + 50 * a, strip.rows - 8),
                cv::FONT_HERSHEY_SIMPLEX, 0.6, colours[a], 2, cv::LINE_AA);
  }
  cv::putText(strip, fmt::format("{:+.2f} mm", hi), cv::Point(2, top + 12),
              cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
  cv::putText(strip, fmt::format("{:+.2f} mm", lo), cv::Point(2, top + h), cv::FONT_HERSHEY_SIMPLEX,
              0.45, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
  cv::putText(strip, fmt::format("displacement, last {:.0f} s", window),
              cv::Point(left + 200, strip.rows - 8), cv::FONT_HERSHEY_SIMPLEX, 0.55,
              cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
}

// A writer for the overlay: H.264 in .mp4 (MPEG-4 part 2 when the FFmpeg build has no H.264
// encoder), Motion JPEG in .avi, FFV1 in .mkv.
vision::Result<cv::VideoWriter> overlayWriter(const std::string& path, double rate, cv::Size size) {
  const std::string ext = std::filesystem::path(path).extension().string();
  std::vector<int> fourccs;
  if (ext == ".mp4") {
    fourccs = {cv::VideoWriter::fourcc('a', 'v', 'c', '1'),
               cv::VideoWriter::fourcc('m', 'p', '4', 'v')};
  } else if (ext == ".avi") {
    fourccs = {cv::VideoWriter::fourcc('M', 'J', 'P', 'G')};
  } else if (ext == ".mkv") {
    fourccs = {cv::VideoWriter::fourcc('F', 'F', 'V', '1')};
  } else {
    return vision::fail(fmt::format("{}: the overlay is .mp4, .avi or .mkv", path));
  }
  for (int f : fourccs) {
    cv::VideoWriter w;
    try {
      w.open(path, cv::CAP_FFMPEG, f, rate, size, true);
    } catch (const cv::Exception&) {
      continue;
    }
    if (w.isOpened()) return w;
  }
  return vision::fail(fmt::format("{}: OpenCV's FFmpeg backend cannot write this video", path));
}

int runExport(const ExportArgs& a) {
  if (a.video.empty() && a.images.empty() && a.overlay.empty())
    return commandError("export", "nothing to do: give --video, --images or --overlay");
  if (!a.overlay.empty() && a.track.empty())
    return commandError("export", "--overlay needs --track (the track CSV of this recording)");
  auto r = record::Reader::open(a.input);
  if (!r) return commandError("export", r.error().message);
  if (const auto& cut = r->truncation(); cut.has_value())
    fmt::print(stderr, "warning: {}: {}\n", a.input, cut.value());
  if (r->size() == 0)
    return commandError("export",
                        fmt::format("{}: the recording holds no complete frame", a.input));
  const size_t n = r->size();
  // The recording's rate: its exposures' median spacing.
  std::vector<int64_t> dt;
  for (size_t i = 1; i < n; ++i) {
    const uint64_t frames = r->meta(i).frame - r->meta(i - 1).frame;
    if (frames > 0)
      dt.push_back((r->meta(i).t_left_ns - r->meta(i - 1).t_left_ns) /
                   static_cast<int64_t>(frames));
  }
  std::sort(dt.begin(), dt.end());
  const double rate =
      dt.empty() || dt[dt.size() / 2] <= 0 ? 30.0 : 1e9 / static_cast<double>(dt[dt.size() / 2]);
  const cv::Size view = r->rig().left.imageSize();

  std::optional<record::StereoVideoWriter> video;
  if (!a.video.empty()) {
    auto layout = record::parseVideoLayout(a.layout);
    if (!layout) return commandError("export", layout.error().message);
    auto w = record::StereoVideoWriter::open(a.video, *layout, view, rate);
    if (!w) return commandError("export", w.error().message);
    video.emplace(std::move(*w));
  }
  std::ofstream images_csv;
  if (!a.images.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(a.images, ec);
    if (ec) return commandError("export", fmt::format("{}: {}", a.images, ec.message()));
    images_csv.open(std::filesystem::path(a.images) / "frames.csv");
    if (!images_csv)
      return commandError("export", fmt::format("{}/frames.csv: cannot write", a.images));
    images_csv << "frame,trigger_seq,t_left_ns,t_right_ns,left,right\n";
  }
  // The overlay's inputs: the track's rows by frame, the deformation beside it.
  std::map<long, std::vector<record::TrackRow>> by_frame;
  std::vector<record::DeformationRow> deformation;
  std::optional<cv::Rect> roi;
  std::optional<cv::VideoWriter> overlay;
  cv::Mat canvas;
  constexpr int kStrip = 220;
  if (!a.overlay.empty()) {
    auto rows = record::readTrackCsv(a.track);
    if (!rows) return commandError("export", rows.error().message);
    for (auto& row : *rows) by_frame[row.frame].push_back(std::move(row));
    std::string def = a.deformation;
    if (def.empty()) {
      const std::filesystem::path p(a.track);
      def = (p.parent_path() / (p.stem().string() + "-deformation.csv")).string();
    }
    if (std::filesystem::exists(def)) {
      auto d = record::readDeformationCsv(def);
      if (!d) return commandError("export", d.error().message);
      deformation = std::move(*d);
    } else if (!a.deformation.empty()) {
      return commandError("export", fmt::format("{}: no such file", def));
    }
    if (!a.roi.empty()) {
      auto rect = parseRect(a.roi, "--roi-left");
      if (!rect) return commandError("export", rect.error().message);
      roi = *rect;
    }
    const cv::Size size(view.width + view.width % 2, view.height + kStrip);
    auto w = overlayWriter(a.overlay, rate, size);
    if (!w) return commandError("export", w.error().message);
    overlay.emplace(std::move(*w));
    canvas.create(size, CV_8UC3);
  }

  cv::Mat left, right, colour;
  size_t def_upto = 0;
  int drawn_frames = 0;
  for (size_t i = 0; i < n; ++i) {
    if (auto ok = r->read(i, left, right); !ok) return commandError("export", ok.error().message);
    const record::FrameMeta& m = r->meta(i);
    if (video) {
      if (auto ok = video->write(left, right, m); !ok)
        return commandError("export", ok.error().message);
    }
    if (images_csv.is_open()) {
      const std::string l = fmt::format("left_{:06d}.png", m.frame);
      const std::string rr = fmt::format("right_{:06d}.png", m.frame);
      const std::filesystem::path dir(a.images);
      if (!cv::imwrite((dir / l).string(), left) || !cv::imwrite((dir / rr).string(), right))
        return commandError("export", fmt::format("{}: cannot write frame {}", a.images, m.frame));
      images_csv << fmt::format("{},{},{},{},{},{}\n", m.frame, m.trigger_seq, m.t_left_ns,
                                m.t_right_ns, l, rr);
    }
    if (overlay) {
      canvas.setTo(cv::Scalar(0, 0, 0));
      cv::Mat top = canvas(cv::Rect(0, 0, view.width, view.height));
      cv::cvtColor(left, colour, cv::COLOR_GRAY2BGR);
      colour.copyTo(top);
      if (roi) cv::rectangle(top, *roi, cv::Scalar(255, 200, 0), 2);
      int ok = 0, total = 0;
      if (const auto it = by_frame.find(static_cast<long>(m.frame)); it != by_frame.end()) {
        ++drawn_frames;
        for (const record::TrackRow& f : it->second) {
          ++total;
          ok += f.ok() ? 1 : 0;
          cv::circle(top, cv::Point2d(f.xl, f.yl), 5, statusColour(f.status), 2, cv::LINE_AA);
        }
      }
      while (def_upto < deformation.size() &&
             deformation[def_upto].frame <= static_cast<long>(m.frame))
        ++def_upto;
      cv::Mat strip = canvas(cv::Rect(0, view.height, canvas.cols, kStrip));
      drawPlot(strip, deformation, def_upto, a.window_s);
      cv::putText(
          top,
          fmt::format("frame {}  t {:.3f} s  {} of {} features ok", m.frame,
                      static_cast<double>(m.t_left_ns - r->meta(0).t_left_ns) * 1e-9, ok, total),
          cv::Point(12, 32), cv::FONT_HERSHEY_SIMPLEX, 0.9, cv::Scalar(255, 255, 255), 2,
          cv::LINE_AA);
      overlay->write(canvas);
    }
    if (!a.quiet && (i + 1) % 100 == 0) fmt::print(stderr, "export: frame {}/{}\n", i + 1, n);
  }
  fmt::print("export: {} pairs of {} at {:.3f} frames/s\n", n, a.input, rate);
  if (video) {
    auto paths = video->finish();
    if (!paths) return commandError("export", paths.error().message);
    for (const std::string& p : *paths) fmt::print("  video: {}\n", p);
  }
  if (images_csv.is_open()) {
    images_csv.close();
    if (!images_csv)
      return commandError("export", fmt::format("{}/frames.csv: write failed", a.images));
    fmt::print("  images: {}/left_*.png, right_*.png, frames.csv\n", a.images);
  }
  if (overlay) {
    overlay->release();
    if (drawn_frames == 0)
      fmt::print(stderr, "warning: {} has no row for any frame of {}\n", a.track, a.input);
    fmt::print("  overlay: {} ({} frames with features)\n", a.overlay, drawn_frames);
  }
  return 0;
}

}  // namespace

CommandRunner addExportCommand(CLI::App& app) {
  auto a = std::make_shared<ExportArgs>();
  CLI::App* cmd = app.add_subcommand(
      "export",
      "A recording to lossless video (FFV1 in Matroska, bit-exact 8-bit grey), to an image "
      "folder (PNG), and to an overlay video (features by status, ROI, displacement plot) for "
      "talks and papers (docs/video.md).");
  cmd->add_option("recording", a->input, "Recording folder")->required();
  cmd->add_option("--video", a->video,
                  "Lossless video: OUT-left.mkv and OUT-right.mkv (--layout two), or OUT.mkv; "
                  "OUT-frames.csv keeps each frame's number and exposure times");
  cmd->add_option("--layout", a->layout, "two (files), sbs (side by side) or tb (top-bottom)")
      ->check(CLI::IsMember({"two", "sbs", "tb"}))
      ->capture_default_str();
  cmd->add_option("--images", a->images,
                  "Image folder: left_NNNNNN.png, right_NNNNNN.png (the recording's frame "
                  "numbers), frames.csv");
  cmd->add_option("--overlay", a->overlay,
                  "Overlay video (.mp4: H.264, .avi: Motion JPEG, .mkv: FFV1) of the left view "
                  "with --track's features by status and the displacement plot");
  cmd->add_option("--track", a->track, "The track CSV of this recording (pulsetrack track)");
  cmd->add_option("--deformation", a->deformation,
                  "Its deformation CSV (default: beside --track, NAME-deformation.csv)");
  cmd->add_option("--roi-left", a->roi, "The left ROI to draw: x,y,w,h (px)");
  cmd->add_option("--window", a->window_s, "Seconds of displacement in the plot")
      ->check(CLI::Range(1.0, 3600.0))
      ->capture_default_str();
  cmd->add_flag("-q,--quiet", a->quiet, "No progress lines");
  return [a] { return runExport(*a); };
}

}  // namespace pulsetrack::tools
