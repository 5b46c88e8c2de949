// What leaves the appliance, met the way its users meet it:
// - a ROS 2 node: tests/ros2_compat/ros2_subscriber, built from the .msg files as ROS 2's
//   Cyclone RMW registers them (keyless, XCDR1, no type information, ROS 2's QoS profiles; it
//   shares no code with the daemon) receives features, deformation and health on a rig's
//   namespaced topics, stamped on the system clock, and nothing of another rig on the same
//   domain under another namespace;
// - the research team: the same recording through the daemon (replay, no pair dropped) and
//   through `pulsetrack track` gives the same features and the same deformation, bit for bit.

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <csignal>
#include <ctime>
#include <fstream>
#include <map>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/core/persistence.hpp>
#include <regex>
#include <sstream>

#include "daemon/daemon_process.hpp"
#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

double realtimeNow() {
  timespec ts{};
  clock_gettime(CLOCK_REALTIME, &ts);
  return static_cast<double>(ts.tv_sec) + static_cast<double>(ts.tv_nsec) * 1e-9;
}

// "key=value" fields of one line of ros2_subscriber's output.
std::map<std::string, std::string> fields(const std::string& line) {
  std::map<std::string, std::string> out;
  std::istringstream ss(line);
  std::string word;
  while (ss >> word) {
    const size_t eq = word.find('=');
    if (eq != std::string::npos) out[word.substr(0, eq)] = word.substr(eq + 1);
  }
  return out;
}

struct Received {
  int exit_code = -1;
  std::string output;
  std::vector<std::map<std::string, std::string>> features, deformation, health, field, tracked,
      images;
};

Received subscribe(uint32_t domain, const std::string& ns, int features, int deformation,
                   int health, int timeout_s, const std::string& command = "", int field = 0,
                   const std::string& targets = "", int tracked = 0, int images = 0) {
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  std::string cmd = std::string(ROS2_SUBSCRIBER) + " --domain " + std::to_string(domain);
  if (!ns.empty()) cmd += " --namespace " + ns;
  cmd += " --features " + std::to_string(features) + " --deformation " +
         std::to_string(deformation) + " --health " + std::to_string(health) + " --timeout " +
         std::to_string(timeout_s);
  if (!command.empty()) cmd += " --command " + command;
  if (field > 0) cmd += " --field " + std::to_string(field);
  if (!targets.empty()) cmd += " " + targets;
  if (tracked > 0) cmd += " --tracked " + std::to_string(tracked);
  if (images > 0) cmd += " --images " + std::to_string(images);
  const test::CommandResult r = test::run(cmd);
  Received got;
  got.exit_code = r.exit_code;
  got.output = r.output;
  std::istringstream lines(r.output);
  std::string line;
  while (std::getline(lines, line)) {
    if (line.rfind("features ", 0) == 0) got.features.push_back(fields(line));
    if (line.rfind("deformation ", 0) == 0) got.deformation.push_back(fields(line));
    if (line.rfind("health ", 0) == 0) got.health.push_back(fields(line));
    if (line.rfind("field ", 0) == 0) got.field.push_back(fields(line));
    if (line.rfind("tracked ", 0) == 0) got.tracked.push_back(fields(line));
    if (line.rfind("image ", 0) == 0) got.images.push_back(fields(line));
  }
  return got;
}

double stampOf(const std::map<std::string, std::string>& f) {
  return std::stod(f.at("sec")) + std::stod(f.at("nanosec")) * 1e-9;
}

TEST(Ros2Output, ANodeBuiltFromTheMsgFilesReceivesANamespacedRigAndNothingOfAnother) {
  test::TempDir dir;
  const uint32_t domain = 86;
  DaemonOptions a, b;
  a.rig = "rig-a";
  a.ros_namespace = "or1";
  a.name = "a";
  b.rig = "rig-b";
  b.ros_namespace = "/site/or2";  // ROS 2's absolute form
  b.name = "b";
  Daemon da(dir, domain, {"--run-for", "120"}, "", {}, a);
  Daemon db(dir, domain, {"--run-for", "120"}, "", {}, b);
  const auto t0 = std::chrono::steady_clock::now();
  const auto secs = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  const double before = realtimeNow();
  const Received ra = subscribe(domain, "or1", 10, 10, 1, 90);
  const double after = realtimeNow();
  const Received rb = subscribe(domain, "site/or2", 3, 3, 1, 90);
  // Nobody publishes without a namespace here: a node there hears nothing.
  const Received none = subscribe(domain, "", 1, 0, 0, 3);
  // A ROS 2 node's Command (built from Command.msg, reliable keep last 10): an ROI outside the
  // image is refused, and the refusal is on that rig's health.
  const Received commanded = subscribe(domain, "or1", 0, 0, 30, 60, "set_roi");
  // pulsetrack ctl and listen reach a rig by its namespace.
  const auto ctl = test::run(test::cli() + " ctl --domain " + std::to_string(domain) +
                             " --namespace site/or2 redetect");
  const auto listen = test::run(test::cli() + " listen --domain " + std::to_string(domain) +
                                " --namespace or1 --count 3");
  kill(da.pid, SIGTERM);
  kill(db.pid, SIGTERM);
  EXPECT_EQ(da.wait(secs), 0);
  EXPECT_EQ(db.wait(secs), 0);
  std::cout << "or1: " << ra.features.size() << " features, " << ra.deformation.size()
            << " deformation, " << ra.health.size()
            << " health samples; site/or2: " << rb.features.size() << ", " << rb.deformation.size()
            << ", " << rb.health.size() << "\n";
  ASSERT_EQ(ra.exit_code, 0) << ra.output;
  ASSERT_EQ(rb.exit_code, 0) << rb.output;
  EXPECT_GE(ra.features.size(), 10U);
  EXPECT_GE(ra.deformation.size(), 10U);
  EXPECT_GE(ra.health.size(), 1U);
  for (const auto* set : {&ra.features, &ra.deformation, &ra.health})
    for (const auto& f : *set) EXPECT_EQ(f.at("rig"), "rig-a") << ra.output;
  for (const auto* set : {&rb.features, &rb.deformation, &rb.health})
    for (const auto& f : *set) EXPECT_EQ(f.at("rig"), "rig-b") << rb.output;
  // The stamps are on the system clock: every one lies between this test's CLOCK_REALTIME
  // readings around the subscription (less the pipeline's and the transport's latency).
  for (const auto& f : ra.features) {
    const double t = stampOf(f);
    EXPECT_GT(t, before - 5.0) << "stamp " << t << ", subscribed at " << before;
    EXPECT_LT(t, after) << "stamp " << t << ", done at " << after;
  }
  double max_features_ok = 0;
  size_t with_velocity = 0;  // every sample but the signal's first has its velocity's delay
  for (const auto& d : ra.deformation) {
    with_velocity += std::stod(d.at("velocity_delay")) > 0.0 ? 1 : 0;
    max_features_ok = std::max(max_features_ok, std::stod(d.at("ok")));
  }
  EXPECT_GE(with_velocity + 1, ra.deformation.size());
  EXPECT_GT(max_features_ok, 10);
  EXPECT_NE(commanded.output.find("command sent request=77"), std::string::npos)
      << commanded.output;
  // Health's counters as the ROS 2 node decodes them (built from Health.msg): the Command it
  // sent (keep last 10, into the daemon's keep-all reader) is counted refused; no outage.
  uint64_t refused = 0;
  for (const auto& h : commanded.health) {
    EXPECT_EQ(h.at("rig"), "rig-a");
    EXPECT_EQ(h.at("source_faults"), "0");
    EXPECT_EQ(h.at("recorder_faults"), "0");
    refused = std::max<uint64_t>(refused, std::stoull(h.at("commands_refused")));
  }
  EXPECT_GE(refused, 1U) << commanded.output;
  EXPECT_NE(ra.output.find("output_state=\"readers matched: features "), std::string::npos)
      << ra.output;
  EXPECT_NE(commanded.output.find("command 77 'set_roi' refused: left ROI 1300,1000 100x100: not "
                                  "inside"),
            std::string::npos)
      << commanded.output;
  EXPECT_EQ(ctl.exit_code, 0) << ctl.output;
  EXPECT_NE(ctl.output.find("on rt/site/or2/pulsetrack/command, DDS domain 86, acknowledged"),
            std::string::npos)
      << ctl.output;
  EXPECT_EQ(listen.exit_code, 0) << listen.output;
  EXPECT_NE(listen.output.find("deform  rig-a"), std::string::npos) << listen.output;
  EXPECT_EQ(listen.output.find("rig-b"), std::string::npos) << listen.output;
  EXPECT_EQ(none.exit_code, 1) << none.output;
  EXPECT_TRUE(none.features.empty()) << none.output;
}

// The cameras' preview as rqt_image_view (or any ROS 2 node) meets it: sensor_msgs/CompressedImage
// built from the .msg file (Debian's ros-sensor-msgs), a JPEG whose own header gives the scaled
// size; at most the configured rate (5 Hz here, 10 fps pairs); each feature's pixels inside the
// full image.
TEST(Ros2Output, TheCamerasPreviewIsACompressedImageAndTheFeaturesCarryTheirPixels) {
  test::TempDir dir;
  const uint32_t domain = 96;
  DaemonOptions o;
  o.extra = "[preview]\nrate_hz = 5.0\nscale = 2\n";
  Daemon d(dir, domain, {"--run-for", "120"}, "", {}, o);
  const auto t0 = std::chrono::steady_clock::now();
  const auto secs = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  const Received got = subscribe(domain, "", 20, 0, 3, 90, "", 0, "", 0, 6);
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  ASSERT_EQ(got.exit_code, 0) << got.output;
  ASSERT_FALSE(got.health.empty());
  const auto& h = got.health.back();
  const int width = std::stoi(h.at("image_width")), height = std::stoi(h.at("image_height"));
  EXPECT_EQ(width, 1360);  // the simulated rig's cameras
  EXPECT_EQ(height, 1024);
  EXPECT_NE(h.at("stages").find("preview:"), std::string::npos) << h.at("stages");
  std::map<std::string, std::vector<double>> stamps;
  for (const auto& im : got.images) {
    EXPECT_EQ(im.at("jpeg"), "1");
    EXPECT_EQ(im.at("format"), "\"mono8;");  // "mono8; jpeg compressed mono8", split at spaces
    EXPECT_EQ(std::stoi(im.at("width")), width / 2);
    EXPECT_EQ(std::stoi(im.at("height")), height / 2);
    EXPECT_GT(std::stoi(im.at("bytes")), 5000);  // textured cortex, not a blank image
    EXPECT_EQ(im.at("frame_id"), "pulsetrack_" + im.at("side") + "_camera");
    stamps[im.at("side")].push_back(stampOf(im));
  }
  ASSERT_GE(stamps["left"].size(), 6U);
  ASSERT_GE(stamps["right"].size(), 6U);
  // Never faster than 5 Hz: consecutive previews' exposures are at least 0.9 periods apart
  // (0.18 s: the schedule's slack; a pair missing when one was due pushes the schedule on).
  for (const auto& [side, t] : stamps)
    for (size_t i = 1; i < t.size(); ++i) EXPECT_GT(t[i] - t[i - 1], 0.15) << side << " " << i;
  // Each ok feature's pixels are where its published 3D position projects: the rig file read
  // with OpenCV's own FileStorage and projectPoints (nothing of the daemon's calibration code).
  cv::FileStorage rig(std::string(PULSETRACK_SOURCE_DIR) + "/config/rigs/paper-rig.yaml",
                      cv::FileStorage::READ);
  ASSERT_TRUE(rig.isOpened());
  cv::Mat m1, d1, m2, d2, rot, t;
  rig["M1"] >> m1;
  rig["D1"] >> d1;
  rig["M2"] >> m2;
  rig["D2"] >> d2;
  rig["R"] >> rot;
  rig["T"] >> t;
  cv::Mat rvec;
  cv::Rodrigues(rot, rvec);
  const double t_scale = cv::norm(t) > 10.0 ? 1e-3 : 1.0;  // T in mm or in m
  int checked = 0;
  double worst = 0.0;
  for (const auto& f : got.features) {
    if (f.at("n") == "0" || f.at("status0") != "0") continue;
    const double lx = std::stod(f.at("lx0")), ly = std::stod(f.at("ly0"));
    const double rx = std::stod(f.at("rx0")), ry = std::stod(f.at("ry0"));
    EXPECT_TRUE(lx >= 0 && lx < width && ly >= 0 && ly < height) << lx << "," << ly;
    EXPECT_TRUE(rx >= 0 && rx < width && ry >= 0 && ry < height) << rx << "," << ry;
    const std::vector<cv::Point3d> p = {
        {std::stod(f.at("x0")), std::stod(f.at("y0")), std::stod(f.at("z0"))}};
    std::vector<cv::Point2d> pl, pr;
    cv::projectPoints(p, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), m1, d1, pl);
    cv::projectPoints(p, rvec, t * t_scale, m2, d2, pr);
    worst = std::max(
        {worst, std::hypot(pl[0].x - lx, pl[0].y - ly), std::hypot(pr[0].x - rx, pr[0].y - ry)});
    ++checked;
  }
  std::cout << checked << " features' pixels against their 3D positions' projections: worst "
            << worst << " px\n";
  EXPECT_GT(checked, 10);
  EXPECT_LT(worst, 1.5);
}

// The dense deformation field as rviz2 (or any ROS 2 node) meets it: sensor_msgs/PointCloud2
// built from the .msg files (Debian's ros-sensor-msgs), each channel found by name and read at its
// declared offset and datatype (ros2_subscriber shares no code with the daemon). Its content
// against the deformation sample of the same pair: the grid's mean displacement is the surface's,
// within 0.1 mm of the features' mean, while the surface moves more than that.
TEST(Ros2Output, TheFieldIsAPointCloud2ANodeDecodesAndTargetsAreFollowed) {
  test::TempDir dir;
  const uint32_t domain = 88;
  DaemonOptions o;
  o.rig = "rig-f";
  o.ros_namespace = "or3";
  Daemon d(dir, domain, {"--run-for", "120"}, "", {}, o);
  const auto t0 = std::chrono::steady_clock::now();
  const auto secs = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  // ~10 s: long enough for the predictor's model to be in use (it needs ~5 s of history).
  const Received r = subscribe(domain, "or3", 0, 120, 0, 120, "", 100);
  // The robot's question, as a ROS 2 node asks it (Targets.msg, TrackedTargets.msg): the grid's
  // middle point in the reference pair (its position less its displacement, from the last
  // cloud) and a point off the surface; then the middle point as it is now (FRAME_LATEST).
  ASSERT_FALSE(r.field.empty()) << r.output;
  const auto& last = r.field.back();
  const cv::Vec3d now(std::stod(last.at("mx")), std::stod(last.at("my")), std::stod(last.at("mz")));
  const cv::Vec3d ref = now - cv::Vec3d(std::stod(last.at("mdx")), std::stod(last.at("mdy")),
                                        std::stod(last.at("mdz")));
  const auto triple = [](const cv::Vec3d& p) {
    return fmt::format("{:.9f},{:.9f},{:.9f}", p[0], p[1], p[2]);
  };
  const Received by_ref =
      subscribe(domain, "or3", 0, 30, 0, 90, "", 0, "--targets '" + triple(ref) + ";0,0,1.45'", 15);
  const Received by_now =
      subscribe(domain, "or3", 0, 0, 0, 90, "", 0,
                "--targets '" + triple(now) + "' --targets-frame latest --set-id 43", 5);
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  ASSERT_GE(r.field.size(), 100U);
  std::map<std::string, const std::map<std::string, std::string>*> deformation_at;
  for (const auto& def : r.deformation)
    deformation_at[def.at("sec") + "." + def.at("nanosec")] = &def;
  int matched = 0, models = 0;
  double worst = 0, moved = 0, worst_predicted = 0;
  for (const auto& f : r.field) {
    EXPECT_EQ(f.at("fields"),
              "\"x:0:7:1,y:4:7:1,z:8:7:1,dx:12:7:1,dy:16:7:1,dz:20:7:1,"
              "confidence:24:7:1,dx_50ms:28:7:1,dy_50ms:32:7:1,dz_50ms:36:7:1,"
              "dx_100ms:40:7:1,dy_100ms:44:7:1,dz_100ms:48:7:1,dx_200ms:52:7:1,"
              "dy_200ms:56:7:1,dz_200ms:60:7:1\"");
    EXPECT_EQ(f.at("missing"), "\"\"");
    EXPECT_EQ(f.at("frame_id"), "pulsetrack_left_camera");
    EXPECT_EQ(f.at("is_bigendian"), "0");
    const uint64_t width = std::stoull(f.at("width")), height = std::stoull(f.at("height"));
    EXPECT_EQ(std::stoull(f.at("point_step")), 64U);
    EXPECT_EQ(std::stoull(f.at("row_step")), 64U * width);
    EXPECT_EQ(std::stoull(f.at("bytes")), 64U * width * height);
    // The default ROI covers ~25 x 20 mm of cortex at 1 mm: hundreds of grid points, most of
    // them within reach of a feature, all at the cortex's distance (45 cm).
    const uint64_t points = std::stoull(f.at("points")), valid = std::stoull(f.at("valid"));
    EXPECT_EQ(points, width * height);
    EXPECT_GT(points, 300U);
    EXPECT_GT(valid, points / 2) << "valid " << valid << " of " << points;
    EXPECT_EQ(f.at("is_dense"), valid == points ? "1" : "0");
    EXPECT_GT(std::stod(f.at("min_z")), 0.40);
    EXPECT_LT(std::stod(f.at("max_z")), 0.50);
    EXPECT_GT(std::stod(f.at("mean_confidence")), 0.5);
    EXPECT_GT(std::stod(f.at("mconf")), 0.9);  // the grid's middle is among the features
    const auto def = deformation_at.find(f.at("sec") + "." + f.at("nanosec"));
    if (def == deformation_at.end()) continue;
    ++matched;
    for (const char* axis : {"x", "y", "z"}) {
      const double fd = std::stod(f.at(std::string("mean_d") + axis));
      const double dd = std::stod(def->second->at(std::string("d") + axis));
      worst = std::max(worst, std::abs(fd - dd));
      moved = std::max(moved, std::abs(dd));
      // The field's predictions agree with the mean's as its displacement does (the grid is
      // predicted with the mean's weights, or held when the mean is).
      int k = 0;
      for (const char* h : {"50ms", "100ms", "200ms"}) {
        const double fp = std::stod(f.at(std::string("mean_d") + axis + "_" + h));
        const double dp =
            std::stod(def->second->at("pd" + std::string(axis) + std::to_string(k++)));
        worst_predicted = std::max(worst_predicted, std::abs(fp - dp));
      }
    }
    models += def->second->at("pm1") == "1" ? 1 : 0;
  }
  std::cout << r.field.size() << " field samples, " << matched
            << " matched to their pair's deformation: the grid's mean displacement within "
            << worst * 1e3 << " mm of the features' mean, which moved up to " << moved * 1e3
            << " mm; its predictions within " << worst_predicted * 1e3
            << " mm of the mean's (the model in use in " << models << ")\n";
  EXPECT_LT(worst_predicted, 1e-4);
  // The model is in use once the predictor has seconds of pairs at the daemon's rate; a build too
  // slow to track every pair (a sanitizer's: none in a row) leaves gaps, and the predictor then
  // rightly holds. So the model's use is judged when the daemon kept up: at least half of the
  // samples follow their predecessor's pair (the scene itself drops a trigger now and then: about
  // 80 % in a row in the release build).
  size_t in_row = 0;
  for (size_t i = 1; i < r.deformation.size(); ++i)
    in_row += std::stoull(r.deformation[i].at("frame")) ==
                      std::stoull(r.deformation[i - 1].at("frame")) + 1
                  ? 1
                  : 0;
  const double kept = r.deformation.size() > 1 ? static_cast<double>(in_row) /
                                                     static_cast<double>(r.deformation.size() - 1)
                                               : 0.0;
  std::cout << "consecutive pairs: " << kept * 100 << " % of the deformation samples\n";
  if (kept >= 0.5)
    EXPECT_GT(models, 5);
  else
    std::cout << "the daemon did not track every pair here: the model's use is not judged\n";
  EXPECT_GE(matched, 10);
  EXPECT_LT(worst, 1e-4);
  EXPECT_GT(moved, 2 * worst);
  EXPECT_GT(moved, 0.05e-3);

  // FRAME_REFERENCE: the references echo what was sent, position = reference + displacement,
  // the middle point moves with the surface (within 0.1 mm of the features' mean), the far
  // point has no confidence and stays where it was.
  ASSERT_EQ(by_ref.exit_code, 0) << by_ref.output;
  ASSERT_GE(by_ref.tracked.size(), 15U);
  deformation_at.clear();
  for (const auto& def : by_ref.deformation)
    deformation_at[def.at("sec") + "." + def.at("nanosec")] = &def;
  const auto v3 = [](const std::map<std::string, std::string>& m, const std::string& k) {
    return cv::Vec3d(std::stod(m.at(k + "x")), std::stod(m.at(k + "y")), std::stod(m.at(k + "z")));
  };
  int with_deformation = 0;
  size_t near_features = 0;
  double target_worst = 0, target_moved = 0, least_confidence = 1.0;
  for (const auto& t : by_ref.tracked) {
    EXPECT_EQ(t.at("set_id"), "42");
    EXPECT_EQ(t.at("rig"), "rig-f");
    EXPECT_EQ(t.at("n"), "2");
    EXPECT_EQ(t.at("n_confidence"), "2");
    EXPECT_LT(cv::norm(v3(t, "r0") - ref), 1e-8) << "the reference echoes what was sent";
    EXPECT_LT(cv::norm(v3(t, "p0") - (v3(t, "r0") + v3(t, "d0"))), 1e-9);
    // The middle point is within the features' reach in every answer; its confidence is high
    // while the features around it are ok, and lower for a pair where one of them is not (an
    // outlier in a build too slow to track every pair: the asan build's 0.69 once).
    const double c0 = std::stod(t.at("c0"));
    EXPECT_GT(c0, 0.0);
    least_confidence = std::min(least_confidence, c0);
    near_features += c0 > 0.9 ? 1 : 0;
    EXPECT_EQ(std::stod(t.at("c1")), 0.0);
    EXPECT_LT(cv::norm(v3(t, "p1") - cv::Vec3d(0, 0, 1.45)), 1e-9);
    const auto def = deformation_at.find(t.at("sec") + "." + t.at("nanosec"));
    if (def == deformation_at.end()) continue;
    ++with_deformation;
    target_worst = std::max(target_worst, cv::norm(v3(t, "d0") - v3(*def->second, "d")));
    target_moved = std::max(target_moved, cv::norm(v3(*def->second, "d")));
  }
  std::cout << by_ref.tracked.size() << " answers to the targets, " << with_deformation
            << " matched to their pair's deformation: the middle point's displacement within "
            << target_worst * 1e3 << " mm of the features' mean, which moved up to "
            << target_moved * 1e3 << " mm\n";
  std::cout << near_features << " of them with the middle point's confidence above 0.9, the least "
            << least_confidence << "\n";
  EXPECT_GE(2 * near_features, by_ref.tracked.size());
  EXPECT_GE(with_deformation, 5);
  EXPECT_LT(target_worst, 1e-4);
  EXPECT_GT(target_moved, 2 * target_worst);
  // FRAME_LATEST: mapped back through the field of the pair it arrived at, so that this pair's
  // answer puts it exactly where it was given.
  // (Answers to the last set, 42, come until the daemon takes the new one, 43.)
  ASSERT_EQ(by_now.exit_code, 0) << by_now.output;
  std::vector<std::map<std::string, std::string>> latest;
  for (const auto& t : by_now.tracked)
    if (t.at("set_id") == "43") latest.push_back(t);
  ASSERT_GE(latest.size(), 2U) << by_now.output;
  const auto first_answer =
      std::min_element(latest.begin(), latest.end(), [](const auto& a, const auto& b) {
        return std::stoull(a.at("frame")) < std::stoull(b.at("frame"));
      });
  EXPECT_LT(cv::norm(v3(*first_answer, "p0") - now), 1e-8) << by_now.output;
  for (const auto& t : latest)
    EXPECT_LT(cv::norm(v3(t, "r0") - v3(*first_answer, "r0")), 1e-12) << by_now.output;
}

// The stages off the features' path (issue 33): the dense field, the stereo refresh and the
// preview, each made slow by 150 ms a pair (pulsetrackd --slow-stage, at 10 pairs/s, the preview
// at 10 a second), skip the pairs that come while they are busy - counted on health - and delay
// no features sample: the track stage keeps up with the source, the publish stage's p99 stays
// far below the stall, and the features come for every pair the daemon did not count as dropped.
TEST(Ros2Output, SlowStagesOffThePathDelayNoFeaturesSampleAndTheirSkipsAreCounted) {
  test::TempDir dir;
  const uint32_t domain = 86;
  DaemonOptions o;
  o.rig = "rig-slow-stages";
  o.extra = "[preview]\nrate_hz = 10.0\n";
  Daemon d(dir, domain,
           {"--run-for", "120", "--slow-stage", "field:150", "--slow-stage", "refresh:150",
            "--slow-stage", "preview:150"},
           "", {}, o);
  const auto t0 = std::chrono::steady_clock::now();
  const auto secs = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  const Received r = subscribe(domain, "", 60, 0, 40, 120, "", 5);
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  std::smatch m;
  std::string last_health;
  std::istringstream lines(r.output);
  for (std::string line; std::getline(lines, line);)
    if (line.rfind("health ", 0) == 0 && line.find("rig=rig-slow-stages") != std::string::npos)
      last_health = line;
  // Features for every pair the daemon did not count as dropped (a busy machine may make the
  // track stage skip a pair: counted; a best-effort sample may rarely be lost on loopback: 2).
  ASSERT_GE(r.features.size(), 60U);
  uint64_t gaps = 0;
  for (size_t i = 1; i < r.features.size(); ++i) {
    const uint64_t a = std::stoull(r.features[i - 1].at("frame")),
                   b = std::stoull(r.features[i].at("frame"));
    gaps += b > a + 1 ? b - a - 1 : 0;
  }
  ASSERT_TRUE(std::regex_search(last_health, m, std::regex(" drops=([0-9]+)"))) << last_health;
  const uint64_t drops = std::stoull(m[1]);
  EXPECT_LE(gaps, drops + 2) << "features frames missing that the daemon did not count";
  ASSERT_TRUE(std::regex_search(last_health, m, std::regex(" frames=([0-9]+)"))) << last_health;
  const uint64_t tracked = std::stoull(m[1]);
  // The track stage keeps up with the source: inline, a 150 ms stall per pair at 10 pairs/s would
  // leave it taking the newest of every second pair or so (a third of them dropped, and the ones
  // taken waiting 50 ms on average); off the path it drops next to none. Its own drops (pairs it
  // never took, results never published: the state text's), not health's drops, which count the
  // pairs a slow source could not deliver too (a sanitizer's simulator renders ~5 a second).
  ASSERT_TRUE(std::regex_search(last_health, m, std::regex(" ([0-9]+) drops, track p99")))
      << last_health;
  const uint64_t stage_drops = std::stoull(m[1]);
  EXPECT_LE(stage_drops * 10, tracked) << "the track stage did not keep up: " << last_health;
  // The last health sample: each slow stage's own latency shows the stall, the publish stage's
  // does not (the track stage's p99 over ~80 pairs is its detection's time).
  const auto p50_p99 = [&](const std::string& stage) -> std::pair<long, long> {
    std::smatch s;
    if (!std::regex_search(last_health, s, std::regex(stage + ":([0-9]+)/([0-9]+)/[0-9]+")))
      return {-1, -1};
    return {std::stol(s[1]), std::stol(s[2])};
  };
  const auto track = p50_p99("track"), publish = p50_p99("publish");
  ASSERT_GE(track.second, 0) << last_health;
  EXPECT_LT(publish.second, 50'000) << last_health;
  for (const char* stage : {"field", "refresh", "preview"})
    EXPECT_GE(p50_p99(stage).first, 150'000) << stage << ": " << last_health;
  // Each stage counts what it did and what it skipped: it did something, no more than the stall
  // lets it, and (field, refresh) no more than there were pairs. Every tracked pair's field was
  // sent, skipped or dropped before it (counted), but for the one in the stage and the one
  // waiting. (Whether a stage skips depends on how fast the pairs come: the sanitizer's track
  // stage is slower than the stall.)
  std::string counted;
  const auto counts = [&](const std::string& what) -> std::pair<uint64_t, uint64_t> {
    std::smatch s;
    if (!std::regex_search(last_health, s, std::regex(what))) return {0, UINT64_MAX};
    counted += std::string(s[0]) + "; ";
    return {std::stoull(s[1]), std::stoull(s[2])};
  };
  const auto field = counts("field stage: ([0-9]+) sent, ([0-9]+) pairs skipped");
  const auto refresh = counts("refresh stage: ([0-9]+) measured, ([0-9]+) pairs skipped");
  const auto preview = counts("preview stage: ([0-9]+) sent, ([0-9]+) copies skipped");
  for (const auto& [done, skipped] : {field, refresh, preview}) {
    EXPECT_GT(done, 0U) << last_health;
    EXPECT_LE(static_cast<double>(done), secs() / 0.150 + 1.0) << counted;
  }
  for (const auto& [done, skipped] : {field, refresh})
    EXPECT_LE(done + skipped, tracked + 2) << counted << tracked << " pairs tracked";
  EXPECT_GE(field.first + field.second + drops + 2, tracked) << counted << tracked << " tracked";
  EXPECT_GE(r.field.size(), 5U);
  std::cout << "slow field, refresh and preview stages (150 ms a pair at 10 pairs/s): " << gaps
            << " features frames missing of " << r.features.size() << " (" << drops
            << " pairs dropped, counted, " << stage_drops << " by the stages); track p50/p99 "
            << track.first << "/" << track.second << " us, publish p99 " << publish.second
            << " us; " << counted << "of " << tracked << " tracked\n";
}

// Every pair of a recording through pulsetrackd (replay, lossless: none dropped) and through
// `pulsetrack track`: the same features (ids, statuses, positions) and the same deformation.
TEST(OfflineEqualsLive, TheDaemonAndTrackGiveTheSameSignalForEveryPair) {
  test::TempDir dir;
  const uint32_t domain = 87;
  const std::string rec = dir / "rec";
  auto made = test::run(test::cli() + " simulate --scene " + kScene + " --out " + rec +
                        " --frames 50 --supersample 1 -q");
  ASSERT_EQ(made.exit_code, 0) << made.output;
  auto reader = record::Reader::open(rec);
  ASSERT_TRUE(reader) << reader.error().message;
  std::map<uint64_t, long> frame_of;  // trigger_seq -> the recording's frame
  for (size_t i = 0; i < reader->size(); ++i)
    frame_of[reader->meta(i).trigger_seq] = static_cast<long>(reader->meta(i).frame);
  // The daemon: a raw keep-all best-effort reader (the writer is best effort), every sample.
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  auto p = dds::Participant::create(domain);
  ASSERT_TRUE(p) << p.error().message;
  dds_qos_t* qos = dds_create_qos();
  dds_qset_reliability(qos, DDS_RELIABILITY_BEST_EFFORT, 0);
  dds_qset_history(qos, DDS_HISTORY_KEEP_ALL, 0);
  const dds_entity_t ft = dds_create_topic(p->get(), &pulsetrack_msgs_msg_dds__Features__desc,
                                           dds::kFeaturesTopic, nullptr, nullptr);
  const dds_entity_t dt = dds_create_topic(p->get(), &pulsetrack_msgs_msg_dds__Deformation__desc,
                                           dds::kDeformationTopic, nullptr, nullptr);
  const dds_entity_t fr = dds_create_reader(p->get(), ft, qos, nullptr);
  const dds_entity_t dr = dds_create_reader(p->get(), dt, qos, nullptr);
  dds_delete_qos(qos);
  ASSERT_GT(fr, 0);
  ASSERT_GT(dr, 0);
  Daemon d(dir, domain, {"--run-for", "300"},
           "kind = \"replay\"\nrecording = \"" + rec +
               "\"\npace = \"realtime\"\nloop = false\nlossless = true\n");
  const auto t0 = std::chrono::steady_clock::now();
  const auto secs = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  std::map<long, std::vector<pulsetrack_msgs_msg_dds__Feature_>> live_features;
  std::map<long, pulsetrack_msgs_msg_dds__Deformation_> live_def;
  // Per frame, per horizon: horizon, dx, dy, dz, sigma, model (copied: the sequences are loaned).
  std::map<long, std::vector<std::array<double, 6>>> live_prediction;
  const auto keep = [&](const pulsetrack_msgs_msg_dds__Deformation_& s) {
    const long f = frame_of.at(s.frame);
    live_def[f] = s;
    live_def[f].rig_id = nullptr;  // not kept past the loan
    live_def[f].header.frame_id = nullptr;
    live_def[f].prediction_horizon = {};
    live_def[f].predicted_displacement = {};
    live_def[f].prediction_sigma = {};
    live_def[f].predicted_by_model = {};
    auto& pred = live_prediction[f];
    pred.clear();
    for (uint32_t k = 0; k < s.prediction_horizon._length; ++k) {
      const auto& v = s.predicted_displacement._buffer[k];
      pred.push_back({s.prediction_horizon._buffer[k], v.x, v.y, v.z, s.prediction_sigma._buffer[k],
                      s.predicted_by_model._buffer[k] ? 1.0 : 0.0});
    }
  };
  const size_t last_frame = reader->size();
  while (secs() < 240.0 && live_features.size() < last_frame) {
    d.drain(secs());
    void* samples[1] = {nullptr};
    dds_sample_info_t info[1];
    bool any = false;
    while (dds_take(fr, samples, info, 1, 1) > 0) {
      any = true;
      if (info[0].valid_data) {
        const auto* s = static_cast<const pulsetrack_msgs_msg_dds__Features_*>(samples[0]);
        auto& v = live_features[frame_of.at(s->frame)];
        v.assign(s->features._buffer, s->features._buffer + s->features._length);
      }
      dds_return_loan(fr, samples, 1);
      samples[0] = nullptr;
    }
    while (dds_take(dr, samples, info, 1, 1) > 0) {
      any = true;
      if (info[0].valid_data) {
        const auto* s = static_cast<const pulsetrack_msgs_msg_dds__Deformation_*>(samples[0]);
        keep(*s);
      }
      dds_return_loan(dr, samples, 1);
      samples[0] = nullptr;
    }
    if (!any) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(300));  // the last deformation
  void* samples[1] = {nullptr};
  dds_sample_info_t info[1];
  while (dds_take(dr, samples, info, 1, 1) > 0) {
    if (info[0].valid_data) {
      const auto* s = static_cast<const pulsetrack_msgs_msg_dds__Deformation_*>(samples[0]);
      keep(*s);
    }
    dds_return_loan(dr, samples, 1);
    samples[0] = nullptr;
  }
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  // Offline, the same ROI as the daemon's (the shipped config's default).
  const std::string track = dir / "track.csv";
  auto off =
      test::run(test::cli() + " track --input " + rec +
                " --roi-left 483,339,400,340 --roi-right 476,344,400,340 --out " + track + " -q");
  ASSERT_EQ(off.exit_code, 0) << off.output;
  auto rows = record::readTrackCsv(track);
  ASSERT_TRUE(rows) << rows.error().message;
  auto def = record::readDeformationCsv(dir / "track-deformation.csv");
  ASSERT_TRUE(def) << def.error().message;
  std::map<long, std::vector<record::TrackRow>> offline_features;
  for (const auto& r : *rows) offline_features[r.frame].push_back(r);
  std::cout << "live: " << live_features.size() << " features samples, " << live_def.size()
            << " deformation; offline: " << offline_features.size() << " frames, " << def->size()
            << " deformation rows, of " << last_frame << " pairs\n";
  // Every pair through both, none lost or dropped.
  EXPECT_EQ(live_features.size(), last_frame);
  EXPECT_EQ(offline_features.size(), last_frame);
  EXPECT_EQ(live_def.size(), def->size());
  int compared = 0;
  for (const auto& [frame, live] : live_features) {
    const auto it = offline_features.find(frame);
    ASSERT_NE(it, offline_features.end()) << "frame " << frame;
    ASSERT_EQ(live.size(), it->second.size()) << "frame " << frame;
    for (size_t i = 0; i < live.size(); ++i) {
      const auto& lf = live[i];
      const auto& of = it->second[i];
      ASSERT_EQ(lf.id, of.id) << "frame " << frame;
      // The status and the gate, as the track file names them.
      EXPECT_EQ(lf.status == 0, of.ok())
          << "frame " << frame << " id " << of.id << " " << of.status;
      // The CSV prints positions to 1e-5 mm.
      EXPECT_NEAR(lf.position.x * 1e3, of.x, 1e-5) << "frame " << frame << " id " << of.id;
      EXPECT_NEAR(lf.position.y * 1e3, of.y, 1e-5) << "frame " << frame << " id " << of.id;
      EXPECT_NEAR(lf.position.z * 1e3, of.z, 1e-5) << "frame " << frame << " id " << of.id;
      ++compared;
    }
  }
  int exact = 0;
  for (const record::DeformationRow& r : *def) {
    const auto it = live_def.find(r.frame);
    ASSERT_NE(it, live_def.end()) << "frame " << r.frame;
    const auto& l = it->second;
    // Bit for bit: the daemon sends mm * 1e-3, the file holds the mm to 17 digits.
    EXPECT_EQ(l.displacement.x, r.dx * 1e-3) << "frame " << r.frame;
    EXPECT_EQ(l.displacement.y, r.dy * 1e-3) << "frame " << r.frame;
    EXPECT_EQ(l.displacement.z, r.dz * 1e-3) << "frame " << r.frame;
    EXPECT_EQ(l.velocity.x, r.vx * 1e-3) << "frame " << r.frame;
    EXPECT_EQ(l.velocity.y, r.vy * 1e-3) << "frame " << r.frame;
    EXPECT_EQ(l.velocity.z, r.vz * 1e-3) << "frame " << r.frame;
    EXPECT_EQ(l.velocity_delay, r.velocity_delay) << "frame " << r.frame;
    EXPECT_EQ(l.displacement_sigma, r.displacement_sigma * 1e-3) << "frame " << r.frame;
    EXPECT_EQ(l.features_ok, static_cast<uint32_t>(r.ok)) << "frame " << r.frame;
    EXPECT_EQ(l.detections, static_cast<uint32_t>(r.detections)) << "frame " << r.frame;
    EXPECT_EQ(l.continuous, r.continuous) << "frame " << r.frame;
    exact += l.displacement.x == r.dx * 1e-3 && l.velocity.z == r.vz * 1e-3 ? 1 : 0;
  }
  std::cout << compared << " feature rows equal, " << exact << " of " << def->size()
            << " deformation samples identical\n";
  EXPECT_GT(compared, 1000);
  // The predictions: the same predictor on both paths, every pair, every horizon, bit for bit.
  std::ifstream pin(dir / "track-prediction.csv");
  std::string line;
  std::getline(pin, line);
  EXPECT_EQ(line, "frame,t,horizon,dx,dy,dz,sigma,model");
  int predictions = 0, by_model = 0;
  std::map<long, int> per_frame;
  while (std::getline(pin, line)) {
    std::vector<std::string> c;
    std::stringstream ss(line);
    for (std::string v; std::getline(ss, v, ',');) c.push_back(v);
    ASSERT_EQ(c.size(), 8U) << line;
    const long frame = std::stol(c[0]);
    const int k = per_frame[frame]++;
    const auto it = live_prediction.find(frame);
    ASSERT_NE(it, live_prediction.end()) << "frame " << frame;
    ASSERT_LT(static_cast<size_t>(k), it->second.size()) << "frame " << frame;
    const auto& l = it->second[static_cast<size_t>(k)];
    EXPECT_EQ(l[0], std::stod(c[2])) << line;
    EXPECT_EQ(l[1], std::stod(c[3]) * 1e-3) << line;
    EXPECT_EQ(l[2], std::stod(c[4]) * 1e-3) << line;
    EXPECT_EQ(l[3], std::stod(c[5]) * 1e-3) << line;
    EXPECT_EQ(l[4], std::stod(c[6]) * 1e-3) << line;
    EXPECT_EQ(l[5], std::stod(c[7])) << line;
    ++predictions;
    by_model += c[7] == "1" ? 1 : 0;
  }
  for (const auto& [frame, pred] : live_prediction) EXPECT_EQ(pred.size(), 3U) << "frame " << frame;
  std::cout << predictions << " predictions identical (" << by_model << " by the model)\n";
  EXPECT_EQ(predictions, 3 * static_cast<int>(def->size()));
  EXPECT_GT(by_model, 0);
}

}  // namespace
}  // namespace pulsetrack
