// Cyclone DDS between two real processes over loopback (own domain id): the ROS 2-named topics
// and types, sensor-data features, transient-local health seen by a late joiner.

#include "pulsetrack/dds/dds.hpp"

#include <gtest/gtest.h>
#include <spawn.h>
#include <sys/wait.h>

#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "data_paths.hpp"

extern char** environ;

namespace pulsetrack::dds {
namespace {

TEST(Dds, TypesAreNamedTheRos2Way) {
  EXPECT_STREQ(pulsetrack_msgs_msg_dds__Features__desc.m_typename,
               "pulsetrack_msgs::msg::dds_::Features_");
  EXPECT_STREQ(pulsetrack_msgs_msg_dds__Health__desc.m_typename,
               "pulsetrack_msgs::msg::dds_::Health_");
}

// One rig per namespace, as ROS 2 names topics; a name ROS 2 would refuse is refused.
TEST(Dds, TopicsFollowTheNamespace) {
  auto none = Topics::forNamespace("");
  ASSERT_TRUE(none);
  EXPECT_EQ(none->features, kFeaturesTopic);
  EXPECT_EQ(none->command, kCommandTopic);
  auto or1 = Topics::forNamespace("or1");
  ASSERT_TRUE(or1);
  EXPECT_EQ(or1->features, "rt/or1/pulsetrack/features");
  EXPECT_EQ(or1->deformation, "rt/or1/pulsetrack/deformation");
  EXPECT_EQ(or1->health, "rt/or1/pulsetrack/health");
  EXPECT_EQ(or1->command, "rt/or1/pulsetrack/command");
  auto nested = Topics::forNamespace("/site_a/or_2");
  ASSERT_TRUE(nested);
  EXPECT_EQ(nested->features, "rt/site_a/or_2/pulsetrack/features");
  for (const char* bad : {"or 1", "1or", "or1/", "or1//x", "or-1", "or1/2x"}) {
    auto t = Topics::forNamespace(bad);
    ASSERT_FALSE(t) << bad;
    EXPECT_NE(t.error().message.find(std::string("'") + (bad[0] == '/' ? bad + 1 : bad) + "'"),
              std::string::npos)
        << t.error().message;
  }
}

// ROS 2 types are keyless, and DDS never matches a keyed endpoint with a keyless one: no @key
// in the IDL, and each struct's extensibility stated.
TEST(Dds, TheIdlIsKeylessAndFinal) {
  std::ifstream f(std::string(PULSETRACK_SOURCE_DIR) + "/msgs/idl/pulsetrack_msgs.idl");
  const std::string idl((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  ASSERT_FALSE(idl.empty());
  size_t structs = 0, finals = 0;
  for (size_t at = idl.find("struct "); at != std::string::npos; at = idl.find("struct ", at + 1)) {
    ++structs;
    finals += at >= 7 && idl.compare(at - 7, 7, "@final ") == 0 ? 1 : 0;
  }
  EXPECT_EQ(structs, 15U);  // 8 of pulsetrack_msgs, 7 of ROS 2's (Time ... CompressedImage)
  EXPECT_EQ(finals, structs);
  std::string code;  // the IDL without its comments
  std::istringstream lines(idl);
  for (std::string line; std::getline(lines, line);) code += line.substr(0, line.find("//")) + "\n";
  EXPECT_EQ(code.find("@key"), std::string::npos);
  EXPECT_EQ(pulsetrack_msgs_msg_dds__Features__desc.m_nkeys, 0U);
  EXPECT_EQ(pulsetrack_msgs_msg_dds__Command__desc.m_nkeys, 0U);
  EXPECT_EQ(sensor_msgs_msg_dds__CompressedImage__desc.m_nkeys, 0U);
}

// The ROS 2 .msg files say what the IDL says: the same fields in the same order (a ROS 2 node
// built from msgs/ros must read what the daemon writes).
std::vector<std::string> idlFields(const std::string& idl, const std::string& type) {
  const size_t at = idl.find("struct " + type + "_ {");
  if (at == std::string::npos) return {};
  const size_t end = idl.find("};", at);
  std::istringstream body(idl.substr(at, end - at));
  std::vector<std::string> out;
  std::string line;
  std::getline(body, line);  // the struct line
  while (std::getline(body, line)) {
    line = line.substr(0, line.find("//"));
    const size_t semi = line.find(';');
    if (semi == std::string::npos) continue;
    std::string decl = line.substr(0, semi);
    decl = decl.substr(0, decl.find('['));
    out.push_back(decl.substr(decl.find_last_of(' ') + 1));
  }
  return out;
}

std::vector<std::string> msgFields(const std::string& path) {
  std::ifstream in(path);
  std::vector<std::string> out;
  std::string line;
  while (std::getline(in, line)) {
    line = line.substr(0, line.find('#'));
    if (line.find('=') != std::string::npos) continue;  // a constant
    std::istringstream ss(line);
    std::string type, name;
    if (ss >> type >> name) out.push_back(name);
  }
  return out;
}

TEST(Dds, Ros2MessagesMatchTheIdl) {
  std::ifstream f(std::string(PULSETRACK_SOURCE_DIR) + "/msgs/idl/pulsetrack_msgs.idl");
  const std::string idl((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  ASSERT_FALSE(idl.empty());
  for (const char* t : {"Feature", "Features", "Deformation", "StageLatency", "Health", "Command",
                        "Targets", "TrackedTargets"}) {
    const auto a = idlFields(idl, t);
    const auto b = msgFields(std::string(PULSETRACK_SOURCE_DIR) + "/msgs/ros/pulsetrack_msgs/msg/" +
                             t + ".msg");
    EXPECT_FALSE(a.empty()) << t;
    EXPECT_EQ(a, b) << t;
  }
  // sensor_msgs/PointCloud2 (the field) and CompressedImage (the preview) as ROS defines them:
  // Debian's ros-sensor-msgs (data_paths.hpp).
  for (const char* t : {"PointField", "PointCloud2", "CompressedImage"}) {
    const auto a = idlFields(idl, t);
    const auto b = msgFields(data::rosMsg("sensor_msgs", t).string());
    EXPECT_FALSE(a.empty()) << t;
    EXPECT_EQ(a, b) << t;
  }
}

TEST(Dds, BadDomainIsAClearError) {
  auto p = Participant::create(500);
  ASSERT_FALSE(p);
  EXPECT_NE(p.error().message.find("domain id 500"), std::string::npos);
}

TEST(Dds, AnotherProcessPublishesFeaturesAndALateJoinerGetsHealth) {
  setenv("CYCLONEDDS_URI", pulsetrack::dds::kLoopbackUri, 1);
  const uint32_t domain = 71;
  pid_t pid = 0;
  std::string d = std::to_string(domain);
  // A cross build's peer runs under the same emulator as this test (qemu-aarch64-static -L
  // SYSROOT, '|'-separated; QEMU_CPU is inherited): qemu-user runs no foreign program it is asked
  // to exec.
  std::vector<std::string> args;
  std::istringstream emulator(PULSETRACK_TEST_EMULATOR);
  for (std::string word; std::getline(emulator, word, '|');) {
    if (!word.empty()) args.push_back(word);
  }
  args.insert(args.end(), {PULSETRACK_DDS_PEER, d, "rig-7"});
  std::vector<char*> argv;
  argv.reserve(args.size() + 1);
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  ASSERT_EQ(posix_spawnp(&pid, argv[0], nullptr, nullptr, argv.data(), environ), 0) << args[0];
  auto p = Participant::create(domain);
  ASSERT_TRUE(p) << p.error().message;
  // Join late: the peer wrote its health before this reader existed.
  auto features = Reader::create(*p, kFeaturesTopic, &pulsetrack_msgs_msg_dds__Features__desc,
                                 Profile::kSensorData);
  ASSERT_TRUE(features) << features.error().message;
  pulsetrack_msgs_msg_dds__Features_ f{};
  int got = 0;
  uint64_t last = 0;
  bool ordered = true;
  while (features->takeOne(&f, std::chrono::milliseconds(3000))) {
    EXPECT_STREQ(f.rig_id, "rig-7");
    EXPECT_STREQ(f.header.frame_id, "pulsetrack_left_camera");
    ASSERT_EQ(f.features._length, 3U);
    EXPECT_EQ(f.features._buffer[2].id, 2);
    EXPECT_DOUBLE_EQ(f.features._buffer[2].position.x, 0.002);
    EXPECT_DOUBLE_EQ(f.features._buffer[0].position.z, 0.45 + 1e-6 * static_cast<double>(f.frame));
    if (got > 0 && f.frame <= last) ordered = false;
    last = f.frame;
    if (++got == 20 || f.frame == 19) break;
  }
  dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
  EXPECT_GE(got, 15);  // best effort over loopback: nearly all
  EXPECT_TRUE(ordered);
  auto health = Reader::create(*p, kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                               Profile::kTransientLocal);
  ASSERT_TRUE(health) << health.error().message;
  pulsetrack_msgs_msg_dds__Health_ h{};
  ASSERT_TRUE(health->takeOne(&h, std::chrono::milliseconds(3000)));
  EXPECT_STREQ(h.rig_id, "rig-7");
  EXPECT_EQ(h.state, 1);
  EXPECT_EQ(h.frames, 1234U);
  EXPECT_STREQ(h.source, "sim");
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
}

}  // namespace
}  // namespace pulsetrack::dds
