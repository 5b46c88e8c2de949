// pulsetrack: the offline tools of the pulsetrack system, one subcommand each.

#include <fmt/format.h>

#include <CLI/CLI.hpp>
#include <map>
#include <string>

#include "pulsetrack/tools/commands.hpp"

int main(int argc, char** argv) try {
  CLI::App app{
      "pulsetrack: stereo tracking of the exposed brain surface (calibration, recording, "
      "replay, simulation, validation and motion analysis tools).",
      "pulsetrack"};
  app.set_version_flag("--version", std::string("pulsetrack ") + PULSETRACK_VERSION);
  app.require_subcommand(1);
  std::map<std::string, pulsetrack::tools::CommandRunner> runners;
  runners["calibrate"] = pulsetrack::tools::addCalibrateCommand(app);
  runners["simulate"] = pulsetrack::tools::addSimulateCommand(app);
  runners["evaluate"] = pulsetrack::tools::addEvaluateCommand(app);
  runners["match"] = pulsetrack::tools::addMatchCommand(app);
  runners["track"] = pulsetrack::tools::addTrackCommand(app);
  runners["listen"] = pulsetrack::tools::addListenCommand(app);
  runners["ctl"] = pulsetrack::tools::addCtlCommand(app);
  runners["validate"] = pulsetrack::tools::addValidateCommand(app);
  runners["analyze"] = pulsetrack::tools::addAnalyzeCommand(app);
  runners["export"] = pulsetrack::tools::addExportCommand(app);
#ifdef PULSETRACK_HAS_CONSOLE
  runners["console"] = pulsetrack::tools::addConsoleCommand(app);
  runners["console-user"] = pulsetrack::tools::addConsoleUserCommand(app);
#endif
#ifdef PULSETRACK_HAS_IGTL
  runners["igtl"] = pulsetrack::tools::addIgtlCommand(app);
#endif
  CLI11_PARSE(app, argc, argv);
  for (const CLI::App* sub : app.get_subcommands()) {
    return runners.at(sub->get_name())();
  }
  return 2;
} catch (const std::exception& e) {
  // Every command reports its own errors; this is the last line of defence, never a crash.
  fmt::print(stderr, "pulsetrack: internal error: {}\n", e.what());
  return 1;
}
