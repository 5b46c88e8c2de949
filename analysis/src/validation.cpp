#include "pulsetrack/analysis/validation.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <map>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"

namespace pulsetrack::analysis {

using vision::fail;

namespace {

// The plate's origin speed (mm/s) and angular speed (deg/s) by central differences of the
// divots' frame within each acquisition.
void speeds(std::vector<FrameResult>& frames) {
  for (size_t i = 0; i < frames.size(); ++i) {
    const auto same = [&](size_t j) {
      return j < frames.size() && frames[j].set == frames[i].set &&
             frames[j].acquisition == frames[i].acquisition && frames[j].measured;
    };
    const size_t a = i > 0 && same(i - 1) ? i - 1 : i;
    const size_t b = same(i + 1) ? i + 1 : i;
    if (a == b || !frames[i].measured) continue;
    const double dt = static_cast<double>(frames[b].t_ns - frames[a].t_ns) * 1e-9;
    if (dt <= 0) continue;
    frames[i].speed_mm_s =
        (frames[b].o_t_d.translation() - frames[a].o_t_d.translation()).norm() / dt;
    frames[i].angular_speed_deg_s =
        rotationErrorDeg(Pose(frames[b].o_t_d.linear() * frames[a].o_t_d.linear().transpose())) /
        dt;
  }
}

GroupTest runTest(std::string name, std::vector<std::string> labels,
                  std::vector<std::vector<double>> values) {
  GroupTest g{std::move(name), std::move(labels), std::move(values), {}, {}, {}};
  auto kw = kruskalWallis(g.values);
  if (kw) {
    g.kw = *kw;
    g.pairs = dunnBonferroni(g.values);
  } else {
    g.kw_error = kw.error().message;
  }
  return g;
}

std::string label(double lo, double hi, const char* unit) {
  if (lo < 0) return fmt::format("< {:.2f} {}", hi, unit);
  if (hi < 0) return fmt::format("> {:.2f} {}", lo, unit);
  return fmt::format("{:.2f}-{:.2f} {}", lo, hi, unit);
}

}  // namespace

vision::Result<ValidationResult> validate(const ValidationInputs& in,
                                          const std::function<void(size_t, size_t)>& progress) {
  const auto dir = in.recording / "tracker";
  const auto pick = [&](const std::filesystem::path& p, const char* name) {
    return p.empty() ? dir / name : p;
  };
  auto reader = record::Reader::open(in.recording);
  if (!reader) return std::unexpected(reader.error());
  if (reader->size() == 0) {
    return fail(fmt::format("{}: the recording holds no complete frame", in.recording.string()));
  }
  auto markers = readPoses(pick(in.markers, "markers.csv"));
  if (!markers) return std::unexpected(markers.error());
  if (!markers->timed && markers->poses.front().frame < 0)
    return fail(
        fmt::format("{}: neither a frame nor a time column: the poses cannot be matched to "
                    "the camera frames",
                    pick(in.markers, "markers.csv").string()));
  auto digitized = readDivots(pick(in.divots, "divots.csv"));
  if (!digitized) return std::unexpected(digitized.error());
  auto digitization = readPoses(pick(in.digitization, "digitization_markers.csv"));
  if (!digitization) return std::unexpected(digitization.error());
  auto protocol = readProtocol(pick(in.protocol, "protocol.csv"));
  if (!protocol) return std::unexpected(protocol.error());

  ValidationResult res;
  res.divots = calibrateDivots(*digitized, digitization->poses.front().pose);

  std::map<long, size_t> frame_index;  // recording frame -> reader index
  for (size_t i = 0; i < reader->size(); ++i)
    frame_index[static_cast<long>(reader->meta(i).frame)] = i;
  std::map<long, Pose> by_frame;
  std::vector<std::pair<int64_t, Pose>> by_time;
  for (const TimedPose& p : markers->poses) {
    if (p.frame >= 0) by_frame[p.frame] = p.pose;
    by_time.emplace_back(p.t_ns, p.pose);
  }
  // Marker poses pair with frames by time within half a frame period: the manifest's rate, or
  // (a manifest without one) the recording's median period per frame index.
  double period_ns = 0.0;
  if (reader->manifest().nominal_fps > 0) {
    period_ns = 1e9 / reader->manifest().nominal_fps;
  } else {
    std::vector<double> periods;
    for (size_t i = 1; i < reader->size(); ++i) {
      const auto& a = reader->meta(i - 1);
      const auto& b = reader->meta(i);
      periods.push_back(double(b.t_left_ns - a.t_left_ns) / double(b.frame - a.frame));
    }
    if (!periods.empty()) {
      std::nth_element(periods.begin(), periods.begin() + long(periods.size() / 2), periods.end());
      period_ns = periods[periods.size() / 2];
    }
  }
  if (!(period_ns > 0.0)) {
    return fail(
        fmt::format("{}: no frame rate: manifest.toml has no nominal_fps and the "
                    "recording's stamps give none",
                    reader->dir().string()));
  }
  const auto half_period = static_cast<int64_t>(0.5 * period_ns);
  const auto markerPose = [&](long frame, int64_t t) -> std::optional<Pose> {
    if (!by_frame.empty()) {
      const auto it = by_frame.find(frame);
      if (it == by_frame.end()) return std::nullopt;
      return it->second;
    }
    const auto it =
        std::min_element(by_time.begin(), by_time.end(), [&](const auto& a, const auto& b) {
          return std::llabs(a.first - t) < std::llabs(b.first - t);
        });
    if (it == by_time.end() || std::llabs(it->first - t) > half_period) return std::nullopt;
    return it->second;
  };

  size_t total = 0, done = 0;
  for (const Acquisition& a : *protocol)
    total += static_cast<size_t>(a.last_frame - a.first_frame + 1);
  vision::TrackerConfig config;
  config.detector = vision::Detector::kDarkBlobs;
  config.max_features = in.max_features;
  cv::Mat left, right;
  std::vector<double> plane_errors;
  for (const Acquisition& a : *protocol) {
    if (a.last_frame > a.first_frame) res.dynamic = true;
    // Every frame is measured on its own (detection, stereo match, triangulation) in a box that
    // follows the plate: at 10 fps and up to 25 mm/s the plate moves ~30 px between frames, more
    // than a video-matching window; a frame-by-frame measurement also keeps frames independent.
    vision::StereoTracker tracker(reader->rig(), config);
    cv::Rect box_l(a.roi_left[0], a.roi_left[1], a.roi_left[2], a.roi_left[3]);
    cv::Rect box_r(a.roi_right[0], a.roi_right[1], a.roi_right[2], a.roi_right[3]);
    cv::Point2d step_l(0, 0), step_r(0, 0);  // the last frame-to-frame shift of the features
    std::optional<std::pair<cv::Point2d, cv::Point2d>> last_centre;
    for (long f = a.first_frame; f <= a.last_frame; ++f) {
      FrameResult fr;
      fr.set = a.set;
      fr.acquisition = a.acquisition;
      fr.frame = f;
      const auto it = frame_index.find(f);
      if (progress) progress(++done, total);
      if (it == frame_index.end()) {
        fr.why = "frame not in the recording";
        res.frames.push_back(fr);
        continue;
      }
      fr.t_ns = reader->meta(it->second).t_left_ns;
      if (auto ok = reader->read(it->second, left, right); !ok) return std::unexpected(ok.error());
      const auto shifted = [&](const cv::Rect& r, const cv::Point2d& d) {
        return cv::Rect(r.x + static_cast<int>(std::lround(d.x)),
                        r.y + static_cast<int>(std::lround(d.y)), r.width, r.height);
      };
      auto n = tracker.initialize(left, right, {shifted(box_l, step_l), shifted(box_r, step_r)},
                                  in.depth_tolerance_mm);
      if (!n) {
        fr.why = n.error().message;
        res.frames.push_back(fr);
        continue;
      }
      std::vector<Vec3> pts;
      std::vector<const vision::Feature*> ok_features;
      for (const vision::Feature& feat : tracker.features()) {
        if (feat.status != vision::FeatureStatus::kOk) continue;
        pts.emplace_back(feat.point[0], feat.point[1], feat.point[2]);
        ok_features.push_back(&feat);
      }
      auto id = identifyPlateFeatures(pts);
      const auto mp = markerPose(f, fr.t_ns);
      if (!id) {
        fr.why = id.error().message;
      } else if (!mp) {
        fr.why = "no reference-tracker pose for this frame";
      } else {
        std::array<Vec3, 6> p{};
        for (size_t k = 0; k < 6; ++k) p[k] = pts[static_cast<size_t>(id->index[k])];
        // The next frame's boxes: around these six, 40 px of margin, moved by the last shift.
        std::vector<cv::Point2f> pl, pr;
        for (size_t k = 0; k < 6; ++k) {
          const vision::Feature& feat = *ok_features[static_cast<size_t>(id->index[k])];
          pl.emplace_back(static_cast<float>(feat.left[0]), static_cast<float>(feat.left[1]));
          pr.emplace_back(static_cast<float>(feat.right[0]), static_cast<float>(feat.right[1]));
        }
        const auto grow = [](const cv::Rect& r) {
          return cv::Rect(r.x - 40, r.y - 40, r.width + 80, r.height + 80);
        };
        box_l = grow(cv::boundingRect(pl));
        box_r = grow(cv::boundingRect(pr));
        const std::pair<cv::Point2d, cv::Point2d> centre{
            cv::Point2d(box_l.x + box_l.width / 2.0, box_l.y + box_l.height / 2.0),
            cv::Point2d(box_r.x + box_r.width / 2.0, box_r.y + box_r.height / 2.0)};
        if (last_centre) {
          step_l = centre.first - last_centre->first;
          step_r = centre.second - last_centre->second;
        }
        last_centre = centre;
        fr.c_t_f = featureFrame(p);
        fr.layout_rms_mm = id->rms_mm;
        std::array<Vec3, 8> d{};
        for (size_t k = 0; k < 8; ++k) d[k] = *mp * res.divots.in_markers[k];  // eq. (7)
        fr.o_t_d = divotFrame(d);
        fr.measured = true;
        const PlaneFit plane = fitPlane(std::vector<Vec3>(p.begin(), p.end()));
        for (const Vec3& q : p)
          plane_errors.push_back(std::fabs((q - plane.centroid).dot(plane.normal)));
      }
      res.frames.push_back(fr);
    }
  }
  res.feature_plane_mm = summarize(plane_errors);
  for (const FrameResult& f : res.frames) (f.measured ? res.frames_measured : res.frames_missing)++;

  // Registration on set 0, unless given.
  if (in.o_t_c) {
    res.o_t_c = *in.o_t_c;
  } else {
    std::vector<Pose> od, cf;
    for (const FrameResult& f : res.frames) {
      if (f.set == 0 && f.measured) {
        od.push_back(f.o_t_d);
        cf.push_back(f.c_t_f);
      }
    }
    if (od.empty())
      return fail(
          "no registration: the protocol has no measured acquisition in set 0 and no "
          "registration was given (--registration FILE from a static session)");
    auto reg = registerFrames(od, cf, in.rotation_scale_mm);
    if (!reg) return std::unexpected(reg.error());
    res.o_t_c = reg->o_t_c;
    std::array<std::vector<double>, 6> axes;
    for (const Pose& e : reg->residuals) {
      const Eigen::AngleAxisd aa(e.linear());
      const Vec3 rv = aa.angle() * aa.axis() * 180.0 / M_PI;
      for (int k = 0; k < 3; ++k) {
        axes[static_cast<size_t>(k)].push_back(std::fabs(e.translation()[k]));
        axes[3 + static_cast<size_t>(k)].push_back(std::fabs(rv[k]));
      }
    }
    for (size_t k = 0; k < 6; ++k) res.table2[k] = summarize(axes[k]);
    res.registration = std::move(*reg);
  }

  // Errors of sets 1..
  speeds(res.frames);
  int sets = 0;
  for (FrameResult& f : res.frames) {
    if (f.set == 0 || !f.measured) continue;
    f.e = errorMatrix(f.o_t_d, res.o_t_c, f.c_t_f);
    f.e_t_mm = translationError(f.e);
    f.e_r_deg = rotationErrorDeg(f.e);
    sets = std::max(sets, f.set);
  }
  std::vector<std::vector<double>> et(static_cast<size_t>(sets)), er(static_cast<size_t>(sets));
  std::vector<std::string> labels;
  for (int s = 1; s <= sets; ++s) labels.push_back(fmt::format("set {}", s));
  for (const FrameResult& f : res.frames) {
    if (f.set == 0 || !f.measured) continue;
    et[static_cast<size_t>(f.set - 1)].push_back(f.e_t_mm);
    er[static_cast<size_t>(f.set - 1)].push_back(f.e_r_deg);
  }
  if (sets >= 2) {
    const char* what = res.dynamic ? "dynamic" : "static";
    res.tests.push_back(
        runTest(fmt::format("{}: translation error (mm) by set", what), labels, et));
    res.tests.push_back(runTest(fmt::format("{}: rotation error (deg) by set", what), labels, er));
  }
  if (res.dynamic) {
    std::vector<double> v, w;
    for (const FrameResult& f : res.frames) {
      if (f.set > 0 && f.measured && f.speed_mm_s >= 0) {
        v.push_back(f.speed_mm_s);
        w.push_back(f.angular_speed_deg_s);
      }
    }
    if (v.size() >= 6) {
      res.speed_limits = equalCountLimits(v, 3);
      res.angular_speed_limits = equalCountLimits(w, 3);
      std::vector<std::vector<double>> tv(3), rw(3);
      for (const FrameResult& f : res.frames) {
        if (f.set == 0 || !f.measured || f.speed_mm_s < 0) continue;
        const auto group = [](double x, const std::vector<double>& lim) {
          return x < lim[0] ? 0 : x <= lim[1] ? 1 : 2;
        };
        tv[static_cast<size_t>(group(f.speed_mm_s, res.speed_limits))].push_back(f.e_t_mm);
        rw[static_cast<size_t>(group(f.angular_speed_deg_s, res.angular_speed_limits))].push_back(
            f.e_r_deg);
      }
      const auto& l = res.speed_limits;
      const auto& m = res.angular_speed_limits;
      res.tests.push_back(
          runTest("dynamic: translation error (mm) by linear speed",
                  {"low " + label(-1, l[0], "mm/s"), "medium " + label(l[0], l[1], "mm/s"),
                   "high " + label(l[1], -1, "mm/s")},
                  tv));
      res.tests.push_back(
          runTest("dynamic: rotation error (deg) by angular speed",
                  {"low " + label(-1, m[0], "deg/s"), "medium " + label(m[0], m[1], "deg/s"),
                   "high " + label(m[1], -1, "deg/s")},
                  rw));
    }
  }
  return res;
}

}  // namespace pulsetrack::analysis
