// The OpenIGTLink bridge: DDS in (one thread), OpenIGTLink out (a thread per client, each with
// a bounded queue). Messages are encoded once, by the library's own classes, and shared by the
// clients' queues; a socket is only ever written by its client's thread, without blocking.

#include "pulsetrack/igtl/bridge.hpp"

#include <arpa/inet.h>
#include <fcntl.h>
#include <fmt/format.h>
#include <igtlImageMessage.h>
#include <igtlMessageHeader.h>
#include <igtlPointMessage.h>
#include <igtlPolyDataMessage.h>
#include <igtlStatusMessage.h>
#include <igtlTimeStamp.h>
#include <igtlTransformMessage.h>
#include <igtl_header.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <Eigen/Dense>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <list>
#include <map>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <thread>

#include "pulsetrack/dds/dds.hpp"

namespace pulsetrack::igtl {

namespace {

using Clock = std::chrono::steady_clock;
using Bytes = std::vector<uint8_t>;
using Message = std::shared_ptr<const Bytes>;

double seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

// The packed bytes of a library message (header and body, CRC set by Pack()).
Message packed(::igtl::MessageBase* m) {
  m->Pack();
  const auto* p = static_cast<const uint8_t*>(m->GetPackPointer());
  return std::make_shared<const Bytes>(p, p + m->GetPackSize());
}

void stampOf(::igtl::MessageBase* m, const builtin_interfaces_msg_dds__Time_& t) {
  ::igtl::TimeStamp::Pointer ts = ::igtl::TimeStamp::New();
  ts->SetTime(static_cast<igtlUint32>(t.sec), t.nanosec);
  m->SetTimeStamp(ts);
}

Message transformMessage(const std::string& name, const Eigen::Isometry3d& t_mm,
                         const builtin_interfaces_msg_dds__Time_* stamp) {
  ::igtl::TransformMessage::Pointer m = ::igtl::TransformMessage::New();
  m->SetDeviceName(name.c_str());
  ::igtl::Matrix4x4 mat;
  const Eigen::Matrix4d& a = t_mm.matrix();
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) mat[r][c] = static_cast<float>(a(r, c));
  m->SetMatrix(mat);
  if (stamp != nullptr) stampOf(m.GetPointer(), *stamp);
  return packed(m.GetPointer());
}

const char* statusGroup(uint8_t status) {
  switch (status) {
    case 0:
      return "ok";
    case 1:
      return "occluded";
    case 2:
      return "lost";
    case 3:
      return "outlier_epipolar";
    case 4:
      return "outlier_surface";
    case 5:
      return "outlier_triangulation";
    default:
      return "unknown";
  }
}

std::array<uint8_t, 4> statusColour(uint8_t status) {
  switch (status) {
    case 0:
      return {0, 200, 0, 255};  // ok: green
    case 1:
      return {255, 200, 0, 255};  // occluded: amber
    case 2:
      return {128, 128, 128, 255};  // lost: grey
    default:
      return {230, 0, 0, 255};  // an outlier: red
  }
}

// A client: its socket, its queue, its thread. The queue is the only thing the DDS thread
// touches (a lock held for a push); the socket is the client thread's alone.
struct Client {
  int fd = -1;
  int wake = -1;  // eventfd: the DDS thread says "more in the queue"
  std::string peer;
  std::mutex m;
  std::deque<Message> queue;
  std::atomic<uint64_t> sent{0}, dropped{0};
  std::atomic<bool> done{false};
  std::thread thread;
  ~Client() {
    if (fd >= 0) close(fd);
    if (wake >= 0) close(wake);
  }
};

}  // namespace

struct Bridge::Impl {
  BridgeOptions o;
  dds::Topics topics;
  std::optional<dds::Participant> participant;
  int listen_fd = -1;
  int bound_port = 0;
  std::atomic<bool> running{true};
  std::mutex clients_m;
  std::list<std::shared_ptr<Client>> clients;
  // The newest message of each type (GET_<TYPE> answers; STATUS and CameraToTracker greet).
  std::mutex latest_m;
  std::map<std::string, Message> latest;
  Clock::time_point last_health = Clock::now();
  bool health_timed_out = false;

  [[nodiscard]] std::string frame() const { return o.camera_to_tracker ? "Tracker" : "Camera"; }
  // mm in the output frame, from m in the camera's.
  [[nodiscard]] Eigen::Vector3d point(double x, double y, double z) const {
    const Eigen::Vector3d mm(x * 1e3, y * 1e3, z * 1e3);
    return o.camera_to_tracker ? Eigen::Vector3d(*o.camera_to_tracker * mm) : mm;
  }
  [[nodiscard]] Eigen::Vector3d vector(double x, double y, double z) const {
    const Eigen::Vector3d mm(x * 1e3, y * 1e3, z * 1e3);
    return o.camera_to_tracker ? Eigen::Vector3d(o.camera_to_tracker->linear() * mm) : mm;
  }

  void broadcast(const std::string& type, const Message& msg) {
    {
      const std::lock_guard lock(latest_m);
      latest[type] = msg;
    }
    const std::lock_guard lock(clients_m);
    for (const auto& c : clients) push(*c, msg);
  }
  void push(Client& c, const Message& msg) const {
    {
      const std::lock_guard lock(c.m);
      if (c.queue.size() >= static_cast<size_t>(o.queue_messages)) {
        c.queue.pop_front();
        c.dropped.fetch_add(1);
      }
      c.queue.push_back(msg);
    }
    const uint64_t one = 1;
    (void)!write(c.wake, &one, sizeof one);
  }

  void onFeatures(const pulsetrack_msgs_msg_dds__Features_& f);
  void onDeformation(const pulsetrack_msgs_msg_dds__Deformation_& d);
  void onHealth(const pulsetrack_msgs_msg_dds__Health_& h);
  void healthTimeOut();
  void onField(const sensor_msgs_msg_dds__PointCloud2_& c);
  void onImage(const sensor_msgs_msg_dds__CompressedImage_& im);
  void ddsLoop();
  void acceptLoop();
  void serve(const std::shared_ptr<Client>& c);
  bool answer(Client& c, const std::string& type);
  void reap(bool all);
};

void Bridge::Impl::onFeatures(const pulsetrack_msgs_msg_dds__Features_& f) {
  ::igtl::PointMessage::Pointer m = ::igtl::PointMessage::New();
  m->SetDeviceName("Features");
  stampOf(m.GetPointer(), f.header.stamp);
  std::vector<Eigen::Vector3d> from, to;
  for (uint32_t i = 0; i < f.features._length; ++i) {
    const auto& ft = f.features._buffer[i];
    ::igtl::PointElement::Pointer e = ::igtl::PointElement::New();
    e->SetName(fmt::format("F{}", ft.id).c_str());
    e->SetGroupName(statusGroup(ft.status));
    std::array<uint8_t, 4> rgba = statusColour(ft.status);
    e->SetRGBA(rgba.data());
    const Eigen::Vector3d p = point(ft.position.x, ft.position.y, ft.position.z);
    e->SetPosition(static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z()));
    e->SetRadius(1.0F);
    e->SetOwner("");
    m->AddPointElement(e);
    if (ft.status == 0) {
      to.push_back(p);
      from.push_back(point(ft.position.x - ft.displacement.x, ft.position.y - ft.displacement.y,
                           ft.position.z - ft.displacement.z));
    }
  }
  broadcast("POINT", packed(m.GetPointer()));
  // The surface's rigid motion: the rotation and translation that take the ok features'
  // reference positions to where they are (least squares, Umeyama), in the output frame.
  if (from.size() >= 3) {
    Eigen::Matrix3Xd a(3, static_cast<Eigen::Index>(from.size()));
    Eigen::Matrix3Xd b(3, static_cast<Eigen::Index>(to.size()));
    for (size_t k = 0; k < from.size(); ++k) {
      a.col(static_cast<Eigen::Index>(k)) = from[k];
      b.col(static_cast<Eigen::Index>(k)) = to[k];
    }
    Eigen::Isometry3d t;
    t.matrix() = Eigen::umeyama(a, b, false);
    broadcast("TRANSFORM:BrainShift",
              transformMessage("BrainShiftTo" + frame(), t, &f.header.stamp));
  }
}

void Bridge::Impl::onDeformation(const pulsetrack_msgs_msg_dds__Deformation_& d) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.translation() = vector(d.displacement.x, d.displacement.y, d.displacement.z);
  broadcast("TRANSFORM:MeanDisplacement",
            transformMessage("MeanDispTo" + frame(), t, &d.header.stamp));
}

void Bridge::Impl::onHealth(const pulsetrack_msgs_msg_dds__Health_& h) {
  last_health = Clock::now();
  health_timed_out = false;
  ::igtl::StatusMessage::Pointer m = ::igtl::StatusMessage::New();
  m->SetDeviceName("Health");
  stampOf(m.GetPointer(), h.header.stamp);
  // ok: OK; starting: not ready; degraded: an error (recoverable); fault: panic (the figures
  // must not be used). The sub-code is the daemon's state (Health.msg's STATE_*).
  static constexpr std::array<int, 4> kCodes = {
      ::igtl::StatusMessage::STATUS_NOT_READY, ::igtl::StatusMessage::STATUS_OK,
      ::igtl::StatusMessage::STATUS_UNKNOWN_ERROR, ::igtl::StatusMessage::STATUS_PANICK_MODE};
  static constexpr std::array<const char*, 4> kNames = {"starting", "ok", "degraded", "fault"};
  const size_t s = std::min<size_t>(h.state, 3);
  m->SetCode(kCodes[s]);
  m->SetSubCode(h.state);
  m->SetErrorName(kNames[s]);
  std::string text = h.state_text != nullptr ? h.state_text : "";
  if (h.last_error != nullptr && *h.last_error != '\0') text += fmt::format(" ({})", h.last_error);
  m->SetStatusString(text.c_str());
  broadcast("STATUS", packed(m.GetPointer()));
  if (o.camera_to_tracker)  // the registration, again for clients that came late or missed it
    broadcast("TRANSFORM:CameraToTracker",
              transformMessage("CameraToTracker", *o.camera_to_tracker, nullptr));
}

void Bridge::Impl::healthTimeOut() {
  if (health_timed_out || seconds(last_health, Clock::now()) < o.health_timeout_s) return;
  health_timed_out = true;
  ::igtl::StatusMessage::Pointer m = ::igtl::StatusMessage::New();
  m->SetDeviceName("Health");
  m->SetCode(::igtl::StatusMessage::STATUS_TIME_OUT);
  m->SetSubCode(0);
  m->SetErrorName("no daemon");
  m->SetStatusString(
      fmt::format("no health from the daemon for {:.0f} s ({})", o.health_timeout_s, topics.health)
          .c_str());
  broadcast("STATUS", packed(m.GetPointer()));
  fmt::print(stderr, "igtl: no health from the daemon on {} for {:.0f} s\n", topics.health,
             o.health_timeout_s);
}

void Bridge::Impl::onField(const sensor_msgs_msg_dds__PointCloud2_& c) {
  // Each channel by its name, read at its declared offset (FLOAT32), as rviz2 reads it.
  const std::array<const char*, 7> names = {"x", "y", "z", "dx", "dy", "dz", "confidence"};
  std::array<int, 7> off{};
  off.fill(-1);
  for (uint32_t i = 0; i < c.fields._length; ++i) {
    const auto& pf = c.fields._buffer[i];
    for (size_t a = 0; a < names.size(); ++a)
      if (pf.name != nullptr && std::strcmp(pf.name, names[a]) == 0 && pf.datatype == 7)
        off[a] = static_cast<int>(pf.offset);
  }
  const uint64_t n = uint64_t{c.width} * c.height;
  if (std::ranges::any_of(off, [](int v) { return v < 0; }) || c.width < 2 ||
      n * c.point_step > c.data._length)
    return;
  const auto at = [&](uint64_t k, size_t a) {
    float v = 0;
    std::memcpy(&v, c.data._buffer + k * c.point_step + static_cast<uint64_t>(off[a]), 4);
    return static_cast<double>(v);
  };
  // The valid grid points, numbered in order; triangles between valid neighbours.
  std::vector<int> index(n, -1);
  ::igtl::PolyDataPointArray::Pointer points = ::igtl::PolyDataPointArray::New();
  std::vector<float> disp, conf;
  int valid = 0;
  for (uint64_t k = 0; k < n; ++k) {
    if (!std::isfinite(at(k, 0)) || !(at(k, 6) > 0.0)) continue;
    index[k] = valid++;
  }
  points->SetNumberOfPoints(valid);
  for (uint64_t k = 0; k < n; ++k) {
    if (index[k] < 0) continue;
    const Eigen::Vector3d p = point(at(k, 0), at(k, 1), at(k, 2));
    const Eigen::Vector3d d = vector(at(k, 3), at(k, 4), at(k, 5));
    points->SetPoint(static_cast<unsigned>(index[k]), static_cast<float>(p.x()),
                     static_cast<float>(p.y()), static_cast<float>(p.z()));
    for (int a = 0; a < 3; ++a) disp.push_back(static_cast<float>(d[a]));
    conf.push_back(static_cast<float>(at(k, 6)));
  }
  ::igtl::PolyDataCellArray::Pointer polygons = ::igtl::PolyDataCellArray::New();
  const uint64_t cols = c.width;
  for (uint64_t r = 0; r + 1 < c.height; ++r) {
    for (uint64_t q = 0; q + 1 < cols; ++q) {
      const int a = index[r * cols + q], b = index[r * cols + q + 1];
      const int e = index[(r + 1) * cols + q], g = index[(r + 1) * cols + q + 1];
      std::array<igtlUint32, 3> t1 = {igtlUint32(a), igtlUint32(b), igtlUint32(g)};
      std::array<igtlUint32, 3> t2 = {igtlUint32(a), igtlUint32(g), igtlUint32(e)};
      if (a >= 0 && b >= 0 && g >= 0) polygons->AddCell(3, t1.data());
      if (a >= 0 && g >= 0 && e >= 0) polygons->AddCell(3, t2.data());
    }
  }
  ::igtl::PolyDataMessage::Pointer m = ::igtl::PolyDataMessage::New();
  m->SetDeviceName("DenseField");
  stampOf(m.GetPointer(), c.header.stamp);
  m->SetPoints(points);
  m->SetPolygons(polygons);
  ::igtl::PolyDataAttribute::Pointer d = ::igtl::PolyDataAttribute::New();
  d->SetType(::igtl::PolyDataAttribute::POINT_VECTOR);
  d->SetName("Displacement");
  d->SetSize(static_cast<igtlUint32>(valid));
  if (valid > 0) d->SetData(disp.data());
  ::igtl::PolyDataAttribute::Pointer s = ::igtl::PolyDataAttribute::New();
  s->SetType(::igtl::PolyDataAttribute::POINT_SCALAR);
  s->SetName("Confidence");
  s->SetSize(static_cast<igtlUint32>(valid));
  if (valid > 0) s->SetData(conf.data());
  m->AddAttribute(d);
  m->AddAttribute(s);
  broadcast("POLYDATA", packed(m.GetPointer()));
}

void Bridge::Impl::onImage(const sensor_msgs_msg_dds__CompressedImage_& im) {
  if (im.data._length == 0) return;
  const cv::Mat buf(1, static_cast<int>(im.data._length), CV_8UC1, im.data._buffer);
  const cv::Mat grey = cv::imdecode(buf, cv::IMREAD_GRAYSCALE);
  if (grey.empty()) return;  // not an image OpenCV reads: nothing to send
  ::igtl::ImageMessage::Pointer m = ::igtl::ImageMessage::New();
  m->SetDeviceName("LeftCamera");
  stampOf(m.GetPointer(), im.header.stamp);
  m->SetDimensions(grey.cols, grey.rows, 1);
  m->SetSpacing(1.0F, 1.0F, 1.0F);
  m->SetScalarTypeToUint8();
  m->SetEndian(::igtl::ImageMessage::ENDIAN_BIG);
  m->SetSubVolume(grey.cols, grey.rows, 1, 0, 0, 0);
  m->AllocateScalars();
  auto* dst = static_cast<uint8_t*>(m->GetScalarPointer());
  for (int r = 0; r < grey.rows; ++r)
    std::memcpy(dst + static_cast<size_t>(r) * static_cast<size_t>(grey.cols), grey.ptr(r),
                static_cast<size_t>(grey.cols));
  broadcast("IMAGE", packed(m.GetPointer()));
}

void Bridge::Impl::ddsLoop() {
  const auto reader = [&](const std::string& topic, const dds_topic_descriptor_t* type,
                          dds::Profile p) -> std::optional<dds::Reader> {
    auto r = dds::Reader::create(*participant, topic.c_str(), type, p);
    if (r) return std::move(*r);
    if (dds::notAllowedBySecurity(r.error())) {
      // A role's limit (a monitor reads health only): its messages are not served.
      fmt::print(stderr, "igtl: {}: its messages are not served\n",
                 dds::notPermitted(*participant, topic, false));
    } else {
      fmt::print(stderr, "igtl: {}: {}\n", topic, r.error().message);
    }
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
  auto image = reader(topics.image_left, &sensor_msgs_msg_dds__CompressedImage__desc,
                      dds::Profile::kSensorData);
  pulsetrack_msgs_msg_dds__Health_ h{};
  pulsetrack_msgs_msg_dds__Features_ f{};
  pulsetrack_msgs_msg_dds__Deformation_ d{};
  sensor_msgs_msg_dds__PointCloud2_ c{};
  sensor_msgs_msg_dds__CompressedImage_ im{};
  Clock::time_point field_sent{}, image_sent{}, last_reap{};
  while (running.load()) {
    bool any = false;
    const Clock::time_point now = Clock::now();
    if (health && health->takeOne(&h, std::chrono::milliseconds(0))) {
      onHealth(h);
      any = true;
    }
    while (features && features->takeOne(&f, std::chrono::milliseconds(0))) {
      onFeatures(f);
      any = true;
    }
    while (deformation && deformation->takeOne(&d, std::chrono::milliseconds(0))) {
      onDeformation(d);
      any = true;
    }
    while (field && field->takeOne(&c, std::chrono::milliseconds(0))) {
      any = true;
      if (o.field_rate_hz > 0 && seconds(field_sent, now) >= 1.0 / o.field_rate_hz) {
        field_sent = now;
        onField(c);
      }
    }
    while (image && image->takeOne(&im, std::chrono::milliseconds(0))) {
      any = true;
      if (o.image_rate_hz > 0 && seconds(image_sent, now) >= 0.95 / o.image_rate_hz) {
        image_sent = now;
        onImage(im);
      }
    }
    healthTimeOut();
    if (seconds(last_reap, now) >= 0.2) {
      last_reap = now;
      reap(false);
    }
    // Idle: wait on the features (the fastest stream) rather than spin.
    if (!any && features) {
      if (features->takeOne(&f, std::chrono::milliseconds(5))) onFeatures(f);
    } else if (!any) {
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
  }
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&d, &pulsetrack_msgs_msg_dds__Deformation__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&c, &sensor_msgs_msg_dds__PointCloud2__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&im, &sensor_msgs_msg_dds__CompressedImage__desc, DDS_FREE_CONTENTS);
}

// Clients whose thread ended: joined, said, forgotten.
void Bridge::Impl::reap(bool all) {
  std::vector<std::shared_ptr<Client>> gone;
  {
    const std::lock_guard lock(clients_m);
    for (auto it = clients.begin(); it != clients.end();) {
      if (all || (*it)->done.load()) {
        gone.push_back(*it);
        it = clients.erase(it);
      } else {
        ++it;
      }
    }
  }
  for (const auto& c : gone) {
    if (c->thread.joinable()) c->thread.join();
  }
}

void Bridge::Impl::acceptLoop() {
  while (running.load()) {
    pollfd p{listen_fd, POLLIN, 0};
    if (poll(&p, 1, 200) <= 0) continue;
    sockaddr_in from{};
    socklen_t len = sizeof from;
    const int fd =
        accept4(listen_fd, reinterpret_cast<sockaddr*>(&from), &len, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) continue;
    char ip[INET_ADDRSTRLEN] = "?";
    inet_ntop(AF_INET, &from.sin_addr, ip, sizeof ip);
    const std::string peer = fmt::format("{}:{}", ip, ntohs(from.sin_port));
    size_t now_clients = 0;
    {
      const std::lock_guard lock(clients_m);
      now_clients = clients.size();
    }
    if (now_clients >= static_cast<size_t>(o.max_clients)) {
      fmt::print(stderr, "igtl: client {} refused: {} clients already (--max-clients)\n", peer,
                 now_clients);
      close(fd);
      continue;
    }
    const int one = 1;
    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    auto c = std::make_shared<Client>();
    c->fd = fd;
    c->wake = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    c->peer = peer;
    // A newcomer is greeted with the health and the registration.
    {
      const std::lock_guard lock(latest_m);
      for (const char* k : {"STATUS", "TRANSFORM:CameraToTracker"}) {
        const auto it = latest.find(k);
        if (it != latest.end()) c->queue.push_back(it->second);
      }
    }
    {
      // Started and listed under the lock: reap() never sees a client whose thread is not set.
      const std::lock_guard lock(clients_m);
      c->thread = std::thread([this, c] { serve(c); });
      clients.push_back(c);
      now_clients = clients.size();
    }
    fmt::print("igtl: client {} connected ({} now)\n", peer, now_clients);
    std::fflush(stdout);
  }
}

// GET_<TYPE>: the newest message of that type (every one of it: both TRANSFORMs), or a STATUS
// "not found" when there is none yet.
bool Bridge::Impl::answer(Client& c, const std::string& type) {
  std::vector<Message> replies;
  {
    const std::lock_guard lock(latest_m);
    for (const auto& [k, v] : latest)
      if (k == type || k.rfind(type + ":", 0) == 0) replies.push_back(v);
  }
  if (replies.empty()) {
    ::igtl::StatusMessage::Pointer m = ::igtl::StatusMessage::New();
    m->SetDeviceName("Health");
    m->SetCode(::igtl::StatusMessage::STATUS_NOT_FOUND);
    m->SetErrorName("none yet");
    m->SetStatusString(fmt::format("no {} from pulsetrack yet", type).c_str());
    replies.push_back(packed(m.GetPointer()));
  }
  for (const Message& r : replies) push(c, r);
  return true;
}

void Bridge::Impl::serve(const std::shared_ptr<Client>& cp) {
  Client& c = *cp;
  Message current;
  size_t offset = 0;
  Clock::time_point progress = Clock::now();
  Bytes in;  // what the client sent, not yet a whole message
  std::string why = "disconnected";
  constexpr size_t kHeader = IGTL_HEADER_SIZE;
  while (running.load()) {
    if (!current) {
      const std::lock_guard lock(c.m);
      if (!c.queue.empty()) {
        current = std::move(c.queue.front());
        c.queue.pop_front();
        offset = 0;
        progress = Clock::now();
      }
    }
    std::array<pollfd, 2> p = {
        pollfd{c.fd, static_cast<short>(POLLIN | (current ? POLLOUT : 0)), 0},
        pollfd{c.wake, POLLIN, 0}};
    if (poll(p.data(), p.size(), 100) < 0) continue;
    if ((p[1].revents & POLLIN) != 0) {
      uint64_t v = 0;
      (void)!read(c.wake, &v, sizeof v);
    }
    if ((p[0].revents & (POLLERR | POLLHUP)) != 0 && (p[0].revents & POLLIN) == 0) break;
    if ((p[0].revents & POLLIN) != 0) {
      std::array<uint8_t, 4096> buf{};
      const ssize_t n = recv(c.fd, buf.data(), buf.size(), 0);
      if (n == 0) break;  // the client closed
      if (n < 0 && errno != EAGAIN && errno != EINTR) break;
      if (n > 0) in.insert(in.end(), buf.begin(), buf.begin() + n);
      // Whole messages: a GET_<TYPE> is answered, anything else read past.
      while (in.size() >= kHeader) {
        ::igtl::MessageHeader::Pointer h = ::igtl::MessageHeader::New();
        h->InitPack();
        std::memcpy(h->GetPackPointer(), in.data(), kHeader);
        h->Unpack();
        const auto body = static_cast<size_t>(h->GetBodySizeToRead());
        if (body > (16U << 20)) {
          why = fmt::format("protocol: a message of {} bytes", body);
          break;
        }
        if (in.size() < kHeader + body) break;
        const std::string type = h->GetDeviceType();
        in.erase(in.begin(), in.begin() + static_cast<std::ptrdiff_t>(kHeader + body));
        if (type.rfind("GET_", 0) == 0) answer(c, type.substr(4));
      }
      if (why != "disconnected") break;
    }
    if (current && (p[0].revents & POLLOUT) != 0) {
      const ssize_t n = send(c.fd, current->data() + offset, current->size() - offset,
                             MSG_NOSIGNAL | MSG_DONTWAIT);
      if (n < 0 && errno != EAGAIN && errno != EINTR) break;
      if (n > 0) {
        offset += static_cast<size_t>(n);
        progress = Clock::now();
        if (offset == current->size()) {
          current.reset();
          c.sent.fetch_add(1);
        }
      }
    }
    if (current && seconds(progress, Clock::now()) > o.stall_timeout_s) {
      why = fmt::format("stalled: took no byte for {:.1f} s", o.stall_timeout_s);
      break;
    }
  }
  size_t left = 0;
  {
    const std::lock_guard lock(clients_m);
    left = clients.empty() ? 0 : clients.size() - 1;
  }
  fmt::print("igtl: client {} gone ({}): {} messages sent, {} dropped ({} left)\n", c.peer, why,
             c.sent.load(), c.dropped.load(), left);
  std::fflush(stdout);
  shutdown(c.fd, SHUT_RDWR);
  c.done.store(true);
}

Bridge::Bridge(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

Bridge::~Bridge() {
  stop();
  if (impl_->listen_fd >= 0) close(impl_->listen_fd);
}

int Bridge::port() const { return impl_->bound_port; }
std::string Bridge::frameName() const { return impl_->frame(); }
void Bridge::stop() { impl_->running.store(false); }

void Bridge::run() {
  Impl& i = *impl_;
  std::thread accept([&i] { i.acceptLoop(); });
  i.ddsLoop();
  accept.join();
  i.reap(true);
}

Result<std::unique_ptr<Bridge>> Bridge::create(const BridgeOptions& options) {
  auto impl = std::make_unique<Impl>();
  impl->o = options;
  if (options.queue_messages < 1 || options.max_clients < 1 || options.stall_timeout_s <= 0)
    return vision::fail("igtl: queue, clients and stall time-out must be positive");
  auto topics = dds::Topics::forNamespace(options.ros_namespace);
  if (!topics) return std::unexpected(topics.error());
  impl->topics = *topics;
  auto p =
      dds::Participant::create(options.domain, options.security ? &*options.security : nullptr);
  if (!p) return std::unexpected(p.error());
  impl->participant.emplace(std::move(*p));
  in_addr addr{};
  if (inet_pton(AF_INET, options.host.c_str(), &addr) != 1)
    return vision::fail(fmt::format("igtl: --host {}: not an IPv4 address", options.host));
  const int fd = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return vision::fail(fmt::format("igtl: socket: {}", std::strerror(errno)));
  const int one = 1;
  setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr = addr;
  a.sin_port = htons(static_cast<uint16_t>(options.port));
  if (bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 || listen(fd, 8) != 0) {
    const int e = errno;
    close(fd);
    return vision::fail(fmt::format("igtl: cannot listen on {}:{}: {}", options.host, options.port,
                                    std::strerror(e)));
  }
  socklen_t len = sizeof a;
  getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len);
  impl->listen_fd = fd;
  impl->bound_port = ntohs(a.sin_port);
  return std::unique_ptr<Bridge>(new Bridge(std::move(impl)));
}

}  // namespace pulsetrack::igtl
