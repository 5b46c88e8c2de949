#pragma once
// The synthetic cortex (issue: simulator): a curved patch of brain surface in a craniotomy,
// with a brain-like texture (a branching vessel network darker than the tissue at several
// scales, fine texture), wet specular highlights that move with the surface and saturate,
// smooth illumination, a passing shadow and an instrument that crosses part of the field.
// It moves as section 6 of the paper measured: slow brain shift (sag), vasomotor 0.03-0.05 Hz,
// breathing ~0.2 Hz with harmonics, cardiac ~1 Hz, amplitudes varying over the surface.
//
// Frames: scene frame {S} has its origin at the centre of the patch, z along the outward
// normal; material coordinates (u, v) are the rest position's (x, y) in {S}, in mm. The rig's
// left camera frame {C} is the reference: CortexScene::position(u, v, t) is the true 3D position
// of a material point at time t in {C}, in mm.

#include <filesystem>
#include <limits>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "pulsetrack/sim/rasterizer.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::sim {

struct Harmonic {
  double multiple = 2.0;  // of the fundamental frequency
  double relative_amplitude = 0.0;
  double phase_rad = 0.0;
};

// A periodic motion component: displacement(u, v, t) = amplitude * signal(t) * weight(u, v) * dir
// with signal(t) = sin(2 pi f t + phase) + sum_h r_h sin(2 pi m_h f t + phase_h) and
// weight(u, v) = 1 + gradient . (u, v) / radius (so its mean over the patch is 1).
struct Oscillation {
  std::string name;  // "vasomotor", "breathing", "cardiac", ...
  double amplitude_mm = 0.0;
  double frequency_hz = 0.0;
  double phase_rad = 0.0;
  std::vector<Harmonic> harmonics;
  cv::Vec2d gradient{0.0, 0.0};        // relative amplitude change per patch radius along u, v
  cv::Vec3d direction{0.0, 0.0, 1.0};  // in {S}; normalized on use
  bool enabled = true;
  // Changes over time (the motion predictor's cases), each exact in the truth. Over
  // [change_start_s, change_start_s + change_duration_s] the frequency goes linearly from
  // frequency_hz to frequency_end_hz and the amplitude from amplitude_mm to amplitude_end_mm (the
  // phase is the frequency's integral); NaN: no change. irregularity > 0: each cycle's length and
  // amplitude are drawn around the nominal with that relative standard deviation (seeded by
  // irregularity_seed), the phase continuous, the amplitude blended over each cycle.
  double frequency_end_hz = std::numeric_limits<double>::quiet_NaN();
  double amplitude_end_mm = std::numeric_limits<double>::quiet_NaN();
  double change_start_s = 0.0;
  double change_duration_s = 0.0;
  double irregularity = 0.0;
  unsigned irregularity_seed = 1;
};

// An Oscillation's signal over time: sin(theta + phase) + sum_h r_h sin(m_h theta + phase_h),
// scaled by the amplitude (mm), where theta is the phase the frequency (changing, irregular)
// integrates to. Cycles of an irregular oscillation are drawn once, up to `horizon_s`.
class OscillationClock {
 public:
  explicit OscillationClock(const Oscillation& o, double horizon_s = 4.0 * 3600.0);
  // The displacement along the direction at the patch's mean (weight 1), mm.
  [[nodiscard]] double value(double t) const;
  [[nodiscard]] double frequency(double t) const;  // Hz, the nominal one at t
  [[nodiscard]] double amplitude(double t) const;  // mm, the nominal one at t

 private:
  [[nodiscard]] double theta(double t) const;  // rad, without the phase
  Oscillation o_;
  bool changes_ = false;
  std::vector<double> cycle_start_, cycle_amp_;  // irregular: per cycle
};

// Slow brain shift: the surface sinks along -z of {S} by depth_mm * (1 - exp(-t / tau)),
// more in the centre than at the rim (weight 1 - 0.5 (r / radius)^2), and turns about
// rotation_axis (in {S}, through the patch centre) by rotation_deg * (1 - exp(-t / tau)): the
// whole deformed surface, oscillations included, so the features' views change shape over hours.
struct Sag {
  double depth_mm = 0.0;
  double time_constant_s = 120.0;
  bool enabled = false;
  double rotation_deg = 0.0;
  cv::Vec3d rotation_axis{1.0, 0.0, 0.0};  // normalized on use
};

// An instrument (a rod, radius in mm) held above the surface, crossing the field between
// start_s and start_s + duration_s along a straight path in {S}.
struct Instrument {
  bool enabled = false;
  double start_s = 0.0;
  double duration_s = 4.0;
  double radius_mm = 3.0;
  double height_mm = 25.0;          // above the patch centre
  cv::Vec2d from_mm{-60.0, -20.0};  // tip position in {S} (x, y) at start and end
  cv::Vec2d to_mm{-5.0, 0.0};
  double length_mm = 120.0;  // the rod runs from the tip away along -x of {S}
  double albedo = 0.45;
  // The fraction of the duration the tip rests at to_mm (the rest of it: coming and going,
  // sinusoidal). 0: it turns round at to_mm (a crossing).
  double hold_fraction = 0.0;
  // Repeated crossings: every period_s from start_s (0: once), `repeats` times (0: for ever).
  double period_s = 0.0;
  int repeats = 0;
};

// A soft shadow band (a hand between lamp and field) sweeping over the field.
struct Shadow {
  bool enabled = false;
  double start_s = 0.0;
  double duration_s = 5.0;
  double depth = 0.45;  // 0: none, 1: black
  double width_mm = 15.0;
  double softness_mm = 6.0;
};

struct CortexSpec {
  double distance_mm = 450.0;     // from the left camera to the patch centre
  double tilt_deg = 30.0;         // surface normal against the viewing direction
  double azimuth_deg = 20.0;      // direction of that tilt
  cv::Vec2d offset_mm{0.0, 0.0};  // patch centre off the left optical axis (x, y in {C})
  double radius_mm = 30.0;        // craniotomy radius
  double curvature_radius_mm = 70.0;
  double gyri_amplitude_mm = 0.8;
  double mesh_step_mm = 0.5;
  double texture_px_per_mm = 32.0;
  int vessel_trees = 16;
  // "brain", or "dots": a test pattern of dark discs (radius 0.4 mm, every 4 mm from (0, 0))
  // whose centroids a test can measure against the model's projection, or "image": a real
  // photograph of tissue (texture_image, e.g. an in-vivo endoscope frame) laid over the surface,
  // texture_image_mm wide, centred, mirrored to cover the patch where it is smaller; its glints
  // (grey >= 240) are inpainted first; its grey levels are the albedo (they belong to that scene's
  // light, not to the tissue).
  std::string texture = "brain";
  std::filesystem::path texture_image;  // resolved against the scene file's folder
  double texture_image_mm = 30.0;
  cv::Mat texture_image_grey;     // the image as read (parseScene reads it, or names why not)
  double tissue_albedo = 165.0;   // grey level of tissue under full light
  double vessel_contrast = 0.55;  // how much darker the largest vessels are
  double wrinkle_slope = 1.0;     // scale of the wet-tissue wrinkles' slopes (0: smooth)
  double specular_strength = 600.0;
  double specular_shininess = 300.0;
  double illumination_gradient = 0.15;
  double illumination_drift = 0.05;  // slow change of the light, relative
  double illumination_period_s = 40.0;
  std::vector<Oscillation> oscillations;
  Sag sag;
  Instrument instrument;
  Shadow shadow;
  unsigned seed = 1;
};

// The motion components of the paper's section 6, as the default cortex case uses them.
std::vector<Oscillation> paperMotion();

class CortexScene {
 public:
  explicit CortexScene(const CortexSpec& spec);

  [[nodiscard]] const CortexSpec& spec() const { return spec_; }
  // {S} -> {C}.
  [[nodiscard]] const cv::Matx33d& rotation() const { return r_cs_; }
  [[nodiscard]] const cv::Vec3d& translation() const { return t_cs_; }

  // Rest position in {S} of material point (u, v) (mm).
  [[nodiscard]] cv::Vec3d restPosition(double u, double v) const;
  // Displacement in {S} at time t.
  [[nodiscard]] cv::Vec3d displacement(double u, double v, double t) const;
  // True position of material point (u, v) at time t, in the left camera frame {C}.
  [[nodiscard]] cv::Vec3d position(double u, double v, double t) const;
  // The material point seen at left pixel `px` at time t (ray cast onto the deformed
  // surface); false when the ray misses the patch.
  bool materialAt(const vision::StereoRig& rig, const cv::Vec2d& px, double t, cv::Vec2d& uv) const;
  // Whether the instrument hides point p ({C}) from a camera centred at `camera_centre` ({C}).
  [[nodiscard]] bool occluded(const cv::Vec3d& p, const cv::Vec3d& camera_centre, double t) const;

  // The albedo texture (CV_32FC1) and its mapping from (u, v) mm to texture px.
  [[nodiscard]] const cv::Mat& texture() const { return texture_; }

  // Renders both views at time t into `left`, `right` (CV_32FC1 radiance, grey levels before
  // camera effects).
  void render(const vision::StereoRig& rig, double t, Rasterizer& raster, cv::Mat& left,
              cv::Mat& right);

 private:
  void buildTexture();
  void buildMeshes();
  [[nodiscard]] cv::Vec3d instrumentTip(double t) const;
  // Time since the start of the instrument's crossing under way at t; negative when none is.
  [[nodiscard]] double instrumentTime(double t) const;
  void shadeVertices(const vision::CameraModel& cam, const cv::Matx33d& r_xc, const cv::Vec3d& t_xc,
                     const cv::Vec3d& camera_centre, double t);

  CortexSpec spec_;
  std::vector<OscillationClock> clocks_;  // per oscillation
  cv::Matx33d r_cs_;
  cv::Vec3d t_cs_;
  cv::Vec3d light_c_;  // lamp position in {C}
  cv::Mat texture_;
  cv::Mat bone_texture_;
  cv::Mat flat_texture_;
  cv::Mat bump_du_, bump_dv_;  // slopes of the wrinkle height field
  double bump_px_per_mm_ = 8.0;
  std::vector<cv::Vec2f> bump_grad_;  // per cortex vertex
  // Cortex mesh: a grid of material points.
  int grid_n_ = 0;
  std::vector<cv::Vec2d> grid_uv_;
  std::vector<cv::Vec3i> cortex_tris_;
  std::vector<cv::Vec3d> world_;  // deformed positions in {C}, per frame
  std::vector<cv::Vec3d> normal_;
  std::vector<ScreenVertex> screen_;
  // Bone rim around the craniotomy.
  std::vector<cv::Vec3d> bone_c_;
  std::vector<cv::Vec2d> bone_uv_;
  std::vector<cv::Vec3i> bone_tris_;
  std::vector<ScreenVertex> bone_screen_;
  // Instrument (a capped cylinder).
  std::vector<cv::Vec3d> tool_local_;  // relative to the tip, in {S}
  std::vector<cv::Vec3i> tool_tris_;
  std::vector<ScreenVertex> tool_screen_;
};

}  // namespace pulsetrack::sim
