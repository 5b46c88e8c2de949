// End to end: pulsetrackd as a real process on the simulated rig; this process subscribes over
// Cyclone DDS on loopback (own domain id), checks the features against the simulator's ground
// truth, and plays systemd on a notify socket it binds: READY=1, WATCHDOG=1 while healthy,
// the pings stopping and health going to fault when the track stage stalls.

#include <fcntl.h>
#include <gtest/gtest.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <csignal>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <optional>
#include <thread>

#include "daemon/daemon_process.hpp"
#include "pulsetrack/dds/dds.hpp"
#include "pulsetrack/record/recording.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"
#include "test_util.hpp"

namespace pulsetrack {
namespace {

// Another process's view of the daemon over DDS: features and health readers on the test's
// domain, their samples, and the seconds since it subscribed.
struct Subscriber {
  std::optional<dds::Participant> participant;
  std::optional<dds::Reader> features, health;
  pulsetrack_msgs_msg_dds__Features_ f{};
  pulsetrack_msgs_msg_dds__Health_ h{};
  std::chrono::steady_clock::time_point t0 = std::chrono::steady_clock::now();

  explicit Subscriber(uint32_t domain) {
    setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
    auto p = dds::Participant::create(domain);
    if (!p) return;
    participant.emplace(std::move(*p));
    auto fr =
        dds::Reader::create(*participant, dds::kFeaturesTopic,
                            &pulsetrack_msgs_msg_dds__Features__desc, dds::Profile::kSensorData);
    auto hr =
        dds::Reader::create(*participant, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                            dds::Profile::kTransientLocal);
    if (fr) features.emplace(std::move(*fr));
    if (hr) health.emplace(std::move(*hr));
  }
  ~Subscriber() {
    dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
    dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
  }
  Subscriber(const Subscriber&) = delete;
  Subscriber& operator=(const Subscriber&) = delete;
  [[nodiscard]] bool ok() const { return features && health; }
  [[nodiscard]] double secs() const {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
};

TEST(Daemon, PublishesTrackedFeaturesThatMatchTheGroundTruthAndTalksToSystemd) {
  test::TempDir dir;
  const uint32_t domain = 73;
  Daemon d(dir, domain, {"--run-for", "60"});
  auto p = dds::Participant::create(domain);
  ASSERT_TRUE(p) << p.error().message;
  auto features = dds::Reader::create(
      *p, dds::kFeaturesTopic, &pulsetrack_msgs_msg_dds__Features__desc, dds::Profile::kSensorData);
  auto deformation =
      dds::Reader::create(*p, dds::kDeformationTopic, &pulsetrack_msgs_msg_dds__Deformation__desc,
                          dds::Profile::kSensorData);
  auto health = dds::Reader::create(*p, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                                    dds::Profile::kTransientLocal);
  ASSERT_TRUE(features && deformation && health);

  auto spec = sim::loadScene(kScene);
  ASSERT_TRUE(spec);
  auto rig = vision::loadRig(spec->rig_path);
  ASSERT_TRUE(rig);
  sim::StereoSimulator truth(*spec, *rig);

  const auto t0 = std::chrono::steady_clock::now();
  const auto secs = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  pulsetrack_msgs_msg_dds__Features_ f{};
  pulsetrack_msgs_msg_dds__Deformation_ def{};
  pulsetrack_msgs_msg_dds__Health_ h{};
  int samples = 0, scored = 0, within = 0, deformations = 0;
  double worst = 0;
  std::map<int, int> health_states;
  // 30 samples and a few health samples, or 40 s (a sanitizer build is slow); then SIGTERM.
  while (secs() < 40.0 && (samples < 30 || health_states[1] < 4)) {
    d.drain(secs());
    if (features->takeOne(&f, std::chrono::milliseconds(50))) {
      ++samples;
      EXPECT_STREQ(f.rig_id, "rig-e2e");
      const double t = truth.frameTime(static_cast<int>(f.frame % 600));
      for (uint32_t i = 0; i < f.features._length; ++i) {
        const auto& ft = f.features._buffer[i];
        if (ft.status != 0) continue;
        const cv::Vec3d mm(ft.position.x * 1e3, ft.position.y * 1e3, ft.position.z * 1e3);
        cv::Vec2d uv;
        if (!truth.cortex()->materialAt(*rig, rig->projectLeft(mm), t, uv)) continue;
        // The surface point under the feature's pixel: the 3D error along the ray and across.
        const double e = cv::norm(truth.cortex()->position(uv[0], uv[1], t) - mm);
        worst = std::max(worst, e);
        ++scored;
        within += e < 0.5 ? 1 : 0;
      }
    }
    while (deformation->takeOne(&def, std::chrono::milliseconds(0))) {
      ++deformations;
      EXPECT_GT(def.features_ok, 10U);
      EXPECT_NEAR(def.centroid.z, 0.45, 0.05);
    }
    while (health->takeOne(&h, std::chrono::milliseconds(0))) ++health_states[h.state];
  }
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  std::cout << "e2e: " << samples << " feature samples, " << deformations << " deformation, "
            << scored << " ok features scored, " << within << " within 0.5 mm of the truth "
            << "(worst " << worst << " mm), health states:";
  for (const auto& [s, n] : health_states) std::cout << " " << s << "x" << n;
  std::cout << "\n";
  // 10 fps here; a sanitizer build renders a few pairs per second.
  EXPECT_GE(samples, 10);
  EXPECT_GE(deformations, 10);
  EXPECT_GT(scored, 500);
  EXPECT_GE(within, scored * 99 / 100);
  EXPECT_GT(health_states[1], 3);  // ok
  bool ready = false, ping = false, status = false;
  for (const auto& [t, s] : d.notes) {
    ready = ready || s == "READY=1";
    ping = ping || s == "WATCHDOG=1";
    status = status || s.rfind("STATUS=ok: ", 0) == 0;
  }
  EXPECT_TRUE(ready);
  EXPECT_TRUE(ping);
  EXPECT_TRUE(status);
  dds_sample_free(&f, &pulsetrack_msgs_msg_dds__Features__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&def, &pulsetrack_msgs_msg_dds__Deformation__desc, DDS_FREE_CONTENTS);
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
}

TEST(Daemon, AStalledTrackStageStopsTheWatchdogAndHealthSaysFault) {
  test::TempDir dir;
  const uint32_t domain = 74;
  Daemon d(dir, domain, {"--run-for", "20", "--stall-track-after", "10"});
  auto p = dds::Participant::create(domain);
  ASSERT_TRUE(p);
  auto health = dds::Reader::create(*p, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                                    dds::Profile::kTransientLocal);
  ASSERT_TRUE(health);
  const auto t0 = std::chrono::steady_clock::now();
  const auto secs = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  pulsetrack_msgs_msg_dds__Health_ h{};
  bool fault = false, ok_after_fault = false;
  // Until the daemon exits (a sanitizer build reaches the stall later, the recovery too).
  while (secs() < 30.0 && !ok_after_fault) {
    d.drain(secs());
    if (health->takeOne(&h, std::chrono::milliseconds(50))) {
      if (h.state == 3) fault = true;
      if (fault && h.state == 1) ok_after_fault = true;
    }
  }
  EXPECT_EQ(d.wait(secs), 0);
  // The longest gap between watchdog pings after the first: the 5 s stall.
  double last = -1, longest = 0;
  for (const auto& [t, s] : d.notes) {
    if (s != "WATCHDOG=1") continue;
    if (last >= 0) longest = std::max(longest, t - last);
    last = t;
  }
  std::cout << "stall: longest gap between WATCHDOG=1 " << longest << " s, health fault seen "
            << fault << ", ok again " << ok_after_fault << "\n";
  EXPECT_TRUE(fault);
  EXPECT_TRUE(ok_after_fault);
  EXPECT_GT(longest, 2.0);
  dds_sample_free(&h, &pulsetrack_msgs_msg_dds__Health__desc, DDS_FREE_CONTENTS);
}

// The technician's view: a bad config stops the daemon before anything starts, with file:line
// (the unit's ExecStartPre runs exactly this); a good one is reported ok.
TEST(Daemon, CheckConfigNamesFileLineOrSaysOk) {
  test::TempDir dir;
  const auto bad = dir.path() / "pulsetrackd.toml";
  std::ofstream(bad) << "rig_id = \"r\"\n[tracker]\nmax_featurs = 50\n";
  auto r = test::run(std::string(PULSETRACKD) + " --check-config -c " + bad.string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("pulsetrackd.toml:3: unknown key 'tracker.max_featurs'"),
            std::string::npos)
      << r.output;
  r = test::run(std::string(PULSETRACKD) + " --check-config -c " + PULSETRACK_SOURCE_DIR +
                "/config/pulsetrackd.toml");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("ok (source sim cortex-60s"), std::string::npos) << r.output;
  // An ROI the rig's images cannot hold: named before anything starts.
  const auto roi = dir.path() / "roi.toml";
  std::ofstream(roi) << "[source]\nscene = \"" << kScene
                     << "\"\n[tracker]\nroi_left = [1300, 1000, 200, 200]\n";
  r = test::run(std::string(PULSETRACKD) + " --check-config -c " + roi.string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("roi.toml: [tracker] left ROI 1300,1000 200x200: not inside the "
                          "1360x1024 image"),
            std::string::npos)
      << r.output;
  r = test::run(std::string(PULSETRACKD) + " -c /nonexistent.toml");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("/nonexistent.toml: cannot open"), std::string::npos) << r.output;
}

// Trigger pulses that never fire and frames one camera lost (the simulated rig's injected
// faults): no pair is ever made of two triggers' frames (the features' frame numbers skip every
// faulty trigger), the counts reach health, and so many losses make it degraded, with the reason.
TEST(Daemon, MissingTriggersAndUnpairedFramesAreCountedNeverPairedWrongly) {
  test::TempDir dir;
  const uint32_t domain = 81;  // every test has its own domain: ctest runs them in parallel
  Daemon d(dir, domain, {"--run-for", "60"},
           "[source.faults]\nmissing_trigger_every = 5\nleft_drop_every = 7\n"
           "right_miss_every = 11\n");
  Subscriber sub(domain);
  ASSERT_TRUE(sub.ok());
  const auto secs = [&] { return sub.secs(); };
  int samples = 0, faulty = 0, degraded = 0;
  uint64_t missing = 0, unpaired = 0;
  std::string trigger_state, reason;
  while (secs() < 40.0 && (samples < 20 || degraded < 2)) {
    d.drain(secs());
    if (sub.features->takeOne(&sub.f, std::chrono::milliseconds(50))) {
      ++samples;
      const uint64_t k = sub.f.frame;
      if (k % 5 == 4 || k % 7 == 6 || k % 11 == 10) ++faulty;
    }
    while (sub.health->takeOne(&sub.h, std::chrono::milliseconds(0))) {
      missing = sub.h.missing_triggers;
      unpaired = sub.h.unpaired;
      trigger_state = sub.h.trigger_state;
      if (sub.h.state == 2) {
        ++degraded;
        reason = sub.h.last_error;
      }
    }
  }
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  std::cout << samples << " feature samples, health: missing triggers " << missing << ", unpaired "
            << unpaired << ", trigger '" << trigger_state << "', reason '" << reason << "'\n";
  EXPECT_GE(samples, 20);
  EXPECT_EQ(faulty, 0);
  EXPECT_GT(missing, 3U);
  EXPECT_GT(unpaired, 3U);
  EXPECT_EQ(trigger_state, "software 10 Hz");
  EXPECT_GE(degraded, 2);
  EXPECT_NE(reason.find("gave no frame pair"), std::string::npos) << reason;
}

// The recorder on a disk that fills (the kernel's file-size limit, prlimit): health says the
// recording stopped and why, tracking goes on, the recording reads back to its last frame.
TEST(Daemon, ARecordingThatFillsTheDiskStopsCleanlyAndTrackingGoesOn) {
  ASSERT_EQ(access("/usr/bin/prlimit", X_OK), 0)
      << "/usr/bin/prlimit (util-linux, essential in Debian) is needed";
  test::TempDir dir;
  const uint32_t domain = 80;
  const auto recordings = dir.path() / "recordings";
  Daemon d(dir, domain, {"--run-for", "60"},
           "[recorder]\nenabled = true\ndir = \"" + recordings.string() + "\"\n",
           {"/usr/bin/prlimit", "--fsize=12000000"});
  Subscriber sub(domain);
  ASSERT_TRUE(sub.ok());
  const auto secs = [&] { return sub.secs(); };
  std::string recorder, stopped;
  int after_stop = 0, not_ok_after = 0;
  while (secs() < 50.0 && after_stop < 10) {
    d.drain(secs());
    if (sub.features->takeOne(&sub.f, std::chrono::milliseconds(50)) && !stopped.empty())
      ++after_stop;
    while (sub.health->takeOne(&sub.h, std::chrono::milliseconds(0))) {
      recorder = sub.h.recorder_state;
      // The first stop: the first segment's frames (the recorder then resumes in DIR-part2,
      // the file-size limit leaving the file system room, and may stop again).
      if (recorder.starts_with("stopped") && stopped.empty()) stopped = recorder;
      if (!stopped.empty() && sub.h.state != 1) ++not_ok_after;
    }
  }
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  std::cout << "recorder: " << stopped << "\n";
  ASSERT_FALSE(stopped.empty()) << "last recorder state: " << recorder;
  EXPECT_NE(stopped.find("not recorded"), std::string::npos) << stopped;
  EXPECT_GE(after_stop, 10);  // features still published after the disk filled
  EXPECT_EQ(not_ok_after, 0);
  ASSERT_TRUE(std::filesystem::exists(recordings));
  std::vector<std::filesystem::path> segments;
  for (const auto& e : std::filesystem::directory_iterator(recordings))
    segments.push_back(e.path());
  std::sort(segments.begin(), segments.end());  // DIR, then DIR-part2, ...
  ASSERT_FALSE(segments.empty());
  EXPECT_EQ(segments[0].filename().string().find("-part"), std::string::npos) << segments[0];
  auto r = record::Reader::open(segments[0]);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_GT(r->size(), 2U);
  cv::Mat l, rr;
  for (size_t i = 0; i < r->size(); ++i) EXPECT_TRUE(r->read(i, l, rr)) << i;
  const auto n = std::stoul(stopped.substr(std::string("stopped after ").size()));
  EXPECT_EQ(r->size(), n);
  for (size_t k = 1; k < segments.size(); ++k) {  // resumed segments read back from frame 0
    EXPECT_EQ(segments[k].string(), segments[0].string() + "-part" + std::to_string(k + 1));
    auto part = record::Reader::open(segments[k]);
    ASSERT_TRUE(part) << part.error().message;
    if (part->size() > 0) {
      EXPECT_EQ(part->meta(0).frame, 0U) << segments[k];
    }
  }
}

// The recorder started and stopped at run time, as the console and `pulsetrack ctl` do it: each
// start a new folder that reads back to the frame health counted; a second start while recording
// is refused with the reason; tracking goes on throughout.
TEST(Daemon, TheRecorderStartsAndStopsOnCommand) {
  test::TempDir dir;
  const uint32_t domain = 95;
  const auto recordings = dir.path() / "recordings";
  Daemon d(dir, domain, {"--run-for", "120"},
           "[recorder]\nenabled = false\ndir = \"" + recordings.string() + "\"\n");
  Subscriber sub(domain);
  ASSERT_TRUE(sub.ok());
  if (!sub.features.has_value()) {
    ADD_FAILURE() << "no features reader";
    return;
  }
  const dds::Reader& features_reader = *sub.features;
  const auto secs = [&] { return sub.secs(); };
  const std::string ctl = test::cli() + " ctl --domain " + std::to_string(domain) + " ";
  // Waits (bounded) for a health sample whose recorder_state starts with `prefix`.
  const auto recorderState = [&](const std::string& prefix) {
    std::string last;
    const double until = secs() + 40.0;
    while (secs() < until) {
      d.drain(secs());
      while (sub.health->takeOne(&sub.h, std::chrono::milliseconds(50))) {
        last = sub.h.recorder_state;
        if (last.starts_with(prefix)) return last;
      }
    }
    return "(timeout) " + last;
  };
  EXPECT_EQ(recorderState("off"), "off");
  std::vector<uint64_t> counted;
  for (int run = 0; run < 2; ++run) {
    const auto start = test::run(ctl + "record-start");
    ASSERT_EQ(start.exit_code, 0) << start.output;
    const std::string recording = recorderState("recording");
    ASSERT_TRUE(recording.starts_with("recording")) << recording;
    if (run == 0) {  // a second start while recording: refused, and why
      const auto again = test::run(ctl + "record-start");
      EXPECT_EQ(again.exit_code, 1) << again.output;
      EXPECT_NE(again.output.find("'record_start' refused: already recording to"),
                std::string::npos)
          << again.output;
    }
    int features = 0;  // tracking goes on while recording
    while (features < 10 && secs() < 100.0) {
      d.drain(secs());
      if (features_reader.takeOne(&sub.f, std::chrono::milliseconds(100))) ++features;
    }
    EXPECT_EQ(features, 10);
    const auto stop = test::run(ctl + "record-stop");
    ASSERT_EQ(stop.exit_code, 0) << stop.output;
    const std::string stopped = recorderState("off (stopped: ");
    ASSERT_TRUE(stopped.starts_with("off (stopped: ")) << stopped;
    counted.push_back(std::stoull(stopped.substr(std::string("off (stopped: ").size())));
  }
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  std::vector<std::filesystem::path> folders;
  for (const auto& e : std::filesystem::directory_iterator(recordings)) folders.push_back(e.path());
  std::sort(folders.begin(), folders.end());
  ASSERT_EQ(folders.size(), 2U);
  for (size_t k = 0; k < 2; ++k) {
    auto r = record::Reader::open(folders[k]);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_GT(r->size(), 5U) << folders[k];
    EXPECT_EQ(r->size(), counted[k]) << folders[k];
    EXPECT_EQ(r->meta(0).frame, 0U);  // each recording starts at its own frame 0
    cv::Mat l, rr;
    EXPECT_TRUE(r->read(r->size() - 1, l, rr));
  }
}

// A subscriber process that dies (SIGKILL, no goodbye) does not disturb the daemon: health
// stays ok and another subscriber keeps receiving.
TEST(Daemon, ASubscriberCrashDoesNotDisturbIt) {
  test::TempDir dir;
  const uint32_t domain = 77;
  Daemon d(dir, domain, {"--run-for", "60"});
  setenv("CYCLONEDDS_URI", dds::kLoopbackUri, 1);
  pid_t listener = 0;
  std::string dom = std::to_string(domain);
  std::vector<std::string> args = {PULSETRACK_CLI, "listen", "--domain", dom, "--seconds", "60"};
  std::vector<char*> argv;
  argv.reserve(args.size() + 1);
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t quiet;
  posix_spawn_file_actions_init(&quiet);
  posix_spawn_file_actions_addopen(&quiet, 1, "/dev/null", O_WRONLY, 0);
  ASSERT_EQ(posix_spawn(&listener, PULSETRACK_CLI, &quiet, nullptr, argv.data(), environ), 0);
  posix_spawn_file_actions_destroy(&quiet);
  Subscriber sub(domain);
  ASSERT_TRUE(sub.ok());
  const auto secs = [&] { return sub.secs(); };
  int before = 0, after = 0, not_ok_after = 0;
  bool killed = false;
  // Warm up: the first features (slow in a sanitizer build); then 3 s, the kill, 5 s.
  for (int k = 0; k < 300 && !sub.features->takeOne(&sub.f, std::chrono::milliseconds(100)); ++k)
    d.drain(secs());
  const double kill_at = secs() + 3.0, end_at = kill_at + 5.0;
  while (secs() < end_at) {
    d.drain(secs());
    if (!killed && secs() > kill_at) {
      kill(listener, SIGKILL);
      waitpid(listener, nullptr, 0);
      killed = true;
    }
    if (sub.features->takeOne(&sub.f, std::chrono::milliseconds(50))) (killed ? after : before)++;
    while (sub.health->takeOne(&sub.h, std::chrono::milliseconds(0))) {
      if (killed && sub.h.state != 1) ++not_ok_after;
    }
  }
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  EXPECT_GT(before, 3);
  EXPECT_GT(after, 5);  // still flowing after the crash
  EXPECT_EQ(not_ok_after, 0);
}

// The capture cycle over the command topic, by `pulsetrack ctl` and by raw samples: redetect
// re-detects (the deformation's count of feature sets goes up), stop stops the features, start
// resumes them; garbage and a flood are refused and reported on health, and the daemon stays ok.
TEST(Daemon, CaptureCycleCommandsAndGarbage) {
  test::TempDir dir;
  const uint32_t domain = 76;
  Daemon d(dir, domain, {"--run-for", "60"});
  Subscriber sub(domain);
  ASSERT_TRUE(sub.ok());
  auto commands =
      dds::Writer::create(*sub.participant, dds::kCommandTopic,
                          &pulsetrack_msgs_msg_dds__Command__desc, dds::Profile::kCommand);
  ASSERT_TRUE(commands);
  auto deformation =
      dds::Reader::create(*sub.participant, dds::kDeformationTopic,
                          &pulsetrack_msgs_msg_dds__Deformation__desc, dds::Profile::kSensorData);
  ASSERT_TRUE(deformation);
  pulsetrack_msgs_msg_dds__Deformation_ def{};
  uint32_t detections = 0;  // the largest feature-set count seen on the deformation topic
  const auto secs = [&] { return sub.secs(); };
  // Features for `seconds`: how many samples, and the largest feature id seen.
  const auto collect = [&](double seconds, int& samples, int& max_id) {
    samples = 0;
    max_id = -1;
    const double until = secs() + seconds;
    while (secs() < until) {
      d.drain(secs());
      while (deformation->takeOne(&def, std::chrono::milliseconds(0)))
        detections = std::max(detections, def.detections);
      if (!sub.features->takeOne(&sub.f, std::chrono::milliseconds(50))) continue;
      ++samples;
      for (uint32_t i = 0; i < sub.f.features._length; ++i)
        max_id = std::max(max_id, sub.f.features._buffer[i].id);
    }
  };
  const std::string ctl =
      test::cli() + " ctl --domain " + std::to_string(domain) + " --rig rig-e2e ";
  int n = 0, id0 = 0, id1 = 0, id2 = 0;
  // Warm up: the first features (detection, discovery; slow in a sanitizer build).
  for (int k = 0; k < 300 && !sub.features->takeOne(&sub.f, std::chrono::milliseconds(100)); ++k)
    d.drain(secs());
  collect(3.0, n, id0);
  EXPECT_GT(n, 3);
  const uint32_t detections0 = detections;
  EXPECT_GE(detections0, 1U);
  auto r = test::run(ctl + "redetect");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  collect(2.0, n, id1);
  // A re-detection happened; it fills around the features kept under their ids (none lost,
  // new ids only where the ROI had room).
  EXPECT_GT(detections, detections0);
  EXPECT_GE(id1, id0);
  r = test::run(ctl + "stop");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  collect(0.5, n, id2);  // in flight
  collect(1.5, n, id2);
  EXPECT_EQ(n, 0);
  r = test::run(ctl + "start");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  collect(3.0, n, id2);
  EXPECT_GT(n, 2);
  EXPECT_GT(id2, id1);  // start detects afresh
  // A left ROI alone (issue 32): the daemon finds the right one in the next pair; no ROI at all
  // (both zero on the wire): the tissue region too. Each is accepted (a refusal reaches ctl:
  // exit 1) and detects afresh (new ids), and tracking goes on.
  int last_id = id2;
  for (const char* args : {"set-roi --roi-left 483,339,400,340", "set-roi"}) {
    r = test::run(ctl + args);
    EXPECT_EQ(r.exit_code, 0) << args << ": " << r.output;
    int id = 0;
    collect(4.0, n, id);
    EXPECT_GT(n, 2) << args;
    EXPECT_GT(id, last_id) << args;
    last_id = id;
  }

  // Garbage: an unknown command with control bytes, a bad ROI, and a flood of them.
  pulsetrack_msgs_msg_dds__Command_ c{};
  std::string rig = "rig-e2e", bad = "rm -rf /\x01\x02", set = "set_roi";
  c.rig_id = rig.data();
  c.command = bad.data();
  c.request_id = 4242;
  ASSERT_TRUE(commands->write(&c));
  for (uint32_t k = 0; k < 2000; ++k) {
    c.request_id = 10000 + k;
    c.command = (k % 2) != 0U ? set.data() : bad.data();
    c.roi_left[2] = -5;
    (void)commands->write(&c);
  }
  bool refused_seen = false;
  int ok_after = 0;
  const double until = secs() + 4.0;
  while (secs() < until) {
    d.drain(secs());
    while (sub.health->takeOne(&sub.h, std::chrono::milliseconds(20))) {
      const std::string err = sub.h.last_error;
      if (err.find("refused") != std::string::npos) refused_seen = true;
      EXPECT_EQ(err.find('\x01'), std::string::npos) << err;  // not echoed raw
      if (refused_seen && sub.h.state == 1) ++ok_after;
    }
    (void)sub.features->takeOne(&sub.f, std::chrono::milliseconds(10));
  }
  EXPECT_TRUE(refused_seen);
  EXPECT_GT(ok_after, 2);  // still tracking, still ok
  // ctl itself refuses what it cannot send.
  r = test::run(ctl + "set-roi --roi-left 1,2,3");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  r = test::run(ctl + "set-roi --roi-right 1,2,30,40");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  // A refusal reaches ctl from the daemon's health: exit 1 with the reason.
  r = test::run(ctl + "set-roi --roi-left 1300,1000,100,100 --roi-right 10,10,100,100");
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("left ROI 1300,1000 100x100: not inside the"), std::string::npos)
      << r.output;
  // A domain no test uses (tests run in parallel, each daemon on its own domain).
  r = test::run(test::cli() + " ctl --domain 231 stop");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("no pulsetrackd is listening"), std::string::npos) << r.output;
  kill(d.pid, SIGTERM);
  EXPECT_EQ(d.wait(secs), 0);
  dds_sample_free(&def, &pulsetrack_msgs_msg_dds__Deformation__desc, DDS_FREE_CONTENTS);
}

}  // namespace
}  // namespace pulsetrack
