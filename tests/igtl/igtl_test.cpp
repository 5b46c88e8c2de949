// `pulsetrack igtl` as 3D Slicer meets it: OpenIGTLink clients nobody here wrote.
// - Debian's own example receiver (openigtlink-examples' Receiver/ReceiveClient.cxx, built from
//   the package's sources by this test's CMake) connects and decodes, CRC checked, the TRANSFORM,
//   POINT, IMAGE and STATUS messages (and reads past POLYDATA, which it does not know).
// - A client written here with the library's own API (igtl::ClientSocket and the message
//   classes; nothing of the bridge's code) decodes every type and checks the values: against the
//   daemon's DDS samples of the same stamp, against the registration file, and against the
//   simulator's truth (each ok feature on the true surface, in the tracker's frame).
// - A client that stalls is disconnected and costs the others nothing; a client that goes is
//   forgotten; a daemon that goes is said (STATUS time-out).

#include <arpa/inet.h>
#include <fcntl.h>
#include <fmt/format.h>
#include <gtest/gtest.h>
#include <igtlClientSocket.h>
#include <igtlImageMessage.h>
#include <igtlMessageHeader.h>
#include <igtlPointMessage.h>
#include <igtlPolyDataMessage.h>
#include <igtlStatusMessage.h>
#include <igtlTransformMessage.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <atomic>
#include <chrono>
#include <cmath>
#include <fstream>
#include <map>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <regex>
#include <sstream>
#include <thread>

#include "daemon/daemon_process.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"
#include "test_util.hpp"

extern char** environ;

namespace pulsetrack {
namespace {

using Clock = std::chrono::steady_clock;

// A program started with its output (stdout and stderr) in a file.
struct Program {
  pid_t pid = 0;
  std::filesystem::path log;
  Program(const std::vector<std::string>& args, std::filesystem::path out) : log(std::move(out)) {
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_addopen(&fa, 1, log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    posix_spawn_file_actions_adddup2(&fa, 1, 2);
    std::vector<std::string> a = args;
    std::vector<char*> argv;
    argv.reserve(a.size() + 1);
    for (auto& s : a) argv.push_back(s.data());
    argv.push_back(nullptr);
    EXPECT_EQ(posix_spawn(&pid, a[0].c_str(), &fa, nullptr, argv.data(), environ), 0) << a[0];
    posix_spawn_file_actions_destroy(&fa);
  }
  [[nodiscard]] std::string output() const {
    std::ifstream in(log);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
  }
  // Waits (bounded) until the output matches; the match's first group.
  std::string waitFor(const std::string& re, double timeout_s) const {
    const std::regex r(re);
    const auto t0 = Clock::now();
    while (std::chrono::duration<double>(Clock::now() - t0).count() < timeout_s) {
      std::smatch m;
      const std::string out = output();
      if (std::regex_search(out, m, r)) return m.size() > 1 ? m[1].str() : m[0].str();
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    return "";
  }
  int stop(int sig = SIGTERM) {
    if (pid <= 0) return -1;
    kill(pid, sig);
    int status = 0;
    waitpid(pid, &status, 0);
    pid = 0;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -WTERMSIG(status);
  }
  ~Program() { stop(SIGKILL); }
  Program(const Program&) = delete;
  Program& operator=(const Program&) = delete;
};

int64_t stampNs(const igtl::MessageBase* m) {
  igtl::TimeStamp::Pointer ts = igtl::TimeStamp::New();
  const_cast<igtl::MessageBase*>(m)->GetTimeStamp(ts);
  igtlUint32 s = 0, ns = 0;
  ts->GetTimeStamp(&s, &ns);
  return int64_t{s} * 1'000'000'000 + ns;
}

// OpenIGTLink's time stamp keeps a 32-bit fraction of a second: 0.23 ns steps.
int64_t dds(const builtin_interfaces_msg_dds__Time_& t) {
  return int64_t{t.sec} * 1'000'000'000 + t.nanosec;
}
bool sameStamp(int64_t a, int64_t b) { return std::llabs(a - b) <= 2; }

struct Point {
  std::string name, group;
  std::array<int, 4> rgba{};
  Eigen::Vector3d p;
};
struct Received {
  std::vector<std::pair<int64_t, std::vector<Point>>> points;
  std::map<std::string, std::vector<std::pair<int64_t, Eigen::Matrix4d>>> transforms;
  std::vector<std::pair<int64_t, cv::Mat>> images;
  struct Poly {
    int64_t t = 0;
    std::vector<Eigen::Vector3d> points;
    std::vector<std::array<uint32_t, 3>> triangles;
    std::vector<Eigen::Vector3d> displacement;
    std::vector<float> confidence;
  };
  std::vector<Poly> polys;
  struct Status {
    int code = 0;
    int64_t subcode = 0;
    std::string name, text;
  };
  std::vector<Status> statuses;
  std::vector<Clock::time_point> point_times;
  int crc_failures = 0;
};

// The library's client, as an application would write it (the examples' pattern).
class Client {
 public:
  explicit Client(int port) {
    socket_ = igtl::ClientSocket::New();
    connected_ = socket_->ConnectToServer("127.0.0.1", port) == 0;
    if (connected_) thread_ = std::thread([this] { loop(); });
  }
  ~Client() { close(); }
  Client(const Client&) = delete;
  Client& operator=(const Client&) = delete;
  [[nodiscard]] bool connected() const { return connected_; }
  void close() {
    stop_ = true;
    if (thread_.joinable()) {
      socket_->CloseSocket();
      thread_.join();
    }
  }
  template <class F>
  auto with(F f) {
    const std::lock_guard lock(m_);
    return f(got_);
  }
  void send(igtl::MessageBase* msg) {
    msg->Pack();
    socket_->Send(msg->GetPackPointer(), msg->GetPackSize());
  }

 private:
  template <class M>
  typename M::Pointer body(const igtl::MessageHeader::Pointer& h) {
    typename M::Pointer m = M::New();
    m->SetMessageHeader(h);
    m->AllocatePack();
    socket_->Receive(m->GetPackBodyPointer(), m->GetPackBodySize());
    if ((m->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) == 0) {
      const std::lock_guard lock(m_);
      ++got_.crc_failures;
      return nullptr;
    }
    return m;
  }
  void loop() {
    socket_->SetReceiveTimeout(500);
    igtl::MessageHeader::Pointer h = igtl::MessageHeader::New();
    while (!stop_) {
      h->InitPack();
      const int r = socket_->Receive(h->GetPackPointer(), h->GetPackSize());
      if (r == 0 && stop_) break;
      if (r != h->GetPackSize()) {
        if (r == 0 && !socket_->GetConnected()) break;
        continue;  // the receive time-out: ask again
      }
      socket_->SetReceiveTimeout(20000);  // a body follows its header
      h->Unpack();
      const std::string type = h->GetDeviceType();
      if (type == "POINT") {
        if (auto m = body<igtl::PointMessage>(h); m) {
          std::vector<Point> pts;
          for (int i = 0; i < m->GetNumberOfPointElement(); ++i) {
            igtl::PointElement::Pointer e;
            m->GetPointElement(i, e);
            Point p;
            p.name = e->GetName();
            p.group = e->GetGroupName();
            igtlUint8 rgba[4];
            e->GetRGBA(rgba);
            for (int k = 0; k < 4; ++k) p.rgba[static_cast<size_t>(k)] = rgba[k];
            igtlFloat32 pos[3];
            e->GetPosition(pos);
            p.p = Eigen::Vector3d(pos[0], pos[1], pos[2]);
            pts.push_back(p);
          }
          const std::lock_guard lock(m_);
          got_.points.emplace_back(stampNs(m.GetPointer()), std::move(pts));
          got_.point_times.push_back(Clock::now());
        }
      } else if (type == "TRANSFORM") {
        if (auto m = body<igtl::TransformMessage>(h); m) {
          igtl::Matrix4x4 mat;
          m->GetMatrix(mat);
          Eigen::Matrix4d a;
          for (int r2 = 0; r2 < 4; ++r2)
            for (int c = 0; c < 4; ++c) a(r2, c) = mat[r2][c];
          const std::lock_guard lock(m_);
          got_.transforms[m->GetDeviceName()].emplace_back(stampNs(m.GetPointer()), a);
        }
      } else if (type == "IMAGE") {
        if (auto m = body<igtl::ImageMessage>(h); m) {
          int size[3];
          m->GetDimensions(size);
          EXPECT_EQ(m->GetScalarType(), igtl::ImageMessage::TYPE_UINT8);
          EXPECT_EQ(size[2], 1);
          EXPECT_STREQ(m->GetDeviceName(), "LeftCamera");
          cv::Mat img(size[1], size[0], CV_8UC1, m->GetScalarPointer());
          const std::lock_guard lock(m_);
          got_.images.emplace_back(stampNs(m.GetPointer()), img.clone());
        }
      } else if (type == "POLYDATA") {
        if (auto m = body<igtl::PolyDataMessage>(h); m) {
          Received::Poly p;
          p.t = stampNs(m.GetPointer());
          igtl::PolyDataPointArray::Pointer pts = m->GetPoints();
          for (int i = 0; pts.IsNotNull() && i < pts->GetNumberOfPoints(); ++i) {
            igtlFloat32 v[3];
            pts->GetPoint(static_cast<unsigned>(i), v);
            p.points.emplace_back(v[0], v[1], v[2]);
          }
          igtl::PolyDataCellArray::Pointer polys = m->GetPolygons();
          for (unsigned i = 0; polys.IsNotNull() && i < polys->GetNumberOfCells(); ++i) {
            std::list<igtlUint32> cell;
            polys->GetCell(i, cell);
            EXPECT_EQ(cell.size(), 3U);
            if (cell.size() == 3) {
              auto it = cell.begin();
              const uint32_t a = *it++, b = *it++, c = *it;
              p.triangles.push_back({a, b, c});
            }
          }
          for (int k = 0; k < m->GetNumberOfAttributes(); ++k) {
            igtl::PolyDataAttribute* at = m->GetAttribute(static_cast<unsigned>(k));
            std::vector<igtlFloat32> v(at->GetSize() * at->GetNumberOfComponents());
            if (!v.empty()) at->GetData(v.data());
            if (std::string(at->GetName()) == "Displacement" &&
                at->GetType() == igtl::PolyDataAttribute::POINT_VECTOR) {
              for (size_t i = 0; i + 2 < v.size(); i += 3)
                p.displacement.emplace_back(v[i], v[i + 1], v[i + 2]);
            }
            if (std::string(at->GetName()) == "Confidence") p.confidence = {v.begin(), v.end()};
          }
          const std::lock_guard lock(m_);
          got_.polys.push_back(std::move(p));
        }
      } else if (type == "STATUS") {
        if (auto m = body<igtl::StatusMessage>(h); m) {
          const std::lock_guard lock(m_);
          got_.statuses.push_back(
              {m->GetCode(), m->GetSubCode(), m->GetErrorName(), m->GetStatusString()});
        }
      } else {
        ADD_FAILURE() << "a message type the bridge does not send: " << type;
        socket_->Skip(h->GetBodySizeToRead(), 0);
      }
      socket_->SetReceiveTimeout(500);
    }
  }
  igtl::ClientSocket::Pointer socket_;
  bool connected_ = false;
  std::atomic<bool> stop_{false};
  std::thread thread_;
  std::mutex m_;
  Received got_;
};

// O_T_C for the test: 30 deg about a skew axis, a metre and more away (mm), as registration.csv.
Eigen::Isometry3d writeRegistration(const std::filesystem::path& path) {
  const Eigen::Quaterniond q(Eigen::AngleAxisd(M_PI / 6, Eigen::Vector3d(1, 2, 3).normalized()));
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = q.toRotationMatrix();
  t.translation() = Eigen::Vector3d(120.5, -340.25, 1180.0);
  std::ofstream(path) << "tx,ty,tz,qw,qx,qy,qz\n"
                      << fmt::format("{:.9f},{:.9f},{:.9f},{:.12f},{:.12f},{:.12f},{:.12f}\n",
                                     t.translation().x(), t.translation().y(), t.translation().z(),
                                     q.w(), q.x(), q.y(), q.z());
  return t;
}

TEST(IgtlBridge, SlicersMessagesCarryTheDaemonsFiguresInTheTrackersFrame) {
  test::TempDir dir;
  const uint32_t domain = 98;
  const Eigen::Isometry3d o_t_c = writeRegistration(dir.path() / "registration.csv");
  DaemonOptions o;
  o.rig = "rig-igtl";
  o.extra = "[preview]\nrate_hz = 5.0\nscale = 2\n";
  Daemon d(dir, domain, {"--run-for", "200"}, "", {}, o);
  Program bridge({PULSETRACK_CLI, "igtl", "--port", "0", "--domain", std::to_string(domain),
                  "--registration", (dir.path() / "registration.csv").string(), "--image-rate", "2",
                  "--field-rate", "2", "--stall-timeout", "2"},
                 dir.path() / "igtl.log");
  const std::string port_text = bridge.waitFor(R"(serving OpenIGTLink on [0-9.]+:(\d+))", 60);
  ASSERT_FALSE(port_text.empty()) << bridge.output();
  const int port = std::stoi(port_text);

  // The daemon's own samples, to match by stamp.
  auto p = dds::Participant::create(domain);
  ASSERT_TRUE(p) << p.error().message;
  auto features = dds::Reader::create(
      *p, dds::kFeaturesTopic, &pulsetrack_msgs_msg_dds__Features__desc, dds::Profile::kSensorData);
  auto deformation =
      dds::Reader::create(*p, dds::kDeformationTopic, &pulsetrack_msgs_msg_dds__Deformation__desc,
                          dds::Profile::kSensorData);
  auto images =
      dds::Reader::create(*p, "rt/pulsetrack/left/image/compressed",
                          &sensor_msgs_msg_dds__CompressedImage__desc, dds::Profile::kSensorData);
  ASSERT_TRUE(features && deformation && images);

  // Debian's example receiver, and the library client; later a client that never reads.
  Program example({IGTL_RECEIVE_CLIENT, "127.0.0.1", std::to_string(port)},
                  dir.path() / "receive_client.log");
  Client client(port);
  ASSERT_TRUE(client.connected());
  struct FeatureSample {
    uint64_t frame = 0;
    std::map<int, std::pair<uint8_t, Eigen::Vector3d>> byId;  // status, m in the camera frame
    std::map<int, Eigen::Vector3d> displacement;              // m
  };
  std::map<int64_t, FeatureSample> dds_features;
  std::map<int64_t, Eigen::Vector3d> dds_displacement;  // m
  std::map<int64_t, cv::Mat> dds_images;
  pulsetrack_msgs_msg_dds__Features_ f{};
  pulsetrack_msgs_msg_dds__Deformation_ def{};
  sensor_msgs_msg_dds__CompressedImage_ im{};
  const auto t0 = Clock::now();
  const auto secs = [&] { return std::chrono::duration<double>(Clock::now() - t0).count(); };
  int stalled_fd = -1;
  Clock::time_point stall_began{};
  const auto enough = [&] {
    return client.with([&](const Received& r) {
      const auto tr = r.transforms;
      return r.points.size() >= 60 && r.images.size() >= 3 && r.polys.size() >= 3 &&
             tr.count("BrainShiftToTracker") > 0 && tr.at("BrainShiftToTracker").size() >= 30 &&
             tr.count("MeanDispToTracker") > 0 && tr.at("MeanDispToTracker").size() >= 30 &&
             tr.count("CameraToTracker") > 0 && !r.statuses.empty() && r.statuses.back().code == 1;
    });
  };
  while (secs() < 150 && !enough()) {
    while (features->takeOne(&f, std::chrono::milliseconds(20))) {
      FeatureSample s{f.frame, {}, {}};
      for (uint32_t i = 0; i < f.features._length; ++i) {
        const auto& ft = f.features._buffer[i];
        s.byId[ft.id] = {ft.status, Eigen::Vector3d(ft.position.x, ft.position.y, ft.position.z)};
        s.displacement[ft.id] =
            Eigen::Vector3d(ft.displacement.x, ft.displacement.y, ft.displacement.z);
      }
      dds_features[dds(f.header.stamp)] = std::move(s);
    }
    while (deformation->takeOne(&def, std::chrono::milliseconds(0)))
      dds_displacement[dds(def.header.stamp)] =
          Eigen::Vector3d(def.displacement.x, def.displacement.y, def.displacement.z);
    while (images->takeOne(&im, std::chrono::milliseconds(0))) {
      const cv::Mat buf(1, static_cast<int>(im.data._length), CV_8UC1, im.data._buffer);
      dds_images[dds(im.header.stamp)] = cv::imdecode(buf, cv::IMREAD_GRAYSCALE);
    }
    // After the first images: a client that connects and never reads (a small receive buffer).
    if (stalled_fd < 0 && client.with([](const Received& r) { return !r.images.empty(); })) {
      stalled_fd = socket(AF_INET, SOCK_STREAM, 0);
      const int small = 4096;
      setsockopt(stalled_fd, SOL_SOCKET, SO_RCVBUF, &small, sizeof small);
      sockaddr_in a{};
      a.sin_family = AF_INET;
      a.sin_port = htons(static_cast<uint16_t>(port));
      a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
      ASSERT_EQ(connect(stalled_fd, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
      stall_began = Clock::now();
    }
  }
  const std::string counts = client.with([](const Received& r) {
    std::string s = fmt::format("POINT {}, IMAGE {}, POLYDATA {}, STATUS {}", r.points.size(),
                                r.images.size(), r.polys.size(), r.statuses.size());
    for (const auto& [name, v] : r.transforms) s += fmt::format(", {} {}", name, v.size());
    return s;
  });
  std::cout << "received: " << counts << "\n";
  ASSERT_TRUE(enough()) << counts << "\n" << bridge.output();
  // The stalled client is cut off (2 s without a byte taken), the others unaffected.
  const std::string stalled = bridge.waitFor(R"(gone \(stalled[^\n]*)", 60);
  EXPECT_FALSE(stalled.empty()) << bridge.output();
  // Debian's example receiver: every type it knows decoded (it prints only what passed the CRC).
  const int example_exit = example.stop();
  const std::string ex = example.output();
  EXPECT_NE(ex.find("Receiving TRANSFORM data type."), std::string::npos) << ex.substr(0, 2000);
  EXPECT_NE(ex.find("Receiving POINT data type."), std::string::npos);
  EXPECT_TRUE(std::regex_search(ex, std::regex(R"( Name      : F\d+)"))) << ex.substr(0, 2000);
  EXPECT_TRUE(std::regex_search(ex, std::regex(R"( GroupName : ok)")));
  EXPECT_NE(ex.find("Device Name           : LeftCamera"), std::string::npos);
  EXPECT_NE(ex.find("Dimensions            : (680, 512, 1)"), std::string::npos);
  EXPECT_NE(ex.find("Scalar Type           : 3"), std::string::npos);
  EXPECT_NE(ex.find(" Code      : 1"), std::string::npos);
  EXPECT_NE(ex.find(" Error Name: ok"), std::string::npos);
  EXPECT_NE(ex.find("Receiving : POLYDATA"), std::string::npos);  // read past, as it should
  std::cout << "Debian's ReceiveClient: " << ex.size() << " bytes of output, exit " << example_exit
            << "\n";

  // The daemon goes: the clients are told (STATUS time-out) within the bridge's 3 s and more.
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  const auto t_gone = Clock::now();
  bool timed_out = false;
  while (!timed_out && std::chrono::duration<double>(Clock::now() - t_gone).count() < 60) {
    timed_out = client.with([](const Received& r) {
      return !r.statuses.empty() && r.statuses.back().code == igtl::StatusMessage::STATUS_TIME_OUT;
    });
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_TRUE(timed_out);
  client.close();
  if (stalled_fd >= 0) close(stalled_fd);
  EXPECT_EQ(bridge.stop(), 0);
  const std::string log = bridge.output();
  std::cout << log;
  // The library client: nothing dropped, though a client beside it stalled.
  EXPECT_TRUE(
      std::regex_search(log, std::regex(R"(gone \(disconnected\): \d+ messages sent, 0 dropped)")))
      << log;

  const Received r = client.with([](const Received& x) { return x; });
  EXPECT_EQ(r.crc_failures, 0);
  // Messages kept coming to this client while the other stalled.
  const auto after_stall = std::count_if(r.point_times.begin(), r.point_times.end(),
                                         [&](Clock::time_point t) { return t > stall_began; });
  EXPECT_GT(after_stall, 20);

  // The registration, as given.
  const Eigen::Matrix4d reg = r.transforms.at("CameraToTracker").back().second;
  EXPECT_LT((reg - o_t_c.matrix()).cwiseAbs().maxCoeff(), 1e-3) << reg;

  // POINT Features: every feature, named by its id, grouped and coloured by its status, at the
  // daemon's position mapped to the tracker's frame; the ok ones on the true surface.
  auto spec = sim::loadScene(kScene);
  ASSERT_TRUE(spec);
  auto rig = vision::loadRig(spec->rig_path);
  ASSERT_TRUE(rig);
  sim::StereoSimulator truth(*spec, *rig);
  const Eigen::Isometry3d c_t_o = o_t_c.inverse();
  int matched = 0, scored = 0, within = 0;
  double worst_copy = 0, worst_truth = 0;
  const char* groups[] = {
      "ok", "occluded", "lost", "outlier_epipolar", "outlier_surface", "outlier_triangulation"};
  for (const auto& [t, pts] : r.points) {
    auto it = dds_features.lower_bound(t - 2);
    if (it == dds_features.end() || !sameStamp(it->first, t)) continue;
    ++matched;
    const FeatureSample& s = it->second;
    EXPECT_EQ(pts.size(), s.byId.size());
    const double tt = truth.frameTime(static_cast<int>(s.frame % 600));
    for (const Point& pt : pts) {
      const int id = std::stoi(pt.name.substr(1));
      ASSERT_TRUE(s.byId.count(id)) << pt.name;
      const auto& [status, pos_m] = s.byId.at(id);
      EXPECT_EQ(pt.group, groups[std::min<int>(status, 5)]);
      EXPECT_EQ(pt.rgba[3], 255);
      worst_copy = std::max(worst_copy, (pt.p - o_t_c * (pos_m * 1e3)).norm());
      if (status != 0) continue;
      const Eigen::Vector3d cam = c_t_o * pt.p;  // back to the camera, mm, by the test's own maths
      cv::Vec2d uv;
      const cv::Vec3d mm(cam.x(), cam.y(), cam.z());
      if (!truth.cortex()->materialAt(*rig, rig->projectLeft(mm), tt, uv)) continue;
      const double e = cv::norm(truth.cortex()->position(uv[0], uv[1], tt) - mm);
      worst_truth = std::max(worst_truth, e);
      ++scored;
      within += e < 0.5 ? 1 : 0;
    }
  }
  std::cout << "POINT: " << r.points.size() << " messages, " << matched
            << " matched to the daemon's samples, worst copy error " << worst_copy << " mm; "
            << scored << " ok features against the truth, " << within << " within 0.5 mm (worst "
            << worst_truth << " mm)\n";
  EXPECT_GE(matched, 20);
  EXPECT_LT(worst_copy, 0.01);  // float32 at ~1.2 m
  EXPECT_GT(scored, 500);
  EXPECT_GE(within, scored * 99 / 100);

  // TRANSFORM MeanDispToTracker: the deformation's displacement, turned into the
  // tracker's frame; no rotation.
  int mean_matched = 0;
  double worst_mean = 0;
  for (const auto& [t, m] : r.transforms.at("MeanDispToTracker")) {
    EXPECT_LT((m.topLeftCorner<3, 3>() - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff(), 1e-6);
    auto it = dds_displacement.lower_bound(t - 2);
    if (it == dds_displacement.end() || !sameStamp(it->first, t)) continue;
    ++mean_matched;
    const Eigen::Vector3d want = o_t_c.linear() * (it->second * 1e3);
    worst_mean = std::max(worst_mean, (m.topRightCorner<3, 1>() - want).norm());
  }
  EXPECT_GE(mean_matched, 10);
  EXPECT_LT(worst_mean, 1e-4);
  // TRANSFORM BrainShiftToTracker: a rigid motion (a rotation, small: the cortex breathes and
  // pulses) that takes the ok features' reference positions to where they are at least as well
  // as their mean displacement does.
  int shift_matched = 0;
  double rms_rigid_sum = 0, rms_mean_sum = 0, worst_angle = 0;
  for (const auto& [t, m] : r.transforms.at("BrainShiftToTracker")) {
    const Eigen::Matrix3d rot = m.topLeftCorner<3, 3>();
    EXPECT_LT((rot * rot.transpose() - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff(), 1e-5);
    EXPECT_NEAR(rot.determinant(), 1.0, 1e-5);
    worst_angle = std::max(worst_angle, Eigen::AngleAxisd(rot).angle() * 180 / M_PI);
    auto it = dds_features.lower_bound(t - 2);
    if (it == dds_features.end() || !sameStamp(it->first, t)) continue;
    Eigen::Isometry3d tt;
    tt.matrix() = m;
    std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> refs;  // reference, now; tracker mm
    Eigen::Vector3d mean = Eigen::Vector3d::Zero();
    for (const auto& [id, sp] : it->second.byId) {
      if (sp.first != 0) continue;
      const Eigen::Vector3d now = o_t_c * (sp.second * 1e3);
      const Eigen::Vector3d ref = o_t_c * ((sp.second - it->second.displacement.at(id)) * 1e3);
      refs.emplace_back(ref, now);
      mean += now - ref;
    }
    if (refs.size() < 3) continue;
    mean /= static_cast<double>(refs.size());
    double rigid = 0, translated = 0;
    for (const auto& [ref, now] : refs) {
      rigid += (tt * ref - now).squaredNorm();
      translated += (ref + mean - now).squaredNorm();
    }
    rms_rigid_sum += std::sqrt(rigid / static_cast<double>(refs.size()));
    rms_mean_sum += std::sqrt(translated / static_cast<double>(refs.size()));
    ++shift_matched;
  }
  std::cout << "BrainShiftToTracker: " << shift_matched << " matched, mean residual "
            << rms_rigid_sum / std::max(1, shift_matched)
            << " mm (a translation alone: " << rms_mean_sum / std::max(1, shift_matched)
            << " mm), rotation at most " << worst_angle << " deg\n";
  EXPECT_GE(shift_matched, 10);
  EXPECT_LE(rms_rigid_sum, rms_mean_sum + 1e-3 * shift_matched);
  EXPECT_LT(worst_angle, 2.0);

  // IMAGE LeftCamera: the daemon's left preview, decoded, pixel for pixel.
  int images_matched = 0;
  for (const auto& [t, img] : r.images) {
    EXPECT_EQ(img.cols, 680);
    EXPECT_EQ(img.rows, 512);
    auto it = dds_images.lower_bound(t - 2);
    if (it == dds_images.end() || !sameStamp(it->first, t)) continue;
    ++images_matched;
    EXPECT_EQ(cv::norm(img, it->second, cv::NORM_INF), 0.0);
  }
  EXPECT_GE(images_matched, 1);

  // POLYDATA DenseField: the surface's grid in the tracker's frame (back in the camera's: the
  // working distance), triangles over it, a displacement per point whose mean is the surface's.
  int polys_matched = 0;
  for (const auto& poly : r.polys) {
    ASSERT_GT(poly.points.size(), 50U);
    EXPECT_GT(poly.triangles.size(), poly.points.size());  // ~2 per point on a full grid
    EXPECT_EQ(poly.displacement.size(), poly.points.size());
    EXPECT_EQ(poly.confidence.size(), poly.points.size());
    for (const auto& tri : poly.triangles)
      for (uint32_t k : tri) ASSERT_LT(k, poly.points.size());
    for (const auto& pt : poly.points) {
      const Eigen::Vector3d cam = c_t_o * pt;
      EXPECT_NEAR(cam.z(), 450.0, 60.0);
    }
    auto it = dds_displacement.lower_bound(poly.t - 2);
    if (it == dds_displacement.end() || !sameStamp(it->first, poly.t)) continue;
    Eigen::Vector3d mean = Eigen::Vector3d::Zero();
    for (const auto& v : poly.displacement) mean += v;
    mean /= static_cast<double>(poly.displacement.size());
    EXPECT_LT((mean - o_t_c.linear() * (it->second * 1e3)).norm(), 0.2);
    ++polys_matched;
  }
  EXPECT_GE(polys_matched, 1);
  // STATUS Health: ok while the daemon tracked, time-out once it went.
  bool ok_seen = false;
  for (const auto& s : r.statuses)
    ok_seen = ok_seen || (s.code == 1 && s.subcode == 1 && s.name == "ok" &&
                          s.text.find("features ok") != std::string::npos);
  EXPECT_TRUE(ok_seen);
  EXPECT_NE(r.statuses.back().text.find("no health from the daemon"), std::string::npos);
  dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&def, &pulsetrack_msgs_msg_dds__Deformation__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&im, &sensor_msgs_msg_dds__CompressedImage__desc, DDS_FREE_CONTENTS);
}

// A bridge whose DDS Security enclave has the monitor role (health only: a display in the
// OR) serves what that role may read - the daemon's health as STATUS - and says which topics
// its permissions do not grant, instead of failing: no features, no deformation, no images.
TEST(IgtlBridge, AMonitorEnclaveServesHealthOnlyAndSaysWhatItMayNotRead) {
  test::TempDir dir;
  const std::string ks = (dir.path() / "ks").string();
  for (const std::string& args :
       {"init " + ks, "add-participant " + ks + " /pulsetrack/daemon --role daemon",
        "add-participant " + ks + " /or/slicer_display --role monitor"}) {
    const test::CommandResult r = test::run(test::sourceDir() + "/scripts/security " + args);
    ASSERT_EQ(r.exit_code, 0) << args << ": " << r.output;
  }
  const uint32_t domain = 97;
  DaemonOptions o;
  o.rig = "rig-igtl";
  o.extra = "[security]\nenclave = \"" + ks + "/enclaves/pulsetrack/daemon\"\n";
  Daemon d(dir, domain, {"--run-for", "200"}, "", {}, o);
  Program bridge({PULSETRACK_CLI, "igtl", "--port", "0", "--domain", std::to_string(domain),
                  "--enclave", ks + "/enclaves/or/slicer_display"},
                 dir.path() / "igtl.log");
  const std::string port_text = bridge.waitFor(R"(serving OpenIGTLink on [0-9.]+:(\d+))", 60);
  ASSERT_FALSE(port_text.empty()) << bridge.output();
  Client client(std::stoi(port_text));
  ASSERT_TRUE(client.connected());
  // The daemon's health, tracking (STATUS OK, sub-code the daemon's state), three times.
  const auto t0 = Clock::now();
  bool healthy = false;
  while (!healthy && std::chrono::duration<double>(Clock::now() - t0).count() < 90) {
    d.drain(0);
    healthy = client.with([](const Received& r) {
      return std::count_if(r.statuses.begin(), r.statuses.end(), [](const Received::Status& st) {
               return st.code == igtl::StatusMessage::STATUS_OK && st.name == "ok";
             }) >= 3;
    });
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  const std::string out = bridge.output();
  const Received r = client.with([](const Received& x) { return x; });
  client.close();
  EXPECT_TRUE(healthy) << r.statuses.size() << " STATUS messages; the bridge said:\n" << out;
  // Nothing the monitor may not read reached the client, and the bridge said why.
  EXPECT_TRUE(r.points.empty() && r.transforms.empty() && r.images.empty() && r.polys.empty())
      << r.points.size() << " POINT, " << r.transforms.size() << " TRANSFORM, " << r.images.size()
      << " IMAGE, " << r.polys.size() << " POLYDATA";
  for (const char* topic : {"rt/pulsetrack/features", "rt/pulsetrack/deformation",
                            "rt/pulsetrack/field", "rt/pulsetrack/left/image/compressed"}) {
    EXPECT_NE(out.find(std::string("igtl: DDS Security: this participant (secured as "
                                   "CN=/or/slicer_display) has no permission to read ") +
                       topic + ": its messages are not served"),
              std::string::npos)
        << topic << " in:\n"
        << out;
  }
  EXPECT_EQ(bridge.stop(), 0);
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait([&] { return std::chrono::duration<double>(Clock::now() - t0).count(); }), 0);
}

// Without a daemon: the clients are told so; a question (GET_POLYDATA) is answered with what
// there is (a STATUS "not found"); bad arguments are clear errors naming the file.
TEST(IgtlBridge, WithoutADaemonItSaysSoAndAnswersQuestions) {
  test::TempDir dir;
  Program bridge({PULSETRACK_CLI, "igtl", "--port", "0", "--domain", "99"},
                 dir.path() / "igtl.log");
  const std::string port_text = bridge.waitFor(R"(serving OpenIGTLink on [0-9.]+:(\d+))", 60);
  ASSERT_FALSE(port_text.empty()) << bridge.output();
  EXPECT_NE(bridge.output().find("the Camera frame"), std::string::npos);
  Client client(std::stoi(port_text));
  ASSERT_TRUE(client.connected());
  igtl::GetPolyDataMessage::Pointer ask = igtl::GetPolyDataMessage::New();
  ask->SetDeviceName("Slicer");
  client.send(ask.GetPointer());
  const auto t0 = Clock::now();
  bool answered = false, timed_out = false;
  while (!(answered && timed_out) &&
         std::chrono::duration<double>(Clock::now() - t0).count() < 60) {
    client.with([&](const Received& r) {
      for (const auto& s : r.statuses) {
        answered = answered || (s.code == igtl::StatusMessage::STATUS_NOT_FOUND &&
                                s.text.find("no POLYDATA") != std::string::npos);
        timed_out = timed_out || s.code == igtl::StatusMessage::STATUS_TIME_OUT;
      }
      return 0;
    });
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_TRUE(answered);
  EXPECT_TRUE(timed_out);
  client.close();
  EXPECT_EQ(bridge.stop(), 0);

  const auto missing = test::run(std::string(PULSETRACK_CLI) + " igtl --registration " +
                                 (dir.path() / "nope.csv").string());
  EXPECT_EQ(missing.exit_code, 1);
  EXPECT_NE(missing.output.find("nope.csv"), std::string::npos) << missing.output;
  const auto host = test::run(std::string(PULSETRACK_CLI) + " igtl --host operating-room");
  EXPECT_EQ(host.exit_code, 1);
  EXPECT_NE(host.output.find("operating-room"), std::string::npos) << host.output;
}

}  // namespace
}  // namespace pulsetrack
