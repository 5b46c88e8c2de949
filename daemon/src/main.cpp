// pulsetrackd: the real-time appliance daemon. Reads its config, runs the pipeline, publishes
// over DDS, talks to systemd (READY, STATUS, WATCHDOG), stops cleanly on SIGTERM/SIGINT.

#include <fmt/format.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <csignal>
#include <cstdio>
#include <optional>
#include <thread>
#include <utility>

#include "pulsetrack/daemon/config.hpp"
#include "pulsetrack/daemon/log.hpp"
#include "pulsetrack/daemon/notify.hpp"
#include "pulsetrack/daemon/pipeline.hpp"
#include "pulsetrack/drivers/libcamera_source.hpp"
#include "pulsetrack/drivers/trigger_box.hpp"
#include "pulsetrack/drivers/v4l2.hpp"
#include "pulsetrack/record/live_recorder.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"
#include "pulsetrack/vision/tracking_session.hpp"

namespace {
volatile std::sig_atomic_t g_stop = 0;
void onSignal(int /*sig*/) { g_stop = 1; }

// --slow-stage's STAGE:MS, or nothing when it is not that.
std::optional<std::pair<pulsetrack::daemon::Pipeline::OffPath, long>> slowStage(
    const std::string& v) {
  const auto colon = v.find(':');
  if (colon == std::string::npos) return std::nullopt;
  const auto& names = pulsetrack::daemon::Pipeline::kOffPathNames;
  const auto* at = std::find(names.begin(), names.end(), v.substr(0, colon));
  const std::string ms = v.substr(colon + 1);
  if (at == names.end() || ms.empty() || ms.size() > 5 ||
      !std::all_of(ms.begin(), ms.end(), [](char c) { return c >= '0' && c <= '9'; }))
    return std::nullopt;
  return std::pair{static_cast<pulsetrack::daemon::Pipeline::OffPath>(at - names.begin()),
                   std::stol(ms)};
}
}  // namespace

namespace {

int run(int argc, char** argv) {
  using namespace pulsetrack;
  CLI::App app(
      "pulsetrackd: tracks the brain surface's motion with a stereo rig and publishes it "
      "over DDS (rt/pulsetrack/features, deformation, health).");
  app.set_version_flag("--version", std::string("pulsetrackd ") + PULSETRACK_VERSION);
  std::string config_path = "/etc/pulsetrack/pulsetrackd.toml";
  bool check = false;
  double run_for = 0.0;
  int stall_after = 0;
  app.add_option("-c,--config", config_path, "Config file (config/pulsetrackd.toml documents it)")
      ->capture_default_str();
  app.add_flag("--check-config", check, "Read the config, report what is wrong, exit");
  app.add_option("--run-for", run_for, "Stop after this many seconds (tests, benchmarks)");
  app.add_option("--stall-track-after", stall_after,
                 "Fault injection: stall the track stage for 5 s after this many frames");
  std::vector<std::string> slow_stages;
  app.add_option("--slow-stage", slow_stages,
                 "Fault injection: STAGE:MS, a stage off the features' path (field, refresh or "
                 "preview) takes MS longer per pair (it must delay no features sample; health "
                 "counts its skips); repeatable")
      ->check([](const std::string& v) -> std::string {
        return slowStage(v)
                   ? ""
                   : "expected STAGE:MS (STAGE field, refresh or preview; MS 0-99999), got '" + v +
                         "'";
      });
  bool list_cameras = false;
  app.add_flag("--list-cameras", list_cameras,
               "List the cameras libcamera sees (their ids for the config), exit");
  CLI11_PARSE(app, argc, argv);
  if (list_cameras) {
    auto cams = drivers::listLibcameraCameras();
    if (!cams) {
      daemon::log::get("source").error("{}", cams.error().message);
      return 1;
    }
    for (const auto& c : *cams) std::printf("%s  %s\n", c.id.c_str(), c.model.c_str());
    if (cams->empty()) std::printf("libcamera sees no camera (V4L2 devices: ls /dev/video*)\n");
    return 0;
  }

  daemon::log::setup(check);
  auto& log_config = daemon::log::get("config");
  auto& log_source = daemon::log::get("source");
  auto& log_pipeline = daemon::log::get("pipeline");
  auto config = daemon::loadDaemonConfig(config_path);
  if (!config) {
    log_config.error("{}", config.error().message);
    return 1;
  }
  std::unique_ptr<drivers::TriggerBox> trigger;  // outlives the source that asks it
  std::unique_ptr<drivers::CameraSource> source;
  if (config->source == daemon::SourceKind::kSim) {
    auto scene = sim::loadScene(config->scene);
    if (!scene) {
      log_config.error("{}", scene.error().message);
      return 1;
    }
    auto rig = vision::loadRig(scene->rig_path);
    if (!rig) {
      log_config.error("{}", rig.error().message);
      return 1;
    }
    scene->supersample = 1;  // live rendering
    source = drivers::makeSimSource(*scene, *rig, config->fps, config->loop, config->sim_faults);
  } else if (config->source == daemon::SourceKind::kV4l2 ||
             config->source == daemon::SourceKind::kLibcamera) {
    // One device carrying both views: a calibration without image_size takes the views' size
    // from the device's frame, when that is set.
    const bool one_device = config->source == daemon::SourceKind::kV4l2 &&
                            config->layout != drivers::StereoLayout::kTwoCameras;
    drivers::V4l2CameraConfig device = config->device_camera;
    cv::Size view;
    if (one_device && device.width > 0 && device.height > 0)
      view = drivers::layoutViewSize(config->layout, {device.width, device.height});
    auto rig = vision::loadRig(
        config->rig, view,
        view.empty() ? std::string() : fmt::format("each view of {}'s frame", device.device));
    if (!rig) {
      log_config.error("{}{}", rig.error().message,
                       one_device && view.empty()
                           ? " (give the device's frame size: [source.device] width and height)"
                           : "");
      return 1;
    }
    if (const std::string note = vision::rigNotes(*rig, config->rig.string()); !note.empty())
      log_config.warn("{}", note);
    if (one_device && (device.width == 0 || device.height == 0)) {
      const cv::Size whole = drivers::layoutFrameSize(config->layout, rig->left.imageSize());
      device.width = whole.width;
      device.height = whole.height;
    }
    if (config->trigger_box && !check) {
      auto hid = drivers::openHidDevice(config->trigger_vendor, config->trigger_product,
                                        config->trigger_serial);
      if (!hid) {
        log_source.error("{}", hid.error().message);
        return 1;
      }
      trigger = std::make_unique<drivers::TriggerBox>(
          std::move(*hid), config->fps, static_cast<uint16_t>(config->trigger_pulse_us));
    }
    if (config->source == daemon::SourceKind::kV4l2) {
      drivers::V4l2StereoConfig v;
      v.left = one_device ? device : config->left_camera;
      v.right = config->right_camera;
      v.layout = config->layout;
      v.fps = config->fps;
      source = drivers::makeV4l2Source(drivers::systemV4l2Io(), v, *rig, trigger.get());
    } else {
      drivers::LibcameraStereoConfig l;
      l.left_id = config->left_libcamera_id;
      l.right_id = config->right_libcamera_id;
      l.width = config->left_camera.width;
      l.height = config->left_camera.height;
      l.buffers = config->left_camera.buffers;
      l.fps = config->fps;
      source = drivers::makeLibcameraSource(l, *rig, trigger.get());
    }
  } else {
    drivers::ReplayOptions o;
    o.pace = config->pace == daemon::Pace::kFast   ? drivers::ReplayOptions::Pace::kFast
             : config->pace == daemon::Pace::kRate ? drivers::ReplayOptions::Pace::kRate
                                                   : drivers::ReplayOptions::Pace::kRecorded;
    o.fps = config->fps;
    o.loop = config->loop;
    o.preload = config->preload;
    auto r = drivers::makeReplaySource(config->recording, o, config->sim_faults);
    if (!r) {
      log_source.error("{}", r.error().message);
      return 1;
    }
    source = std::move(*r);
  }
  if (auto roi =
          vision::TrackingSession::checkRoi(source->rig(), config->roi, config->depth_tolerance_mm);
      !roi) {
    log_config.error("{}: [tracker] {}", config_path, roi.error().message);
    return 1;
  }
  // DDS Security's files are checked before anything runs (and by --check-config): when
  // [security] is configured and a file is wrong, the daemon does not start, unsecured or not.
  std::string security = "unsecured";
  const std::optional<dds::SecurityFiles>& configured = config->security;
  const dds::SecurityFiles* security_files = configured.has_value() ? &*configured : nullptr;
  if (security_files != nullptr) {
    auto subject = security_files->check();
    if (!subject) {
      daemon::log::get("dds").error("{}: [security] {}", config_path, subject.error().message);
      return 1;
    }
    security = "secured as " + *subject;
  }
  if (check) {
    std::printf("%s: ok (source %s, rig %s, DDS domain %u, topics %s, %s)\n", config_path.c_str(),
                source->name().c_str(), config->rig_id.c_str(), config->domain_id,
                config->topics.features.c_str(), security.c_str());
    return 0;
  }
  auto participant = dds::Participant::create(config->domain_id, security_files);
  if (!participant) {
    daemon::log::get("dds").error("{}", participant.error().message);
    return 1;
  }
  std::signal(SIGTERM, onSignal);
  std::signal(SIGINT, onSignal);
  // A file-size limit reached by the recorder must fail its write (EFBIG, handled), not kill
  // the tracking.
  std::signal(SIGXFSZ, SIG_IGN);
  if (trigger) {
    if (auto ok = trigger->start(); !ok) {
      log_source.error("{}", ok.error().message);
      return 1;
    }
  }
  daemon::Pipeline pipeline(*config, std::move(source), *participant);
  if (config->record) {
    // Tracking matters more than the recording: say it and run on.
    if (const std::string why = pipeline.startRecording(); !why.empty())
      daemon::log::get("recorder").warn("not recording: {}", why);
  }
  auto started = pipeline.start();
  if (!started) {
    log_pipeline.error("{}", started.error().message);
    return 1;
  }
  for (const std::string& w : *started) log_pipeline.warn("{}", w);
  log_pipeline.info("running, rig {}, DDS domain {}, topics {}, DDS {}", config->rig_id,
                    config->domain_id, config->topics.features, participant->securityState());
  if (security_files == nullptr) {
    daemon::log::get("dds").warn(
        "DDS Security is off: any participant on domain {} can command this appliance (lab use "
        "only; [security] in the config, docs/security.md)",
        config->domain_id);
  }
  for (const std::string& v : slow_stages) {  // checked by the option
    if (const auto stage = slowStage(v))
      pipeline.slowStageBy(stage->first, std::chrono::milliseconds(stage->second));
  }
  const daemon::Notifier notifier;
  const auto period = std::chrono::milliseconds(config->health_period_ms);
  const auto t0 = std::chrono::steady_clock::now();
  daemon::State last = daemon::State::kStarting;
  bool stalled = false;
  while (g_stop == 0) {
    std::this_thread::sleep_for(period);
    if (stall_after > 0 && !stalled && pipeline.tracked() >= static_cast<uint64_t>(stall_after)) {
      pipeline.stallTrackFor(std::chrono::seconds(5));
      stalled = true;
    }
    const daemon::State s = pipeline.health(notifier);
    if (s != last) {
      // The journal's priority says how bad: fault is an error, degraded a warning.
      log_pipeline.log(s == daemon::State::kFault      ? spdlog::level::err
                       : s == daemon::State::kDegraded ? spdlog::level::warn
                                                       : spdlog::level::info,
                       "state {}", daemon::toString(s));
      last = s;
    }
    if (run_for > 0 &&
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() >= run_for)
      break;
  }
  notifier.stopping();
  pipeline.stop();
  (void)pipeline.stopRecording();  // says what it recorded
  if (trigger) trigger->stop();
  log_pipeline.info("stopped after {} tracked pairs", pipeline.tracked());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {
    pulsetrack::daemon::log::get("pipeline").critical("fatal: {}", e.what());
  }
  return 1;
}
