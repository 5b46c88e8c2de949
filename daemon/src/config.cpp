#include "pulsetrack/daemon/config.hpp"

#include <fmt/format.h>

#include <algorithm>

#include "pulsetrack/cfg/table_reader.hpp"

namespace pulsetrack::daemon {

using cfg::TableReader;
using vision::fail;

namespace {

cv::Rect rect(TableReader& r, const char* key, const cv::Rect& def, std::string& error,
              const std::string& file) {
  const std::vector<double> v =
      r.numbers(key, {double(def.x), double(def.y), double(def.width), double(def.height)}, 4, 4,
                0.0, 100000.0);
  for (const double x : v) {
    if (x != std::floor(x) && error.empty())
      error = fmt::format("{}: {}: expected 4 whole numbers of pixels", file, r.child(key));
  }
  if (v[2] < 1 || v[3] < 1) {
    if (error.empty())
      error = fmt::format("{}: {}: width and height must be positive", file, r.child(key));
  }
  return {static_cast<int>(v[0]), static_cast<int>(v[1]), static_cast<int>(v[2]),
          static_cast<int>(v[3])};
}

rt::ThreadPolicy policy(TableReader& r, const char* key, const rt::ThreadPolicy& def,
                        std::string& error) {
  rt::ThreadPolicy p = def;
  if (const toml::table* t = r.table(key)) {
    TableReader s(*t, r.file(), r.child(key), &error);
    p.fifo_priority = s.integer("priority", def.fifo_priority, 0, 99);
    p.cpu = s.integer("cpu", def.cpu, -1, 1023);
    s.finish();
  }
  return p;
}

void camera(const toml::table& t, const std::string& file, const std::string& prefix,
            drivers::V4l2CameraConfig& c, std::string& libcamera_id, std::string& error) {
  TableReader s(t, file, prefix, &error);
  c.device = s.string("device", c.device);
  libcamera_id = s.string("libcamera_id", "");
  c.width = s.integer("width", c.width, 16, 16384);
  c.height = s.integer("height", c.height, 16, 16384);
  c.pixel_format = s.string("pixel_format", "GREY", {"GREY", "Y16", "YUYV"});
  c.buffers = s.integer("buffers", c.buffers, 3, 32);
  const int exposure = s.integer("exposure_us", 0, 0, 10'000'000);
  if (exposure > 0) c.exposure_us = exposure;
  const int gain = s.integer("gain", -1, -1, 1'000'000);
  if (gain >= 0) c.gain = gain;
  c.trigger_control = static_cast<uint32_t>(s.integer("trigger_control", 0, 0, 0x7fffffff));
  c.trigger_value = s.integer("trigger_value", 1, -1'000'000, 1'000'000);
  s.finish();
}

}  // namespace

vision::Result<DaemonConfig> parseDaemonConfig(const std::string& text,
                                               const std::filesystem::path& path) {
  const std::string file = path.string();
  toml::table root;
  if (std::string syntax; !cfg::parseToml(text, file, root, syntax)) return fail(syntax);
  DaemonConfig c;
  std::string error;
  TableReader r(root, file, "", &error);
  c.rig_id = r.string("rig_id", c.rig_id);
  if (c.rig_id.empty() && error.empty()) error = fmt::format("{}: rig_id must not be empty", file);
  if (const toml::table* t = r.table("dds")) {
    TableReader d(*t, file, "dds", &error);
    c.domain_id = static_cast<uint32_t>(d.integer("domain_id", 0, 0, 232));
    c.ros_namespace = d.string("namespace", "");
    d.finish();
    auto topics = dds::Topics::forNamespace(c.ros_namespace);
    if (!topics && error.empty())
      error = fmt::format("{}: [dds] namespace: {}", file, topics.error().message);
    else if (topics)
      c.topics = *topics;
  }
  if (const toml::table* t = r.table("security")) {
    // DDS Security: an SROS2 enclave folder, or each file (overriding the enclave's).
    TableReader sec(*t, file, "security", &error);
    const std::string enclave = sec.string("enclave", "");
    dds::SecurityFiles f = dds::SecurityFiles::inEnclave(path.parent_path() / enclave);
    const auto named = [&](const char* key, std::filesystem::path& target) {
      const std::string value = sec.string(key, "");
      if (!value.empty()) target = path.parent_path() / value;
      return !value.empty();
    };
    int given = 0;
    given += static_cast<int>(named("identity_ca", f.identity_ca));
    given += static_cast<int>(named("certificate", f.certificate));
    given += static_cast<int>(named("private_key", f.private_key));
    given += static_cast<int>(named("permissions_ca", f.permissions_ca));
    given += static_cast<int>(named("governance", f.governance));
    given += static_cast<int>(named("permissions", f.permissions));
    sec.finish();
    if (enclave.empty() && given < 6 && error.empty()) {
      error = fmt::format(
          "{}: [security] needs enclave = \"DIR\" (an SROS2 enclave folder) or all six files "
          "(identity_ca, certificate, private_key, permissions_ca, governance, permissions); "
          "remove [security] to run unsecured",
          file);
    }
    c.security = f;
    if (c.domain_id > 230 && error.empty()) {
      error =
          fmt::format("{}: [dds] domain_id {} with [security]: DDS Security's domains are 0-230",
                      file, c.domain_id);
    }
  }
  if (const toml::table* t = r.table("source")) {
    TableReader s(*t, file, "source", &error);
    const std::string kind = s.string("kind", "sim", {"sim", "replay", "v4l2", "libcamera"});
    c.source = kind == "replay"      ? SourceKind::kReplay
               : kind == "v4l2"      ? SourceKind::kV4l2
               : kind == "libcamera" ? SourceKind::kLibcamera
                                     : SourceKind::kSim;
    const std::string scene = s.string("scene", "scenes/cortex-60s.toml");
    const std::string recording = s.string("recording", "");
    c.scene = path.parent_path() / scene;
    if (!recording.empty()) c.recording = path.parent_path() / recording;
    c.fps = s.number("fps", c.fps, 0.1, 1000.0);
    const std::string pace = s.string("pace", "realtime", {"realtime", "fast", "rate"});
    c.pace = pace == "fast" ? Pace::kFast : pace == "rate" ? Pace::kRate : Pace::kRealtime;
    c.preload = s.boolean("preload", c.preload);
    c.loop = s.boolean("loop", c.loop);
    c.lossless = s.boolean("lossless", c.lossless);
    const std::string rig = s.string("rig", "");
    if (!rig.empty()) c.rig = path.parent_path() / rig;
    c.left_camera.device = "/dev/video0";
    c.right_camera.device = "/dev/video1";
    if (const toml::table* lt = s.table("left"))
      camera(*lt, file, "source.left", c.left_camera, c.left_libcamera_id, error);
    if (const toml::table* rtab = s.table("right"))
      camera(*rtab, file, "source.right", c.right_camera, c.right_libcamera_id, error);
    const std::string layout = s.string("layout", "two", {"two", "sbs", "tb"});
    c.layout = layout == "sbs"  ? drivers::StereoLayout::kSideBySide
               : layout == "tb" ? drivers::StereoLayout::kTopBottom
                                : drivers::StereoLayout::kTwoCameras;
    c.device_camera.device = "/dev/video0";
    c.device_camera.width = 0;  // the rig's
    c.device_camera.height = 0;
    if (const toml::table* dt = s.table("device")) {
      std::string unused;
      camera(*dt, file, "source.device", c.device_camera, unused, error);
    }
    const bool one_device = c.layout != drivers::StereoLayout::kTwoCameras;
    if (one_device && c.source != SourceKind::kV4l2 && error.empty())
      error = fmt::format(
          "{}: source.layout = \"{}\" (one device carrying both views) is for kind = \"v4l2\"",
          file, layout);
    if (one_device && (s.table("left") != nullptr || s.table("right") != nullptr) && error.empty())
      error = fmt::format(
          "{}: source.layout = \"{}\": one device carries both views: describe it in "
          "[source.device], not [source.left] / [source.right]",
          file, layout);
    if (!one_device && s.table("device") != nullptr && error.empty())
      error = fmt::format(
          "{}: [source.device] is for one device carrying both views (layout = \"sbs\" or "
          "\"tb\"); two cameras are [source.left] and [source.right]",
          file);
    const bool hardware = c.source == SourceKind::kV4l2 || c.source == SourceKind::kLibcamera;
    if (hardware && c.rig.empty() && error.empty())
      error = fmt::format("{}: source.rig (the rig's calibration) is required with kind = \"{}\"",
                          file, kind);
    if (c.source == SourceKind::kLibcamera &&
        (c.left_libcamera_id.empty() || c.right_libcamera_id.empty()) && error.empty())
      error = fmt::format(
          "{}: source.left.libcamera_id and source.right.libcamera_id are required with kind = "
          "\"libcamera\" (pulsetrackd --list-cameras shows them)",
          file);
    if (const toml::table* f = s.table("faults")) {
      TableReader ft(*f, file, "source.faults", &error);
      drivers::SimFaults& sf = c.sim_faults;
      sf.missing_trigger_every = ft.integer("missing_trigger_every", 0, 0, 1000000);
      sf.left_drop_every = ft.integer("left_drop_every", 0, 0, 1000000);
      sf.right_miss_every = ft.integer("right_miss_every", 0, 0, 1000000);
      sf.outage_every_s = ft.number("outage_every_s", 0.0, 0.0, 86400.0);
      sf.outage_s = ft.number("outage_s", 0.0, 0.0, 3600.0);
      ft.finish();
      if ((sf.outage_every_s > 0) != (sf.outage_s > 0) && error.empty())
        error = fmt::format(
            "{}: source.faults: outage_every_s and outage_s go together (both 0, or both set)",
            file);
      if (sf.outage_every_s > 0 && sf.outage_s >= sf.outage_every_s && error.empty())
        error = fmt::format(
            "{}: source.faults: outage_s ({:g}) must be shorter than outage_every_s ({:g})", file,
            sf.outage_s, sf.outage_every_s);
      const bool pairing = sf.left_drop_every + sf.right_miss_every > 0;
      const bool any = pairing || sf.missing_trigger_every > 0 || sf.outage_every_s > 0;
      const bool at_rate = c.source == SourceKind::kReplay && c.pace == Pace::kRate;
      if (any && c.source != SourceKind::kSim && !(at_rate && !pairing) && error.empty())
        error = fmt::format(
            "{}: source.faults: only the simulated rig (kind = \"sim\") can show injected "
            "faults, and a replay at a rate (pace = \"rate\") missing triggers and outages",
            file);
    }
    s.finish();
    if (c.lossless && c.source != SourceKind::kReplay && error.empty())
      error = fmt::format("{}: source.lossless: only a replay can wait for the pipeline", file);
    if (c.source == SourceKind::kReplay && c.recording.empty() && error.empty())
      error = fmt::format("{}: source.recording is required with kind = \"replay\"", file);
  } else {
    c.scene = path.parent_path() / "scenes/cortex-60s.toml";
  }
  if (const toml::table* t = r.table("trigger")) {
    TableReader s(*t, file, "trigger", &error);
    c.trigger_box = s.string("kind", "none", {"none", "box"}) == "box";
    c.trigger_vendor = static_cast<uint16_t>(s.integer("vendor_id", 0x1209, 0, 0xffff));
    c.trigger_product = static_cast<uint16_t>(s.integer("product_id", 0x7054, 0, 0xffff));
    c.trigger_serial = s.string("serial", "");
    c.trigger_pulse_us = s.integer("pulse_width_us", 100, 1, 100000);
    s.finish();
    if (c.trigger_box && c.layout != drivers::StereoLayout::kTwoCameras && error.empty())
      error = fmt::format(
          "{}: [trigger] kind = \"box\" with one device carrying both views (source.layout): "
          "its views are exposed together, there is nothing to trigger",
          file);
  }
  if (const toml::table* t = r.table("recorder")) {
    TableReader s(*t, file, "recorder", &error);
    c.record = s.boolean("enabled", false);
    const std::string dir = s.string("dir", "/var/lib/pulsetrack/recordings");
    c.record_dir = path.parent_path() / dir;
    c.record_slots = s.integer("slots", 32, 2, 4096);
    c.record_min_free_mb = s.integer("min_free_mb", 1024, 0, 1000000);
    c.record_resume = s.boolean("resume", true);
    s.finish();
  } else {
    c.record_dir = "/var/lib/pulsetrack/recordings";
  }
  if (const toml::table* t = r.table("tracker")) {
    TableReader s(*t, file, "tracker", &error);
    c.roi.left = rect(s, "roi_left", c.roi.left, error, file);
    c.roi.right = rect(s, "roi_right", c.roi.right, error, file);
    c.depth_tolerance_mm = s.number("depth_tolerance_mm", c.depth_tolerance_mm, 0.1, 500.0);
    c.retry_interval_s = s.number("retry_interval_s", c.retry_interval_s, 0.05, 3600.0);
    c.velocity_window_s = s.number("velocity_window_s", c.velocity_window_s, 0.0, 10.0);
    c.tracker.max_features = s.integer("max_features", c.tracker.max_features, 1, 1000);
    c.tracker.detector = s.string("detector", "harris", {"harris", "blobs"}) == "blobs"
                             ? vision::Detector::kDarkBlobs
                             : vision::Detector::kHarris;
    c.tracker.refinement = s.boolean("refinement", c.tracker.refinement);
    c.tracker.stereo_refresh =
        s.integer("stereo_refresh", c.tracker.stereo_refresh, 0, c.tracker.max_features);
    c.tracker.template_refresh =
        s.integer("template_refresh", c.tracker.template_refresh, 0, c.tracker.max_features);
    c.tracker.min_stereo_confirmed =
        s.number("min_stereo_confirmed", c.tracker.min_stereo_confirmed, 0.0, 1.0);
    const std::string scale = s.string("scale", "auto", {"auto", "1", "0.5"});
    c.tracker_scale = scale == "1" ? 1.0 : scale == "0.5" ? 0.5 : 0.0;
    s.finish();
  }
  if (const toml::table* t = r.table("field")) {
    TableReader s(*t, file, "field", &error);
    vision::FieldConfig& f = c.field;
    f.enabled = s.boolean("enabled", f.enabled);
    f.spacing_mm = s.number("spacing_mm", f.spacing_mm, 0.05, 20.0);
    f.margin_mm = s.number("margin_mm", f.margin_mm, 0.0, 50.0);
    f.smoothing = s.number("smoothing", f.smoothing, 1e-6, 1e6);
    f.huber_k = s.number("huber_k", f.huber_k, 1.0, 100.0);
    f.max_grid_points = s.integer("max_grid_points", f.max_grid_points, 4, 1'000'000);
    f.reach = s.number("reach", f.reach, 1.0, 100.0);
    s.finish();
    if (auto ok = vision::checkFieldConfig(f); !ok && error.empty())
      error = fmt::format("{}: {}", file, ok.error().message);
  }
  if (const toml::table* t = r.table("preview")) {
    TableReader s(*t, file, "preview", &error);
    c.preview.enabled = s.boolean("enabled", c.preview.enabled);
    c.preview.rate_hz = s.number("rate_hz", c.preview.rate_hz, 0.2, 30.0);
    c.preview.scale = s.integer("scale", c.preview.scale, 1, 8);
    c.preview.jpeg_quality = s.integer("jpeg_quality", c.preview.jpeg_quality, 10, 100);
    s.finish();
  }
  if (const toml::table* t = r.table("prediction")) {
    TableReader s(*t, file, "prediction", &error);
    vision::PredictionConfig& p = c.prediction;
    p.enabled = s.boolean("enabled", p.enabled);
    std::vector<double> ms(p.horizons_s.size());
    std::transform(p.horizons_s.begin(), p.horizons_s.end(), ms.begin(),
                   [](double h) { return h * 1e3; });
    ms = s.numbers("horizons_ms", ms, 1, vision::kMaxHorizons, 1.0, 2000.0);
    p.horizons_s.resize(ms.size());
    std::transform(ms.begin(), ms.end(), p.horizons_s.begin(), [](double h) { return h * 1e-3; });
    p.step_s = s.number("step_ms", p.step_s * 1e3, 5.0, 500.0) * 1e-3;
    p.order = s.integer("order", p.order, 2, vision::kMaxOrder);
    p.memory_s = s.number("memory_s", p.memory_s, 1.0, 3600.0);
    p.error_memory_s = s.number("error_memory_s", p.error_memory_s, 0.5, 600.0);
    s.finish();
    if (auto ok = vision::checkPredictionConfig(p); !ok && error.empty())
      error = fmt::format("{}: {}", file, ok.error().message);
  }
  if (const toml::table* t = r.table("realtime")) {
    TableReader s(*t, file, "realtime", &error);
    c.lock_memory = s.boolean("lock_memory", c.lock_memory);
    c.deadline_ms = s.number("deadline_ms", c.deadline_ms, 0.1, 10000.0);
    c.capture = policy(s, "capture", c.capture, error);
    c.track = policy(s, "track", c.track, error);
    c.publish = policy(s, "publish", c.publish, error);
    c.off_path = policy(s, "off_path", c.off_path, error);
    if (c.off_path.fifo_priority != 0 && error.empty()) {
      error = fmt::format(
          "{}: [realtime] off_path priority is {}: the stages off the features' path run at "
          "normal priority (0), so that they never take a core from it",
          file, c.off_path.fifo_priority);
    }
    s.finish();
  }
  if (const toml::table* t = r.table("health")) {
    TableReader s(*t, file, "health", &error);
    c.health_period_ms = s.integer("period_ms", c.health_period_ms, 10, 60000);
    s.finish();
  }
  r.finish();
  if (!error.empty()) return fail(error);
  return c;
}

vision::Result<DaemonConfig> loadDaemonConfig(const std::filesystem::path& path) {
  std::string text;
  if (std::string error; !cfg::readTomlText(path, "config file", text, error)) return fail(error);
  return parseDaemonConfig(text, path);
}

}  // namespace pulsetrack::daemon
