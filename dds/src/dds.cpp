#include "pulsetrack/dds/dds.hpp"

#include <fmt/format.h>

#include <filesystem>
#include <utility>

namespace pulsetrack::dds {

namespace {

std::string why(dds_return_t rc) { return dds_strretcode(rc); }

dds_qos_t* makeQos(Profile profile) {
  dds_qos_t* qos = dds_create_qos();
  switch (profile) {
    case Profile::kSensorData:
      dds_qset_reliability(qos, DDS_RELIABILITY_BEST_EFFORT, 0);
      dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, 5);
      dds_qset_durability(qos, DDS_DURABILITY_VOLATILE);
      break;
    case Profile::kTransientLocal:
      dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
      dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, 1);
      dds_qset_durability(qos, DDS_DURABILITY_TRANSIENT_LOCAL);
      break;
    case Profile::kCommand:
      // Every command arrives, in order, or its write fails: keep-all with a bounded history, so
      // a burst is flow-controlled (the writer blocks up to 100 ms, then its write times out)
      // instead of older commands being replaced unseen (a keep-last 10 history lost 729 of a
      // 1000-command flood in the soak), and a flooding participant cannot grow the daemon's
      // memory. History kind is not part of QoS matching: a ROS 2 publisher with rclcpp's
      // default (keep-last 10, reliable) still matches.
      dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
      dds_qset_history(qos, DDS_HISTORY_KEEP_ALL, DDS_LENGTH_UNLIMITED);
      dds_qset_resource_limits(qos, 64, DDS_LENGTH_UNLIMITED, DDS_LENGTH_UNLIMITED);
      dds_qset_durability(qos, DDS_DURABILITY_VOLATILE);
      break;
  }
  return qos;
}

Result<dds_entity_t> makeTopic(const Participant& p, const char* topic,
                               const dds_topic_descriptor_t* type) {
  const dds_entity_t t = dds_create_topic(p.get(), type, topic, nullptr, nullptr);
  if (t < 0) {
    return std::unexpected(vision::Error{
        fmt::format("DDS: cannot create topic {} ({}): {}", topic, type->m_typename, why(t)), t});
  }
  return t;
}

}  // namespace

bool notAllowedBySecurity(const vision::Error& e) {
  return e.code == DDS_RETCODE_NOT_ALLOWED_BY_SECURITY;
}

std::string notPermitted(const Participant& p, std::string_view topic, bool write) {
  return fmt::format("DDS Security: this participant ({}) has no permission to {} {}",
                     p.securityState(), write ? "publish on" : "read", topic);
}

Result<Topics> Topics::forNamespace(std::string_view ns) {
  if (!ns.empty() && ns.front() == '/') ns.remove_prefix(1);
  std::string prefix = "rt/";
  if (!ns.empty()) {
    const auto bad = [&](const char* why) {
      return vision::fail(
          fmt::format("DDS namespace '{}': {} (ROS 2 names: segments of letters, "
                      "digits and '_' separated by '/', e.g. or1 or site/or1)",
                      ns, why));
    };
    bool segment_start = true;
    for (const char ch : ns) {
      const bool alpha = (ch >= 'a' && ch <= 'z') || (ch >= 'A' && ch <= 'Z') || ch == '_';
      const bool digit = ch >= '0' && ch <= '9';
      if (ch == '/') {
        if (segment_start) return bad("an empty segment");
        segment_start = true;
        continue;
      }
      if (!alpha && !digit) return bad(fmt::format("'{}' is not allowed", ch).c_str());
      if (segment_start && digit) return bad("a segment starts with a digit");
      segment_start = false;
    }
    if (segment_start) return bad("it ends with '/'");
    prefix += std::string(ns) + "/";
  }
  prefix += "pulsetrack/";
  return Topics{prefix + "features",
                prefix + "deformation",
                prefix + "health",
                prefix + "command",
                prefix + "field",
                prefix + "targets",
                prefix + "targets_tracked",
                prefix + "left/image/compressed",
                prefix + "right/image/compressed"};
}

Entity& Entity::operator=(Entity&& o) noexcept {
  if (this != &o) {
    if (e_ > 0) dds_delete(e_);
    e_ = o.e_;
    o.e_ = 0;
  }
  return *this;
}

Entity::~Entity() {
  if (e_ > 0) dds_delete(e_);
}

Result<Participant> Participant::create(uint32_t domain_id, const SecurityFiles* security) {
  if (domain_id > 232)
    return vision::fail(fmt::format("DDS: domain id {} is out of range (0-232)", domain_id));
  std::string subject;
  dds_qos_t* qos = nullptr;
  if (security != nullptr) {
    if (domain_id > 230) {
      return vision::fail(fmt::format(
          "DDS Security: domain id {} is out of the secured range 0-230 (Cyclone DDS's access "
          "control refuses higher ids)",
          domain_id));
    }
    auto checked = security->check();
    if (!checked) return vision::fail("DDS Security: " + checked.error().message);
    subject = *checked;
    // The OMG DDS Security properties, as Cyclone DDS's own examples set them.
    qos = dds_create_qos();
    const auto file = [](const std::filesystem::path& p) {
      return "file:" + std::filesystem::absolute(p).lexically_normal().string();
    };
    const std::pair<const char*, std::string> props[] = {
        {"dds.sec.auth.library.path", securityPluginPath("auth")},
        {"dds.sec.auth.library.init", "init_authentication"},
        {"dds.sec.auth.library.finalize", "finalize_authentication"},
        {"dds.sec.crypto.library.path", securityPluginPath("crypto")},
        {"dds.sec.crypto.library.init", "init_crypto"},
        {"dds.sec.crypto.library.finalize", "finalize_crypto"},
        {"dds.sec.access.library.path", securityPluginPath("ac")},
        {"dds.sec.access.library.init", "init_access_control"},
        {"dds.sec.access.library.finalize", "finalize_access_control"},
        {"dds.sec.auth.identity_ca", file(security->identity_ca)},
        {"dds.sec.auth.identity_certificate", file(security->certificate)},
        {"dds.sec.auth.private_key", file(security->private_key)},
        {"dds.sec.access.permissions_ca", file(security->permissions_ca)},
        {"dds.sec.access.governance", file(security->governance)},
        {"dds.sec.access.permissions", file(security->permissions)},
    };
    for (const auto& [name, value] : props) dds_qset_prop(qos, name, value.c_str());
  }
  const dds_entity_t e = dds_create_participant(domain_id, qos, nullptr);
  if (qos != nullptr) dds_delete_qos(qos);
  if (e < 0 && security != nullptr) {
    return vision::fail(fmt::format(
        "DDS Security: cannot join domain {} as {} (certificate {}): {} (Cyclone DDS refused the "
        "files; its trace, CYCLONEDDS_URI with <Tracing><Category>security</Category>, says why)",
        domain_id, subject, security->certificate.string(), why(e)));
  }
  if (e < 0)
    return vision::fail(fmt::format(
        "DDS: cannot join domain {}: {} (check CYCLONEDDS_URI and the network interface)",
        domain_id, why(e)));
  Participant p;
  p.p_ = Entity(e);
  p.domain_ = domain_id;
  if (security != nullptr) p.security_state_ = "secured as " + subject;
  return p;
}

Result<Writer> Writer::create(const Participant& p, const char* topic,
                              const dds_topic_descriptor_t* type, Profile profile) {
  auto t = makeTopic(p, topic, type);
  if (!t) return std::unexpected(t.error());
  Writer w;
  w.topic_ = Entity(*t);
  w.name_ = topic;
  dds_qos_t* qos = makeQos(profile);
  const dds_entity_t e = dds_create_writer(p.get(), *t, qos, nullptr);
  dds_delete_qos(qos);
  if (e < 0) {
    return std::unexpected(
        vision::Error{fmt::format("DDS: cannot create a writer on {}: {}", topic, why(e)), e});
  }
  w.writer_ = Entity(e);
  return w;
}

Result<void> Writer::write(const void* sample) const {
  if (const dds_return_t rc = dds_write(writer_.get(), sample); rc != DDS_RETCODE_OK)
    return vision::fail(fmt::format("DDS: write on {} failed: {}", name_, why(rc)));
  return {};
}

bool Writer::waitForAcks(std::chrono::milliseconds timeout) const {
  return dds_wait_for_acks(writer_.get(),
                           std::chrono::duration_cast<std::chrono::nanoseconds>(timeout).count()) ==
         DDS_RETCODE_OK;
}

int Writer::matchedReaders() const {
  dds_publication_matched_status_t st{};
  if (dds_get_publication_matched_status(writer_.get(), &st) != DDS_RETCODE_OK) return 0;
  return static_cast<int>(st.current_count);
}

Result<Reader> Reader::create(const Participant& p, const char* topic,
                              const dds_topic_descriptor_t* type, Profile profile) {
  auto t = makeTopic(p, topic, type);
  if (!t) return std::unexpected(t.error());
  Reader r;
  r.topic_ = Entity(*t);
  r.type_ = type;
  r.name_ = topic;
  dds_qos_t* qos = makeQos(profile);
  const dds_entity_t e = dds_create_reader(p.get(), *t, qos, nullptr);
  dds_delete_qos(qos);
  if (e < 0) {
    return std::unexpected(
        vision::Error{fmt::format("DDS: cannot create a reader on {}: {}", topic, why(e)), e});
  }
  r.reader_ = Entity(e);
  const dds_entity_t cond = dds_create_readcondition(e, DDS_ANY_STATE);
  const dds_entity_t ws = dds_create_waitset(p.get());
  if (cond < 0 || ws < 0 || dds_waitset_attach(ws, cond, 0) != DDS_RETCODE_OK)
    return vision::fail(fmt::format("DDS: cannot wait on {}", topic));
  r.condition_ = Entity(cond);
  r.waitset_ = Entity(ws);
  return r;
}

bool Reader::takeOne(void* sample, std::chrono::milliseconds timeout) const {
  void* samples[1] = {sample};
  dds_sample_info_t info[1];
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    const dds_return_t n = dds_take(reader_.get(), samples, info, 1, 1);
    if (n > 0 && info[0].valid_data) return true;
    const auto left = deadline - std::chrono::steady_clock::now();
    if (left <= std::chrono::nanoseconds(0)) return false;
    if (n <= 0) {
      dds_waitset_wait(waitset_.get(), nullptr, 0,
                       std::chrono::duration_cast<std::chrono::nanoseconds>(left).count());
    }
  }
}

int Reader::matchedWriters() const {
  dds_subscription_matched_status_t st{};
  if (dds_get_subscription_matched_status(reader_.get(), &st) != DDS_RETCODE_OK) return 0;
  return static_cast<int>(st.current_count);
}

builtin_interfaces_msg_dds__Time_ stamp(int64_t ns) {
  builtin_interfaces_msg_dds__Time_ t{};
  t.sec = static_cast<int32_t>(ns / 1'000'000'000);
  t.nanosec = static_cast<uint32_t>(ns % 1'000'000'000);
  return t;
}

}  // namespace pulsetrack::dds
