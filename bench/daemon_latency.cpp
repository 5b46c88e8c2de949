// End-to-end latency of pulsetrackd: a frame pair handed over by the source -> the features
// sample received by a subscriber process over DDS (loopback). The daemon replays a recording
// from memory at 30, 60 and 120 Hz, restamping each pair on hand-over as a live camera would
// (the daemon maps that time onto the system clock for the stamp, as for a live camera); this
// process subscribes and takes CLOCK_REALTIME now - stamp per sample. Prints p50, p99, p99.9, max
// and the frames lost (gaps in the frame numbers received), with the daemon's own drop and deadline
// counts from its health. With
// --security, the same with DDS Security (scripts/security's keystore: authentication, signed
// RTPS, encrypted topics), to see what security costs.
// --preview, the cameras' preview (JPEG at 5 Hz, read by a subscriber as the console reads it) on
// or off, to see that it leaves the tracking's latency as it was.
// --off-path, the stages off the features' path (the dense field, the stereo refresh) on or off,
// to see what they cost the path on this machine's cores.
// --pin, the track stage alone on the last CPU, the daemon's other stages on the first (the
// layout a board with cores to spare would give the path, here on 2).
// --receiver-fifo P, this process's threads (Cyclone's receive thread among them) at SCHED_FIFO P,
// as a robot's real-time subscriber would run, so that what is measured is the daemon and the
// transport, not this process waiting for a core behind the daemon's normal-priority stages.
//   daemon_latency [--seconds S] [--rates 30,60,120] [--features N] [--security off|on|both]
//                  [--preview off|on|both] [--off-path on|off|both] [--receiver-fifo P] [--pin]
// The run is 5 minutes per rate: --seconds 300.

#include <sched.h>
#include <spawn.h>
#include <sys/wait.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <utility>
#include <vector>

#include "bench_process.hpp"
#include "pulsetrack/dds/dds.hpp"
#include "pulsetrack/rt/heartbeat.hpp"

namespace {

using pulsetrack::bench::spawn;
using pulsetrack::bench::waitExit;

int64_t realtimeNs() {
  timespec ts{};
  clock_gettime(CLOCK_REALTIME, &ts);
  return int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

// Every thread of this process at SCHED_FIFO `priority` (those started later inherit it).
void setFifo(int priority) {
  sched_param p{};
  p.sched_priority = priority;
  for (const auto& t : std::filesystem::directory_iterator("/proc/self/task")) {
    const pid_t tid = std::stoi(t.path().filename().string());
    if (sched_setscheduler(tid, SCHED_FIFO, &p) != 0) {
      std::fprintf(stderr, "daemon_latency: SCHED_FIFO %d for thread %d: %s\n", priority, tid,
                   std::strerror(errno));
    }
  }
}

}  // namespace

int main(int argc, char** argv) try {
  double seconds = 20;
  std::vector<double> rates = {30, 60, 120};
  int features = 100;
  CLI::App app{
      "End-to-end latency of pulsetrackd: frame handed over -> features sample received by "
      "another process over DDS (loopback), replaying a recording from memory at each rate.",
      "daemon_latency"};
  app.add_option("--seconds", seconds, "Seconds per rate (the issue's run: 300)")
      ->check(CLI::PositiveNumber);
  app.add_option("--rates", rates, "Trigger rates in Hz, comma separated")
      ->delimiter(',')
      ->check(CLI::Range(1.0, 1000.0));
  app.add_option("--features", features, "Features tracked")->check(CLI::Range(1, 1000));
  std::string security = "off";
  app.add_option("--security", security,
                 "DDS Security: off, on (scripts/security's keystore) or both, one after the other")
      ->check(CLI::IsMember({"off", "on", "both"}))
      ->capture_default_str();
  std::string preview = "on";
  app.add_option("--preview", preview,
                 "The cameras' preview (5 Hz JPEG, a subscriber reading it): off, on or both")
      ->check(CLI::IsMember({"off", "on", "both"}))
      ->capture_default_str();
  std::string off_path = "on";
  app.add_option("--off-path", off_path,
                 "The stages off the features' path (dense field, stereo refresh): on, off or both")
      ->check(CLI::IsMember({"off", "on", "both"}))
      ->capture_default_str();
  int receiver_fifo = 0;
  app.add_option(
         "--receiver-fifo", receiver_fifo,
         "This process's threads (the subscriber's) at SCHED_FIFO with this priority (1-99; "
         "0: normal, as a desktop subscriber)")
      ->check(CLI::Range(0, 99));
  bool pin = false;
  app.add_flag("--pin", pin,
               "The track stage on the last CPU alone, every other stage of the daemon on the "
               "first ([realtime] cpu; the field, refresh and preview as off_path)");
  CLI11_PARSE(app, argc, argv);
  const int last_cpu = static_cast<int>(std::thread::hardware_concurrency()) - 1;
  if (pin && last_cpu < 1) {
    std::fprintf(stderr, "daemon_latency: --pin needs at least 2 CPUs\n");
    return 2;
  }
  setenv("CYCLONEDDS_URI", pulsetrack::dds::kLoopbackUri, 1);
  const auto dir =
      std::filesystem::temp_directory_path() / ("pulsetrack-latency-" + std::to_string(getpid()));
  std::filesystem::create_directories(dir);
  const std::string rec = (dir / "rec").string();
  std::fprintf(stderr, "daemon_latency: recording 60 frames of the cortex scene...\n");
  if (waitExit(spawn({PULSETRACK_CLI, "simulate", "--scene",
                      std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-60s.toml",
                      "--out", rec, "--frames", "60", "--supersample", "1", "--quiet"})) != 0) {
    std::fprintf(stderr, "daemon_latency: pulsetrack simulate failed\n");
    return 1;
  }
  const std::string keystore = (dir / "keystore").string();
  if (security != "off") {
    const std::string script = std::string(PULSETRACK_SOURCE_DIR) + "/scripts/security";
    for (const auto& args : std::vector<std::vector<std::string>>{
             {script, "init", keystore},
             {script, "add-participant", keystore, "/pulsetrack/daemon", "--role", "daemon"},
             {script, "add-participant", keystore, "/bench/subscriber", "--role", "subscriber"}}) {
      if (waitExit(spawn(args)) != 0) {
        std::fprintf(stderr, "daemon_latency: scripts/security %s failed\n", args[1].c_str());
        return 1;
      }
    }
  }
  std::printf("frame handed over -> features sample received by another process (DDS, loopback)\n");
  std::printf(
      "%-10s %-8s %-8s %6s %8s %9s %9s %9s %9s %7s %8s %9s %s\n", "DDS", "preview", "off-path",
      "rate", "samples", "p50 us", "p99 us", "p99.9 us", "max us", "lost", "drops", "deadline",
      "track stage (handed over -> tracked) p50/p99 us, preview stage p50/p99 us, capture's copy "
      "p50/p99 us, images received");
  int domain = 90;
  const auto wanted = [](const std::string& choice, bool on) {
    return choice == "both" || (choice == "on") == on;
  };
  std::vector<std::tuple<bool, bool, bool, double>> runs;
  for (const bool secured : {false, true}) {
    for (const bool with_preview : {false, true}) {
      for (const bool with_off_path : {true, false}) {
        if (!wanted(security, secured) || !wanted(preview, with_preview) ||
            !wanted(off_path, with_off_path))
          continue;
        for (const double rate : rates)
          runs.emplace_back(secured, with_preview, with_off_path, rate);
      }
    }
  }
  for (const auto& [secured, with_preview, with_off_path, rate] : runs) {
    const auto cfg = dir / "pulsetrackd.toml";
    std::ofstream(cfg) << "rig_id = \"bench\"\n[dds]\ndomain_id = " << domain
                       << "\n[source]\nkind = \"replay\"\nrecording = \"" << rec
                       << "\"\npace = \"rate\"\nfps = " << rate
                       << "\nloop = true\npreload = true\n[tracker]\nmax_features = " << features
                       << (with_off_path ? "" : "\nstereo_refresh = 0")
                       << "\n[health]\nperiod_ms = 500\n[preview]\nenabled = "
                       << (with_preview ? "true" : "false") << "\n"
                       << (with_off_path ? "" : "[field]\nenabled = false\n");
    if (pin) {
      std::ofstream(cfg, std::ios::app)
          << "[realtime]\ncapture = { priority = 80, cpu = 0 }\ntrack = { priority = 70, cpu = "
          << last_cpu
          << " }\npublish = { priority = 60, cpu = 0 }\noff_path = { priority = 0, cpu = 0 }\n";
    }
    if (secured) {
      std::ofstream(cfg, std::ios::app)
          << "[security]\nenclave = \"" << keystore << "/enclaves/pulsetrack/daemon\"\n";
    }
    const pid_t d = spawn({PULSETRACKD, "-c", cfg.string(), "--run-for",
                           std::to_string(static_cast<int>(seconds + 4))});
    const auto files =
        pulsetrack::dds::SecurityFiles::inEnclave(keystore + "/enclaves/bench/subscriber");
    auto p = pulsetrack::dds::Participant::create(static_cast<uint32_t>(domain),
                                                  secured ? &files : nullptr);
    if (!p) {
      std::fprintf(stderr, "daemon_latency: %s\n", p.error().message.c_str());
      return 1;
    }
    auto reader = pulsetrack::dds::Reader::create(*p, pulsetrack::dds::kFeaturesTopic,
                                                  &pulsetrack_msgs_msg_dds__Features__desc,
                                                  pulsetrack::dds::Profile::kSensorData);
    auto health = pulsetrack::dds::Reader::create(*p, pulsetrack::dds::kHealthTopic,
                                                  &pulsetrack_msgs_msg_dds__Health__desc,
                                                  pulsetrack::dds::Profile::kTransientLocal);
    if (!p || !reader || !health) return 1;
    // The preview read as the console reads it (both cameras), so that its cost is all there.
    std::vector<pulsetrack::dds::Reader> images;
    if (with_preview) {
      for (const char* side : {"left", "right"}) {
        auto r = pulsetrack::dds::Reader::create(
            *p, (std::string("rt/pulsetrack/") + side + "/image/compressed").c_str(),
            &sensor_msgs_msg_dds__CompressedImage__desc, pulsetrack::dds::Profile::kSensorData);
        if (!r) return 1;
        images.push_back(std::move(*r));
      }
    }
    if (receiver_fifo > 0) setFifo(receiver_fifo);  // Cyclone's threads exist by now
    // The dense field (its own stage, off the features' path): pair -> field received, taken
    // by a thread of its own as soon as it arrives.
    auto field = pulsetrack::dds::Reader::create(*p, "rt/pulsetrack/field",
                                                 &sensor_msgs_msg_dds__PointCloud2__desc,
                                                 pulsetrack::dds::Profile::kSensorData);
    if (!field) return 1;
    std::vector<double> field_us;
    std::atomic<bool> measuring{true};
    // Skip the first 2 s: detection, DDS discovery, page faults.
    const int64_t t_start = pulsetrack::rt::monotonicNs() + 2'000'000'000;
    // The machine's own scheduling, meanwhile (cyclictest's measure): a thread at SCHED_FIFO 90
    // that sleeps to an absolute time every millisecond and records how late it woke. Each pair
    // crosses four such wake-ups (the source's, the track, publish and receive threads').
    std::vector<double> wake_us;
    wake_us.reserve(static_cast<size_t>(seconds * 1000.0) + 1000);
    std::thread wake_thread([&] {
      sched_param sp{};
      sp.sched_priority = 90;
      const bool fifo = sched_setscheduler(0, SCHED_FIFO, &sp) == 0;
      timespec next{};
      clock_gettime(CLOCK_MONOTONIC, &next);
      while (measuring.load()) {
        next.tv_nsec += 1'000'000;
        if (next.tv_nsec >= 1'000'000'000) {
          next.tv_nsec -= 1'000'000'000;
          ++next.tv_sec;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, nullptr);
        const int64_t now = pulsetrack::rt::monotonicNs();
        if (fifo && now >= t_start && wake_us.size() < wake_us.capacity())
          wake_us.push_back(
              static_cast<double>(now - (int64_t{next.tv_sec} * 1'000'000'000 + next.tv_nsec)) *
              1e-3);
      }
    });
    std::thread field_thread([&] {
      sensor_msgs_msg_dds__PointCloud2_ cloud{};
      while (measuring.load()) {
        if (!field->takeOne(&cloud, std::chrono::milliseconds(100))) continue;
        if (pulsetrack::rt::monotonicNs() < t_start) continue;
        field_us.push_back(
            static_cast<double>(realtimeNs() - (int64_t{cloud.header.stamp.sec} * 1'000'000'000 +
                                                cloud.header.stamp.nanosec)) *
            1e-3);
      }
      dds_sample_free(&cloud, &sensor_msgs_msg_dds__PointCloud2__desc, DDS_FREE_CONTENTS);
    });
    sensor_msgs_msg_dds__CompressedImage_ im{};
    uint64_t images_received = 0;
    pulsetrack_msgs_msg_dds__Features_ f{};
    pulsetrack_msgs_msg_dds__Health_ h{};
    std::vector<double> us;
    uint64_t first = 0, last = 0, received = 0;
    const int64_t t_end = t_start + static_cast<int64_t>(seconds * 1e9);
    while (pulsetrack::rt::monotonicNs() < t_end) {
      for (const auto& ir : images)
        while (ir.takeOne(&im, std::chrono::milliseconds(0))) ++images_received;
      if (!reader->takeOne(&f, std::chrono::milliseconds(100))) continue;
      // The stamp is on the system clock (the daemon maps the hand-over time onto it).
      if (pulsetrack::rt::monotonicNs() < t_start) continue;
      const int64_t now = realtimeNs();
      const int64_t stamp = int64_t{f.header.stamp.sec} * 1'000'000'000 + f.header.stamp.nanosec;
      us.push_back(static_cast<double>(now - stamp) * 1e-3);
      if (received == 0) first = f.frame;
      last = f.frame;
      ++received;
    }
    measuring.store(false);
    field_thread.join();
    wake_thread.join();
    std::sort(wake_us.begin(), wake_us.end());
    while (health->takeOne(&h, std::chrono::milliseconds(0))) {
    }
    std::sort(us.begin(), us.end());
    std::sort(field_us.begin(), field_us.end());
    const auto pctOf = [](const std::vector<double>& v, double q) {
      return v.empty() ? 0.0
                       : v[std::min(v.size() - 1,
                                    static_cast<size_t>(q * static_cast<double>(v.size())))];
    };
    const auto pct = [&](double q) { return pctOf(us, q); };
    const uint64_t expected = received > 0 ? last - first + 1 : 0;
    std::string stages;
    for (uint32_t i = 0; i < h.stages._length; ++i) {
      const std::string name = h.stages._buffer[i].stage;
      if (name == "track" || name.rfind("preview", 0) == 0) {
        stages += std::to_string(h.stages._buffer[i].p50_us) + "/" +
                  std::to_string(h.stages._buffer[i].p99_us) + "  ";
      }
    }
    if (with_preview) stages += std::to_string(images_received);
    std::printf("%-10s %-8s %-8s %4.0f Hz %8zu %9.0f %9.0f %9.0f %9.0f %7llu %8llu %9llu %s\n",
                secured ? "secured" : "unsecured", with_preview ? "on" : "off",
                with_off_path ? "on" : "off", rate, us.size(), pct(0.5), pct(0.99), pct(0.999),
                us.empty() ? 0.0 : us.back(), static_cast<unsigned long long>(expected - received),
                static_cast<unsigned long long>(h.drops),
                static_cast<unsigned long long>(h.deadline_misses), stages.c_str());
    // Where the time goes: each stage as the daemon's health measures it (capture: the source's
    // hand-over; track: handed over -> tracked; publish: tracked -> features and deformation
    // written; field: handed over -> field written, its own stage), then the field as received.
    std::string breakdown;
    double path_p50 = 0.0;  // the features' path in the daemon: capture + track + publish
    for (uint32_t i = 0; i < h.stages._length; ++i) {
      const auto& st = h.stages._buffer[i];
      const std::string name = st.stage;
      if (name == "capture" || name == "track" || name == "publish") path_p50 += st.p50_us;
      breakdown += std::string(breakdown.empty() ? "" : ", ") + st.stage + " " +
                   std::to_string(st.p50_us) + "/" + std::to_string(st.p99_us) + "/" +
                   std::to_string(st.max_us);
    }
    std::printf("           stages p50/p99/max us: %s\n", breakdown.c_str());
    // What the daemon's stages leave of the median: the features' way to this process (DDS over
    // loopback, the receive thread's wake-up) and the stages' hand-overs.
    std::printf(
        "           path p50: capture + track + publish %.0f us, received - that %.0f us (DDS "
        "to this process and the wake-ups)\n",
        path_p50, pct(0.5) - path_p50);
    std::printf(
        "           this machine's wake-up lateness (SCHED_FIFO thread, 1 ms sleeps, %zu): p50 "
        "%.0f "
        "us, p99 %.0f us, p99.9 %.0f us, max %.0f us\n",
        wake_us.size(), pctOf(wake_us, 0.5), pctOf(wake_us, 0.99), pctOf(wake_us, 0.999),
        wake_us.empty() ? 0.0 : wake_us.back());
    std::printf(
        "           field received (pair handed over -> cloud received): %zu samples, p50 %.0f "
        "us, p99 %.0f us, max %.0f us; %s\n",
        field_us.size(), pctOf(field_us, 0.5), pctOf(field_us, 0.99),
        field_us.empty() ? 0.0 : field_us.back(), h.output_state ? h.output_state : "");
    std::fflush(stdout);
    waitExit(d);
    dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
    dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
    dds_sample_free(&im, &sensor_msgs_msg_dds__CompressedImage__desc, DDS_FREE_CONTENTS);
    ++domain;
  }
  std::filesystem::remove_all(dir);
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "daemon_latency: %s\n", e.what());
  return 1;
}
