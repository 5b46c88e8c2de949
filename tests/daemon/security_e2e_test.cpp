// DDS Security with real processes and real files (scripts/security, openssl, Cyclone DDS's
// plugins as Debian ships them): a secured pulsetrackd obeys a permitted controller and no one
// else - not a participant without a certificate, not one whose certificate comes from another
// CA, not one whose certificate is valid but whose permissions do not include the command topic
// - and keeps tracking through the attempts; a missing, expired, foreign or tampered file is an
// error naming it, and the daemon does not start (unsecured or otherwise).

#include <gtest/gtest.h>

#include <csignal>
#include <fstream>
#include <functional>
#include <sstream>

#include "daemon/daemon_process.hpp"
#include "pulsetrack/dds/security.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

const std::string kSecurityScript = std::string(PULSETRACK_SOURCE_DIR) + "/scripts/security";

std::string readAll(const std::filesystem::path& p) {
  std::ifstream in(p);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

void security(const std::string& args) {
  const test::CommandResult r = test::run(kSecurityScript + " " + args);
  ASSERT_EQ(r.exit_code, 0) << "scripts/security " << args << ": " << r.output;
}

// Keystore A (the appliance's) with a daemon, a controller, a subscriber and a monitor; keystore
// B (someone else's CA) with a controller of the same name.
class Keystores : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TempDir();
    const std::string a = (dir_->path() / "a").string(), b = (dir_->path() / "b").string();
    security("init " + a);
    security("add-participant " + a + " /pulsetrack/daemon --role daemon");
    security("add-participant " + a + " /or/console --role controller");
    security("add-participant " + a + " /robot/arm --role subscriber");
    security("add-participant " + a + " /or/display --role monitor");
    security("init " + b);
    security("add-participant " + b + " /or/console --role controller");
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  static std::filesystem::path enclave(const char* keystore, const char* name) {
    return dir_->path() / keystore / "enclaves" / name;
  }
  static test::TempDir* dir_;
};
test::TempDir* Keystores::dir_ = nullptr;

// Waits (bounded) for a health sample of the rig that satisfies `want`; the last one seen. The
// daemon's notifications are read meanwhile (a full notify socket would block its sd_notify).
std::string waitForHealth(Daemon& daemon, const dds::Reader& health, const std::string& rig,
                          const std::function<bool(const pulsetrack_msgs_msg_dds__Health_&)>& want,
                          std::chrono::seconds timeout, bool* found) {
  pulsetrack_msgs_msg_dds__Health_ h{};
  std::string last = "no health sample";
  *found = false;
  const auto until = std::chrono::steady_clock::now() + timeout;
  while (!*found && std::chrono::steady_clock::now() < until) {
    daemon.drain(0);
    if (!health.takeOne(&h, std::chrono::milliseconds(200)) || rig != h.rig_id) continue;
    last = std::string("tracking_state '") + h.tracking_state + "', security_state '" +
           h.security_state + "', frames " + std::to_string(h.frames);
    *found = want(h);
  }
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
  return last;
}

std::string ctl(uint32_t domain, const std::string& enclave_args, const std::string& command) {
  return test::cli() + " ctl --domain " + std::to_string(domain) + " --rig rig-sec " +
         enclave_args + " " + command;
}

TEST_F(Keystores, OnlyAPermittedControllerCommandsTheDaemon) {
  const uint32_t domain = 91;
  const test::TempDir dir;
  DaemonOptions opt;
  opt.rig = "rig-sec";
  opt.extra = "[security]\nenclave = \"" + enclave("a", "pulsetrack/daemon").string() + "\"\n";
  Daemon daemon(dir, domain, {}, "", {}, opt);

  // The OR display (role monitor: health only) reads the health of the secured daemon.
  const dds::SecurityFiles display = dds::SecurityFiles::inEnclave(enclave("a", "or/display"));
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto participant = dds::Participant::create(domain, &display);
  ASSERT_TRUE(participant) << participant.error().message;
  EXPECT_EQ(participant->securityState(), "secured as CN=/or/display");
  auto health =
      dds::Reader::create(*participant, "rt/pulsetrack/health",
                          &pulsetrack_msgs_msg_dds__Health__desc, dds::Profile::kTransientLocal);
  ASSERT_TRUE(health) << health.error().message;
  // The monitor may not read the features: its permissions do not grant them.
  auto features =
      dds::Reader::create(*participant, "rt/pulsetrack/features",
                          &pulsetrack_msgs_msg_dds__Features__desc, dds::Profile::kSensorData);
  ASSERT_FALSE(features);
  EXPECT_NE(features.error().message.find("rt/pulsetrack/features"), std::string::npos);

  uint64_t frames_before = 0;
  const auto tracking = [&](const pulsetrack_msgs_msg_dds__Health_& h) {
    frames_before = h.frames;
    return std::string(h.tracking_state).rfind("tracking ", 0) == 0 &&
           std::string(h.security_state) == "secured as CN=/pulsetrack/daemon";
  };
  bool found = false;
  std::string last =
      waitForHealth(daemon, *health, "rig-sec", tracking, std::chrono::seconds(90), &found);
  ASSERT_TRUE(found) << "the secured daemon never reported tracking: " << last;

  // 1. No certificate: an unsecured participant is not let into the domain.
  const test::CommandResult none = test::run(ctl(domain, "", "stop"));
  daemon.drain(0);
  EXPECT_EQ(none.exit_code, 1) << none.output;
  EXPECT_NE(none.output.find("no pulsetrackd is listening"), std::string::npos) << none.output;
  // 2. A controller whose certificate another CA signed: authentication fails.
  const test::CommandResult foreign =
      test::run(ctl(domain, "--enclave " + enclave("b", "or/console").string(), "stop"));
  EXPECT_EQ(foreign.exit_code, 1) << foreign.output;
  EXPECT_NE(foreign.output.find("no pulsetrackd is listening"), std::string::npos)
      << foreign.output;
  // 3. A valid certificate without permission for the command topic (the robot subscribes):
  // its writer is refused.
  const test::CommandResult robot =
      test::run(ctl(domain, "--enclave " + enclave("a", "robot/arm").string(), "stop"));
  // It is told which permission it lacks and which role has it (and what DDS said).
  const auto refusedCommand = [](const test::CommandResult& r, const std::string& subject) {
    EXPECT_EQ(r.exit_code, 1) << r.output;
    EXPECT_NE(r.output.find("ctl: DDS Security: this participant (secured as CN=" + subject +
                            ") has no permission to publish on rt/pulsetrack/command: commands "
                            "need an enclave of the controller role"),
              std::string::npos)
        << r.output;
    EXPECT_NE(r.output.find("rt/pulsetrack/command (pulsetrack_msgs::msg::dds_::Command_): Not "
                            "Allowed By Security"),
              std::string::npos)
        << r.output;
  };
  refusedCommand(robot, "/robot/arm");
  // The same for the OR display (role monitor).
  const auto display_enclave = "--enclave " + enclave("a", "or/display").string();
  refusedCommand(test::run(ctl(domain, display_enclave, "stop")), "/or/display");

  // What each role may read, as `pulsetrack listen` shows it: the monitor sees health and is told
  // that the deformation is not its to read (no "cannot create topic" exit); the subscriber sees
  // both.
  const std::string listen =
      test::cli() + " listen --domain " + std::to_string(domain) + " --rig rig-sec --seconds 60 ";
  const test::CommandResult monitor_listens = test::run(listen + display_enclave + " --count 1");
  daemon.drain(0);
  EXPECT_EQ(monitor_listens.exit_code, 0) << monitor_listens.output;
  EXPECT_NE(monitor_listens.output.find("health  rig-sec "), std::string::npos)
      << monitor_listens.output;
  EXPECT_NE(monitor_listens.output.find("listen: DDS Security: this participant (secured as "
                                        "CN=/or/display) has no permission to read "
                                        "rt/pulsetrack/deformation: showing health only"),
            std::string::npos)
      << monitor_listens.output;
  EXPECT_EQ(monitor_listens.output.find("deform  "), std::string::npos) << monitor_listens.output;
  const test::CommandResult robot_listens = test::run(
      listen + "--enclave " + enclave("a", "robot/arm").string() + " --count 2 --every 1");
  daemon.drain(0);
  EXPECT_EQ(robot_listens.exit_code, 0) << robot_listens.output;
  EXPECT_NE(robot_listens.output.find("deform  rig-sec frame"), std::string::npos)
      << robot_listens.output;
  EXPECT_EQ(robot_listens.output.find("no permission"), std::string::npos) << robot_listens.output;

  // The daemon obeyed none of them: it still tracks, frames still counting.
  const uint64_t frames_after_attacks = frames_before;
  const auto still = [&](const pulsetrack_msgs_msg_dds__Health_& h) {
    return std::string(h.tracking_state).rfind("tracking ", 0) == 0 &&
           h.frames > frames_after_attacks;
  };
  last = waitForHealth(daemon, *health, "rig-sec", still, std::chrono::seconds(60), &found);
  EXPECT_TRUE(found) << "after the refused participants: " << last;

  // 4. The OR console (role controller, this CA): obeyed.
  const test::CommandResult console =
      test::run(ctl(domain, "--enclave " + enclave("a", "or/console").string(), "stop"));
  EXPECT_EQ(console.exit_code, 0) << console.output;
  EXPECT_NE(console.output.find("acknowledged"), std::string::npos) << console.output;
  const auto stopped = [](const pulsetrack_msgs_msg_dds__Health_& h) {
    return std::string(h.tracking_state).rfind("tracking ", 0) != 0;
  };
  last = waitForHealth(daemon, *health, "rig-sec", stopped, std::chrono::seconds(60), &found);
  EXPECT_TRUE(found) << "the permitted stop was not obeyed: " << last;

  kill(daemon.pid, SIGTERM);
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_EQ(daemon.wait([&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }),
            0);
}

// The enclave as a consumer that shares no code with pulsetrack meets it: ros2_subscriber (built
// from the .msg files) with Cyclone DDS's own XML security configuration, the plugins found by
// dpkg, not by pulsetrack's dds layer.
TEST_F(Keystores, AForeignSubscriberWithItsEnclaveReceivesTheSecuredTopics) {
  const uint32_t domain = 94;
  const test::TempDir dir;
  DaemonOptions opt;
  opt.rig = "rig-sec";
  // With the cameras' preview: a subscriber may read the images (a monitor may not:
  // tests/igtl/igtl_test.cpp).
  opt.extra = "[security]\nenclave = \"" + enclave("a", "pulsetrack/daemon").string() +
              "\"\n[preview]\nrate_hz = 5.0\nscale = 2\n";
  Daemon daemon(dir, domain, {}, "", {}, opt);
  const test::CommandResult where = test::run("dpkg -L libddsc0debian");
  const size_t at = where.output.find("/libdds_security_auth.so");
  ASSERT_NE(at, std::string::npos) << where.output;
  const std::string plugins =
      where.output.substr(where.output.rfind('\n', at) + 1, at - where.output.rfind('\n', at) - 1);
  const auto robot = enclave("a", "robot/arm");
  const auto lib = [&](const char* name, const char* init, const char* fini) {
    return "<Library path=\"" + plugins + "/libdds_security_" + name + ".so\" initFunction=\"" +
           init + "\" finalizeFunction=\"" + fini + "\"/>";
  };
  const auto file = [&](const char* name) { return "file:" + (robot / name).string(); };
  const std::string uri =
      "<CycloneDDS><Domain id=\"any\"><General><Interfaces><NetworkInterface name=\"lo\"/>"
      "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery>"
      "<ParticipantIndex>auto</ParticipantIndex><Peers><Peer Address=\"127.0.0.1\"/></Peers>"
      "</Discovery><Security><Authentication>" +
      lib("auth", "init_authentication", "finalize_authentication") + "<IdentityCA>" +
      file("identity_ca.cert.pem") + "</IdentityCA><IdentityCertificate>" + file("cert.pem") +
      "</IdentityCertificate><PrivateKey>" + file("key.pem") +
      "</PrivateKey></Authentication><AccessControl>" +
      lib("ac", "init_access_control", "finalize_access_control") + "<PermissionsCA>" +
      file("permissions_ca.cert.pem") + "</PermissionsCA><Governance>" + file("governance.p7s") +
      "</Governance><Permissions>" + file("permissions.p7s") +
      "</Permissions></AccessControl><Cryptographic>" +
      lib("crypto", "init_crypto", "finalize_crypto") +
      "</Cryptographic></Security></Domain></CycloneDDS>";
  const std::string uri_file = (dir.path() / "cyclonedds.xml").string();
  std::ofstream(uri_file) << uri;
  const test::CommandResult r = test::run(
      "CYCLONEDDS_URI=file://" + uri_file + " " + ROS2_SUBSCRIBER + " --domain " +
      std::to_string(domain) + " --features 3 --deformation 3 --health 1 --images 1 --timeout 90");
  kill(daemon.pid, SIGTERM);
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_EQ(daemon.wait([&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }),
            0);
  EXPECT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("security_state=\"secured as CN=/pulsetrack/daemon\""), std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("summary features=3 deformation=3 health="), std::string::npos)
      << r.output;
}

// The daemon's config naming `files` (an [security] table's body); its --check-config output.
test::CommandResult checkConfig(const test::TempDir& dir, const std::string& security_body,
                                bool check_only = true) {
  const auto cfg = dir.path() / "pulsetrackd.toml";
  std::ofstream(cfg) << "rig_id = \"rig-sec\"\n[dds]\ndomain_id = 92\n[source]\nkind = \"sim\"\n"
                     << "scene = \"" << kScene << "\"\n[realtime]\nlock_memory = false\n"
                     << "capture = { priority = 0 }\ntrack = { priority = 0 }\n"
                     << "publish = { priority = 0 }\n[security]\n"
                     << security_body;
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  return test::run(std::string(PULSETRACKD) + " -c " + cfg.string() +
                   (check_only ? " --check-config" : ""));
}

TEST_F(Keystores, BadSecurityFilesAreNamedAndTheDaemonDoesNotStart) {
  const test::TempDir dir;
  const auto daemon = enclave("a", "pulsetrack/daemon");
  const auto quoted = [](const std::filesystem::path& p) { return "\"" + p.string() + "\""; };
  const auto files = [&](const std::filesystem::path& d, const std::string& override_key = "",
                         const std::filesystem::path& override_file = {}) {
    std::string body = "enclave = " + quoted(d) + "\n";
    if (!override_key.empty()) body += override_key + " = " + quoted(override_file) + "\n";
    return body;
  };

  // The good enclave passes, and says whom it is.
  test::CommandResult r = checkConfig(dir, files(daemon));
  EXPECT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("secured as CN=/pulsetrack/daemon"), std::string::npos) << r.output;

  struct Case {
    const char* what;
    std::string body;
    std::string expect;
  };
  const auto missing = dir.path() / "nowhere" / "cert.pem";
  security("add-participant " + (dir_->path() / "a").string() +
           " /pulsetrack/old --role daemon --days 0");
  std::this_thread::sleep_for(std::chrono::milliseconds(1100));  // past its notAfter
  const auto tampered = dir.path() / "permissions.p7s";
  {
    std::string text = readAll(daemon / "permissions.p7s");
    const size_t at = text.find("<topic>rt/*pulsetrack/command</topic>");
    ASSERT_NE(at, std::string::npos);
    text.replace(at, 0, "<topic>rt/*pulsetrack/health</topic>\n");  // the daemon reads...
    std::ofstream(tampered) << text;
  }
  const std::vector<Case> cases = {
      {"missing certificate", files(daemon, "certificate", missing),
       missing.string() + ": cannot read the identity certificate: No such file or directory"},
      {"expired certificate", files(enclave("a", "pulsetrack/old")),
       (enclave("a", "pulsetrack/old") / "cert.pem").string() +
           ": the identity certificate expired on"},
      {"another CA's certificate",
       files(daemon, "certificate", enclave("b", "or/console") / "cert.pem"),
       (enclave("b", "or/console") / "cert.pem").string() +
           ": the identity certificate is not signed by the identity CA " +
           (daemon / "identity_ca.cert.pem").string()},
      {"another participant's key",
       files(daemon, "private_key", enclave("a", "or/console") / "key.pem"),
       (enclave("a", "or/console") / "key.pem").string() +
           ": the private key does not belong to the certificate"},
      {"tampered permissions", files(daemon, "permissions", tampered),
       tampered.string() + ": the permissions is not signed by the permissions CA"},
      {"another participant's permissions",
       files(daemon, "permissions", enclave("a", "or/console") / "permissions.p7s"),
       (enclave("a", "or/console") / "permissions.p7s").string() +
           ": the permissions are granted to 'CN=/or/console', the certificate"},
      {"governance of another CA",
       files(daemon, "governance", enclave("b", "or/console") / "governance.p7s"),
       (enclave("b", "or/console") / "governance.p7s").string() +
           ": the governance is not signed by the permissions CA"},
      {"no files", "", "[security] needs enclave = \"DIR\""},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    r = checkConfig(dir, c.body);
    EXPECT_NE(r.exit_code, 0) << r.output;
    EXPECT_NE(r.output.find(c.expect), std::string::npos) << r.output;
  }
  // Not only --check-config: the daemon itself refuses to start, it does not run unsecured.
  r = checkConfig(dir, files(enclave("a", "pulsetrack/old")), false);
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("expired on"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("running"), std::string::npos) << r.output;
}

TEST(Unsecured, TheDaemonRunsAndHealthAndTheJournalSaySo) {
  const uint32_t domain = 93;
  const test::TempDir dir;
  DaemonOptions opt;
  opt.rig = "rig-open";
  Daemon daemon(dir, domain, {}, "", {}, opt);
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto participant = dds::Participant::create(domain);
  ASSERT_TRUE(participant) << participant.error().message;
  EXPECT_EQ(participant->securityState(), "unsecured");
  auto health =
      dds::Reader::create(*participant, "rt/pulsetrack/health",
                          &pulsetrack_msgs_msg_dds__Health__desc, dds::Profile::kTransientLocal);
  ASSERT_TRUE(health) << health.error().message;
  bool found = false;
  const std::string last = waitForHealth(
      daemon, *health, "rig-open",
      [](const pulsetrack_msgs_msg_dds__Health_& h) {
        return std::string(h.security_state) == "unsecured";
      },
      std::chrono::seconds(60), &found);
  EXPECT_TRUE(found) << last;
  kill(daemon.pid, SIGTERM);
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_EQ(daemon.wait([&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }),
            0);
}

}  // namespace
}  // namespace pulsetrack
