// pulsetrack simulate / pulsetrack evaluate: synthetic recordings with ground truth, and the
// score of a track against it.

#include <fmt/format.h>

#include <chrono>
#include <fstream>
#include <memory>

#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "pulsetrack/sim/evaluate.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/tools/commands.hpp"

namespace pulsetrack::tools {

namespace {

struct SimulateArgs {
  std::string scene;
  std::string out;
  int frames = 0;
  double fps = 0.0;
  int supersample = 0;
  bool quiet = false;
};

std::string duration(double s) {
  return s >= 60 ? fmt::format("{}m{:02d}s", static_cast<int>(s) / 60, static_cast<int>(s) % 60)
                 : fmt::format("{:.0f}s", s);
}

int runSimulate(const SimulateArgs& a) {
  auto spec = sim::loadScene(a.scene);
  if (!spec) return commandError("simulate", spec.error().message);
  if (a.frames > 0) spec->frames = a.frames;
  if (a.fps > 0) spec->fps = a.fps;
  if (a.supersample > 0) spec->supersample = a.supersample;
  auto rig = vision::loadRig(spec->rig_path);
  if (!rig)
    return commandError("simulate", fmt::format("scene {}: {}", a.scene, rig.error().message));
  sim::StereoSimulator simulator(*spec, *rig);
  const int n = simulator.frameCount();
  if (!a.quiet) {
    fmt::print(stderr, "simulating {} ({} frames at {} fps, {}x{}, supersample {}) into {}\n",
               spec->name, n, spec->fps, rig->left.imageSize().width, rig->left.imageSize().height,
               spec->supersample, a.out);
  }
  const auto start = std::chrono::steady_clock::now();
  int last_pct = -1;
  auto ok = sim::writeSimulation(simulator, a.out, [&](int done, int total) {
    const int pct = 100 * done / total;
    if (a.quiet || (pct / 10 == last_pct / 10 && done != total)) return;
    last_pct = pct;
    const double elapsed =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    const double rate = done / std::max(elapsed, 1e-9);
    fmt::print(stderr, "  frame {}/{} ({}%), {:.1f} frames/s, {} left\n", done, total, pct, rate,
               duration((total - done) / std::max(rate, 1e-9)));
  });
  if (!ok) return commandError("simulate", ok.error().message);
  int dropped = 0;
  for (int i = 0; i < n; ++i) dropped += simulator.dropped(i) ? 1 : 0;
  fmt::print(
      "recording written to {}: {} frames ({} dropped by the simulated camera), ground truth in "
      "{}/truth\n",
      a.out, n - dropped, dropped, a.out);
  return 0;
}

struct EvaluateArgs {
  std::string recording;
  std::string track;
  std::string out;
  double threshold = 0.5;
  bool fields = false;
};

int runEvaluate(const EvaluateArgs& a) {
  const std::filesystem::path dir(a.recording);
  auto spec = sim::loadScene(dir / "scene.toml");
  if (!spec) {
    return commandError(
        "evaluate", fmt::format("{} is not a simulated recording (its scene.toml: {})", a.recording,
                                spec.error().message));
  }
  auto reader = record::Reader::open(dir);
  if (!reader) return commandError("evaluate", reader.error().message);
  sim::StereoSimulator simulator(*spec, reader->rig());
  auto rows = record::readTrackCsv(a.track);
  if (!rows) return commandError("evaluate", rows.error().message);
  auto ev = sim::evaluateTrack(simulator, *rows, a.threshold, a.fields);
  if (!ev) return commandError("evaluate", fmt::format("{}: {}", a.track, ev.error().message));
  std::string not_ok;
  long not_ok_rows = 0;
  for (const auto& [status, count] : ev->not_ok) {
    not_ok += fmt::format("{}{} {}", not_ok.empty() ? "" : ", ", status, count);
    not_ok_rows += count;
  }
  const sim::FeatureScore* worst = nullptr;
  std::vector<double> per;
  for (const auto& f : ev->per_feature) {
    per.push_back(f.rms_mm);
    if (worst == nullptr || f.rms_mm > worst->rms_mm) worst = &f;
  }
  std::sort(per.begin(), per.end());
  fmt::print(
      "features              {} ({} without ground truth)\n"
      "rows scored (ok)      {}\n"
      "3D error              RMS {:.4f} mm, median {:.4f}, p99 {:.4f}, max {:.4f}\n"
      "outliers > {:.2f} mm    {} ({:.2f} % of ok rows)\n",
      ev->features, ev->unmatched, ev->rows_ok, ev->rms_mm, ev->median_mm, ev->p99_mm, ev->max_mm,
      ev->outlier_threshold_mm, ev->outliers,
      ev->rows_ok > 0 ? 100.0 * static_cast<double>(ev->outliers) / static_cast<double>(ev->rows_ok)
                      : 0.0);
  if (ev->rows_ok > 0) {
    fmt::print(
        "error parts           per-feature bias {:.4f} mm, slow change {:.4f}, pair-to-pair noise "
        "{:.4f} (their squares add up to the RMS's; averaging pairs removes only the noise)\n",
        ev->parts.bias_mm, ev->parts.slow_mm, ev->parts.noise_mm);
  }
  if (worst != nullptr) {
    fmt::print("per-feature RMS       median {:.4f} mm, worst {:.4f} mm (id {}, {})\n",
               per[per.size() / 2], worst->rms_mm, worst->id, worst->truth);
  }
  fmt::print("rows not ok           {}{}\n", not_ok_rows,
             not_ok.empty() ? "" : " (" + not_ok + ")");
  if (!a.out.empty()) {
    std::ofstream f(a.out);
    f << "frame,id,error_mm,ex,ey,ez\n";
    for (const auto& r : ev->rows) {
      if (std::isnan(r.error_mm)) continue;
      f << fmt::format("{},{},{:.6f},{:.6f},{:.6f},{:.6f}\n", r.frame, r.id, r.error_mm,
                       r.error_vec[0], r.error_vec[1], r.error_vec[2]);
    }
    if (!f) return commandError("evaluate", fmt::format("{}: write failed", a.out));
    fmt::print("per-row errors        {}\n", a.out);
  }
  return 0;
}

}  // namespace

int simulateScene(const std::string& scene, const std::string& out, bool quiet) {
  SimulateArgs a;
  a.scene = scene;
  a.out = out;
  a.quiet = quiet;
  return runSimulate(a);
}

CommandRunner addSimulateCommand(CLI::App& app) {
  auto args = std::make_shared<SimulateArgs>();
  CLI::App* cmd = app.add_subcommand("simulate",
                                     "Render a scene (config/scenes/*.toml: cortex, plate-static, "
                                     "plate-dynamic) through its rig into a "
                                     "recording with ground truth (docs/recording-format.md).");
  cmd->add_option("--scene", args->scene, "Scene file (TOML)")
      ->required()
      ->check(CLI::ExistingFile);
  cmd->add_option("--out", args->out, "Recording folder to create (must not exist or be empty)")
      ->required();
  cmd->add_option("--frames", args->frames, "Frames to render (default: the scene's)")
      ->check(CLI::Range(1, 10'000'000));
  cmd->add_option("--fps", args->fps, "Frame rate (default: the scene's)")
      ->check(CLI::Range(0.1, 1000.0));
  cmd->add_option("--supersample", args->supersample, "Anti-aliasing samples per pixel side (1-4)")
      ->check(CLI::Range(1, 4));
  cmd->add_flag("-q,--quiet", args->quiet, "No progress lines");
  return [args] { return runSimulate(*args); };
}

CommandRunner addEvaluateCommand(CLI::App& app) {
  auto args = std::make_shared<EvaluateArgs>();
  CLI::App* cmd = app.add_subcommand(
      "evaluate",
      "Score a track (CSV from `pulsetrack track`) against a simulated recording's ground truth.");
  cmd->add_option("--recording", args->recording, "Simulated recording folder")->required();
  cmd->add_option("--track", args->track, "Track CSV: frame,t,id,xl,yl,xr,yr,x,y,z,ncc,nmi,status")
      ->required();
  cmd->add_option("--outlier-mm", args->threshold,
                  "Error above which an ok row counts as an outlier")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--out", args->out, "Write per-row errors (CSV)");
  cmd->add_flag("--fields", args->fields,
                "The track was made from the recording's fields (`pulsetrack track --fields`): "
                "its frame 2i+k is frame i's field k, k/2 of a frame later");
  return [args] { return runEvaluate(*args); };
}

}  // namespace pulsetrack::tools
