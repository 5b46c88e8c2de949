// pulsetrack listen: subscribes to a rig's deformation and health over DDS and shows them in
// the terminal, one line per sample (or per --every), until Ctrl-C, --count or --seconds.

#include <fmt/format.h>

#include <chrono>
#include <memory>
#include <optional>
#include <string_view>
#include <thread>

#include "pulsetrack/dds/dds.hpp"
#include "pulsetrack/tools/commands.hpp"

namespace pulsetrack::tools {

namespace {

struct ListenArgs {
  uint32_t domain = 0;
  std::string ns;
  std::string enclave;  // DDS Security: an SROS2 enclave folder; empty: unsecured
  std::string rig;
  double seconds = 0.0;
  int count = 0;
  int every = 1;
};

const char* stateName(uint8_t s) {
  static const char* names[] = {"starting", "ok", "degraded", "fault"};
  return s < 4 ? names[s] : "unknown";
}

int runListen(const ListenArgs& a) {
  std::optional<dds::SecurityFiles> security;
  if (!a.enclave.empty()) security = dds::SecurityFiles::inEnclave(a.enclave);
  auto p = dds::Participant::create(a.domain, security ? &*security : nullptr);
  if (!p) return fmt::print(stderr, "listen: {}\n", p.error().message), 1;
  using dds::notAllowedBySecurity;
  auto topics = dds::Topics::forNamespace(a.ns);
  if (!topics) return fmt::print(stderr, "listen: {}\n", topics.error().message), 2;
  auto def =
      dds::Reader::create(*p, topics->deformation.c_str(),
                          &pulsetrack_msgs_msg_dds__Deformation__desc, dds::Profile::kSensorData);
  auto health =
      dds::Reader::create(*p, topics->health.c_str(), &pulsetrack_msgs_msg_dds__Health__desc,
                          dds::Profile::kTransientLocal);
  // A role that may read health only (DDS Security's `monitor`: a health display) is shown
  // health, and told what it may not read; any other failure is an error.
  const bool health_only = !def && notAllowedBySecurity(def.error()) && health;
  if (!def && !health_only) return fmt::print(stderr, "listen: {}\n", def.error().message), 1;
  if (!health) {
    if (notAllowedBySecurity(health.error()))
      fmt::print(stderr, "listen: {}\n", dds::notPermitted(*p, topics->health, false));
    return fmt::print(stderr, "listen: {}\n", health.error().message), 1;
  }
  catchStopSignals();
  if (health_only) {
    fmt::print(stderr,
               "listen: {}: showing health only (the deformation needs an enclave of the "
               "subscriber or controller role); --count counts health lines\n",
               dds::notPermitted(*p, topics->deformation, false));
  }
  fmt::print(stderr, "listening on DDS domain {} ({}); Ctrl-C to stop\n", a.domain,
             health_only ? topics->health : topics->deformation + " and " + topics->health);
  pulsetrack_msgs_msg_dds__Deformation_ d{};
  pulsetrack_msgs_msg_dds__Health_ h{};
  const auto t0 = std::chrono::steady_clock::now();
  int shown = 0, seen = 0;
  bool quiet_said = false;
  auto last = t0;
  auto last_health = t0;
  int last_state = -1;
  while (!stopRequested()) {
    if (a.seconds > 0 &&
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() >= a.seconds)
      break;
    while (health->takeOne(&h, std::chrono::milliseconds(0))) {
      if (!a.rig.empty() && a.rig != h.rig_id) continue;
      // Health on a change of state, else every 5 s.
      const auto now = std::chrono::steady_clock::now();
      if (h.state == last_state && now - last_health < std::chrono::seconds(5)) continue;
      last_state = h.state;
      last_health = now;
      fmt::print(
          "health  {} {:9} {:.1f} fps, {} frames, {} drops, {} deadline misses, "
          "{} missing triggers, {} unpaired, {} source outages, {} commands ({} refused); {}, "
          "trigger {}{}\n",
          h.rig_id, stateName(h.state), h.fps, h.frames, h.drops, h.deadline_misses,
          h.missing_triggers, h.unpaired, h.source_faults, h.commands_accepted + h.commands_refused,
          h.commands_refused, h.source, h.trigger_state,
          h.last_error[0] != 0 ? fmt::format(" ({})", h.last_error) : "");
      if (h.recorder_state != nullptr && std::string_view(h.recorder_state) != "off")
        fmt::print("        recorder {}\n", h.recorder_state);
      if (h.tracking_state != nullptr) fmt::print("        {}\n", h.tracking_state);
      if (h.clock_state != nullptr) fmt::print("        stamps {}\n", h.clock_state);
      if (h.security_state != nullptr) fmt::print("        DDS {}\n", h.security_state);
      if (h.output_state != nullptr) fmt::print("        {}\n", h.output_state);
      for (uint32_t i = 0; i < h.stages._length; ++i) {
        const auto& s = h.stages._buffer[i];
        fmt::print("        {:8} p50 {} us, p99 {} us, max {} us\n", s.stage, s.p50_us, s.p99_us,
                   s.max_us);
      }
      std::fflush(stdout);
      if (health_only && a.count > 0 && ++shown >= a.count) break;
    }
    if (health_only) {
      if (a.count > 0 && shown >= a.count) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      continue;
    }
    if (!def->takeOne(&d, std::chrono::milliseconds(200))) {
      if (!quiet_said && std::chrono::steady_clock::now() - last > std::chrono::seconds(3)) {
        fmt::print(stderr,
                   "listen: no deformation samples for 3 s (is pulsetrackd running on "
                   "domain {}?)\n",
                   a.domain);
        quiet_said = true;
      }
      continue;
    }
    last = std::chrono::steady_clock::now();
    quiet_said = false;
    if (!a.rig.empty() && a.rig != d.rig_id) continue;
    if (seen++ % a.every != 0) continue;
    const double t = d.header.stamp.sec + d.header.stamp.nanosec * 1e-9;
    fmt::print(
        "deform  {} frame {:6} t {:10.3f} s  displacement {:+8.4f} {:+8.4f} {:+8.4f} mm  "
        "|v| {:6.3f} mm/s ({:.0f} ms ago)  +-{:.4f} mm  {}/{} ok{}\n",
        d.rig_id, d.frame, t, d.displacement.x * 1e3, d.displacement.y * 1e3,
        d.displacement.z * 1e3,
        1e3 * std::sqrt(d.velocity.x * d.velocity.x + d.velocity.y * d.velocity.y +
                        d.velocity.z * d.velocity.z),
        d.velocity_delay * 1e3, d.displacement_sigma * 1e3, d.features_ok, d.features_total,
        d.continuous ? "" : "  (restarted)");
    std::fflush(stdout);
    if (a.count > 0 && ++shown >= a.count) break;
  }
  dds_sample_free(&d, &pulsetrack_msgs_msg_dds__Deformation__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
  return shown > 0 || a.count == 0 ? 0 : 3;
}

}  // namespace

CommandRunner addListenCommand(CLI::App& app) {
  auto a = std::make_shared<ListenArgs>();
  CLI::App* cmd = app.add_subcommand(
      "listen", "Show a running pulsetrackd's deformation and health (DDS) in the terminal.");
  cmd->add_option("--domain", a->domain, "DDS domain id (the daemon's dds.domain_id)")
      ->check(CLI::Range(0, 232))
      ->capture_default_str();
  cmd->add_option("--namespace", a->ns,
                  "The daemon's topic namespace ([dds] namespace; default none)");
  cmd->add_option("--enclave", a->enclave,
                  "DDS Security: this participant's SROS2 enclave folder (KEYSTORE/enclaves/NAME, "
                  "scripts/security); needed when the daemon's domain is secured");
  cmd->add_option("--rig", a->rig, "Only this rig id (default: the namespace's)");
  cmd->add_option("--seconds", a->seconds, "Stop after this long")->check(CLI::NonNegativeNumber);
  cmd->add_option(
         "--count", a->count,
         "Stop after this many deformation lines (health lines where the enclave may read health "
         "only: DDS Security's monitor role); exit 3 if none")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--every", a->every, "Show every Nth deformation sample")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  return [a] { return runListen(*a); };
}

}  // namespace pulsetrack::tools
