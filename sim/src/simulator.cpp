#include <fmt/format.h>
#include <toml++/toml.h>

#include <Eigen/Geometry>
#include <cmath>
#include <fstream>
#include <opencv2/core/eigen.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "pulsetrack/cfg/table_reader.hpp"
#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/sim/scene.hpp"

namespace pulsetrack::sim {

using vision::fail;

StereoSimulator::StereoSimulator(const SceneSpec& spec, const vision::StereoRig& rig)
    : spec_(spec),
      rig_(rig),
      raster_(rig.left.imageSize(), spec.supersample),
      left_fx_(spec.camera, rig.left.imageSize(), spec.seed * 2 + 1),
      right_fx_(spec.camera_right.value_or(spec.camera), rig.left.imageSize(), spec.seed * 2 + 2) {
  if (spec_.kind == SceneKind::kCortex) {
    cortex_ = std::make_unique<CortexScene>(spec_.cortex);
  } else {
    plate_ = std::make_unique<PlateScene>(spec_.plate, spec_.fps, spec_.seed);
  }
}

StereoSimulator::~StereoSimulator() = default;

int StereoSimulator::frameCount() const {
  if (plate_) {
    const int all = static_cast<int>(plate_->samples().size());
    return spec_.frames > 0 ? std::min(spec_.frames, all) : all;
  }
  return spec_.frames > 0 ? spec_.frames : static_cast<int>(10 * spec_.fps);
}

double StereoSimulator::frameTime(int i) const {
  if (plate_) return plate_->samples().at(static_cast<size_t>(i)).t;
  return i / spec_.fps;
}

bool StereoSimulator::dropped(int i) const { return left_fx_.dropped(static_cast<uint64_t>(i)); }

void StereoSimulator::render(int i, cv::Mat& left, cv::Mat& right) {
  const double t = frameTime(i);
  if (cortex_) {
    cortex_->render(rig_, t, raster_, radiance_l_, radiance_r_);
    if (spec_.interlaced) {
      // The bottom field (odd rows) half a frame later; each field's exposure through the lens
      // on its own (blurring the woven frame would mix the two instants in every row).
      cortex_->render(rig_, t + 0.5 / spec_.fps, raster_, field_l_, field_r_);
      left_fx_.defocus(radiance_l_);
      left_fx_.defocus(field_l_);
      right_fx_.defocus(radiance_r_);
      right_fx_.defocus(field_r_);
      for (int y = 1; y < radiance_l_.rows; y += 2) {
        field_l_.row(y).copyTo(radiance_l_.row(y));
        field_r_.row(y).copyTo(radiance_r_.row(y));
      }
    }
  } else {
    plate_->render(rig_, plate_->samples().at(static_cast<size_t>(i)).c_t_p, raster_, radiance_l_,
                   radiance_r_);
  }
  left_fx_.apply(radiance_l_, t, left, spec_.interlaced);
  right_fx_.apply(radiance_r_, t, right, spec_.interlaced);
}

namespace {

std::string poseColumns(const Pose& p) {
  Eigen::Matrix3d r;
  cv::cv2eigen(cv::Mat(p.r), r);
  const Eigen::Quaterniond q(r);
  return fmt::format("{:.9f},{:.9f},{:.9f},{:.12f},{:.12f},{:.12f},{:.12f}", p.t[0], p.t[1], p.t[2],
                     q.w(), q.x(), q.y(), q.z());
}

int64_t toNs(double t) { return static_cast<int64_t>(std::llround(t * 1e9)); }

vision::Result<void> writeText(const std::filesystem::path& path, const std::string& text) {
  std::ofstream f(path);
  f << text;
  if (!f) return fail(fmt::format("{}: write failed", path.string()));
  return {};
}

}  // namespace

vision::Result<void> writeSimulation(StereoSimulator& sim, const std::filesystem::path& out,
                                     const std::function<void(int, int)>& progress) {
  const SceneSpec& spec = sim.spec();
  const cv::Size size = sim.rig().left.imageSize();
  record::Manifest m;
  m.source = "sim:" + spec.name;
  m.rig_id = spec.name;
  m.width = size.width;
  m.height = size.height;
  m.nominal_fps = spec.fps;
  auto writer = record::Writer::create(out, m, sim.rig(), 1);
  if (!writer) return std::unexpected(writer.error());
  std::string scene_text = spec.source_text;
  if (spec.kind == SceneKind::kCortex && spec.cortex.texture == "image") {
    // The recording carries the photograph its surface wears (pulsetrack evaluate reads the
    // scene from the recording): texture.png beside scene.toml, which names it.
    bool written = false;
    try {
      written = cv::imwrite((out / "texture.png").string(), spec.cortex.texture_image_grey);
    } catch (const cv::Exception& e) {
      return fail(fmt::format("{}: cannot write: {}", (out / "texture.png").string(), e.err));
    }
    if (!written) return fail(fmt::format("{}: cannot write", (out / "texture.png").string()));
    toml::table root;
    std::string syntax;
    if (!cfg::parseToml(scene_text, spec.source_path.string(), root, syntax)) return fail(syntax);
    if (toml::table* cortex = root["cortex"].as_table())
      cortex->insert_or_assign("texture_image", "texture.png");
    std::ostringstream text;
    text << "# " << spec.source_path.string() << ", its texture_image copied to texture.png\n"
         << root << "\n";
    scene_text = text.str();
  }
  if (auto ok = writeText(out / "scene.toml", scene_text); !ok) return ok;
  std::error_code ec;
  std::filesystem::create_directories(out / "truth", ec);
  if (ec) return fail(fmt::format("{}: {}", (out / "truth").string(), ec.message()));

  std::string truth;
  const int n = sim.frameCount();
  if (const CortexScene* cortex = sim.cortex()) {
    // The centre of mass of the patch's material points (a 1 mm grid over the craniotomy):
    // the signal the paper's section 6 analyses.
    std::vector<cv::Vec2d> material;
    const double r = cortex->spec().radius_mm - 1.0;
    for (double v = -r; v <= r; v += 1.0) {
      for (double u = -r; u <= r; u += 1.0) {
        if (u * u + v * v <= r * r) material.emplace_back(u, v);
      }
    }
    truth = "frame,t_ns,recorded,com_x,com_y,com_z\n";
    for (int i = 0; i < n; ++i) {
      cv::Vec3d com(0, 0, 0);
      for (const cv::Vec2d& uv : material) com += cortex->position(uv[0], uv[1], sim.frameTime(i));
      com *= 1.0 / static_cast<double>(material.size());
      truth += fmt::format("{},{},{},{:.9f},{:.9f},{:.9f}\n", i, toNs(sim.frameTime(i)),
                           sim.dropped(i) ? 0 : 1, com[0], com[1], com[2]);
    }
    if (auto ok = writeText(out / "truth/cortex.csv", truth); !ok) return ok;
  } else if (const PlateScene* plate = sim.plate()) {
    truth = "frame,t_ns,recorded,set,acquisition,frame_in_acquisition,tx,ty,tz,qw,qx,qy,qz\n";
    std::string tracker = "frame,t_ns,tx,ty,tz,q0,qx,qy,qz\n";
    std::string tracker_true = tracker;
    for (int i = 0; i < n; ++i) {
      const PlateSample& s = plate->samples()[static_cast<size_t>(i)];
      truth += fmt::format("{},{},{},{},{},{},{}\n", i, toNs(s.t), sim.dropped(i) ? 0 : 1, s.set,
                           s.acquisition, s.frame_in_acquisition, poseColumns(s.c_t_p));
      tracker += fmt::format("{},{},{}\n", i, toNs(s.t), poseColumns(s.o_t_m));
      tracker_true += fmt::format("{},{},{}\n", i, toNs(s.t),
                                  poseColumns(plate->oTc() * s.c_t_p * plate->pTm()));
    }
    if (auto ok = writeText(out / "truth/plate.csv", truth); !ok) return ok;
    if (auto ok = writeText(out / "truth/tracker_markers.csv", tracker_true); !ok) return ok;
    std::filesystem::create_directories(out / "tracker", ec);
    if (auto ok = writeText(out / "tracker/markers.csv", tracker); !ok) return ok;
    std::string divots = "divot,x,y,z\n";
    for (size_t d = 0; d < 8; ++d) {
      const cv::Vec3d& p = plate->digitizedDivots()[d];
      divots += fmt::format("{},{:.6f},{:.6f},{:.6f}\n", d + 1, p[0], p[1], p[2]);
    }
    if (auto ok = writeText(out / "tracker/divots.csv", divots); !ok) return ok;
    // The experimenter's log: which frames are which acquisition (set 0: the registration set)
    // and the box drawn around the six features on each acquisition's first frame.
    std::string protocol =
        "set,acquisition,first_frame,last_frame,roi_left_x,roi_left_y,roi_left_w,roi_left_h,"
        "roi_right_x,roi_right_y,roi_right_w,roi_right_h\n";
    for (int i = 0; i < n;) {
      const PlateSample& s = plate->samples()[static_cast<size_t>(i)];
      int last = i;
      while (last + 1 < n && plate->samples()[static_cast<size_t>(last) + 1].set == s.set &&
             plate->samples()[static_cast<size_t>(last) + 1].acquisition == s.acquisition)
        ++last;
      std::vector<cv::Point2f> pl, pr;
      for (const cv::Vec3d& f : nominalFeatures()) {
        const cv::Vec2d a = sim.rig().projectLeft(s.c_t_p * f);
        const cv::Vec2d b = sim.rig().projectRight(s.c_t_p * f);
        pl.emplace_back(static_cast<float>(a[0]), static_cast<float>(a[1]));
        pr.emplace_back(static_cast<float>(b[0]), static_cast<float>(b[1]));
      }
      const auto box = [](const std::vector<cv::Point2f>& pts) {
        const cv::Rect r = cv::boundingRect(pts);
        return cv::Rect(r.x - 40, r.y - 40, r.width + 80, r.height + 80);
      };
      const cv::Rect bl = box(pl), br = box(pr);
      protocol +=
          fmt::format("{},{},{},{},{},{},{},{},{},{},{},{}\n", s.set, s.acquisition, i, last, bl.x,
                      bl.y, bl.width, bl.height, br.x, br.y, br.width, br.height);
      i = last + 1;
    }
    if (auto ok = writeText(out / "tracker/protocol.csv", protocol); !ok) return ok;
    if (auto ok =
            writeText(out / "tracker/digitization_markers.csv",
                      "tx,ty,tz,q0,qx,qy,qz\n" + poseColumns(plate->digitizationMarkers()) + "\n");
        !ok) {
      return ok;
    }
    if (auto ok = writeText(out / "truth/transforms.csv",
                            "name,tx,ty,tz,qw,qx,qy,qz\nO_T_C," + poseColumns(plate->oTc()) +
                                "\nP_T_M," + poseColumns(plate->pTm()) + "\n");
        !ok) {
      return ok;
    }
  }

  cv::Mat left, right;
  for (int i = 0; i < n; ++i) {
    if (!sim.dropped(i)) {
      sim.render(i, left, right);
      const int64_t t = toNs(sim.frameTime(i));
      const record::FrameMeta meta{static_cast<uint64_t>(i), 1000ULL + static_cast<uint64_t>(i), t,
                                   t, 0};
      if (auto ok = writer->write(meta, left, right); !ok) return ok;
    }
    if (progress) progress(i + 1, n);
  }
  return writer->close();
}

}  // namespace pulsetrack::sim
