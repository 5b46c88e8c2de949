#pragma once
// pulsetrackd's configuration (config/pulsetrackd.toml documents every key).

#include <filesystem>
#include <optional>
#include <string>

#include "pulsetrack/dds/dds.hpp"
#include "pulsetrack/drivers/source.hpp"
#include "pulsetrack/drivers/v4l2.hpp"
#include "pulsetrack/rt/thread_policy.hpp"
#include "pulsetrack/vision/deformation_field.hpp"
#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/motion_predictor.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"

namespace pulsetrack::daemon {

enum class SourceKind { kSim, kReplay, kV4l2, kLibcamera };
enum class Pace { kRealtime, kFast, kRate };

// [preview]: the cameras' low-rate view (sensor_msgs/CompressedImage, JPEG), off the real-time
// path: rt/[NS/]pulsetrack/{left,right}/image/compressed.
struct PreviewConfig {
  bool enabled = true;
  double rate_hz = 5.0;   // at most this often (0.2 to 30)
  int scale = 2;          // each side divided by this (1 to 8)
  int jpeg_quality = 80;  // 10 to 100
};

struct DaemonConfig {
  std::string rig_id = "rig-0";
  uint32_t domain_id = 0;
  std::string ros_namespace;  // [dds] namespace: one rig per topic namespace (ROS 2's)
  dds::Topics topics = *dds::Topics::forNamespace("");
  // [security]: DDS Security's files; none: unsecured (lab use, health says so).
  std::optional<dds::SecurityFiles> security;
  SourceKind source = SourceKind::kSim;
  std::filesystem::path scene;      // sim: resolved against the config file's folder
  std::filesystem::path recording;  // replay
  double fps = 30.0;
  Pace pace = Pace::kRealtime;
  bool loop = true;
  bool preload = false;
  // replay: hand over the next pair only when the last one is published (no pair dropped, at
  // the tracker's pace): the live pipeline's output for every pair of a recording.
  bool lossless = false;
  drivers::SimFaults sim_faults;  // [source.faults]
  // v4l2: the two cameras ([source.left], [source.right]) and the rig's calibration.
  drivers::V4l2CameraConfig left_camera, right_camera;
  // v4l2, [source] layout = "sbs" or "tb": one device carrying both views ([source.device]; its
  // width and height 0 until set: then the rig's image size, doubled along the layout).
  drivers::StereoLayout layout = drivers::StereoLayout::kTwoCameras;
  drivers::V4l2CameraConfig device_camera;
  std::string left_libcamera_id, right_libcamera_id;  // libcamera: the cameras' ids
  std::filesystem::path rig;
  // [trigger]: the HID trigger box, or none (free-running cameras: a health warning).
  bool trigger_box = false;
  uint16_t trigger_vendor = 0, trigger_product = 0;
  std::string trigger_serial;
  int trigger_pulse_us = 100;
  // [recorder]: lossless recording of the live stream, off the real-time path.
  bool record = false;
  std::filesystem::path record_dir;  // a new folder per run inside it
  int record_slots = 32;
  int record_min_free_mb = 1024;  // the recording stops below this much free space
  bool record_resume = true;      // and resumes (a new segment) when the disk has room again
  vision::Roi roi{{483, 339, 400, 340}, {476, 344, 400, 340}};
  double depth_tolerance_mm = 20.0;
  double retry_interval_s = 1.0;    // between detections that found nothing
  double velocity_window_s = 0.25;  // the published velocity's least-squares window
  double tracker_scale = 0.0;       // [tracker] scale: 0 auto, 1, 0.5 (SessionConfig::scale)
  vision::TrackerConfig tracker;
  vision::FieldConfig field;            // [field]: the dense deformation field (rt/.../field)
  vision::PredictionConfig prediction;  // [prediction]: latency compensation, with deformation
  PreviewConfig preview;
  bool lock_memory = true;
  double deadline_ms = 20.0;
  rt::ThreadPolicy capture{80, -1}, track{70, -1}, publish{60, -1};
  // The stages off the features' path (field, refresh, preview): always normal priority; their
  // CPU (-1: any). On a board, CPUs other than the track stage's keep them out of its caches.
  rt::ThreadPolicy off_path{0, -1};
  int health_period_ms = 500;
};

vision::Result<DaemonConfig> parseDaemonConfig(const std::string& text,
                                               const std::filesystem::path& path);
vision::Result<DaemonConfig> loadDaemonConfig(const std::filesystem::path& path);

}  // namespace pulsetrack::daemon
