// gate_eval: every gate of the stereo tracker measured against ground truth (issue 14): false
// reject and false accept per gate on real photographs with ground-truth disparity (beside a
// plain OpenCV matcher on the same pair) and on a simulated scene with truth, plus the hard
// scene's robustness and accuracy figures. The thresholds in TrackerConfig are chosen from
// these tables (see the comments there and docs/gates.md).

#include "pulsetrack/sim/gate_eval.hpp"

#include <fmt/format.h>

#include <CLI/CLI.hpp>
#include <cstdio>
#include <exception>
#include <string>
#include <vector>

#include "data_paths.hpp"

using namespace pulsetrack;

int main(int argc, char** argv) try {
  CLI::App app{
      "Measure each tracker gate's false-reject and false-accept rates against ground truth: "
      "photographs with true disparity and a simulated scene"};
  std::string scene = std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-hard.toml";
  // DIR[,FILE,SCALE]: the Middlebury pairs of ../shared/data by default (data_paths.hpp).
  std::vector<std::string> photos;
  for (const auto& m : data::middlebury()) {
    photos.push_back(fmt::format("{},{},{}", m.dir.string(), m.disparity, m.scale));
  }
  int pairs = 0;
  int dmin = 4, dmax = 60;
  bool no_scene = false;
  app.add_option("--scene", scene, "Cortex scene file (with truth)")->capture_default_str();
  app.add_option("--pairs", pairs, "Pairs of the scene to run (0: all)")
      ->check(CLI::NonNegativeNumber);
  app.add_option(
         "--photos", photos,
         "Photographs with true disparity: DIR[,FILE,SCALE], DIR holding left.png, "
         "right.png and FILE (default disparity.pgm; grey/SCALE = px, default 4; 0 unknown)")
      ->capture_default_str();
  app.add_option("--dmin", dmin, "Smallest disparity of the photographs, px")
      ->capture_default_str();
  app.add_option("--dmax", dmax, "Largest disparity of the photographs, px")->capture_default_str();
  double right_px = 0.3;
  std::string samples_csv;
  app.add_option("--samples-csv", samples_csv,
                 "Write every feature of every pair to this CSV: an ok one's 3D and image errors, "
                 "another's gate and visibility (the scene)");
  app.add_option("--right-px", right_px,
                 "The scene: a match within this of the truth in both views is right")
      ->capture_default_str();
  app.add_flag("--no-scene", no_scene, "Photographs only");
  bool no_photos = false;
  app.add_flag("--no-photos", no_photos, "The scene only");
  // The thresholds, to sweep them (defaults: TrackerConfig's).
  vision::TrackerConfig config;
  const auto sweep = [&app](const char* name, auto& value, const char* help) {
    app.add_option(name, value, help)->capture_default_str();
  };
  sweep("--specular-threshold", config.specular_threshold, "Glint grey level");
  sweep("--specular-margin", config.specular_margin_px, "Glint margin, px");
  sweep("--min-ncc", config.min_ncc, "NCC gate");
  sweep("--min-stereo-ncc", config.min_stereo_ncc, "Stereo NCC gate");
  sweep("--max-sheen", config.max_sheen, "Sheen gate");
  sweep("--max-epipolar-spread", config.max_epipolar_spread_px,
        "Epipolar gate against the neighbours' offset, px");
  sweep("--stereo-ramp", config.stereo_ramp,
        "The stereo match models an intensity ramp across the patch (true/false)");
  sweep("--min-nmi", config.min_nmi, "NMI gate");
  sweep("--template-refresh", config.template_refresh,
        "Recent templates taken per pair (0: the frame-0 templates only)");
  sweep("--min-stereo-confirmed", config.min_stereo_confirmed,
        "Stereo confirmation: the share of a feature's refresh matches that must pass (0: off)");
  sweep("--stereo-translation-fallback", config.stereo_translation_fallback,
        "Unsettled affine stereo matches refined in translation where the ceiling is not filled "
        "(true/false)");
  sweep("--max-epipolar", config.max_epipolar_px, "Epipolar gate, px");
  sweep("--max-ncc-drop", config.max_ncc_drop, "NCC drop gate");
  sweep("--min-distance", config.min_distance_px, "Corners at least this far apart, px");
  sweep("--sensitivity-min", config.sensitivity_min,
        "Weakest corner, fraction of the strongest Harris response");
  sweep("--min-isotropy", config.min_isotropy, "Corner isotropy gate");
  sweep("--min-fill", config.min_fill,
        "Detection matches more corners while fewer than this share of the ceiling pass");
  sweep("--max-motion", config.max_motion_px,
        "Motion gate: disparity change beyond the neighbours', px");
  sweep("--min-block-ncc", config.min_block_ncc,
        "Depth-edge gate: the template's corner blocks' NCC at the match");
  sweep("--grid", config.grid_cols, "Detection grid: cells per side");
  sweep("--glint-excess", config.glint_excess,
        "Tracking glint gate: grey levels over the gain-scaled brightest pixel at detection");
  sweep("--dark-delta", config.dark_delta,
        "Corners darker than their neighbourhood by at least this, grey levels");
  sweep("--dense-distance", config.dense_distance_px,
        "Corners between the spaced ones down to this spacing, px (after all of those)");
  sweep("--max-left-right", config.max_left_right_px, "Left-right gate, px");
  CLI11_PARSE(app, argc, argv);
  config.grid_rows = config.grid_cols;

  if (no_photos) photos.clear();
  for (const std::string& photo : photos) {
    const auto parts = [&photo] {
      std::vector<std::string> v;
      std::string::size_type start = 0;
      for (auto comma = photo.find(',');; comma = photo.find(',', start)) {
        v.push_back(photo.substr(start, comma - start));
        if (comma == std::string::npos) return v;
        start = comma + 1;
      }
    }();
    const std::string& dir = parts[0];
    if (parts.size() != 1 && parts.size() != 3) {
      fmt::print(stderr, "gate_eval: --photos '{}': give DIR or DIR,FILE,SCALE\n", photo);
      return 2;
    }
    if (const std::string why = data::absent(dir); !why.empty()) {
      fmt::print(stderr, "gate_eval: {} (--no-photos for the scene alone)\n", why);
      return 1;
    }
    double scale = 4.0;
    if (parts.size() == 3) {
      try {
        scale = std::stod(parts[2]);
      } catch (const std::exception&) {
        scale = 0;
      }
      if (!(scale > 0)) {
        fmt::print(stderr, "gate_eval: --photos '{}': SCALE must be a positive number\n", photo);
        return 2;
      }
    }
    auto p = sim::loadPhotoPair(dir, parts.size() == 3 ? parts[1] : "disparity.pgm", scale);
    if (!p) {
      fmt::print(stderr, "gate_eval: {}\n", p.error().message);
      return 1;
    }
    auto e = sim::evaluatePhotoPair(*p, config, dmin, dmax);
    if (!e) {
      fmt::print(stderr, "gate_eval: {}: {}\n", dir, e.error().message);
      return 1;
    }
    fmt::print("{}",
               sim::formatGateTable(e->table, fmt::format("photograph {} ({}):", p->name, dir)));
    fmt::print(
        "  pulsetrack: {} candidates, {} accepted, {} of {} with truth within 1 px ({:.1f} %)\n"
        "  plain OpenCV matcher: {} corners, {} accepted, {} of {} with truth within 1 px "
        "({:.1f} %)\n\n",
        e->candidates, e->accepted, e->accepted_good, e->accepted_judged,
        100.0 * e->accepted_good / std::max(1, e->accepted_judged), e->plain.candidates,
        e->plain.accepted, e->plain.accepted_good, e->plain.judged,
        100.0 * e->plain.accepted_good / std::max(1, e->plain.judged));
  }
  if (no_scene) return 0;
  auto spec = sim::loadScene(scene);
  if (!spec) {
    fmt::print(stderr, "gate_eval: {}\n", spec.error().message);
    return 1;
  }
  auto rig = vision::loadRig(spec->rig_path);
  if (!rig) {
    fmt::print(stderr, "gate_eval: {}\n", rig.error().message);
    return 1;
  }
  sim::StereoSimulator s(*spec, *rig);
  sim::SceneRunOptions opt;
  opt.pairs = pairs;
  opt.right_px = right_px;
  opt.samples_csv = samples_csv;
  opt.tracker = config;
  auto run = sim::runScene(s, opt);
  if (!run) {
    fmt::print(stderr, "gate_eval: {}\n", run.error().message);
    return 1;
  }
  fmt::print("{}\n",
             sim::formatGateTable(run->detection, fmt::format("{}: detections", spec->name)));
  fmt::print("{}\n", sim::formatGateTable(run->tracking,
                                          fmt::format("{}: tracking, every pair", spec->name)));
  int at50 = 0;
  for (int ok : run->ok_per_pair) at50 += ok >= 50 ? 1 : 0;
  fmt::print(
      "{}: {} pairs; first pair {} ok of ceiling {}; textured grid cells {}, of them without a "
      "feature {}; detections {}; distinct ids {}; pairs with >= 50 ok {:.1f} %\n"
      "  instrument: covers {:.1f} % of the ROI from either camera while it rests ({:.1f} % of the "
      "left ROI box); {} features hidden then, {} back under their ids 1 s after it left ({:.1f} "
      "%)\n"
      "  accuracy: {} ok samples, 3D RMS {:.4f} mm, max {:.3f} mm, above 0.5 mm {}; mean "
      "displacement error {:.4f} mm RMS per axis; breathing amplitude off by {:.2f} %, cardiac "
      "{:.2f} %\n  time per tracked pair: track {:.3f} ms (re-acquisition included; {:.1f} ok, {} "
      "features), stereo refresh after it {:.3f} ms\n",
      spec->name, run->pairs, run->first_ok, config.max_features, run->textured_cells,
      run->empty_textured_cells, run->detections, run->distinct_ids,
      100.0 * at50 / std::max(1, run->pairs), 100.0 * run->instrument_covers,
      100.0 * run->instrument_covers_box, run->hidden, run->back_within_1s,
      100.0 * run->back_within_1s / std::max(1, run->hidden), run->ok_samples, run->rms_3d_mm,
      run->max_3d_mm, run->above_half_mm, run->displacement_rms_mm, 100.0 * run->breathing_error,
      100.0 * run->cardiac_error, run->ms_per_pair_tracking, run->mean_ok, config.max_features,
      run->ms_per_pair_refresh);
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "gate_eval: internal error: %s\n", e.what());
  return 1;
}
