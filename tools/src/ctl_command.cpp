// pulsetrack ctl: the operator's capture cycle for a running pulsetrackd, over the DDS command
// topic: start, stop, redetect, set-roi. Waits for the daemon's reader, sends once (reliable),
// waits for the daemon's acknowledgement, and reports the daemon's refusal if its health says so
// within 2 s (exit 1).

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <memory>
#include <optional>
#include <string_view>
#include <thread>

#include "pulsetrack/dds/dds.hpp"
#include "pulsetrack/tools/commands.hpp"

namespace pulsetrack::tools {

namespace {

struct CtlArgs {
  uint32_t domain = 0;
  std::string ns;
  std::string enclave;  // DDS Security: an SROS2 enclave folder; empty: unsecured
  std::string rig;
  std::string command;
  std::vector<int> roi_left, roi_right;
  double depth_mm = 20.0;
  uint32_t request_id = 0;
};

int runCtl(const CtlArgs& a) {
  std::optional<dds::SecurityFiles> security;
  if (!a.enclave.empty()) security = dds::SecurityFiles::inEnclave(a.enclave);
  auto p = dds::Participant::create(a.domain, security ? &*security : nullptr);
  if (!p) return fmt::print(stderr, "ctl: {}\n", p.error().message), 1;
  auto topics = dds::Topics::forNamespace(a.ns);
  if (!topics) return fmt::print(stderr, "ctl: {}\n", topics.error().message), 2;
  auto w = dds::Writer::create(*p, topics->command.c_str(), &pulsetrack_msgs_msg_dds__Command__desc,
                               dds::Profile::kCommand);
  if (!w && dds::notAllowedBySecurity(w.error())) {
    fmt::print(stderr,
               "ctl: {}: commands need an enclave of the controller role (scripts/security "
               "add-participant KEYSTORE NAME --role controller; docs/security.md)\n  ({})\n",
               dds::notPermitted(*p, topics->command, true), w.error().message);
    return 1;
  }
  if (!w) return fmt::print(stderr, "ctl: {}\n", w.error().message), 1;
  auto health =
      dds::Reader::create(*p, topics->health.c_str(), &pulsetrack_msgs_msg_dds__Health__desc,
                          dds::Profile::kTransientLocal);
  if (!health) return fmt::print(stderr, "ctl: {}\n", health.error().message), 1;
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (w->matchedReaders() == 0 && std::chrono::steady_clock::now() < until)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  if (w->matchedReaders() == 0) {
    fmt::print(stderr, "ctl: no pulsetrackd is listening on {} on DDS domain {} (5 s)\n",
               topics->command, a.domain);
    return 1;
  }
  pulsetrack_msgs_msg_dds__Command_ c{};
  std::string rig = a.rig, cmd = a.command;
  std::replace(cmd.begin(), cmd.end(), '-', '_');  // set-roi, record-start, record-stop
  c.rig_id = rig.data();
  c.command = cmd.data();
  c.request_id = a.request_id != 0
                     ? a.request_id
                     : static_cast<uint32_t>(
                           std::chrono::system_clock::now().time_since_epoch().count() & 0xffffff);
  if (a.command == "set-roi") {
    // Without --roi-right the daemon finds it in the next pair (the left ROI's epipolar search);
    // without either, the left one too (the best well-textured region): all zero on the wire.
    const bool left_ok = a.roi_left.empty() || a.roi_left.size() == 4;
    const bool right_ok = a.roi_right.empty() || (a.roi_right.size() == 4 && !a.roi_left.empty());
    if (!left_ok || !right_ok) {
      fmt::print(stderr,
                 "ctl: set-roi takes --roi-left x,y,w,h and --roi-right x,y,w,h; either "
                 "may be left out for the daemon to find it (the right one only with a "
                 "left one)\n");
      return 2;
    }
    for (int i = 0; i < 4; ++i) {
      const auto k = static_cast<size_t>(i);
      c.roi_left[i] = a.roi_left.empty() ? 0 : a.roi_left[k];
      c.roi_right[i] = a.roi_right.empty() ? 0 : a.roi_right[k];
    }
    c.depth_tolerance_m = a.depth_mm * 1e-3;
  }
  if (auto ok = w->write(&c); !ok) return fmt::print(stderr, "ctl: {}\n", ok.error().message), 1;
  // Reliable delivery to the daemon's reader.
  if (!w->waitForAcks(std::chrono::seconds(5))) {
    fmt::print(stderr, "ctl: '{}' sent on {} but not acknowledged within 5 s\n", cmd,
               topics->command);
    return 1;
  }
  // A refusal shows on health (last_error "command <request_id> ... refused: why").
  const std::string tag = fmt::format("command {} ", c.request_id);
  pulsetrack_msgs_msg_dds__Health_ h{};
  std::string refusal;
  const auto listen_until = std::chrono::steady_clock::now() + std::chrono::seconds(2);
  while (refusal.empty() && std::chrono::steady_clock::now() < listen_until) {
    if (health->takeOne(&h, std::chrono::milliseconds(100)) && h.last_error != nullptr &&
        std::string_view(h.last_error).starts_with(tag))
      refusal = h.last_error;
  }
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
  if (!refusal.empty()) {
    fmt::print(stderr, "ctl: {}\n", refusal);
    return 1;
  }
  fmt::print("ctl: sent '{}' (request {}) on {}, DDS domain {}, acknowledged\n", cmd, c.request_id,
             topics->command, a.domain);
  return 0;
}

}  // namespace

CommandRunner addCtlCommand(CLI::App& app) {
  auto a = std::make_shared<CtlArgs>();
  CLI::App* cmd = app.add_subcommand(
      "ctl",
      "Drive a running pulsetrackd's capture cycle: start, stop, redetect, set-roi, and its "
      "recorder: record-start, record-stop.");
  cmd->add_option("command", a->command,
                  "start | stop | redetect | set-roi | record-start | record-stop")
      ->required()
      ->check(
          CLI::IsMember({"start", "stop", "redetect", "set-roi", "record-start", "record-stop"}));
  cmd->add_option("--domain", a->domain, "DDS domain id")
      ->check(CLI::Range(0, 232))
      ->capture_default_str();
  cmd->add_option("--namespace", a->ns, "The daemon's topic namespace ([dds] namespace)");
  cmd->add_option("--enclave", a->enclave,
                  "DDS Security: this participant's SROS2 enclave folder (KEYSTORE/enclaves/NAME, "
                  "scripts/security); needed when the daemon's domain is secured");
  cmd->add_option("--rig", a->rig,
                  "The daemon's rig_id (a check: default, whichever rig the namespace has)");
  cmd->add_option("--roi-left", a->roi_left,
                  "set-roi: x,y,w,h (px); default: the daemon finds the best well-textured "
                  "region in the next pair")
      ->delimiter(',');
  cmd->add_option("--roi-right", a->roi_right,
                  "set-roi: x,y,w,h (px); default: the daemon finds it in the next pair by "
                  "searching the left ROI's epipolar lines from 20 mm to 1 m")
      ->delimiter(',');
  cmd->add_option("--depth", a->depth_mm, "set-roi with --roi-right: depth tolerance (mm)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--request-id", a->request_id, "Echoed in the health's last_error on refusal");
  return [a] { return runCtl(*a); };
}

}  // namespace pulsetrack::tools
