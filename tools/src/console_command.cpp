// pulsetrack console: the operating-room console's server (console/console.hpp), and
// pulsetrack console-user: its users file.

#include <fmt/format.h>
#include <termios.h>
#include <unistd.h>

#include <filesystem>
#include <iostream>
#include <memory>

#include "pulsetrack/console/console.hpp"
#include "pulsetrack/console/credentials.hpp"
#include "pulsetrack/tools/commands.hpp"

namespace pulsetrack::tools {

namespace {

// The page's folder as installed: beside the program (BIN/../share/pulsetrack/console, wherever
// the package put it), else where this build would install it.
std::string installedWww() {
  std::error_code ec;
  const std::filesystem::path exe = std::filesystem::read_symlink("/proc/self/exe", ec);
  if (!ec) {
    const auto beside = exe.parent_path().parent_path() / "share/pulsetrack/console";
    if (std::filesystem::is_regular_file(beside / "index.html", ec)) return beside.string();
  }
  return PULSETRACK_CONSOLE_WWW;
}

struct ConsoleArgs {
  console::ConsoleOptions o;
  std::string www = installedWww();
  std::string enclave;
};

int runConsole(const ConsoleArgs& a) {
  console::ConsoleOptions o = a.o;
  o.www = a.www;
  if (!a.enclave.empty()) o.security = dds::SecurityFiles::inEnclave(a.enclave);
  auto c = console::Console::create(o);
  if (!c) return commandError("console", c.error().message);
  fmt::print("console: serving {}\n", (*c)->banner());
  std::fflush(stdout);
  serveUntilSignal([&] { (*c)->run(); }, [&] { (*c)->stop(); });
  fmt::print("console: stopped\n");
  return 0;
}

// A password from the terminal (not echoed), or the first line of stdin when it is not one.
std::string readPassword(const char* prompt, bool& ok) {
  std::string line;
  if (isatty(STDIN_FILENO) == 0) {
    ok = static_cast<bool>(std::getline(std::cin, line));
    return line;
  }
  fmt::print(stderr, "{}", prompt);
  termios old{};
  tcgetattr(STDIN_FILENO, &old);
  termios quiet = old;
  quiet.c_lflag &= ~static_cast<tcflag_t>(ECHO);
  tcsetattr(STDIN_FILENO, TCSANOW, &quiet);
  ok = static_cast<bool>(std::getline(std::cin, line));
  tcsetattr(STDIN_FILENO, TCSANOW, &old);
  fmt::print(stderr, "\n");
  return line;
}

struct UserArgs {
  std::string users, name, role = "operator";
};

int runConsoleUser(const UserArgs& a) {
  bool ok = false;
  const std::string pw = readPassword("password: ", ok);
  if (!ok) return commandError("console-user", "no password given (stdin ended)");
  if (isatty(STDIN_FILENO) != 0) {
    const std::string again = readPassword("again: ", ok);
    if (!ok || again != pw) return commandError("console-user", "the passwords differ");
  }
  const console::Role role =
      a.role == "operator" ? console::Role::kOperator : console::Role::kViewer;
  if (auto r = console::setUser(a.users, a.name, role, pw); !r)
    return commandError("console-user", r.error().message);
  fmt::print("console-user: {} ({}) set in {}\n", a.name, a.role, a.users);
  return 0;
}

}  // namespace

CommandRunner addConsoleCommand(CLI::App& app) {
  auto a = std::make_shared<ConsoleArgs>();
  CLI::App* cmd = app.add_subcommand(
      "console",
      "Serve the operating-room console: a web page (HTTPS) with the cameras, the features, the "
      "ROI drawn by hand, start/stop/re-detect/recorder, health, the displacement and its "
      "spectrum, the dense field. A process of its own, a DDS participant of its own.");
  cmd->add_option("--host", a->o.host, "Address to listen on (localhost unless configured)")
      ->capture_default_str();
  cmd->add_option("--port", a->o.port, "TCP port (0: any free one, printed)")
      ->check(CLI::Range(0, 65535))
      ->capture_default_str();
  cmd->add_option("--cert", a->o.cert,
                  "TLS certificate, PEM (scripts/security tls KEYSTORE NAME makes one from the DDS "
                  "keystore's CA)")
      ->required();
  cmd->add_option("--key", a->o.key, "Its private key, PEM")->required();
  cmd->add_option("--users", a->o.users, "The users file (pulsetrack console-user makes it)")
      ->required();
  cmd->add_option("--rig", a->o.rig, "The rig file the daemon uses (the right ROI's derivation)")
      ->required();
  cmd->add_option("--www", a->www, "The page's folder (default: the installed one)")
      ->capture_default_str();
  cmd->add_option("--domain", a->o.domain, "DDS domain id")
      ->check(CLI::Range(0, 232))
      ->capture_default_str();
  cmd->add_option("--namespace", a->o.ros_namespace, "The daemon's topic namespace ([dds])");
  cmd->add_option("--enclave", a->enclave,
                  "DDS Security: this console's SROS2 enclave (role controller: it may command)");
  cmd->add_option("--working-distance", a->o.working_distance_mm,
                  "mm: the right ROI's depth before any feature is seen")
      ->check(CLI::Range(10.0, 10000.0))
      ->capture_default_str();
  cmd->add_option("--session-hours", a->o.session_hours, "A login lasts this long")
      ->check(CLI::Range(0.01, 72.0))
      ->capture_default_str();
  return [a] { return runConsole(*a); };
}

CommandRunner addConsoleUserCommand(CLI::App& app) {
  auto a = std::make_shared<UserArgs>();
  CLI::App* cmd = app.add_subcommand(
      "console-user",
      "Add a console user or change their password or role (the password is asked, or read as "
      "the first line of stdin).");
  cmd->add_option("--users", a->users, "The users file (created, mode 0600)")->required();
  cmd->add_option("--user", a->name, "User name")->required();
  cmd->add_option("--role", a->role, "operator (may command) or viewer")
      ->check(CLI::IsMember({"operator", "viewer"}))
      ->capture_default_str();
  return [a] { return runConsoleUser(*a); };
}

}  // namespace pulsetrack::tools
