// `pulsetrack validate` and `pulsetrack analyze`: the paper's sections 4-6 on the team's data.

#include <fmt/format.h>

#include <filesystem>
#include <memory>

#include "pulsetrack/analysis/motion.hpp"
#include "pulsetrack/analysis/report.hpp"
#include "pulsetrack/analysis/validation.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "pulsetrack/tools/commands.hpp"

namespace pulsetrack::tools {

namespace {

struct ValidateArgs {
  std::string scene, recording, markers, divots, digitization, protocol, registration, out;
  double depth = 20.0;
  double rotation_scale = 10.0;
  bool quiet = false;
};

int runValidate(const ValidateArgs& a) {
  analysis::ValidationInputs in;
  in.recording = a.recording;
  if (!a.scene.empty()) {
    // A simulator scene: rendered first into OUT/recording, then validated like a real session.
    in.recording = std::filesystem::path(a.out) / "recording";
    if (const int rc = simulateScene(a.scene, in.recording.string(), a.quiet); rc != 0) return rc;
  }
  in.markers = a.markers;
  in.divots = a.divots;
  in.digitization = a.digitization;
  in.protocol = a.protocol;
  in.depth_tolerance_mm = a.depth;
  in.rotation_scale_mm = a.rotation_scale;
  if (!a.registration.empty()) {
    auto reg = analysis::readRegistration(a.registration);
    if (!reg) return commandError("validate", reg.error().message);
    in.o_t_c = *reg;
  }
  size_t last_pct = 101;
  auto r = analysis::validate(in, [&](size_t done, size_t total) {
    const size_t pct = 100 * done / std::max<size_t>(1, total);
    if (!a.quiet && pct / 10 != last_pct / 10) {
      fmt::print(stderr, "validate: {:3}% ({} of {} frames)\n", pct, done, total);
      last_pct = pct;
    }
  });
  if (!r) return commandError("validate", r.error().message);
  fmt::print("{}", analysis::formatValidation(*r));
  auto files = analysis::writeValidationReport(
      *r, a.out,
      fmt::format("Validation of {}", a.scene.empty()
                                          ? std::filesystem::path(a.recording).filename().string()
                                          : std::filesystem::path(a.scene).stem().string()));
  if (!files) return commandError("validate", files.error().message);
  fmt::print("report: {}\n", (std::filesystem::path(a.out) / "report.html").string());
  return 0;
}

struct AnalyzeArgs {
  std::vector<std::string> tracks;
  std::string out;
};

int runAnalyze(const AnalyzeArgs& a) {
  std::vector<analysis::NamedMotion> all;
  for (const std::string& path : a.tracks) {
    vision::Result<analysis::MotionAnalysis> m;
    if (record::isDeformationCsv(path)) {  // the session's signal, as pulsetrackd publishes it
      auto rows = record::readDeformationCsv(path);
      if (!rows) return commandError("analyze", rows.error().message);
      m = analysis::analyzeMotion(*rows);
    } else {
      auto rows = record::readTrackCsv(path);
      if (!rows) return commandError("analyze", rows.error().message);
      m = analysis::analyzeMotion(*rows);
    }
    if (!m) return commandError("analyze", fmt::format("{}: {}", path, m.error().message));
    all.push_back({std::filesystem::path(path).stem().string(), std::move(*m)});
    fmt::print("{}", analysis::formatMotion(all.back()));
  }
  auto files = analysis::writeMotionReport(all, a.out);
  if (!files) return commandError("analyze", files.error().message);
  fmt::print("report: {}\n", (std::filesystem::path(a.out) / "report.html").string());
  return 0;
}

}  // namespace

CommandRunner addValidateCommand(CLI::App& app) {
  auto args = std::make_shared<ValidateArgs>();
  CLI::App* cmd = app.add_subcommand(
      "validate",
      "The paper's validation (sections 4-5) of a plate recording against the reference "
      "tracker: O_T_C registration and Table II, per-frame errors, Kruskal-Wallis across sets and "
      "speeds, Figs. 7-8, an HTML report (docs/validation.md).");
  auto* rec = cmd->add_option("--recording", args->recording, "Plate recording folder")
                  ->check(CLI::ExistingDirectory);
  auto* scene = cmd->add_option("--scene", args->scene,
                                "Or a simulator plate scene (config/scenes/plate-*.toml), rendered "
                                "into OUT/recording first")
                    ->check(CLI::ExistingFile);
  rec->excludes(scene);
  cmd->callback([rec, scene] {
    if (rec->count() + scene->count() == 0) throw CLI::RequiredError("--recording or --scene");
  });
  cmd->add_option(
      "--markers", args->markers,
      "Reference tracker's markers' poses per frame (default RECORDING/tracker/markers.csv)");
  cmd->add_option("--divots", args->divots,
                  "Digitized divots divot,x,y,z (default RECORDING/tracker/divots.csv)");
  cmd->add_option(
      "--digitization-markers", args->digitization,
      "Markers' pose while digitizing (default RECORDING/tracker/digitization_markers.csv)");
  cmd->add_option(
      "--protocol", args->protocol,
      "Acquisitions: set, frames and the features' boxes (default RECORDING/tracker/protocol.csv)");
  cmd->add_option("--registration", args->registration,
                  "O_T_C from an earlier run's registration.csv (a session without set 0)");
  cmd->add_option("--depth", args->depth, "Depth tolerance of the stereo search, mm")
      ->check(CLI::Range(0.1, 500.0))
      ->capture_default_str();
  cmd->add_option("--rotation-scale", args->rotation_scale,
                  "Eq. (20): rotation residuals are scaled by this many mm per rad to weigh like "
                  "the translation residuals (the features' span)")
      ->check(CLI::Range(0.01, 10000.0))
      ->capture_default_str();
  cmd->add_option("--out", args->out, "Report folder (CSV, PNG, report.html)")->required();
  cmd->add_flag("-q,--quiet", args->quiet, "No progress lines");
  return [args] { return runValidate(*args); };
}

CommandRunner addAnalyzeCommand(CLI::App& app) {
  auto args = std::make_shared<AnalyzeArgs>();
  CLI::App* cmd = app.add_subcommand(
      "analyze",
      "Brain motion from tracks (section 6): the cloud's displacement, missing frames filled, "
      "spectrum with named peaks (vasomotor, breathing, cardiac), feature speeds, Fig. 9, HTML.");
  cmd->add_option("tracks", args->tracks,
                  "Deformation files (`pulsetrack track` writes NAME-deformation.csv: the signal "
                  "pulsetrackd publishes) or track CSV files, one per acquisition")
      ->required()
      ->check(CLI::ExistingFile);
  cmd->add_option("--out", args->out, "Report folder (CSV, PNG, report.html)")->required();
  return [args] { return runAnalyze(*args); };
}

}  // namespace pulsetrack::tools
