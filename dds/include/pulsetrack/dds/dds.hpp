#pragma once
// A thin, move-only C++ layer over Cyclone DDS's C API (types from msgs/idl by idlc).
// Topic names follow ROS 2 (rt/[<namespace>/]pulsetrack/..., one rig per namespace: the types
// are keyless, as ROS 2's), QoS the ROS 2 profiles (docs/ros2.md): sensor data (best effort,
// keep last 5, volatile) for the streams, reliable transient-local (keep last 1) for health,
// reliable keep-last-10 for commands.

#include <dds/dds.h>

#include <chrono>
#include <cstdint>
#include <string>
#include <string_view>

#include "pulsetrack/dds/security.hpp"
#include "pulsetrack/vision/error.hpp"
#include "pulsetrack_msgs.h"

namespace pulsetrack::dds {

using vision::Result;

// The DDS topic names of one rig: rt/<namespace>/pulsetrack/<leaf>, or rt/pulsetrack/<leaf>
// without a namespace, as ROS 2 names the topic /<namespace>/pulsetrack/<leaf>.
// Without a namespace (the default).
inline constexpr const char* kFeaturesTopic = "rt/pulsetrack/features";
inline constexpr const char* kDeformationTopic = "rt/pulsetrack/deformation";
inline constexpr const char* kHealthTopic = "rt/pulsetrack/health";
inline constexpr const char* kCommandTopic = "rt/pulsetrack/command";
inline constexpr const char* kFieldTopic = "rt/pulsetrack/field";
struct Topics {
  std::string features, deformation, health, command;
  std::string field;                     // the dense deformation field, sensor_msgs/PointCloud2
  std::string targets, targets_tracked;  // points a robot wants followed, and the answers
  // The cameras' low-rate preview, sensor_msgs/CompressedImage: .../{left,right}/image/compressed
  // (image_transport's "compressed" transport of .../{left,right}/image).
  std::string image_left, image_right;
  // The namespace follows ROS 2's rules for names: segments of letters, digits and underscores
  // separated by '/', none starting with a digit; a leading '/' is allowed (ROS 2's absolute
  // form), a trailing one is not. Empty: no namespace.
  static Result<Topics> forNamespace(std::string_view ns);
};

// A CYCLONEDDS_URI that keeps DDS on loopback (no multicast, the local peer named): tests,
// benchmarks and the demo, so that they disturb no one on the network.
inline constexpr const char* kLoopbackUri =
    "<CycloneDDS><Domain id=\"any\"><General><Interfaces><NetworkInterface name=\"lo\"/>"
    "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>"
    "auto</ParticipantIndex><Peers><Peer Address=\"127.0.0.1\"/></Peers></Discovery></Domain>"
    "</CycloneDDS>";

enum class Profile { kSensorData, kTransientLocal, kCommand };

// An owned DDS entity (deleted with its children).
class Entity {
 public:
  Entity() = default;
  explicit Entity(dds_entity_t e) : e_(e) {}
  Entity(Entity&& o) noexcept : e_(o.e_) { o.e_ = 0; }
  Entity& operator=(Entity&& o) noexcept;
  Entity(const Entity&) = delete;
  Entity& operator=(const Entity&) = delete;
  ~Entity();
  [[nodiscard]] dds_entity_t get() const { return e_; }

 private:
  dds_entity_t e_ = 0;
};

class Participant {
 public:
  // With `security`, a participant of a secured domain (its files checked first, errors naming
  // them): it never falls back to an unsecured one.
  static Result<Participant> create(uint32_t domain_id, const SecurityFiles* security = nullptr);
  [[nodiscard]] dds_entity_t get() const { return p_.get(); }
  [[nodiscard]] uint32_t domain() const { return domain_; }
  // "unsecured", or "secured as CN=/pulsetrack/daemon" (the certificate's subject).
  [[nodiscard]] const std::string& securityState() const { return security_state_; }

 private:
  Entity p_;
  uint32_t domain_ = 0;
  std::string security_state_ = "unsecured";
};

class Writer {
 public:
  static Result<Writer> create(const Participant& p, const char* topic,
                               const dds_topic_descriptor_t* type, Profile profile);
  // Publishes one sample of the writer's type.
  Result<void> write(const void* sample) const;
  // Readers currently matched (discovery), for health and tests.
  [[nodiscard]] int matchedReaders() const;
  // Waits until every matched reliable reader acknowledged what was written (false: timeout).
  [[nodiscard]] bool waitForAcks(std::chrono::milliseconds timeout) const;

 private:
  Entity topic_, writer_;
  std::string name_;
};

class Reader {
 public:
  static Result<Reader> create(const Participant& p, const char* topic,
                               const dds_topic_descriptor_t* type, Profile profile);
  // Waits up to `timeout` for data; takes one sample into `sample` (of the reader's type,
  // zero-initialized at first; its strings and sequences are reused from take to take, and
  // freed by the caller with dds_sample_free(..., DDS_FREE_CONTENTS)). False on timeout.
  bool takeOne(void* sample, std::chrono::milliseconds timeout) const;
  [[nodiscard]] int matchedWriters() const;

 private:
  Entity topic_, reader_, waitset_, condition_;
  const dds_topic_descriptor_t* type_ = nullptr;
  std::string name_;
};

// True where a topic, reader or writer was refused by DDS Security's access control (the
// enclave's permissions do not grant it): a role's limit, which a tool reports and works within
// (a monitor shows health), not a fault.
bool notAllowedBySecurity(const vision::Error& e);
// "DDS Security: this participant (secured as CN=/or/display) has no permission to read
// rt/pulsetrack/deformation" (or "to publish on").
std::string notPermitted(const Participant& p, std::string_view topic, bool write);

// Header stamp from a time in ns (CLOCK_REALTIME or the trigger's time base).
builtin_interfaces_msg_dds__Time_ stamp(int64_t ns);

}  // namespace pulsetrack::dds
