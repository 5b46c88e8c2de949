#include "pulsetrack/sim/scene.hpp"

#include <fmt/format.h>
#include <toml++/toml.h>

#include <opencv2/imgcodecs.hpp>
#include <set>

#include "pulsetrack/cfg/table_reader.hpp"

namespace pulsetrack::sim {

using cfg::TableReader;
using vision::fail;

namespace {

void readCameraKeys(TableReader& r, CameraEffectsSpec& c) {
  c.blur_sigma_px = r.number("blur_sigma_px", c.blur_sigma_px, 0.0, 10.0);
  c.noise_sigma = r.number("noise_sigma", c.noise_sigma, 0.0, 50.0);
  c.vignetting = r.number("vignetting", c.vignetting, 0.0, 0.9);
  const auto vc =
      r.numbers("vignetting_centre_px", {c.vignetting_centre_px[0], c.vignetting_centre_px[1]}, 2,
                2, -2000.0, 2000.0);
  c.vignetting_centre_px = {vc[0], vc[1]};
  c.gain = r.number("gain", c.gain, 0.2, 5.0);
  c.gain_amplitude = r.number("gain_amplitude", c.gain_amplitude, 0.0, 0.9);
  c.gain_period_s = r.number("gain_period_s", c.gain_period_s, 0.1, 1e6);
  c.gain_phase_deg = r.number("gain_phase_deg", c.gain_phase_deg, -360.0, 360.0);
  c.jpeg_quality = r.integer("jpeg_quality", c.jpeg_quality, 0, 100);
}

// [camera] applies to both cameras; [camera.right] overrides any of its keys for the right one
// (unequal gains, independent drift, different lenses). Frame drops are the pair's.
void readCamera(TableReader& r, CameraEffectsSpec& left, std::optional<CameraEffectsSpec>& right) {
  readCameraKeys(r, left);
  left.drop_probability = r.number("drop_probability", left.drop_probability, 0.0, 0.5);
  if (const toml::table* t = r.table("right")) {
    right = left;
    TableReader rr(*t, r.file(), r.child("right"), r.errorSink());
    readCameraKeys(rr, *right);
    rr.finish();
  }
  r.finish();
}

constexpr double kDeg = CV_PI / 180.0;

void readOscillation(TableReader& r, Oscillation& o) {
  o.name = r.string("name", o.name);
  o.enabled = r.boolean("enabled", true);
  o.amplitude_mm = r.number("amplitude_mm", o.amplitude_mm, 0.0, 20.0);
  o.frequency_hz = r.number("frequency_hz", o.frequency_hz, 0.0, 20.0);
  o.phase_rad = r.number("phase_deg", o.phase_rad / kDeg, -360.0, 360.0) * kDeg;
  const auto g = r.numbers("gradient", {o.gradient[0], o.gradient[1]}, 2, 2, -0.9, 0.9);
  o.gradient = {g[0], g[1]};
  const auto d =
      r.numbers("direction", {o.direction[0], o.direction[1], o.direction[2]}, 3, 3, -1e3, 1e3);
  o.direction = {d[0], d[1], d[2]};
  // Changes over time: the NaN defaults mean none (a key present must be a number in range).
  o.frequency_end_hz = r.number("frequency_end_hz", o.frequency_end_hz, 0.0, 20.0);
  o.amplitude_end_mm = r.number("amplitude_end_mm", o.amplitude_end_mm, 0.0, 20.0);
  o.change_start_s = r.number("change_start_s", o.change_start_s, 0.0, 1e6);
  o.change_duration_s = r.number("change_duration_s", o.change_duration_s, 0.0, 1e6);
  o.irregularity = r.number("irregularity", o.irregularity, 0.0, 0.5);
  o.irregularity_seed = static_cast<unsigned>(
      r.integer("irregularity_seed", static_cast<int>(o.irregularity_seed), 0, 1'000'000'000));
  if (const toml::array* hs = r.arrayOfTables("harmonics")) {
    o.harmonics.clear();
    for (size_t i = 0; i < hs->size(); ++i) {
      TableReader hr(*hs->get(i)->as_table(), r.file(),
                     r.child("harmonics") + fmt::format("[{}]", i), r.errorSink());
      Harmonic h;
      h.multiple = hr.number("multiple", 2.0, 1.0, 20.0);
      h.relative_amplitude = hr.number("relative_amplitude", 0.0, 0.0, 10.0);
      h.phase_rad = hr.number("phase_deg", 0.0, -360.0, 360.0) * kDeg;
      hr.finish();
      o.harmonics.push_back(h);
    }
  }
  r.finish();
}

void readCortex(TableReader& r, CortexSpec& c) {
  c.distance_mm = r.number("distance_mm", c.distance_mm, 200.0, 1000.0);
  c.tilt_deg = r.number("tilt_deg", c.tilt_deg, 0.0, 70.0);
  c.azimuth_deg = r.number("azimuth_deg", c.azimuth_deg, -360.0, 360.0);
  const auto off = r.numbers("offset_mm", {c.offset_mm[0], c.offset_mm[1]}, 2, 2, -100.0, 100.0);
  c.offset_mm = {off[0], off[1]};
  c.radius_mm = r.number("radius_mm", c.radius_mm, 5.0, 60.0);
  c.curvature_radius_mm = r.number("curvature_radius_mm", c.curvature_radius_mm, 20.0, 1e4);
  c.gyri_amplitude_mm = r.number("gyri_amplitude_mm", c.gyri_amplitude_mm, 0.0, 5.0);
  c.mesh_step_mm = r.number("mesh_step_mm", c.mesh_step_mm, 0.1, 2.0);
  c.texture_px_per_mm = r.number("texture_px_per_mm", c.texture_px_per_mm, 4.0, 64.0);
  c.vessel_trees = r.integer("vessel_trees", c.vessel_trees, 0, 100);
  c.texture = r.string("texture", c.texture, {"brain", "dots", "image"});
  c.texture_image = r.string("texture_image", "");
  c.texture_image_mm = r.number("texture_image_mm", c.texture_image_mm, 1.0, 500.0);
  c.tissue_albedo = r.number("tissue_albedo", c.tissue_albedo, 10.0, 250.0);
  c.vessel_contrast = r.number("vessel_contrast", c.vessel_contrast, 0.0, 0.95);
  c.wrinkle_slope = r.number("wrinkle_slope", c.wrinkle_slope, 0.0, 5.0);
  c.specular_strength = r.number("specular_strength", c.specular_strength, 0.0, 5000.0);
  c.specular_shininess = r.number("specular_shininess", c.specular_shininess, 1.0, 5000.0);
  c.illumination_gradient = r.number("illumination_gradient", c.illumination_gradient, 0.0, 0.9);
  c.illumination_drift = r.number("illumination_drift", c.illumination_drift, 0.0, 0.9);
  c.illumination_period_s = r.number("illumination_period_s", c.illumination_period_s, 0.1, 1e6);
  if (const toml::array* motions = r.arrayOfTables("motion")) {
    c.oscillations.clear();
    for (size_t i = 0; i < motions->size(); ++i) {
      TableReader mr(*motions->get(i)->as_table(), r.file(),
                     r.child("motion") + fmt::format("[{}]", i), r.errorSink());
      Oscillation o;
      readOscillation(mr, o);
      c.oscillations.push_back(o);
    }
  }
  if (const toml::table* t = r.table("sag")) {
    TableReader sr(*t, r.file(), r.child("sag"), r.errorSink());
    c.sag.enabled = sr.boolean("enabled", true);
    c.sag.depth_mm = sr.number("depth_mm", c.sag.depth_mm, 0.0, 30.0);
    c.sag.time_constant_s = sr.number("time_constant_s", c.sag.time_constant_s, 1.0, 1e6);
    c.sag.rotation_deg = sr.number("rotation_deg", c.sag.rotation_deg, -45.0, 45.0);
    const auto axis = sr.numbers(
        "rotation_axis", {c.sag.rotation_axis[0], c.sag.rotation_axis[1], c.sag.rotation_axis[2]},
        3, 3, -1e3, 1e3);
    c.sag.rotation_axis = {axis[0], axis[1], axis[2]};
    sr.require("rotation_axis", cv::norm(c.sag.rotation_axis) > 1e-9, "must not be zero");
    sr.finish();
  }
  if (const toml::table* t = r.table("instrument")) {
    TableReader ir(*t, r.file(), r.child("instrument"), r.errorSink());
    Instrument& in = c.instrument;
    in.enabled = ir.boolean("enabled", true);
    in.start_s = ir.number("start_s", in.start_s, 0.0, 1e6);
    in.duration_s = ir.number("duration_s", in.duration_s, 0.1, 1e6);
    in.radius_mm = ir.number("radius_mm", in.radius_mm, 0.5, 20.0);
    in.height_mm = ir.number("height_mm", in.height_mm, 1.0, 300.0);
    const auto from = ir.numbers("from_mm", {in.from_mm[0], in.from_mm[1]}, 2, 2, -500.0, 500.0);
    const auto to = ir.numbers("to_mm", {in.to_mm[0], in.to_mm[1]}, 2, 2, -500.0, 500.0);
    in.from_mm = {from[0], from[1]};
    in.hold_fraction = ir.number("hold_fraction", in.hold_fraction, 0.0, 0.95);
    in.to_mm = {to[0], to[1]};
    in.albedo = ir.number("albedo", in.albedo, 0.0, 1.0);
    in.period_s = ir.number("period_s", in.period_s, 0.0, 1e6);
    in.repeats = ir.integer("repeats", in.repeats, 0, 1000000);
    ir.require("period_s", in.period_s == 0.0 || in.period_s >= in.duration_s,
               "must be 0 (once) or at least duration_s");
    ir.finish();
  }
  if (const toml::table* t = r.table("shadow")) {
    TableReader hr(*t, r.file(), r.child("shadow"), r.errorSink());
    Shadow& s = c.shadow;
    s.enabled = hr.boolean("enabled", true);
    s.start_s = hr.number("start_s", s.start_s, 0.0, 1e6);
    s.duration_s = hr.number("duration_s", s.duration_s, 0.1, 1e6);
    s.depth = hr.number("depth", s.depth, 0.0, 1.0);
    s.width_mm = hr.number("width_mm", s.width_mm, 1.0, 200.0);
    s.softness_mm = hr.number("softness_mm", s.softness_mm, 0.1, 100.0);
    hr.finish();
  }
  r.finish();
}

void readPlate(TableReader& r, PlateSpec& p) {
  p.protocol = r.string("protocol", "static", {"static", "dynamic"}) == "dynamic"
                   ? PlateProtocol::kDynamic
                   : PlateProtocol::kStatic;
  p.registration_acquisitions =
      r.integer("registration_acquisitions", p.registration_acquisitions, 0, 1000);
  p.sets = r.integer("sets", p.sets, 1, 100);
  p.acquisitions_per_set = r.integer("acquisitions_per_set", p.acquisitions_per_set, 1, 1000);
  p.frames_per_acquisition =
      r.integer("frames_per_acquisition", p.frames_per_acquisition, 1, 100000);
  p.set_depths_mm = r.numbers("set_depths_mm", p.set_depths_mm, 1, 100, 200.0, 1000.0);
  p.depth_spread_mm = r.number("depth_spread_mm", p.depth_spread_mm, 0.0, 100.0);
  p.lateral_range_mm = r.number("lateral_range_mm", p.lateral_range_mm, 0.0, 100.0);
  p.max_tilt_deg = r.number("max_tilt_deg", p.max_tilt_deg, 0.0, 60.0);
  p.max_speed_mm_s = r.number("max_speed_mm_s", p.max_speed_mm_s, 0.0, 500.0);
  p.max_angular_speed_deg_s =
      r.number("max_angular_speed_deg_s", p.max_angular_speed_deg_s, 0.0, 180.0);
  p.tracker_noise_mm = r.number("tracker_noise_mm", p.tracker_noise_mm, 0.0, 5.0);
  p.setup_seed = r.integer("setup_seed", p.setup_seed, 0, 1 << 30);
  r.finish();
}

}  // namespace

vision::Result<SceneSpec> parseScene(const std::string& text, const std::filesystem::path& path) {
  const std::string file = path.string();
  toml::table root;
  if (std::string syntax; !cfg::parseToml(text, file, root, syntax)) return fail(syntax);
  SceneSpec s;
  s.source_text = text;
  s.source_path = path;
  std::string error;
  TableReader r(root, file, "", &error);
  s.name = r.string("name", path.stem().string());
  const std::string kind = r.string("kind", "", {"cortex", "plate"});
  if (kind.empty() && error.empty())
    error = fmt::format("{}: key 'kind' is missing (cortex or plate)", file);
  s.kind = kind == "plate" ? SceneKind::kPlate : SceneKind::kCortex;
  const std::string rig = r.string("rig", "");
  if (rig.empty() && error.empty())
    error = fmt::format("{}: key 'rig' is missing (path of a rig YAML)", file);
  s.rig_path = path.parent_path() / rig;
  s.fps = r.number("fps", s.fps, 0.1, 1000.0);
  s.frames = r.integer("frames", s.frames, 1, 10'000'000);
  s.seed = static_cast<unsigned>(r.integer("seed", 1, 0, 1'000'000'000));
  s.supersample = r.integer("supersample", s.supersample, 1, 4);
  s.interlaced = r.boolean("interlaced", false);
  s.cortex.oscillations = paperMotion();
  if (const toml::table* t = r.table("camera")) {
    TableReader cr(*t, file, "camera", &error);
    readCamera(cr, s.camera, s.camera_right);
  }
  if (const toml::table* t = r.table("cortex")) {
    TableReader cr(*t, file, "cortex", &error);
    readCortex(cr, s.cortex);
  }
  if (const toml::table* t = r.table("plate")) {
    TableReader pr(*t, file, "plate", &error);
    readPlate(pr, s.plate);
  }
  r.finish();
  if (!error.empty()) return fail(error);
  if (s.interlaced && s.kind != SceneKind::kCortex)
    return fail(
        fmt::format("{}: interlaced = true needs kind = \"cortex\" (a plate's poses are "
                    "per frame)",
                    file));
  if (s.kind == SceneKind::kCortex && s.cortex.texture == "image") {
    if (s.cortex.texture_image.empty()) {
      return fail(
          fmt::format("{}: cortex.texture = \"image\" needs cortex.texture_image (the "
                      "path of a grey or colour photograph of tissue)",
                      file));
    }
    s.cortex.texture_image = path.parent_path() / s.cortex.texture_image;
    cv::Mat grey;
    try {
      grey = cv::imread(s.cortex.texture_image.string(), cv::IMREAD_GRAYSCALE);
    } catch (const cv::Exception& e) {
      return fail(fmt::format("{}: cortex.texture_image {}: {}", file,
                              s.cortex.texture_image.string(), e.err));
    }
    if (grey.empty() || grey.cols < 16 || grey.rows < 16) {
      return fail(fmt::format(
          "{}: cortex.texture_image {}: {}", file, s.cortex.texture_image.string(),
          grey.empty() ? "cannot read it as an image (missing, or not a format OpenCV reads; the "
                         "shipped real-texture scenes read ../shared/data beside the checkout)"
                       : "smaller than 16x16 px"));
    }
    s.cortex.texture_image_grey = grey;
  }
  s.cortex.seed = s.seed;
  return s;
}

vision::Result<SceneSpec> loadScene(const std::filesystem::path& path) {
  std::string text;
  if (std::string error; !cfg::readTomlText(path, "scene file", text, error)) return fail(error);
  return parseScene(text, path);
}

}  // namespace pulsetrack::sim
