// The soak: pulsetrackd for a long run (the issue's: 30 minutes) on the simulated rig, with
// faults injected on a schedule, checked the way a technician and a robot team would see them.
//
// The daemon replays, from memory, pairs rendered by the simulator (`pulsetrack simulate`) at
// the rate of a live camera (30 Hz, restamped as a camera stamps its exposure: the figures are the
// daemon's, not the renderer's), with its recorder on and the appliance's real-time settings.
// Each window (5 minutes in the run) holds one of each fault:
//   - camera outage: the cameras go away for 4 s and come back ([source.faults] outage_every_s,
//     outage_s: the source says kFault as a driver whose device vanished); the trigger goes on;
//   - missing triggers all along (every 997th pulse never fires);
//   - subscriber killed (SIGKILL) and restarted: the ROS 2 subscriber built from the .msg files;
//     a fresh one must receive features, deformation and health;
//   - command flood: 1000 commands as fast as DDS takes them (a third valid `start`, the rest
//     refused: unknown verbs and malformed ROIs), counted on health, tracking untouched;
//   - the recorder's disk filling: the recordings go to a small tmpfs (mounted here, as root)
//     that the recorder fills until it stops at its reserve; the "technician" deletes the older
//     segments and the recorder must resume by itself in a new segment (and fill it again).
// Printed: RSS at the start and the end, per-window latency (exposure -> features sample received
// by this process, DDS on loopback) p50/p99/p99.9/max and samples lost, the daemon's stage p99s,
// and each fault with how it was counted on health and how long recovery took. It fails (exit 1)
// when the daemon died or exited non-zero, the systemd watchdog would have fired (a gap in
// WATCHDOG=1 longer than the unit's WatchdogSec=3s: "a stage restarted"), health said fault, a
// fault was not counted or not recovered, a recording segment does not read back, or RSS grew by
// more than 10 %.
//   soak [--minutes 30] [--window-s 300] [--rate 30] [--disk-mb 1024]

#include <fcntl.h>
#include <fmt/format.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/mount.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "bench_process.hpp"
#include "pulsetrack/dds/dds.hpp"
#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/rt/heartbeat.hpp"

namespace {

using pulsetrack::bench::spawn;
using pulsetrack::bench::waitExit;

namespace fs = std::filesystem;

double now_s() { return static_cast<double>(pulsetrack::rt::monotonicNs()) * 1e-9; }

int64_t realtimeNs() {
  timespec ts{};
  clock_gettime(CLOCK_REALTIME, &ts);
  return int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

long rssKb(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind("VmRSS:", 0) == 0) return std::strtol(line.c_str() + 6, nullptr, 10);
  }
  return -1;
}

struct HealthSample {
  double t = 0;
  uint8_t state = 0;
  uint64_t frames = 0, missing = 0, source_faults = 0, recorder_faults = 0, accepted = 0,
           refused = 0, drops = 0, deadline_misses = 0;
  std::string source_state, tracking, recorder, output, last_error;
  uint32_t track_p99 = 0, publish_p99 = 0, capture_p99 = 0;
};

struct Window {
  std::vector<double> latency_us;
  uint64_t first = 0, last = 0, received = 0;
  long rss_kb = -1;
};

double pct(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(q * static_cast<double>(v.size())))];
}

int failures = 0;
void check(bool ok, const std::string& what) {
  std::printf("  %s %s\n", ok ? "ok  " : "FAIL", what.c_str());
  std::fflush(stdout);
  if (!ok) ++failures;
}

}  // namespace

int main(int argc, char** argv) try {
  double minutes = 30, window_s = 300, rate = 30;
  int disk_mb = 1024;
  CLI::App app{
      "The soak: pulsetrackd for a long run on the simulated rig with faults injected on a "
      "schedule (camera outage, missing triggers, a subscriber killed and restarted, a command "
      "flood, the recorder's disk filling); prints RSS, per-window latency and each fault's "
      "count and recovery; exit 1 on any failed check.",
      "soak"};
  app.add_option("--minutes", minutes, "Length of the run (the issue's: 30)")
      ->check(CLI::Range(1.0, 24 * 60.0))
      ->capture_default_str();
  app.add_option("--window-s", window_s, "One window: one fault of each kind, latency per window")
      ->check(CLI::Range(20.0, 3600.0))
      ->capture_default_str();
  app.add_option("--rate", rate, "Trigger rate, Hz")
      ->check(CLI::Range(1.0, 200.0))
      ->capture_default_str();
  app.add_option("--disk-mb", disk_mb, "Size of the recorder's tmpfs (needs root)")
      ->check(CLI::Range(256, 65536))
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  const int windows = std::max(1, static_cast<int>(std::lround(minutes * 60 / window_s)));
  const double total_s = windows * window_s;
  setenv("CYCLONEDDS_URI", pulsetrack::dds::kLoopbackUri, 1);
  const fs::path dir = fs::temp_directory_path() / ("pulsetrack-soak-" + std::to_string(getpid()));
  fs::create_directories(dir);
  const std::string rec = (dir / "rec").string();
  std::fprintf(stderr, "soak: rendering 60 frames of the cortex scene...\n");
  if (waitExit(spawn({PULSETRACK_CLI, "simulate", "--scene",
                      std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-60s.toml",
                      "--out", rec, "--frames", "60", "--supersample", "1", "--quiet"})) != 0) {
    std::fprintf(stderr, "soak: pulsetrack simulate failed\n");
    return 1;
  }
  // The recorder's disk: a tmpfs of --disk-mb, with a 256 MB reserve.
  const fs::path disk = dir / "disk";
  fs::create_directories(disk);
  const std::string size = "size=" + std::to_string(disk_mb) + "m";
  const bool disk_fault = ::mount("tmpfs", disk.c_str(), "tmpfs", 0, size.c_str()) == 0;
  if (!disk_fault) {
    std::printf(
        "soak: SKIPPED the disk fault: mounting a tmpfs for the recorder needs root (%s); the "
        "recorder stays off\n",
        std::strerror(errno));
  }
  const fs::path recordings = disk / "recordings";
  const uint32_t domain = 120;
  const fs::path cfg = dir / "pulsetrackd.toml";
  std::ofstream(cfg) << "rig_id = \"soak\"\n[dds]\ndomain_id = " << domain
                     << "\n[source]\nkind = \"replay\"\nrecording = \"" << rec
                     << "\"\npace = \"rate\"\nfps = " << rate
                     << "\nloop = true\npreload = true\n[source.faults]\n"
                        "missing_trigger_every = 997\noutage_every_s = "
                     << window_s << "\noutage_s = 4.0\n[recorder]\nenabled = "
                     << (disk_fault ? "true" : "false") << "\ndir = \"" << recordings.string()
                     << "\"\nmin_free_mb = 256\n[health]\nperiod_ms = 500\n";
  fs::create_directories(recordings);
  // The notify socket, read as systemd reads it; the watchdog as the unit sets it (3 s).
  const std::string sock = (dir / "notify").string();
  const int notify_fd = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
  sockaddr_un a{};
  a.sun_family = AF_UNIX;
  sock.copy(a.sun_path, sizeof a.sun_path - 1);
  if (bind(notify_fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
    std::fprintf(stderr, "soak: cannot bind %s\n", sock.c_str());
    return 1;
  }
  setenv("NOTIFY_SOCKET", sock.c_str(), 1);
  setenv("WATCHDOG_USEC", "3000000", 1);
  const double t0 = now_s();
  const pid_t daemon = spawn({PULSETRACKD, "-c", cfg.string()}, (dir / "journal.txt").c_str());
  unsetenv("NOTIFY_SOCKET");
  unsetenv("WATCHDOG_USEC");
  std::atomic<bool> stop{false};
  std::mutex mutex;
  std::vector<double> pings;
  bool ready = false;
  std::thread notify([&] {
    char buf[4096];
    while (!stop.load()) {
      pollfd p{notify_fd, POLLIN, 0};
      if (poll(&p, 1, 100) <= 0) continue;
      for (;;) {
        const ssize_t n = recv(notify_fd, buf, sizeof buf, 0);
        if (n <= 0) break;
        const std::string s(buf, static_cast<size_t>(n));
        const std::lock_guard lock(mutex);
        if (s.find("WATCHDOG=1") != std::string::npos) pings.push_back(now_s() - t0);
        if (s.find("READY=1") != std::string::npos) ready = true;
      }
    }
  });
  // This process's subscriptions: features (latency, frame numbers) and health (everything).
  auto p = pulsetrack::dds::Participant::create(domain, nullptr);
  if (!p) {
    std::fprintf(stderr, "soak: %s\n", p.error().message.c_str());
    return 1;
  }
  auto features = pulsetrack::dds::Reader::create(*p, pulsetrack::dds::kFeaturesTopic,
                                                  &pulsetrack_msgs_msg_dds__Features__desc,
                                                  pulsetrack::dds::Profile::kSensorData);
  auto health = pulsetrack::dds::Reader::create(*p, pulsetrack::dds::kHealthTopic,
                                                &pulsetrack_msgs_msg_dds__Health__desc,
                                                pulsetrack::dds::Profile::kTransientLocal);
  auto command = pulsetrack::dds::Writer::create(*p, pulsetrack::dds::kCommandTopic,
                                                 &pulsetrack_msgs_msg_dds__Command__desc,
                                                 pulsetrack::dds::Profile::kCommand);
  if (!features || !health || !command) {
    std::fprintf(stderr, "soak: cannot create the DDS readers and writer\n");
    return 1;
  }
  std::vector<Window> win(static_cast<size_t>(windows));
  std::vector<HealthSample> hs;
  std::thread reader([&] {
    pulsetrack_msgs_msg_dds__Features_ f{};
    pulsetrack_msgs_msg_dds__Health_ h{};
    while (!stop.load()) {
      while (health->takeOne(&h, std::chrono::milliseconds(0))) {
        HealthSample s;
        s.t = now_s() - t0;
        s.state = h.state;
        s.frames = h.frames;
        s.missing = h.missing_triggers;
        s.source_faults = h.source_faults;
        s.recorder_faults = h.recorder_faults;
        s.accepted = h.commands_accepted;
        s.refused = h.commands_refused;
        s.drops = h.drops;
        s.deadline_misses = h.deadline_misses;
        s.source_state = h.source_state;
        s.tracking = h.tracking_state;
        s.recorder = h.recorder_state;
        s.output = h.output_state;
        s.last_error = h.last_error;
        for (uint32_t i = 0; i < h.stages._length; ++i) {
          const std::string stage = h.stages._buffer[i].stage;
          const uint32_t p99 = h.stages._buffer[i].p99_us;
          (stage == "capture" ? s.capture_p99
           : stage == "track" ? s.track_p99
                              : s.publish_p99) = p99;
        }
        const std::lock_guard lock(mutex);
        hs.push_back(std::move(s));
      }
      if (!features->takeOne(&f, std::chrono::milliseconds(100))) continue;
      const int64_t stamp = int64_t{f.header.stamp.sec} * 1'000'000'000 + f.header.stamp.nanosec;
      const double latency_us = static_cast<double>(realtimeNs() - stamp) * 1e-3;
      const double t = now_s() - t0;
      const auto w = static_cast<size_t>(t / window_s);
      if (t < 5 || w >= win.size()) continue;  // start-up: detection, discovery
      const std::lock_guard lock(mutex);
      Window& cur = win[w];
      cur.latency_us.push_back(latency_us);
      if (cur.received == 0) cur.first = f.frame;
      cur.last = f.frame;
      ++cur.received;
    }
    dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
    dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
  });
  const auto latest = [&] {
    const std::lock_guard lock(mutex);
    return hs.empty() ? HealthSample{} : hs.back();
  };
  bool died = false;
  const auto alive = [&] {
    if (died) return false;
    int status = 0;
    if (waitpid(daemon, &status, WNOHANG) == daemon) died = true;
    return !died;
  };
  // Waits (bounded) for `pred` on the latest health sample; returns the seconds it took or -1.
  const auto waitHealth = [&](double timeout_s, auto pred) {
    const double start = now_s();
    while (now_s() - start < timeout_s && alive()) {
      if (pred(latest())) return now_s() - start;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    return -1.0;
  };
  const std::string subscriber_log = (dir / "subscriber.txt").string();
  const auto longSubscriber = [&] {
    return spawn({ROS2_SUBSCRIBER, "--domain", std::to_string(domain), "--features", "1000000000",
                  "--deformation", "0", "--health", "0", "--timeout", "100000"},
                 "/dev/null");
  };
  pid_t subscriber = longSubscriber();
  std::printf("soak: %d windows of %.0f s, %.0f Hz, %s\n", windows, window_s, rate,
              disk_fault ? "recorder on a tmpfs" : "no recorder");
  std::printf("faults (each: counted on health, recovered):\n");
  std::fflush(stdout);
  if (waitHealth(120, [](const HealthSample& s) { return s.state == 1; }) < 0) {
    check(false, "the daemon reached state ok within 120 s");
  }
  const double warm = now_s() - t0;
  for (int i = 0; i < 300 && command->matchedReaders() < 1; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  long rss_start = -1;
  uint32_t request = 0;
  int subscribers_ok = 0, floods_ok = 0, disks_ok = 0;
  uint64_t sent_total = 0;
  for (int w = 0; w < windows && alive(); ++w) {
    const double base = w * window_s;
    const auto at = [&](double frac) {
      while (now_s() - t0 < base + frac * window_s && alive())
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    };
    at(0.1);
    if (w == 0) rss_start = rssKb(daemon);
    // A subscriber killed and restarted: a fresh one receives every topic.
    at(0.3);
    kill(subscriber, SIGKILL);
    waitExit(subscriber);
    {
      const double start = now_s();
      const int rc =
          waitExit(spawn({ROS2_SUBSCRIBER, "--domain", std::to_string(domain), "--features", "30",
                          "--deformation", "30", "--health", "1", "--timeout", "60"},
                         subscriber_log.c_str()));
      check(rc == 0, fmt::format("window {}: subscriber killed; a restarted one received 30 "
                                 "features, 30 deformation, health in {:.1f} s (exit {})",
                                 w + 1, now_s() - start, rc));
      subscribers_ok += rc == 0 ? 1 : 0;
      subscriber = longSubscriber();
    }
    // A command flood.
    at(0.5);
    {
      const HealthSample before = latest();
      pulsetrack_msgs_msg_dds__Command_ c{};
      std::string rig = "soak";
      c.rig_id = rig.data();
      const char* verbs[] = {"start", "bogus", "set_roi"};
      uint64_t sent = 0, valid = 0;
      const double flood_start = now_s();
      for (int i = 0; i < 1000; ++i) {
        c.request_id = ++request;
        c.command = const_cast<char*>(verbs[i % 3]);
        // Malformed: a negative width (all zero is valid since issue 32: "find the ROI").
        for (int k = 0; k < 4; ++k) c.roi_left[k] = c.roi_right[k] = 0;
        c.roi_left[2] = -5;
        if (command->write(&c)) {  // a write that timed out (flow control) was not sent
          ++sent;
          valid += i % 3 == 0 ? 1 : 0;
        }
      }
      (void)command->waitForAcks(std::chrono::seconds(10));
      const double flood_s = now_s() - flood_start;
      sent_total += sent;
      double took = waitHealth(30, [&](const HealthSample& s) {
        return s.accepted + s.refused >= before.accepted + before.refused + sent;
      });
      const HealthSample after = latest();
      const uint64_t acc = after.accepted - before.accepted, ref = after.refused - before.refused;
      const bool tracking = after.tracking.rfind("tracking", 0) == 0 && after.state != 3;
      check(took >= 0 && acc == valid && ref == sent - valid && tracking,
            fmt::format("window {}: command flood: {} sent in {:.2f} s ({} writes timed out: flow "
                        "control), health counted {} accepted + {} refused; still {}",
                        w + 1, sent, flood_s, 1000 - sent, acc, ref, after.tracking));
      floods_ok += took >= 0 && acc == valid && ref == sent - valid && tracking ? 1 : 0;
    }
    // The disk: the recorder has filled it to its reserve (a fault); the technician deletes the
    // recordings (each read back first: complete, nothing cut); the recorder resumes by itself in
    // a new segment and fills the disk again.
    at(0.7);
    if (disk_fault) {
      const HealthSample before = latest();
      const double full = waitHealth(
          60, [&](const HealthSample& s) { return s.recorder.rfind("stopped", 0) == 0; });
      std::vector<fs::path> segments;
      for (const auto& e : fs::directory_iterator(recordings)) segments.push_back(e.path());
      std::sort(segments.begin(), segments.end(), [](const fs::path& x, const fs::path& y) {
        return fs::last_write_time(x) < fs::last_write_time(y);
      });
      bool readable = !segments.empty();
      for (size_t i = 0; i < segments.size(); ++i) {  // all closed: the recorder is stopped
        auto r = pulsetrack::record::Reader::open(segments[i]);
        readable = readable && r && r->size() > 0 && !r->truncation().has_value();
        fs::remove_all(segments[i]);
      }
      const uint64_t faults_before = latest().recorder_faults;
      const double resumed = waitHealth(
          30, [&](const HealthSample& s) { return s.recorder.rfind("recording", 0) == 0; });
      const double refilled =
          waitHealth(120, [&](const HealthSample& s) { return s.recorder_faults > faults_before; });
      const bool ok = full >= 0 && readable && resumed >= 0 && refilled >= 0;
      check(ok, fmt::format("window {}: disk full (recorder faults {} -> {}); {} segments read "
                            "back and deleted; resumed in {:.1f} s; filled again after {:.1f} s",
                            w + 1, before.recorder_faults, latest().recorder_faults,
                            segments.size(), resumed, refilled));
      disks_ok += ok ? 1 : 0;
    }
    at(0.97);
    const std::lock_guard lock(mutex);
    win[static_cast<size_t>(w)].rss_kb = rssKb(daemon);
  }
  const bool was_alive = alive();
  const long rss_end = rssKb(daemon);
  kill(daemon, SIGTERM);
  const int rc = died ? -1 : waitExit(daemon);
  kill(subscriber, SIGKILL);
  waitExit(subscriber);
  stop = true;
  reader.join();
  notify.join();
  // The outages, from the health stream: each counted, each followed by frames again.
  const HealthSample last = latest();
  const double t_end = last.t;
  int outages_recovered = 0, outages_at_end = 0;
  {
    const std::lock_guard lock(mutex);
    for (size_t i = 1; i < hs.size(); ++i) {
      if (hs[i].source_faults == hs[i - 1].source_faults) continue;
      const double t_fault = hs[i].t;
      if (t_fault > t_end - 15) {  // an outage the run ended in (events ran late): not waited for
        ++outages_at_end;
        continue;
      }
      double back = -1;
      std::string why;  // what health said while the source was away
      for (size_t j = i; j < hs.size() && hs[j].t < t_fault + 10 && why.empty(); ++j) {
        if (hs[j].source_state == "stalled") why = hs[j].last_error;
      }
      for (size_t j = i + 1; j < hs.size(); ++j) {
        if (hs[j].frames > hs[i].frames + 30 && hs[j].source_state == "running" &&
            hs[j].tracking.rfind("tracking", 0) == 0) {
          back = hs[j].t - t_fault;
          break;
        }
      }
      check(back >= 0,
            fmt::format("camera outage {} at {:.0f} s ('{}'): tracking again {:.1f} s "
                        "after health counted it",
                        hs[i].source_faults, t_fault, hs[i].last_error.substr(0, 80), back));
      outages_recovered += back >= 0 ? 1 : 0;
    }
  }
  const int outages_injected = windows - 1;
  check(
      last.source_faults >= static_cast<uint64_t>(outages_injected) &&
          outages_recovered + outages_at_end == static_cast<int>(last.source_faults),
      fmt::format("outages: {} injected, {} counted on health, {} recovered{}", outages_injected,
                  last.source_faults, outages_recovered,
                  outages_at_end > 0 ? fmt::format(" ({} as the run ended)", outages_at_end) : ""));
  const auto expected_missing = static_cast<uint64_t>(last.frames / 997);
  check(last.missing >= expected_missing,
        fmt::format("missing triggers counted: {} (every 997th pulse: at least {}, plus the "
                    "outages' pulses)",
                    last.missing, expected_missing));
  std::printf(
      "\nhealth at the end: %s; frames %llu, drops %llu, deadline misses %llu, source "
      "outages %llu, recorder faults %llu, commands %llu accepted / %llu refused; %s\n",
      last.state == 1   ? "ok"
      : last.state == 2 ? "degraded"
                        : "other",
      static_cast<unsigned long long>(last.frames), static_cast<unsigned long long>(last.drops),
      static_cast<unsigned long long>(last.deadline_misses),
      static_cast<unsigned long long>(last.source_faults),
      static_cast<unsigned long long>(last.recorder_faults),
      static_cast<unsigned long long>(last.accepted), static_cast<unsigned long long>(last.refused),
      last.output.c_str());
  std::printf("  recorder: %s\n", last.recorder.c_str());
  {
    const std::lock_guard lock(mutex);
    std::printf("state changes on health (after start-up):\n");
    for (size_t i = 1; i < hs.size(); ++i) {
      if (hs[i].state == hs[i - 1].state || hs[i].t < warm) continue;
      std::printf("  %7.1f s  %s  %s\n", hs[i].t,
                  hs[i].state == 1   ? "ok      "
                  : hs[i].state == 2 ? "degraded"
                                     : "other   ",
                  hs[i].state == 1 ? "" : hs[i].last_error.substr(0, 140).c_str());
    }
  }
  // The daemon's life.
  double max_gap = 0;
  size_t n_pings = 0;
  {
    const std::lock_guard lock(mutex);
    n_pings = pings.size();
    for (size_t i = 1; i < pings.size(); ++i) {
      if (pings[i - 1] >= warm) max_gap = std::max(max_gap, pings[i] - pings[i - 1]);
    }
  }
  bool said_fault = false;
  for (const HealthSample& s : hs) said_fault = said_fault || (s.t > warm && s.state == 3);
  std::printf("\nthe daemon:\n");
  check(
      was_alive && rc == 0,
      fmt::format("alive for the {:.0f} s and stopped cleanly on SIGTERM (exit {})", total_s, rc));
  check(ready && n_pings > 0 && max_gap < 3.0,
        fmt::format("watchdog fed all along: {} WATCHDOG=1, longest gap {:.2f} s (WatchdogSec "
                    "3 s): no stage stalled, nothing restarted",
                    n_pings, max_gap));
  check(!said_fault, "health never said fault");
  const double growth =
      rss_start > 0 ? static_cast<double>(rss_end - rss_start) / static_cast<double>(rss_start)
                    : 1.0;
  check(rss_start > 0 && growth < 0.10,
        fmt::format("RSS {} MB at {:.0f} s, {} MB at the end ({:+.1f} %)", rss_start / 1024,
                    0.1 * window_s, rss_end / 1024, 100 * growth));
  std::printf(
      "\nexposure -> features sample received by another process (DDS, loopback), per "
      "window:\n%6s %8s %8s %8s %9s %8s %6s %9s\n",
      "window", "samples", "p50 us", "p99 us", "p99.9 us", "max us", "lost", "RSS MB");
  for (size_t i = 0; i < win.size(); ++i) {
    const Window& wd = win[i];
    const uint64_t expected = wd.received > 0 ? wd.last - wd.first + 1 : 0;
    std::printf("%6zu %8zu %8.0f %8.0f %9.0f %8.0f %6llu %9ld\n", i + 1, wd.latency_us.size(),
                pct(wd.latency_us, 0.5), pct(wd.latency_us, 0.99), pct(wd.latency_us, 0.999),
                pct(wd.latency_us, 1.0), static_cast<unsigned long long>(expected - wd.received),
                wd.rss_kb / 1024);
  }
  std::printf("(lost: frame numbers not received, the outages' and missing triggers' included)\n");
  std::printf("stage p99 at the end: capture %u us, track %u us, publish %u us\n", last.capture_p99,
              last.track_p99, last.publish_p99);
  std::printf(
      "\nsummary: %d windows, %d/%d subscriber restarts, %d/%d floods (%llu commands), "
      "%d/%d disk faults recovered, %d outages recovered; %s\n",
      windows, subscribers_ok, windows, floods_ok, windows,
      static_cast<unsigned long long>(sent_total), disk_fault ? disks_ok : 0,
      disk_fault ? windows : 0, outages_recovered, failures == 0 ? "PASS" : "FAIL");
  std::printf("journal: %s\n", (dir / "journal.txt").c_str());
  if (disk_fault) ::umount2(disk.c_str(), MNT_DETACH);
  if (failures == 0) fs::remove_all(dir);
  return failures == 0 ? 0 : 1;
} catch (const std::exception& e) {
  std::fprintf(stderr, "soak: %s\n", e.what());
  return 1;
}
