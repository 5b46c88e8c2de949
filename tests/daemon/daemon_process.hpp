#pragma once
// pulsetrackd as a real process for the end-to-end tests: its config written into a temporary
// folder (the simulated rig unless told otherwise), systemd played on a notify socket the test
// binds, its notifications collected.

#include <poll.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <fstream>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "pulsetrack/dds/dds.hpp"
#include "test_util.hpp"

extern char** environ;

namespace pulsetrack {

inline const std::string kScene =
    std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-60s.toml";

struct DaemonOptions {
  std::string rig = "rig-e2e";
  std::string ros_namespace;
  std::string extra;                 // more config, after [health]
  std::string name = "pulsetrackd";  // the config file's and the notify socket's name
};

struct Daemon {
  pid_t pid = 0;
  int notify_fd = -1;
  // (seconds since start, datagram); read it after wait().
  std::vector<std::pair<double, std::string>> notes;

  // `source_extra`: lines in [source] (e.g. another kind); `opt`: the rig, its namespace, more
  // config, the files' names.
  Daemon(const test::TempDir& dir, uint32_t domain, const std::vector<std::string>& extra,
         const std::string& source_extra = "", const std::vector<std::string>& wrapper = {},
         const DaemonOptions& opt = {}) {
    const auto cfg = dir.path() / (opt.name + ".toml");
    std::ofstream(cfg) << "rig_id = \"" << opt.rig << "\"\n[dds]\ndomain_id = " << domain
                       << "\nnamespace = \"" << opt.ros_namespace << "\"\n[source]\n"
                       << (source_extra.find("kind") == std::string::npos
                               ? "kind = \"sim\"\nscene = \"" + kScene + "\"\nfps = 10.0\n"
                               : "")
                       << source_extra
                       << "[realtime]\nlock_memory = false\n"
                          "capture = { priority = 0 }\ntrack = { priority = 0 }\n"
                          "publish = { priority = 0 }\n[health]\nperiod_ms = 200\n"
                       << opt.extra;
    const std::string sock = (dir.path() / (opt.name + ".notify")).string();
    notify_fd = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    sockaddr_un a{};
    a.sun_family = AF_UNIX;
    sock.copy(a.sun_path, sizeof a.sun_path - 1);
    EXPECT_EQ(bind(notify_fd, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
    setenv("CYCLONEDDS_URI", pulsetrack::dds::kLoopbackUri, 1);
    setenv("NOTIFY_SOCKET", sock.c_str(), 1);
    setenv("WATCHDOG_USEC", "1000000", 1);
    unsetenv("WATCHDOG_PID");
    std::vector<std::string> args = wrapper;
    for (const std::string& arg : {std::string(PULSETRACKD), std::string("-c"), cfg.string()})
      args.push_back(arg);
    args.insert(args.end(), extra.begin(), extra.end());
    std::vector<char*> argv;
    argv.reserve(args.size() + 1);
    for (auto& s : args) argv.push_back(s.data());
    argv.push_back(nullptr);
    EXPECT_EQ(posix_spawn(&pid, args[0].c_str(), nullptr, nullptr, argv.data(), environ), 0);
    unsetenv("NOTIFY_SOCKET");
    unsetenv("WATCHDOG_USEC");
    // The notifications are read all the time, as systemd reads them: a full datagram queue
    // (net.unix.max_dgram_qlen, 10 on some machines) would block the daemon's sd_notify and
    // with it its health loop.
    reader_ = std::thread([this, t0 = std::chrono::steady_clock::now()] {
      char buf[4096];
      while (!stop_.load()) {
        pollfd p{notify_fd, POLLIN, 0};
        if (poll(&p, 1, 50) <= 0) continue;
        for (;;) {
          const ssize_t n = recv(notify_fd, buf, sizeof buf, 0);
          if (n <= 0) break;
          const double t =
              std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
          const std::lock_guard<std::mutex> lock(mutex_);
          notes.emplace_back(t, std::string(buf, static_cast<size_t>(n)));
        }
      }
    });
  }
  // Kept for the tests' loops: the notifications are read by a thread of their own (below).
  void drain(double /*t*/) {}
  // Waits for the daemon to exit, reading its notifications meanwhile (a full datagram queue
  // would block its sd_notify, as it would under a systemd that stopped reading).
  int wait(const std::function<double()>& /*secs*/) {
    int status = 0;
    for (;;) {
      const pid_t r = waitpid(pid, &status, WNOHANG);
      if (r == pid || r < 0) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    stopReading();
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  }
  ~Daemon() {
    stopReading();
    if (notify_fd >= 0) close(notify_fd);
  }
  Daemon(const Daemon&) = delete;
  Daemon& operator=(const Daemon&) = delete;

 private:
  // Stops the reader after a last read of what the daemon sent; `notes` is then complete.
  void stopReading() {
    if (!reader_.joinable()) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    stop_ = true;
    reader_.join();
  }
  std::thread reader_;
  std::atomic<bool> stop_{false};
  std::mutex mutex_;
};

}  // namespace pulsetrack
