// pulsetrack match / pulsetrack track: the tracking core on one pair or a whole sequence, the
// same code the daemon runs per frame.

#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <charconv>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <optional>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "pulsetrack/record/video.hpp"
#include "pulsetrack/tools/commands.hpp"
#include "pulsetrack/tools/field_output.hpp"
#include "pulsetrack/tools/image_pairs.hpp"
#include "pulsetrack/vision/fields.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"
#include "pulsetrack/vision/tracking_session.hpp"

namespace pulsetrack::tools {

namespace {

struct CommonArgs {
  std::string rig;
  std::string rectified;
  std::vector<std::string> camera_info;
  std::string roi_left;
  std::string roi_right;
  double depth = 20.0;
  std::string depth_range;
  int max_features = 100;
  int stereo_refresh = vision::TrackerConfig{}.stereo_refresh;
  int template_refresh = vision::TrackerConfig{}.template_refresh;
  bool no_refinement = false;
  std::string detector = "harris";
  std::string out;

  [[nodiscard]] vision::TrackerConfig config() const {
    vision::TrackerConfig c;
    c.max_features = max_features;
    c.stereo_refresh = stereo_refresh;
    c.template_refresh = template_refresh;
    c.refinement = !no_refinement;
    c.detector = detector == "blobs" ? vision::Detector::kDarkBlobs : vision::Detector::kHarris;
    return c;
  }
};

void addCommon(CLI::App* cmd, CommonArgs& a) {
  cmd->add_option("--rig", a.rig,
                  "Rig YAML: pulsetrack calibrate's, or OpenCV's stereo calibration (M1 D1 M2 D2 "
                  "R T; image_size and rms optional)");
  cmd->add_option("--rectified", a.rectified,
                  "Instead of --rig, for already rectified images: f,cx,cy,baseline_mm (focal "
                  "length and principal point in px)");
  cmd->add_option("--camera-info", a.camera_info,
                  "Instead of --rig: the left and right ROS camera_info YAML files of a stereo "
                  "pair (LEFT.yaml,RIGHT.yaml)")
      ->delimiter(',')
      ->expected(2);
  cmd->add_option(
      "--roi-left", a.roi_left,
      "Left ROI on the tissue: x,y,w,h (px); default: the best well-textured region (glare "
      "and dark borders left out) in the first pair's left image, said as found");
  cmd->add_option("--roi-right", a.roi_right,
                  "The corresponding right ROI: x,y,w,h (px); default: found in the first pair "
                  "by searching the left ROI's epipolar lines over --depth-range");
  cmd->add_option("--depth", a.depth,
                  "With --roi-right: depth tolerance of the stereo search box (mm)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--depth-range", a.depth_range,
                  "Without --roi-right: the depths searched for the left ROI's surface, "
                  "near,far in mm")
      ->default_str("20,1000");
  cmd->add_option("--max-features", a.max_features, "Feature ceiling")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  cmd->add_option("--stereo-refresh", a.stereo_refresh,
                  "Features whose stereo match is taken again per pair and averaged (takes the "
                  "first pair's sensor noise out of the positions; 0: off)")
      ->check(CLI::Range(0, 1000))
      ->capture_default_str();
  cmd->add_option("--template-refresh", a.template_refresh,
                  "Features per pair whose look becomes their recent template, searched where the "
                  "first pair's template finds nothing (tissue that changes its look: a beating "
                  "heart; 0: off)")
      ->check(CLI::Range(0, 1000))
      ->capture_default_str();
  cmd->add_flag("--no-refinement", a.no_refinement,
                "NCC with the paper's quadratic peak only (no sub-pixel refinement)");
  cmd->add_option("--detector", a.detector,
                  "harris: corners on tissue (the paper's); blobs: small dark blobs, centred "
                  "(the validation plate's holes)")
      ->check(CLI::IsMember({"harris", "blobs"}))
      ->capture_default_str();
  cmd->add_option("--out", a.out, "CSV to write")->required();
}

// The left ROI, and the right one when given (else empty: found in the pair).
vision::Result<vision::Roi> rois(const CommonArgs& a) {
  if (a.roi_left.empty()) {
    if (!a.roi_right.empty()) return vision::fail("--roi-right needs --roi-left");
    return vision::Roi{};  // both found in the first pair
  }
  auto l = parseRect(a.roi_left, "--roi-left");
  if (!l) return std::unexpected(l.error());
  if (a.roi_right.empty()) return vision::Roi{*l, {}};
  auto r = parseRect(a.roi_right, "--roi-right");
  if (!r) return std::unexpected(r.error());
  return vision::Roi{*l, *r};
}

vision::Result<vision::StereoSearchConfig> searchConfig(const CommonArgs& a) {
  if (a.depth_range.empty()) return vision::StereoSearchConfig{};
  return vision::parseDepthRange(a.depth_range);
}

// The rig from --rig, --rectified or --camera-info (one of them), for images of data_size
// (named data_name in messages): a calibration without image_size takes it from them.
vision::Result<vision::StereoRig> loadRigArgs(const CommonArgs& a, cv::Size data_size,
                                              const std::string& data_name) {
  const int given = static_cast<int>(!a.rig.empty()) + static_cast<int>(!a.rectified.empty()) +
                    static_cast<int>(!a.camera_info.empty());
  if (given > 1) return vision::fail("give one of --rig, --rectified and --camera-info");
  if (given == 0) return vision::fail("give the cameras: --rig, --rectified or --camera-info");
  if (!a.rectified.empty()) return vision::parseRectified(a.rectified, data_size);
  if (!a.camera_info.empty())
    return vision::loadCameraInfoPair(a.camera_info[0], a.camera_info[1], data_size, data_name);
  auto rig = vision::loadRig(a.rig, data_size, data_name);
  if (rig) {
    if (const std::string note = vision::rigNotes(*rig, a.rig); !note.empty())
      fmt::print(stderr, "note: {}\n", note);
  }
  return rig;
}

bool rigGiven(const CommonArgs& a) {
  return !a.rig.empty() || !a.rectified.empty() || !a.camera_info.empty();
}

vision::Result<cv::Mat> readGrey(const std::string& path) {
  cv::Mat img;
  try {
    img = cv::imread(path, cv::IMREAD_GRAYSCALE);
  } catch (const cv::Exception& e) {
    return vision::fail(fmt::format("{}: cannot read image: {}", path, e.err));
  }
  if (img.empty()) return vision::fail(fmt::format("{}: unreadable image", path));
  return img;
}

struct MatchArgs : CommonArgs {
  std::string left;
  std::string right;
};

int runMatch(const MatchArgs& a) {
  auto roi = rois(a);
  if (!roi) return commandError("match", roi.error().message);
  auto search = searchConfig(a);
  if (!search) return commandError("match", search.error().message);
  auto left = readGrey(a.left);
  if (!left) return commandError("match", left.error().message);
  auto right = readGrey(a.right);
  if (!right) return commandError("match", right.error().message);
  auto rig = loadRigArgs(a, left->size(), a.left);
  if (!rig) return commandError("match", rig.error().message);
  double depth = a.depth;
  if (roi->right == cv::Rect()) {
    auto found =
        vision::findStereoRoi(*rig, *left, *right, roi->left, 2 * vision::kAffineSide, *search);
    if (!found) return commandError("match", found.error().message);
    fmt::print("stereo search     {}\n", found->summary());
    roi->left = found->left;
    roi->right = found->right;
    depth = found->tolerance_mm;
  }
  if (auto usable = vision::TrackingSession::checkRoi(*rig, *roi, depth); !usable)
    return commandError("match", usable.error().message);
  const vision::TrackerConfig config = a.config();
  vision::StereoTracker tracker(*rig, config);
  auto ok = tracker.initialize(*left, *right, *roi, depth);
  if (!ok) return commandError("match", ok.error().message);
  std::ofstream out(a.out);
  out << "id,xl,yl,xr,yr,ncc,nmi,epipolar_px,x,y,z,status\n";
  int id = 0;
  for (const vision::StereoCandidate& c : tracker.candidates()) {
    out << fmt::format(
        "{},{:.4f},{:.4f},{:.4f},{:.4f},{:.4f},{:.4f},{:.4f},{:.5f},{:.5f},{:.5f},{}\n", id++,
        c.left[0], c.left[1], c.right[0], c.right[1], c.ncc, c.nmi, c.epipolar_px, c.point[0],
        c.point[1], c.point[2], vision::statusText(c.status, c.gate));
  }
  if (!out) return commandError("match", fmt::format("{}: write failed", a.out));
  fmt::print("gates             {}\n", tracker.fittedGates().summary());
  fmt::print("{} candidates, {} ok, written to {}\n", tracker.candidates().size(), *ok, a.out);
  return 0;
}

struct TrackArgs : CommonArgs {
  std::string input;
  std::string left;
  std::string right;
  std::string video, left_video, right_video, layout = "sbs";
  std::string fields;  // "", "tff" or "bff"
  std::string scale = "auto";
  std::string deformation;
  double fps = 10.0;
  double retry_interval = vision::SessionConfig{}.retry_interval_s;
  double velocity_window = vision::SessionConfig{}.velocity_window_s;
  bool quiet = false;
  std::string field, targets, targets_out;
  int field_every = 10;
  double field_spacing = vision::FieldConfig{}.spacing_mm;
  double field_smoothing = vision::FieldConfig{}.smoothing;
};

// The deformation file: --deformation, or beside --out (track.csv -> track-deformation.csv).
std::string deformationPath(const TrackArgs& a) {
  if (!a.deformation.empty()) return a.deformation;
  std::filesystem::path p(a.out);
  return (p.parent_path() / (p.stem().string() + "-deformation.csv")).string();
}

int runTrack(const TrackArgs& a) {
  auto roi = rois(a);
  if (!roi) return commandError("track", roi.error().message);
  auto search = searchConfig(a);
  if (!search) return commandError("track", search.error().message);
  std::optional<record::Reader> reader;
  std::optional<record::StereoVideoReader> video;
  std::vector<std::pair<std::string, std::string>> pairs;
  vision::StereoRig rig;
  const int inputs = static_cast<int>(!a.input.empty()) +
                     static_cast<int>(!a.left.empty() || !a.right.empty()) +
                     static_cast<int>(!a.video.empty()) +
                     static_cast<int>(!a.left_video.empty() || !a.right_video.empty());
  if (inputs > 1)
    return commandError("track",
                        "give one input: --input, --left/--right, --video, or "
                        "--left-video/--right-video");
  if (!a.video.empty() || !a.left_video.empty() || !a.right_video.empty()) {
    if (!rigGiven(a))
      return commandError("track",
                          "--rig, --rectified or --camera-info is required with video files");
    auto layout = record::parseVideoLayout(a.video.empty() ? "two" : a.layout);
    if (!layout) return commandError("track", layout.error().message);
    if (a.video.empty() && (a.left_video.empty() || a.right_video.empty()))
      return commandError("track", "give both --left-video and --right-video");
    auto v = a.video.empty() ? record::StereoVideoReader::open(a.left_video, a.right_video, *layout)
                             : record::StereoVideoReader::open(a.video, "", *layout);
    if (!v) return commandError("track", v.error().message);
    video.emplace(std::move(*v));
  } else if (!a.input.empty()) {
    auto r = record::Reader::open(a.input);
    if (!r) return commandError("track", r.error().message);
    if (const auto& cut = r->truncation(); cut.has_value())
      fmt::print(stderr, "warning: {}: {}\n", a.input, cut.value());
    for (const std::string& w : r->warnings()) fmt::print(stderr, "warning: {}\n", w);
    if (r->size() == 0)
      return commandError("track",
                          fmt::format("{}: the recording holds no complete frame", a.input));
    reader.emplace(std::move(*r));
    rig = reader->rig();
  } else {
    if (a.left.empty() || a.right.empty())
      return commandError("track",
                          "give --input RECORDING, --left and --right globs, --video FILE or "
                          "--left-video and --right-video");
    auto p = pairImages(a.left, a.right);
    if (!p) return commandError("track", p.error().message);
    pairs = std::move(*p);
  }
  if (rigGiven(a)) {
    // The data's size: a calibration without image_size takes it, one with it must agree.
    cv::Size data_size;
    std::string data_name;
    if (video) {
      data_size = video->viewSize();
      data_name = fmt::format("each view of {}", video->name());
    } else if (reader) {
      data_size = reader->rig().left.imageSize();
      data_name = fmt::format("the recording {}", a.input);
    } else {
      auto first = readGrey(pairs.front().first);
      if (!first) return commandError("track", first.error().message);
      data_size = first->size();
      data_name = pairs.front().first;
    }
    auto r = loadRigArgs(a, data_size, data_name);
    if (!r) return commandError("track", r.error().message);
    rig = *r;
  } else if (!reader) {
    return commandError("track",
                        "--rig, --rectified or --camera-info is required with image sequences");
  }
  if (auto ok = vision::TrackingSession::checkRoi(rig, *roi, a.depth); !ok)
    return commandError("track", ok.error().message);
  // A video's length is known at its end (a container's frame count is an estimate).
  size_t n = reader ? reader->size() : video ? 0 : pairs.size();
  // The daemon's policy, the same code: detection, retries, re-detection, stereo refresh and
  // the deformation (offline = live).
  vision::SessionConfig sc;
  sc.tracker = a.config();
  sc.roi = *roi;
  sc.depth_tolerance_mm = a.depth;
  sc.search = *search;
  sc.retry_interval_s = a.retry_interval;
  sc.velocity_window_s = a.velocity_window;
  sc.scale = a.scale == "auto" ? 0.0 : std::stod(a.scale);
  vision::TrackingSession session(rig, sc);
  // The dense field and the targets' answers (the daemon's field, the same code).
  std::vector<cv::Vec3d> targets;
  if (!a.targets.empty()) {
    auto t = readPoints(a.targets);
    if (!t) return commandError("track", t.error().message);
    targets = std::move(*t);
  }
  std::optional<FieldOutput> field_out;
  if (!a.field.empty() || !targets.empty()) {
    vision::FieldConfig fc;
    fc.spacing_mm = a.field_spacing;
    fc.smoothing = a.field_smoothing;
    if (auto ok = vision::checkFieldConfig(fc); !ok)
      return commandError("track", ok.error().message);
    std::string targets_out = a.targets_out;
    if (targets_out.empty() && !targets.empty()) {
      const std::filesystem::path p(a.out);
      targets_out = (p.parent_path() / (p.stem().string() + "-targets.csv")).string();
    }
    auto fo = FieldOutput::open(a.field, a.field_every, targets, targets_out, fc,
                                sc.tracker.max_features);
    if (!fo) return commandError("track", fo.error().message);
    field_out.emplace(std::move(*fo));
  }
  std::vector<record::TrackRow> rows;
  std::vector<record::DeformationRow> deformation;
  // The predictions, as pulsetrackd publishes them with each deformation sample (beside --out:
  // track.csv -> track-prediction.csv).
  const std::string prediction_path = [&] {
    const std::filesystem::path p(a.out);
    return (p.parent_path() / (p.stem().string() + "-prediction.csv")).string();
  }();
  std::ofstream prediction_out(prediction_path);
  if (!prediction_out)
    return commandError("track", fmt::format("{}: cannot write", prediction_path));
  prediction_out << "frame,t,horizon,dx,dy,dz,sigma,model\n";
  long prediction_rows = 0;
  std::vector<double> step_us;
  cv::Mat left, right;
  // Interlaced video: each frame's two fields tracked as pairs of their own, half a frame apart.
  const bool split = !a.fields.empty();
  const double frame_s =
      video    ? 1.0 / video->rate()
      : reader ? (reader->manifest().nominal_fps > 0.0 ? 1.0 / reader->manifest().nominal_fps : 0.0)
               : 1.0 / a.fps;
  if (split && !(frame_s > 0.0))
    return commandError("track", fmt::format("--fields: {} states no frame rate (manifest.toml "
                                             "nominal_fps), so the fields' times are unknown",
                                             a.input));
  const auto order =
      a.fields == "bff" ? vision::FieldOrder::kBottomFirst : vision::FieldOrder::kTopFirst;
  std::array<cv::Mat, 2> field_l, field_r;
  int initial = -1;
  uint64_t reason_seen = 0, range_seen = 0;
  // One pair (a frame, or one of its fields) through the session, into the outputs.
  const auto track_pair = [&](const cv::Mat& l, const cv::Mat& r, long frame, double t,
                              uint64_t seq, int64_t t_ns) -> int {
    const auto t0 = std::chrono::steady_clock::now();
    const vision::PairResult& pr = session.process(l, r, seq, t_ns);
    if (!pr.detected) {
      step_us.push_back(
          std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count());
    }
    if (session.reasonSerial() != reason_seen && !session.reason().empty()) {
      reason_seen = session.reasonSerial();
      if (!a.quiet) fmt::print(stderr, "frame {}: not tracking: {}\n", frame, session.reason());
    }
    if (session.rangeSerial() != range_seen) {
      range_seen = session.rangeSerial();
      if (!a.quiet)
        fmt::print(stderr, "frame {}: stereo search: {}\n", frame, session.stereoRange().summary());
    }
    if (pr.detected && !a.quiet) {
      fmt::print(stderr, "frame {}: {} features {}; gates {}\n", frame, session.tracker().okCount(),
                 initial < 0 ? "detected" : "re-detected (too few ok)",
                 session.tracker().fittedGates().summary());
    }
    if (pr.detected && initial < 0) initial = session.tracker().okCount();
    for (const vision::Feature& f : pr.features) {
      rows.push_back({frame, t, f.id, f.left[0], f.left[1], f.right[0], f.right[1], f.point[0],
                      f.point[1], f.point[2], f.ncc, f.nmi, vision::statusText(f.status, f.gate)});
    }
    if (const vision::Deformation& d = pr.deformation; d.valid) {
      deformation.push_back({frame, t, d.displacement[0], d.displacement[1], d.displacement[2],
                             d.velocity[0], d.velocity[1], d.velocity[2], d.velocity_delay_s,
                             d.displacement_sigma_mm, d.velocity_sigma_mm_s, d.centroid[0],
                             d.centroid[1], d.centroid[2], d.ok, d.total,
                             static_cast<int>(d.detections), d.continuous});
      for (int k = 0; k < d.prediction.horizons; ++k) {
        const auto kk = static_cast<size_t>(k);
        const cv::Vec3d& p = d.prediction.displacement[kk];
        prediction_out << fmt::format("{},{:.17g},{:.17g},{:.17g},{:.17g},{:.17g},{:.17g},{}\n",
                                      frame, t, d.prediction.horizon_s[kk], p[0], p[1], p[2],
                                      d.prediction.sigma_mm[kk], d.prediction.model[kk] ? 1 : 0);
        ++prediction_rows;
      }
    }
    if (field_out && pr.state == vision::SessionState::kTracking) {
      if (auto ok = field_out->add(frame, t, pr.features, pr.detected, pr.deformation.detections,
                                   pr.deformation.displacement);
          !ok)
        return commandError("track", ok.error().message);
    }
    // As the daemon does once a pair's result is out: match some features' stereo again.
    session.afterPublish(l, r);
    return 0;
  };
  for (size_t i = 0; video || i < n; ++i) {
    long frame = static_cast<long>(i);
    double t = static_cast<double>(i) / a.fps;
    auto t_ns = static_cast<int64_t>(std::llround(t * 1e9));
    uint64_t seq = i;
    if (video) {
      record::VideoFrame vf;
      auto more = video->next(left, right, vf);
      if (!more) return commandError("track", more.error().message);
      if (!*more) {
        n = i;
        break;
      }
      frame = static_cast<long>(vf.frame);
      seq = vf.frame;  // a dropped frame is a gap, as a missing trigger is
      t_ns = vf.t_ns;
      t = static_cast<double>(t_ns) * 1e-9;
    } else if (reader) {
      if (auto ok = reader->read(i, left, right); !ok)
        return commandError("track", ok.error().message);
      frame = static_cast<long>(reader->meta(i).frame);
      seq = reader->meta(i).trigger_seq;
      t_ns = reader->meta(i).t_left_ns;
      t = static_cast<double>(t_ns) * 1e-9;
    } else {
      auto l = readGrey(pairs[i].first);
      if (!l) return commandError("track", l.error().message);
      auto r = readGrey(pairs[i].second);
      if (!r) return commandError("track", r.error().message);
      left = *l;
      right = *r;
    }
    if (!split) {
      if (const int rc = track_pair(left, right, frame, t, seq, t_ns); rc != 0) return rc;
    } else {
      vision::splitFields(left, order, field_l[0], field_l[1]);
      vision::splitFields(right, order, field_r[0], field_r[1]);
      // Field k of frame i: CSV frame 2i + k, sequence 2 seq + k, k/2 of a frame later.
      for (int k = 0; k < 2; ++k) {
        const auto kk = static_cast<size_t>(k);
        const double tk = t + 0.5 * frame_s * k;
        const int64_t tk_ns = t_ns + std::llround(0.5e9 * frame_s * k);
        if (const int rc =
                track_pair(field_l[kk], field_r[kk], 2 * frame + k, tk, 2 * seq + kk, tk_ns);
            rc != 0)
          return rc;
      }
    }
    if (!a.quiet && (i + 1) % 50 == 0) {
      fmt::print(stderr, "frame {}/{}: {} of {} features ok\n", i + 1,
                 video ? std::string("?") : std::to_string(n), session.tracker().okCount(),
                 session.tracker().features().size());
    }
  }
  if (video) {
    for (const std::string& w : video->warnings()) fmt::print(stderr, "warning: {}\n", w);
    fmt::print("video             {}: {} pairs at {:.3f} frames/s, {} missing, {} unpaired\n",
               video->name(), n, video->rate(), video->missing(), video->unpaired());
  }
  if (initial < 0) {
    return commandError("track",
                        fmt::format("no features in any of the {} pairs: {}", n, session.reason()));
  }
  if (auto ok = record::writeTrackCsv(a.out, rows); !ok)
    return commandError("track", ok.error().message);
  const std::string def_path = deformationPath(a);
  if (auto ok = record::writeDeformationCsv(def_path, deformation); !ok)
    return commandError("track", ok.error().message);
  prediction_out.close();
  if (!prediction_out)
    return commandError("track", fmt::format("{}: write failed", prediction_path));
  std::sort(step_us.begin(), step_us.end());
  const auto pct = [&](double p) {
    return step_us.empty()
               ? 0.0
               : step_us[std::min(step_us.size() - 1,
                                  static_cast<size_t>(p * static_cast<double>(step_us.size())))];
  };
  fmt::print(
      "frames            {}\n"
      "features          {} at the first detection, {} ok at the last frame, {} re-detections\n"
      "per-frame step    p50 {:.0f} us, p99 {:.0f} us, max {:.0f} us (pairs without detection)\n"
      "track written to  {}\n"
      "deformation       {} ({} pairs)\n"
      "prediction        {} ({} rows: frame,t,horizon,dx,dy,dz,sigma,model)\n",
      n, initial, session.tracker().okCount(), session.redetections(), pct(0.5), pct(0.99),
      step_us.empty() ? 0.0 : step_us.back(), a.out, def_path, deformation.size(), prediction_path,
      prediction_rows);
  if (session.rangeSerial() > 0)
    fmt::print("stereo search     {}\n", session.stereoRange().summary());
  if (initial >= 0) fmt::print("gates             {}\n", session.tracker().fittedGates().summary());
  if (const int n_unconfirmed = session.tracker().unconfirmedCount(); n_unconfirmed > 0) {
    fmt::print(
        "stereo check      {} feature(s) retired: their stereo match in the next pairs failed the "
        "stereo NCC gate that the first pair's passed (sheen in one view, a borderline match)\n",
        n_unconfirmed);
  }
  if (initial >= 0 && session.scale() != 1.0)
    fmt::print("scale             {}\n", session.scaleSummary());
  if (field_out) {
    auto lines = field_out->finish();
    if (!lines) return commandError("track", lines.error().message);
    for (const std::string& l : *lines) fmt::print("{}\n", l);
  }
  return 0;
}

}  // namespace

CommandRunner addMatchCommand(CLI::App& app) {
  auto args = std::make_shared<MatchArgs>();
  CLI::App* cmd = app.add_subcommand(
      "match", "Detect features in the left ROI and match them in the right image (one pair).");
  addCommon(cmd, *args);
  cmd->add_option("--left", args->left, "Left image")->required();
  cmd->add_option("--right", args->right, "Right image")->required();
  return [args] { return runMatch(*args); };
}

CommandRunner addTrackCommand(CLI::App& app) {
  auto args = std::make_shared<TrackArgs>();
  CLI::App* cmd =
      app.add_subcommand("track",
                         "Track features through a recording, an image sequence or stereo video; "
                         "writes frame,t,id,xl,yl,xr,yr,x,y,z,ncc,nmi,status.");
  addCommon(cmd, *args);
  cmd->add_option("--input", args->input,
                  "Recording folder (its rig.yaml is used unless --rig is given)");
  cmd->add_option("--left", args->left,
                  "Left images, a quoted glob ('DIR/left_*.png', sorted by name)");
  cmd->add_option("--right", args->right, "Right images, a quoted glob");
  cmd->add_option("--video", args->video,
                  "One video file with both views (--layout), any codec FFmpeg reads; time "
                  "stamps from the container, a dropped frame a gap (docs/video.md)");
  cmd->add_option("--layout", args->layout,
                  "--video's layout: sbs (side by side, left view left) or tb (top-bottom, left "
                  "view on top)")
      ->check(CLI::IsMember({"sbs", "tb"}))
      ->capture_default_str();
  cmd->add_option("--left-video", args->left_video, "The left view's video file");
  cmd->add_option("--right-video", args->right_video,
                  "The right view's video file (pairs by time stamp with the left's)");
  cmd->add_option("--fields", args->fields,
                  "Interlaced video (SD endoscope cameras): track each frame's two fields as pairs "
                  "of their own, half a frame apart, each made full height (the other field's rows "
                  "interpolated); tff: the top field (even rows) first, bff: the bottom. The CSVs' "
                  "frame 2i+k is frame i's field k (docs/video.md)")
      ->check(CLI::IsMember({"tff", "bff"}));
  cmd->add_option("--scale", args->scale,
                  "The scale the tracker works at: 1, 0.5 (half size: for video whose detail is "
                  "several pixels wide, e.g. SD upscaled to 720x576), or auto (1, or 0.5 where it "
                  "detects 1.25x as many features; said). Positions are always in the images' "
                  "pixels")
      ->check(CLI::IsMember({"auto", "1", "0.5"}))
      ->capture_default_str();
  cmd->add_option("--fps", args->fps, "Frame rate of an image sequence")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--deformation", args->deformation,
                  "The surface's deformation per pair, as pulsetrackd publishes it (default: "
                  "beside --out, NAME-deformation.csv)");
  cmd->add_option("--retry-interval", args->retry_interval,
                  "Seconds between detections while none finds features")
      ->check(CLI::Range(0.05, 3600.0))
      ->capture_default_str();
  cmd->add_option("--velocity-window", args->velocity_window,
                  "The velocity's least-squares window (s); its group delay is in the file")
      ->check(CLI::Range(0.0, 10.0))
      ->capture_default_str();
  cmd->add_option("--field", args->field,
                  "The dense deformation field (as pulsetrackd publishes it) to this CSV: "
                  "frame,t,signal,row,col,x,y,z,dx,dy,dz,confidence (mm), every --field-every "
                  "pairs; figures beside it (FIELD-map.png, FIELD-points.png)");
  cmd->add_option("--field-every", args->field_every, "Write the field every N pairs")
      ->check(CLI::Range(1, 1000000))
      ->capture_default_str();
  cmd->add_option("--field-spacing", args->field_spacing, "The field's grid spacing (mm)")
      ->capture_default_str();
  cmd->add_option("--field-smoothing", args->field_smoothing,
                  "The field's spline smoothing (mm^2; docs/ros2.md: how the default was chosen)")
      ->capture_default_str();
  cmd->add_option("--targets", args->targets,
                  "Points to follow (CSV x,y,z in mm, as they were in the first tracked pair): "
                  "where each is in every pair, from the field, to --targets-out");
  cmd->add_option("--targets-out", args->targets_out,
                  "Where the targets' answers go (default: beside --out, NAME-targets.csv): "
                  "frame,t,target,x,y,z,dx,dy,dz,confidence");
  cmd->add_flag("-q,--quiet", args->quiet, "No progress lines");
  return [args] { return runTrack(*args); };
}

}  // namespace pulsetrack::tools
