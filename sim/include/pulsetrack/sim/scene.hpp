#pragma once
// Scene files (config/scenes/*.toml) and the stereo simulator that renders them. The simulator
// is also a camera: StereoSimulator::render() produces frame pairs one at a time into caller
// buffers, which is what the daemon's sim source drives at the configured rate.

#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "pulsetrack/sim/camera_effects.hpp"
#include "pulsetrack/sim/cortex.hpp"
#include "pulsetrack/sim/plate.hpp"
#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::sim {

enum class SceneKind { kCortex, kPlate };

struct SceneSpec {
  std::string name;
  SceneKind kind = SceneKind::kCortex;
  std::filesystem::path rig_path;  // resolved against the scene file's folder
  double fps = 10.0;
  int frames = 0;  // 0: the scene's own count (cortex: 10 s; plate: its whole protocol)
  unsigned seed = 1;
  int supersample = 2;
  // The cameras deliver interlaced video (SD endoscope cameras): each frame's even rows (the top
  // field) are exposed at the frame's time, its odd rows half a frame later. Cortex scenes only.
  // Each field's exposure is blurred by the lens on its own; then the woven frame takes the
  // sensor's noise and the compression (which mixes the fields, as a recorder's does).
  bool interlaced = false;
  CameraEffectsSpec camera;  // both cameras ([camera]), or the left one when camera_right is set
  std::optional<CameraEffectsSpec> camera_right;  // [camera] with [camera.right]'s keys over it
  CortexSpec cortex;
  PlateSpec plate;
  std::string source_text;  // the file as read, copied into recordings
  std::filesystem::path source_path;
};

// Parses a scene file. Unknown keys, wrong types and out-of-range values are errors that name
// file:line and the key.
vision::Result<SceneSpec> loadScene(const std::filesystem::path& path);
vision::Result<SceneSpec> parseScene(const std::string& text, const std::filesystem::path& path);

class StereoSimulator {
 public:
  StereoSimulator(const SceneSpec& spec, const vision::StereoRig& rig);
  ~StereoSimulator();
  StereoSimulator(const StereoSimulator&) = delete;
  StereoSimulator& operator=(const StereoSimulator&) = delete;

  [[nodiscard]] const SceneSpec& spec() const { return spec_; }
  [[nodiscard]] const vision::StereoRig& rig() const { return rig_; }
  // How many frames the scene has (plate protocols fix it; cortex: spec.frames).
  [[nodiscard]] int frameCount() const;
  // Scene time of frame i, s.
  [[nodiscard]] double frameTime(int i) const;
  // Whether the camera drops frame i (it is then not recorded; its gap shows in time stamps).
  [[nodiscard]] bool dropped(int i) const;
  // Renders frame i into 8-bit grey images of the rig's size.
  void render(int i, cv::Mat& left, cv::Mat& right);

  [[nodiscard]] const CortexScene* cortex() const { return cortex_.get(); }
  [[nodiscard]] const PlateScene* plate() const { return plate_.get(); }

 private:
  SceneSpec spec_;
  vision::StereoRig rig_;
  Rasterizer raster_;
  CameraEffects left_fx_;
  CameraEffects right_fx_;
  std::unique_ptr<CortexScene> cortex_;
  std::unique_ptr<PlateScene> plate_;
  cv::Mat radiance_l_, radiance_r_;
  cv::Mat field_l_, field_r_;  // the later field's radiance (interlaced)
};

// Writes the scene as a recording (docs/recording-format.md) with scene.toml and truth/.
// `progress(done, total)` is called after each frame.
vision::Result<void> writeSimulation(StereoSimulator& sim, const std::filesystem::path& out,
                                     const std::function<void(int, int)>& progress = {});

}  // namespace pulsetrack::sim
