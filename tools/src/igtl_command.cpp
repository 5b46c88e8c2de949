// pulsetrack igtl: the OpenIGTLink bridge (igtl/bridge.hpp), for 3D Slicer and PLUS.

#include <fmt/format.h>

#include <memory>

#include "pulsetrack/analysis/report.hpp"
#include "pulsetrack/igtl/bridge.hpp"
#include "pulsetrack/tools/commands.hpp"

namespace pulsetrack::tools {

namespace {

struct IgtlArgs {
  igtl::BridgeOptions o;
  std::string enclave, registration;
};

int runIgtl(const IgtlArgs& a) {
  igtl::BridgeOptions o = a.o;
  if (!a.enclave.empty()) o.security = dds::SecurityFiles::inEnclave(a.enclave);
  if (!a.registration.empty()) {
    auto reg = analysis::readRegistration(a.registration);
    if (!reg) return commandError("igtl", reg.error().message);
    o.camera_to_tracker = *reg;
  }
  auto b = igtl::Bridge::create(o);
  if (!b) return commandError("igtl", b.error().message);
  fmt::print("igtl: serving OpenIGTLink on {}:{} (the {} frame{}), DDS domain {}{}\n", o.host,
             (*b)->port(), (*b)->frameName(),
             a.registration.empty() ? "" : ", registration " + a.registration, o.domain,
             o.ros_namespace.empty() ? "" : ", namespace " + o.ros_namespace);
  std::fflush(stdout);
  serveUntilSignal([&] { (*b)->run(); }, [&] { (*b)->stop(); });
  fmt::print("igtl: stopped\n");
  return 0;
}

}  // namespace

CommandRunner addIgtlCommand(CLI::App& app) {
  auto a = std::make_shared<IgtlArgs>();
  CLI::App* cmd = app.add_subcommand(
      "igtl",
      "Serve a rig's output to OpenIGTLink clients (3D Slicer's OpenIGTLinkIF, PLUS): "
      "TRANSFORM BrainShiftTo<Frame> and MeanDispTo<Frame>, POINT Features, POLYDATA "
      "DenseField, IMAGE LeftCamera, STATUS Health (docs/slicer.md). A process of its own, a "
      "DDS participant of its own; it accepts no command.");
  cmd->add_option("--host", a->o.host,
                  "IPv4 address to listen on (0.0.0.0: every interface; OpenIGTLink has no "
                  "authentication: a network of its own)")
      ->capture_default_str();
  cmd->add_option("--port", a->o.port, "TCP port (18944: Slicer's default; 0: any free one)")
      ->check(CLI::Range(0, 65535))
      ->capture_default_str();
  cmd->add_option("--domain", a->o.domain, "DDS domain id")
      ->check(CLI::Range(0, 232))
      ->capture_default_str();
  cmd->add_option("--namespace", a->o.ros_namespace, "The daemon's topic namespace ([dds])");
  cmd->add_option("--enclave", a->enclave,
                  "DDS Security: this bridge's SROS2 enclave (role subscriber: it only reads)");
  cmd->add_option("--registration", a->registration,
                  "O_T_C (registration.csv of `pulsetrack validate`: tx,ty,tz,qw,qx,qy,qz in mm): "
                  "everything in the tracker's frame, and TRANSFORM CameraToTracker");
  cmd->add_option("--image-rate", a->o.image_rate_hz,
                  "Hz: IMAGE LeftCamera at most this often, from the daemon's preview (0: never)")
      ->check(CLI::Range(0.0, 30.0))
      ->capture_default_str();
  cmd->add_option("--field-rate", a->o.field_rate_hz,
                  "Hz: POLYDATA DenseField at most this often (0: never)")
      ->check(CLI::Range(0.0, 60.0))
      ->capture_default_str();
  cmd->add_option("--max-clients", a->o.max_clients, "Clients at once")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  cmd->add_option("--queue", a->o.queue_messages,
                  "Messages queued per client; beyond, its oldest are dropped (counted)")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  cmd->add_option("--stall-timeout", a->o.stall_timeout_s,
                  "s: a client that takes no byte for this long is disconnected")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  return [a] { return runIgtl(*a); };
}

}  // namespace pulsetrack::tools
