#pragma once
// The `pulsetrack` subcommands. Each registers its options on the CLI11 app and returns the
// process exit code when run: 0 success, 1 failure (a message on stderr says what and where).

#include <CLI/CLI.hpp>
#include <functional>
#include <opencv2/core.hpp>
#include <string>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::tools {

using CommandRunner = std::function<int()>;

// Registers `calibrate` and returns what runs it once options are parsed.
CommandRunner addCalibrateCommand(CLI::App& app);
CommandRunner addSimulateCommand(CLI::App& app);
CommandRunner addEvaluateCommand(CLI::App& app);
CommandRunner addMatchCommand(CLI::App& app);
CommandRunner addTrackCommand(CLI::App& app);
CommandRunner addListenCommand(CLI::App& app);
CommandRunner addCtlCommand(CLI::App& app);
CommandRunner addValidateCommand(CLI::App& app);
CommandRunner addAnalyzeCommand(CLI::App& app);
CommandRunner addExportCommand(CLI::App& app);
#ifdef PULSETRACK_HAS_CONSOLE
CommandRunner addConsoleCommand(CLI::App& app);
CommandRunner addConsoleUserCommand(CLI::App& app);
#endif
#ifdef PULSETRACK_HAS_IGTL
CommandRunner addIgtlCommand(CLI::App& app);
#endif

// Renders a scene file into a recording folder as `pulsetrack simulate` does; 0 on success.
int simulateScene(const std::string& scene, const std::string& out, bool quiet);

// A rectangle given as "x,y,w,h" (pixels) to `option`; the error names the option and the text.
vision::Result<cv::Rect> parseRect(const std::string& text, const char* option);

// "pulsetrack COMMAND: error: MESSAGE" on stderr; returns 1, the failure exit code.
int commandError(const char* command, const std::string& message);

// SIGINT and SIGTERM from now on ask the command to stop (stopRequested() turns true) instead of
// killing it.
void catchStopSignals();
[[nodiscard]] bool stopRequested() noexcept;

// A server's foreground life: `run` blocks until `stop` is called, which happens at SIGINT or
// SIGTERM (catchStopSignals). SIGPIPE is ignored: a client that goes away is an error on its
// socket, not the server's end.
void serveUntilSignal(const std::function<void()>& run, const std::function<void()>& stop);

}  // namespace pulsetrack::tools
