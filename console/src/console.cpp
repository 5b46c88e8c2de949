#include "pulsetrack/console/console.hpp"

#include <fmt/format.h>
#include <fmt/ranges.h>
#include <openssl/rand.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <thread>
#include <vector>

#include "http.hpp"
#include "pulsetrack/analysis/motion.hpp"
#include "pulsetrack/console/credentials.hpp"
#include "pulsetrack/dds/dds.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"
#include "pulsetrack/vision/tracking_session.hpp"

namespace pulsetrack::console {

using json = nlohmann::json;
using vision::fail;
using Clock = std::chrono::steady_clock;

namespace {

constexpr const char* kCookie = "pt_session";
constexpr size_t kMaxEvents = 4096;        // the hub's backlog (a slow browser skips ahead)
constexpr double kSpectrumWindowS = 60.0;  // the spectrum's window
constexpr double kHistoryS = 90.0;

double seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

double stampSeconds(const builtin_interfaces_msg_dds__Time_& t) {
  return static_cast<double>(t.sec) + static_cast<double>(t.nanosec) * 1e-9;
}

std::string randomToken() {
  std::array<unsigned char, 32> b{};
  if (RAND_bytes(b.data(), static_cast<int>(b.size())) != 1) return {};
  std::string out;
  for (const unsigned char c : b) out += fmt::format("{:02x}", c);
  return out;
}

// A JPEG's size from its first SOFn marker (ITU T.81 B.2.2); 0 x 0 when there is none.
std::pair<int, int> jpegSize(const uint8_t* d, size_t n) {
  if (n < 4 || d[0] != 0xFF || d[1] != 0xD8) return {0, 0};
  size_t i = 2;
  while (i + 9 <= n && d[i] == 0xFF) {
    const uint8_t m = d[i + 1];
    const size_t len = (static_cast<size_t>(d[i + 2]) << 8U) | d[i + 3];
    if (m >= 0xC0 && m <= 0xCF && m != 0xC4 && m != 0xC8 && m != 0xCC) {
      return {(d[i + 7] << 8) | d[i + 8], (d[i + 5] << 8) | d[i + 6]};
    }
    i += 2 + len;
  }
  return {0, 0};
}

std::string cookieToken(const httplib::Request& req) {
  const std::string c = req.get_header_value("Cookie");
  const std::string key = std::string(kCookie) + "=";
  for (size_t at = 0; at < c.size();) {
    while (at < c.size() && (c[at] == ' ' || c[at] == ';')) ++at;
    const size_t end = c.find(';', at);
    const std::string part = c.substr(at, end == std::string::npos ? std::string::npos : end - at);
    if (part.rfind(key, 0) == 0) return part.substr(key.size());
    if (end == std::string::npos) break;
    at = end + 1;
  }
  return {};
}

void replyJson(httplib::Response& res, int status, const json& body) {
  res.status = status;
  res.set_content(body.dump(), "application/json");
}

// Broadcasts named events to every Server-Sent Events stream; new streams first get the latest
// event of each kind that describes a state (health, link, roi, spectrum, field).
class Hub {
 public:
  void publish(const std::string& name, const json& data, bool state) {
    std::string text = "event: " + name + "\ndata: " + data.dump() + "\n\n";
    {
      const std::lock_guard lock(m_);
      events_.emplace_back(next_++, text);
      if (events_.size() > kMaxEvents) events_.pop_front();
      if (state) latest_[name] = std::move(text);
    }
    cv_.notify_all();
  }
  // A new stream's position and its first chunk (the states).
  uint64_t subscribe(std::string& first) {
    const std::lock_guard lock(m_);
    first = "retry: 2000\n\n";
    for (const auto& [name, text] : latest_) first += text;
    return next_;
  }
  // The events from `cursor` on (waits up to `wait` for one); empty on timeout or when stopped.
  std::string next(uint64_t& cursor, std::chrono::milliseconds wait) {
    std::unique_lock lock(m_);
    cv_.wait_for(lock, wait, [&] { return stopped_ || next_ > cursor; });
    std::string out;
    for (const auto& [seq, text] : events_) {
      if (seq < cursor) continue;
      out += text;
    }
    cursor = next_;
    return out;
  }
  void stop() {
    {
      const std::lock_guard lock(m_);
      stopped_ = true;
    }
    cv_.notify_all();
  }

 private:
  std::mutex m_;
  std::condition_variable cv_;
  std::deque<std::pair<uint64_t, std::string>> events_;
  std::map<std::string, std::string> latest_;
  uint64_t next_ = 1;
  bool stopped_ = false;
};

struct Session {
  std::string user;
  Role role = Role::kViewer;
  Clock::time_point expires;
};

struct PendingCommand {
  uint32_t request_id = 0;
  std::string command;
  uint64_t accepted_base = 0, refused_base = 0;
  Clock::time_point sent;
  json roi;  // set_roi: the ROI that will be in force
};

}  // namespace

struct Console::Impl {
  ConsoleOptions o;
  Credentials users;
  vision::StereoRig rig;
  std::optional<dds::Participant> participant;
  dds::Topics topics;
  std::optional<dds::Writer> commander;
  std::string commander_error;  // why this console may not command (DDS Security), or ""
  // The topics this console's enclave may not read (DDS Security: a monitor reads health only);
  // the DDS thread's.
  std::vector<std::string> read_denied;
  std::unique_ptr<httplib::SSLServer> server;
  int bound_port = 0;
  Hub hub;
  std::atomic<bool> running{true};
  std::thread dds_thread;

  std::mutex m;  // everything below
  std::map<std::string, Session> sessions;
  std::deque<Clock::time_point> failed_logins;
  std::optional<Clock::time_point> last_health;
  uint64_t accepted = 0, refused = 0;
  std::string last_error;
  std::array<std::string, 2> image;  // the latest preview JPEG, left and right
  std::array<uint64_t, 2> image_seq{};
  double median_depth_mm = 0;  // of the last ok features (the right ROI's depth)
  std::deque<std::pair<double, analysis::Vec3>> history;  // (stamp s, displacement mm)
  std::vector<PendingCommand> pending;
  uint32_t next_request = 0;

  // --- DDS ---------------------------------------------------------------------------------
  void ddsLoop();
  void onHealth(const pulsetrack_msgs_msg_dds__Health_& h);
  void onFeatures(const pulsetrack_msgs_msg_dds__Features_& f, Clock::time_point& last_sent);
  void onDeformation(const pulsetrack_msgs_msg_dds__Deformation_& d);
  void onField(const sensor_msgs_msg_dds__PointCloud2_& c, Clock::time_point& last_sent);
  void onImage(int side, const sensor_msgs_msg_dds__CompressedImage_& im);
  void spectrum();
  void link(Clock::time_point now);
  void resolvePending(Clock::time_point now);

  // --- HTTP --------------------------------------------------------------------------------
  void routes();
  std::optional<Session> session(const httplib::Request& req);
  void command(const httplib::Request& req, httplib::Response& res, const Session& s);
};

// ----------------------------------------------------------------------------------------------

void Console::Impl::onHealth(const pulsetrack_msgs_msg_dds__Health_& h) {
  static constexpr std::array<const char*, 4> kStates = {"starting", "ok", "degraded", "fault"};
  json stages = json::array();
  for (uint32_t i = 0; i < h.stages._length; ++i) {
    const auto& s = h.stages._buffer[i];
    stages.push_back({{"stage", s.stage != nullptr ? s.stage : ""},
                      {"p50_us", s.p50_us},
                      {"p99_us", s.p99_us},
                      {"max_us", s.max_us}});
  }
  const auto str = [](const char* s) { return std::string(s != nullptr ? s : ""); };
  json j = {{"state", h.state < kStates.size() ? kStates[h.state] : "fault"},
            {"state_text", str(h.state_text)},
            {"fps", h.fps},
            {"frames", h.frames},
            {"drops", h.drops},
            {"deadline_misses", h.deadline_misses},
            {"unpaired", h.unpaired},
            {"missing_triggers", h.missing_triggers},
            {"source_faults", h.source_faults},
            {"recorder_faults", h.recorder_faults},
            {"commands_accepted", h.commands_accepted},
            {"commands_refused", h.commands_refused},
            {"source", str(h.source)},
            {"source_state", str(h.source_state)},
            {"trigger_state", str(h.trigger_state)},
            {"recorder_state", str(h.recorder_state)},
            {"tracking_state", str(h.tracking_state)},
            {"clock_state", str(h.clock_state)},
            {"security_state", str(h.security_state)},
            {"output_state", str(h.output_state)},
            {"last_error", str(h.last_error)},
            {"stages", stages},
            {"image_width", h.image_width},
            {"image_height", h.image_height}};
  {
    const std::lock_guard lock(m);
    last_health = Clock::now();
    accepted = h.commands_accepted;
    refused = h.commands_refused;
    last_error = str(h.last_error);
  }
  hub.publish("health", j, true);
}

void Console::Impl::onFeatures(const pulsetrack_msgs_msg_dds__Features_& f,
                               Clock::time_point& last_sent) {
  std::vector<double> depths;
  json items = json::array();
  for (uint32_t i = 0; i < f.features._length; ++i) {
    const auto& x = f.features._buffer[i];
    if (x.status == 0) depths.push_back(x.position.z * 1e3);
    const auto px = [](float v) { return std::round(static_cast<double>(v) * 10.0) / 10.0; };
    items.push_back({x.id, x.status, px(x.left_x), px(x.left_y), px(x.right_x), px(x.right_y)});
  }
  if (!depths.empty()) {
    std::nth_element(depths.begin(), depths.begin() + static_cast<long>(depths.size() / 2),
                     depths.end());
    const std::lock_guard lock(m);
    median_depth_mm = depths[depths.size() / 2];
  }
  const Clock::time_point now = Clock::now();
  if (seconds(last_sent, now) < 0.1) return;  // at most 10 a second to the browsers
  last_sent = now;
  hub.publish("features", {{"frame", f.frame}, {"items", items}}, false);
}

void Console::Impl::onDeformation(const pulsetrack_msgs_msg_dds__Deformation_& d) {
  const double t = stampSeconds(d.header.stamp);
  const analysis::Vec3 mm(d.displacement.x * 1e3, d.displacement.y * 1e3, d.displacement.z * 1e3);
  {
    const std::lock_guard lock(m);
    if (!history.empty() && t <= history.back().first) history.clear();  // a restart or a jump
    history.emplace_back(t, mm);
    while (!history.empty() && t - history.front().first > kHistoryS) history.pop_front();
  }
  hub.publish("deformation",
              {{"t", t},
               {"dx", mm[0]},
               {"dy", mm[1]},
               {"dz", mm[2]},
               {"ok", d.features_ok},
               {"total", d.features_total}},
              false);
}

void Console::Impl::spectrum() {
  std::vector<double> t;
  std::vector<analysis::Vec3> x;
  {
    const std::lock_guard lock(m);
    if (history.empty()) return;
    const double end = history.back().first;
    for (const auto& [s, v] : history) {
      if (end - s > kSpectrumWindowS) continue;
      t.push_back(s);
      x.push_back(v);
    }
  }
  const double span = t.empty() ? 0.0 : t.back() - t.front();
  if (span < 20.0) {
    hub.publish("spectrum",
                {{"error", fmt::format("needs 20 s of displacement, have {:.0f} s", span)}}, true);
    return;
  }
  auto a = analysis::analyzeSeries(t, x, 0, {});
  if (!a) {
    hub.publish("spectrum", {{"error", a.error().message}}, true);
    return;
  }
  json f = json::array(), amp = json::array(), peaks = json::array();
  for (size_t i = 0; i < a->frequency_hz.size(); ++i) {
    if (a->frequency_hz[i] > 3.0) break;
    f.push_back(std::round(a->frequency_hz[i] * 1e4) / 1e4);
    amp.push_back(std::round(a->amplitude_mm[i] * 1e5) / 1e5);
  }
  for (const analysis::SpectralPeak& p : a->peaks) {
    peaks.push_back(
        {{"frequency_hz", p.frequency_hz}, {"amplitude_mm", p.amplitude_mm}, {"name", p.name}});
  }
  hub.publish("spectrum",
              {{"frequency_hz", f}, {"amplitude_mm", amp}, {"peaks", peaks}, {"window_s", span}},
              true);
}

void Console::Impl::onField(const sensor_msgs_msg_dds__PointCloud2_& c,
                            Clock::time_point& last_sent) {
  const Clock::time_point now = Clock::now();
  if (seconds(last_sent, now) < 0.5) return;
  last_sent = now;
  // Each channel found by its name, read at its declared offset (FLOAT32), as rviz2 reads it.
  int off[3] = {-1, -1, -1};
  const char* names[3] = {"dx", "dy", "dz"};
  for (uint32_t i = 0; i < c.fields._length; ++i) {
    for (int a = 0; a < 3; ++a) {
      const auto& pf = c.fields._buffer[i];
      if (pf.name != nullptr && std::string(pf.name) == names[a] && pf.datatype == 7)
        off[a] = static_cast<int>(pf.offset);
    }
  }
  const uint64_t points = uint64_t{c.width} * c.height;
  if (off[0] < 0 || off[1] < 0 || off[2] < 0 || c.point_step < 12 ||
      points * c.point_step > c.data._length)
    return;
  json mag = json::array();
  double max_mm = 0;
  for (uint64_t k = 0; k < points; ++k) {
    float v[3];
    for (int a = 0; a < 3; ++a)
      std::memcpy(&v[a], c.data._buffer + k * c.point_step + static_cast<uint64_t>(off[a]), 4);
    const double mm =
        1e3 * std::sqrt(double(v[0]) * v[0] + double(v[1]) * v[1] + double(v[2]) * v[2]);
    if (std::isfinite(mm)) {
      mag.push_back(std::round(mm * 1e4) / 1e4);
      max_mm = std::max(max_mm, mm);
    } else {
      mag.push_back(nullptr);
    }
  }
  hub.publish("field",
              {{"rows", c.height}, {"cols", c.width}, {"magnitude_mm", mag}, {"max_mm", max_mm}},
              true);
}

void Console::Impl::onImage(int side, const sensor_msgs_msg_dds__CompressedImage_& im) {
  const auto [w, h] = jpegSize(im.data._buffer, im.data._length);
  if (w <= 0 || h <= 0) return;  // not a JPEG: nothing a browser could show
  uint64_t seq = 0;
  {
    const std::lock_guard lock(m);
    image[static_cast<size_t>(side)].assign(reinterpret_cast<const char*>(im.data._buffer),
                                            im.data._length);
    seq = ++image_seq[static_cast<size_t>(side)];
  }
  hub.publish("image",
              {{"side", side == 0 ? "left" : "right"},
               {"seq", seq},
               {"frame", stampSeconds(im.header.stamp)},
               {"width", w},
               {"height", h}},
              false);
}

void Console::Impl::link(Clock::time_point now) {
  std::optional<Clock::time_point> seen;
  {
    const std::lock_guard lock(m);
    seen = last_health;
  }
  const std::string where = fmt::format("DDS domain {}, namespace '{}'", o.domain, o.ros_namespace);
  const bool up = seen && seconds(*seen, now) < o.daemon_timeout_s;
  std::string text;
  if (!seen)
    text =
        fmt::format("no pulsetrackd seen on {} (is it running? same domain and namespace?)", where);
  else if (!up)
    text = fmt::format(
        "no pulsetrackd on {} for {:.0f} s: the daemon stopped or the DDS link is "
        "lost",
        where, seconds(*seen, now));
  else
    text = fmt::format("pulsetrackd on {}: health {:.1f} s ago", where, seconds(*seen, now));
  if (!read_denied.empty() && participant) {
    text += fmt::format("; this console's DDS Security permissions ({}) do not grant reading {}",
                        participant->securityState(), fmt::join(read_denied, ", "));
  }
  hub.publish("link",
              {{"daemon", up},
               {"dds", participant.has_value()},
               {"text", text},
               {"may_command", commander_error.empty()},
               {"command_error", commander_error},
               {"read_denied", read_denied}},
              true);
}

void Console::Impl::resolvePending(Clock::time_point now) {
  // Health counts the daemon's acceptances and refusals; a refusal names its request. The
  // console's commands are taken in order: each is "accepted" once the count passes what it was
  // when it was sent plus the ones before it still pending.
  std::vector<json> fates;
  {
    const std::lock_guard lock(m);
    for (auto it = pending.begin(); it != pending.end();) {
      const std::string tag = fmt::format("command {} ", it->request_id);
      std::string state;
      std::string text;
      if (refused > it->refused_base && last_error.rfind(tag, 0) == 0) {
        state = "refused";
        text = last_error;
      } else if (accepted > it->accepted_base) {
        state = "accepted";
        text = fmt::format("'{}' accepted by pulsetrackd", it->command);
      } else if (seconds(it->sent, now) > 5.0) {
        state = "unacknowledged";
        text = fmt::format("'{}' sent, but pulsetrackd's health did not count it within 5 s",
                           it->command);
      }
      if (state.empty()) {
        ++it;
        continue;
      }
      fates.push_back({{"request_id", it->request_id},
                       {"command", it->command},
                       {"state", state},
                       {"text", text}});
      if (state == "accepted" && !it->roi.is_null()) fates.push_back({{"roi", it->roi}});
      if (state != "accepted") {  // it took no acceptance: the ones after it wait for one less
        for (auto later = std::next(it); later != pending.end(); ++later)
          if (later->accepted_base > 0) --later->accepted_base;
      }
      it = pending.erase(it);
    }
  }
  for (const json& f : fates) {
    if (f.contains("roi"))
      hub.publish("roi", f["roi"], true);
    else
      hub.publish("command", f, false);
  }
}

void Console::Impl::ddsLoop() {
  const auto reader = [&](const std::string& topic, const dds_topic_descriptor_t* type,
                          dds::Profile p) -> std::optional<dds::Reader> {
    auto r = dds::Reader::create(*participant, topic.c_str(), type, p);
    if (r) return std::move(*r);
    if (dds::notAllowedBySecurity(r.error())) {
      // A role's limit, not a fault: the link says what this console cannot show.
      read_denied.push_back(topic);
      return std::nullopt;
    }
    hub.publish("link", {{"daemon", false}, {"dds", false}, {"text", r.error().message}}, true);
    return std::nullopt;
  };
  auto health =
      reader(topics.health, &pulsetrack_msgs_msg_dds__Health__desc, dds::Profile::kTransientLocal);
  auto features =
      reader(topics.features, &pulsetrack_msgs_msg_dds__Features__desc, dds::Profile::kSensorData);
  auto deformation = reader(topics.deformation, &pulsetrack_msgs_msg_dds__Deformation__desc,
                            dds::Profile::kSensorData);
  auto field =
      reader(topics.field, &sensor_msgs_msg_dds__PointCloud2__desc, dds::Profile::kSensorData);
  std::array<std::optional<dds::Reader>, 2> images = {
      reader(topics.image_left, &sensor_msgs_msg_dds__CompressedImage__desc,
             dds::Profile::kSensorData),
      reader(topics.image_right, &sensor_msgs_msg_dds__CompressedImage__desc,
             dds::Profile::kSensorData)};
  pulsetrack_msgs_msg_dds__Health_ h{};
  pulsetrack_msgs_msg_dds__Features_ f{};
  pulsetrack_msgs_msg_dds__Deformation_ d{};
  sensor_msgs_msg_dds__PointCloud2_ c{};
  sensor_msgs_msg_dds__CompressedImage_ im{};
  Clock::time_point features_sent{}, field_sent{}, last_link{}, last_spectrum{};
  while (running.load()) {
    bool any = false;
    if (health && health->takeOne(&h, std::chrono::milliseconds(0))) {
      onHealth(h);
      any = true;
    }
    for (int k = 0; k < 8 && features && features->takeOne(&f, std::chrono::milliseconds(0)); ++k) {
      onFeatures(f, features_sent);
      any = true;
    }
    for (int k = 0; k < 8 && deformation && deformation->takeOne(&d, std::chrono::milliseconds(0));
         ++k) {
      onDeformation(d);
      any = true;
    }
    if (field && field->takeOne(&c, std::chrono::milliseconds(0))) {
      onField(c, field_sent);
      any = true;
    }
    for (int s = 0; s < 2; ++s) {
      const std::optional<dds::Reader>& r = images[static_cast<size_t>(s)];
      if (r.has_value() && r->takeOne(&im, std::chrono::milliseconds(0))) {
        onImage(s, im);
        any = true;
      }
    }
    const Clock::time_point now = Clock::now();
    if (seconds(last_link, now) >= 1.0) {
      last_link = now;
      link(now);
    }
    if (seconds(last_spectrum, now) >= 2.0) {
      last_spectrum = now;
      spectrum();
    }
    resolvePending(now);
    if (!any) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&d, &pulsetrack_msgs_msg_dds__Deformation__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&c, &sensor_msgs_msg_dds__PointCloud2__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&im, &sensor_msgs_msg_dds__CompressedImage__desc, DDS_FREE_CONTENTS);
}

// ----------------------------------------------------------------------------------------------

std::optional<Session> Console::Impl::session(const httplib::Request& req) {
  const std::string token = cookieToken(req);
  if (token.empty()) return std::nullopt;
  const std::lock_guard lock(m);
  const auto it = sessions.find(token);
  if (it == sessions.end()) return std::nullopt;
  if (Clock::now() > it->second.expires) {
    sessions.erase(it);
    return std::nullopt;
  }
  return it->second;
}

namespace {

std::optional<cv::Rect> rectFrom(const json& v) {
  if (!v.is_array() || v.size() != 4) return std::nullopt;
  std::array<int, 4> r{};
  for (size_t i = 0; i < 4; ++i) {
    if (!v[i].is_number_integer()) return std::nullopt;
    const auto x = v[i].get<int64_t>();
    if (x < -100000 || x > 100000) return std::nullopt;
    r[i] = static_cast<int>(x);
  }
  return cv::Rect(r[0], r[1], r[2], r[3]);
}

std::string rectText(const cv::Rect& r) {
  return fmt::format("{},{} {}x{}", r.x, r.y, r.width, r.height);
}

}  // namespace

void Console::Impl::command(const httplib::Request& req, httplib::Response& res, const Session& s) {
  if (s.role != Role::kOperator) {
    return replyJson(
        res, 403,
        {{"error", fmt::format("user '{}' is a viewer: commands need an operator", s.user)}});
  }
  if (!commander) {
    return replyJson(res, 403,
                     {{"error", "this console may not command the appliance: " + commander_error}});
  }
  const json body = json::parse(req.body, nullptr, false);
  if (body.is_discarded() || !body.is_object() || !body.contains("command") ||
      !body["command"].is_string())
    return replyJson(res, 400, {{"error", "expected JSON {\"command\": \"...\"}"}});
  const std::string what = body["command"].get<std::string>();
  static const std::vector<std::string> kCommands = {"start",   "stop",         "redetect",
                                                     "set_roi", "record_start", "record_stop"};
  if (std::find(kCommands.begin(), kCommands.end(), what) == kCommands.end()) {
    return replyJson(res, 400,
                     {{"error", fmt::format("unknown command '{}' (start, stop, redetect, set_roi, "
                                            "record_start, record_stop)",
                                            what.substr(0, 32))}});
  }
  {
    const std::lock_guard lock(m);
    if (!last_health || seconds(*last_health, Clock::now()) > o.daemon_timeout_s) {
      return replyJson(
          res, 503,
          {{"error", fmt::format("no pulsetrackd on DDS domain {}, namespace '{}': not sent",
                                 o.domain, o.ros_namespace)}});
    }
  }
  pulsetrack_msgs_msg_dds__Command_ c{};
  std::string rig_id;  // empty: the rig of this namespace
  c.rig_id = rig_id.data();
  std::string cmd = what;
  c.command = cmd.data();
  json roi;
  if (what == "set_roi") {
    const auto left = body.contains("roi_left") ? rectFrom(body["roi_left"]) : std::nullopt;
    if (!left)
      return replyJson(res, 400, {{"error", "roi_left must be [x, y, width, height] (px)"}});
    const json& tol_j = body.contains("depth_tolerance_mm") ? body["depth_tolerance_mm"] : json();
    if (!tol_j.is_number())
      return replyJson(res, 400, {{"error", "depth_tolerance_mm must be a number"}});
    const double tol = tol_j.get<double>();
    double depth = 0;
    {
      const std::lock_guard lock(m);
      depth = median_depth_mm > 0 ? median_depth_mm : o.working_distance_mm;
    }
    const cv::Rect right = vision::TrackingSession::rightRoiFor(rig, *left, depth, tol);
    if (auto ok = vision::TrackingSession::checkRoi(rig, {*left, right}, tol); !ok)
      return replyJson(res, 400, {{"error", ok.error().message}});
    for (int i = 0; i < 4; ++i) {
      c.roi_left[i] =
          std::array{left->x, left->y, left->width, left->height}[static_cast<size_t>(i)];
      c.roi_right[i] =
          std::array{right.x, right.y, right.width, right.height}[static_cast<size_t>(i)];
    }
    c.depth_tolerance_m = tol * 1e-3;
    roi = {{"left", {left->x, left->y, left->width, left->height}},
           {"right", {right.x, right.y, right.width, right.height}},
           {"depth_tolerance_mm", tol}};
  }
  PendingCommand p;
  {
    const std::lock_guard lock(m);
    c.request_id = ++next_request;
    p = {c.request_id, what, accepted + pending.size(), refused, Clock::now(), roi};
  }
  if (auto ok = commander->write(&c); !ok)
    return replyJson(res, 503, {{"error", "not sent: " + ok.error().message}});
  {
    const std::lock_guard lock(m);
    pending.push_back(p);
  }
  const json sent = {{"request_id", c.request_id},
                     {"command", what},
                     {"state", "sent"},
                     {"text", fmt::format("'{}' sent by {}", what, s.user)}};
  hub.publish("command", sent, false);
  replyJson(res, 200, sent);
}

void Console::Impl::routes() {
  httplib::SSLServer& svr = *server;
  svr.new_task_queue = [] { return new httplib::ThreadPool(32); };
  // Every answer: no caching of the API, no sniffing, no framing, scripts only from here.
  svr.set_post_routing_handler([](const httplib::Request& req, httplib::Response& res) {
    res.set_header("X-Content-Type-Options", "nosniff");
    res.set_header("X-Frame-Options", "DENY");
    res.set_header("Referrer-Policy", "no-referrer");
    res.set_header("Strict-Transport-Security", "max-age=31536000");
    res.set_header("Content-Security-Policy",
                   "default-src 'self'; img-src 'self' blob: data:; style-src 'self' "
                   "'unsafe-inline'; script-src 'self'; connect-src 'self'; frame-ancestors "
                   "'none'");
    if (req.path.rfind("/api/", 0) == 0) res.set_header("Cache-Control", "no-store");
  });
  // Authentication before anything is served (the page's files included).
  svr.set_pre_routing_handler([this](const httplib::Request& req, httplib::Response& res) {
    const std::string& p = req.path;
    const bool open = p == "/login.html" || p == "/style.css" || p == "/login.js" ||
                      p == "/favicon.ico" || p.rfind("/vendor/", 0) == 0 ||
                      (p == "/api/login" && req.method == "POST");
    if (open || session(req)) return httplib::Server::HandlerResponse::Unhandled;
    if (p.rfind("/api/", 0) == 0) {
      replyJson(res, 401, {{"error", "not logged in"}});
    } else {
      res.status = 302;
      res.set_header("Location", "/login.html");
    }
    return httplib::Server::HandlerResponse::Handled;
  });
  svr.Post("/api/login", [this](const httplib::Request& req, httplib::Response& res) {
    const Clock::time_point now = Clock::now();
    {
      const std::lock_guard lock(m);
      while (!failed_logins.empty() && seconds(failed_logins.front(), now) > 60.0)
        failed_logins.pop_front();
      if (failed_logins.size() >= 5) {
        return replyJson(res, 429,
                         {{"error", "too many wrong passwords: wait a minute and try again"}});
      }
    }
    const std::string user = req.get_param_value("user");
    const std::string password = req.get_param_value("password");
    const std::optional<Role> role = users.verify(user, password);
    if (!role) {
      {
        const std::lock_guard lock(m);
        failed_logins.push_back(now);
      }
      return replyJson(res, 401, {{"error", "wrong user or password"}});
    }
    const std::string token = randomToken();
    if (token.empty()) return replyJson(res, 500, {{"error", "no random bytes for a session"}});
    {
      const std::lock_guard lock(m);
      const auto life = std::chrono::duration_cast<Clock::duration>(
          std::chrono::duration<double>(o.session_hours * 3600.0));
      sessions[token] = {user, *role, now + life};
    }
    res.set_header("Set-Cookie",
                   fmt::format("{}={}; Path=/; HttpOnly; Secure; SameSite=Strict", kCookie, token));
    replyJson(res, 200, {{"ok", true}, {"user", user}, {"role", toString(*role)}});
  });
  svr.Post("/api/logout", [this](const httplib::Request& req, httplib::Response& res) {
    {
      const std::lock_guard lock(m);
      sessions.erase(cookieToken(req));
    }
    res.set_header("Set-Cookie", fmt::format("{}=; Path=/; HttpOnly; Secure; SameSite=Strict; "
                                             "Max-Age=0",
                                             kCookie));
    replyJson(res, 200, {{"ok", true}});
  });
  svr.Get("/api/whoami", [this](const httplib::Request& req, httplib::Response& res) {
    const auto s = session(req);
    if (!s) return replyJson(res, 401, {{"error", "not logged in"}});
    replyJson(res, 200, {{"user", s->user}, {"role", toString(s->role)}});
  });
  svr.Get("/api/events", [this](const httplib::Request& req, httplib::Response& res) {
    const std::string token = cookieToken(req);
    auto cursor = std::make_shared<uint64_t>(0);
    auto first = std::make_shared<std::string>();
    *cursor = hub.subscribe(*first);
    res.set_header("Cache-Control", "no-store");
    res.set_chunked_content_provider(
        "text/event-stream", [this, cursor, first, token](size_t, httplib::DataSink& sink) {
          if (!first->empty()) {
            const std::string s = std::move(*first);
            first->clear();
            return sink.write(s.data(), s.size());
          }
          {  // a logout or an expiry ends the stream
            const std::lock_guard lock(m);
            const auto it = sessions.find(token);
            if (it == sessions.end() || Clock::now() > it->second.expires) return false;
          }
          std::string chunk = hub.next(*cursor, std::chrono::milliseconds(1000));
          if (!running.load()) return false;
          if (chunk.empty()) chunk = ": keep-alive\n\n";
          return sink.write(chunk.data(), chunk.size());
        });
  });
  svr.Get(R"(/api/image/(left|right))",
          [this](const httplib::Request& req, httplib::Response& res) {
            const size_t side = req.matches[1] == "left" ? 0 : 1;
            std::string jpeg;
            {
              const std::lock_guard lock(m);
              jpeg = image[side];
            }
            if (jpeg.empty()) return replyJson(res, 404, {{"error", "no preview yet"}});
            res.set_content(jpeg, "image/jpeg");
          });
  svr.Get("/api/roi_right", [this](const httplib::Request& req, httplib::Response& res) {
    cv::Rect left;
    double tol = 0;
    try {
      const std::string r = req.get_param_value("roi_left");
      size_t a = 0;
      std::array<int, 4> v{};
      for (size_t i = 0; i < 4; ++i) {
        const size_t b = r.find(',', a);
        size_t used = 0;
        const std::string part = r.substr(a, b == std::string::npos ? std::string::npos : b - a);
        v[i] = std::stoi(part, &used);
        if (used != part.size() || (i < 3 && b == std::string::npos) ||
            (i == 3 && b != std::string::npos))
          throw std::invalid_argument("roi");
        a = b + 1;
      }
      left = {v[0], v[1], v[2], v[3]};
      size_t used = 0;
      const std::string t = req.get_param_value("depth_tolerance_mm");
      tol = std::stod(t, &used);
      if (used != t.size()) throw std::invalid_argument("tol");
    } catch (const std::exception&) {
      return replyJson(res, 400, {{"error", "expected roi_left=x,y,w,h and depth_tolerance_mm=N"}});
    }
    double depth = 0;
    {
      const std::lock_guard lock(m);
      depth = median_depth_mm > 0 ? median_depth_mm : o.working_distance_mm;
    }
    const cv::Rect right = vision::TrackingSession::rightRoiFor(rig, left, depth, tol);
    if (auto ok = vision::TrackingSession::checkRoi(rig, {left, right}, tol); !ok)
      return replyJson(res, 400, {{"error", ok.error().message}});
    replyJson(res, 200,
              {{"right", {right.x, right.y, right.width, right.height}},
               {"depth_mm", depth},
               {"text", fmt::format("right {} for depths {:.0f} +- {:.0f} mm", rectText(right),
                                    depth, tol)}});
  });
  svr.Post("/api/command", [this](const httplib::Request& req, httplib::Response& res) {
    const auto s = session(req);
    if (!s) return replyJson(res, 401, {{"error", "not logged in"}});
    command(req, res, *s);
  });
  svr.Get("/", [](const httplib::Request&, httplib::Response& res) {
    res.status = 302;
    res.set_header("Location", "/index.html");
  });
  if (!svr.set_mount_point("/", o.www.string())) {
    // checked in create(); kept here so that a folder removed since is not served silently
  }
}

// ----------------------------------------------------------------------------------------------

vision::Result<std::unique_ptr<Console>> Console::create(const ConsoleOptions& options) {
  auto impl = std::make_unique<Impl>();
  impl->o = options;
  for (const auto& [what, p] :
       {std::pair{"TLS certificate", options.cert}, std::pair{"TLS private key", options.key}}) {
    if (p.empty()) return fail(fmt::format("the {} is needed (--cert, --key)", what));
    if (!std::filesystem::is_regular_file(p))
      return fail(fmt::format("{}: {} not found", p.string(), what));
  }
  if (!std::filesystem::is_regular_file(options.www / "index.html"))
    return fail(
        fmt::format("{}: not the console's page folder (no index.html)", options.www.string()));
  auto users = Credentials::load(options.users);
  if (!users) return std::unexpected(users.error());
  impl->users = std::move(*users);
  auto rig = vision::loadRig(options.rig);
  if (!rig) return std::unexpected(rig.error());
  impl->rig = *rig;
  auto topics = dds::Topics::forNamespace(options.ros_namespace);
  if (!topics) return std::unexpected(topics.error());
  impl->topics = *topics;
  auto p =
      dds::Participant::create(options.domain, options.security ? &*options.security : nullptr);
  if (!p) return std::unexpected(p.error());
  impl->participant.emplace(std::move(*p));
  // Commands as a permitted participant: under DDS Security a console whose permissions do not
  // grant publishing on .../command gets no writer; it still shows the appliance, and says why.
  auto w = dds::Writer::create(*impl->participant, impl->topics.command.c_str(),
                               &pulsetrack_msgs_msg_dds__Command__desc, dds::Profile::kCommand);
  if (w) {
    impl->commander.emplace(std::move(*w));
  } else if (dds::notAllowedBySecurity(w.error())) {
    impl->commander_error = dds::notPermitted(*impl->participant, impl->topics.command, true) +
                            " (commands need an enclave of the controller role: docs/security.md)";
  } else {
    impl->commander_error = w.error().message;
  }
  impl->server = std::make_unique<httplib::SSLServer>(options.cert.c_str(), options.key.c_str());
  if (!impl->server->is_valid()) {
    return fail(
        fmt::format("{}, {}: OpenSSL refused the certificate or its key (PEM, and the key "
                    "the certificate's?)",
                    options.cert.string(), options.key.string()));
  }
  impl->routes();
  if (options.port == 0) {
    impl->bound_port = impl->server->bind_to_any_port(options.host);
  } else {
    impl->bound_port = impl->server->bind_to_port(options.host, options.port) ? options.port : -1;
  }
  if (impl->bound_port <= 0) {
    return fail(fmt::format("cannot listen on {}:{} (in use? an address of this machine?)",
                            options.host, options.port));
  }
  impl->dds_thread = std::thread([raw = impl.get()] { raw->ddsLoop(); });
  return std::unique_ptr<Console>(new Console(std::move(impl)));
}

Console::Console(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

Console::~Console() {
  stop();
  if (impl_->dds_thread.joinable()) impl_->dds_thread.join();
}

int Console::port() const { return impl_->bound_port; }

void Console::run() { impl_->server->listen_after_bind(); }

void Console::stop() {
  impl_->running.store(false);
  impl_->hub.stop();
  impl_->server->stop();
}

std::string Console::banner() const {
  const std::optional<dds::Participant>& p = impl_->participant;
  const std::string dds = p.has_value() ? p->securityState() : std::string("no DDS");
  return fmt::format("https://{}:{}/ ({} users; DDS domain {}, namespace '{}', {}; {})",
                     impl_->o.host, impl_->bound_port, impl_->users.users().size(), impl_->o.domain,
                     impl_->o.ros_namespace, dds,
                     impl_->commander_error.empty() ? "may command"
                                                    : "may NOT command: " + impl_->commander_error);
}

}  // namespace pulsetrack::console
