#pragma once
// The paper's validation plate (section 3.B) and protocol (section 4): an 80 x 80 mm plate
// with six features (0.5 mm conical holes, eq. 5) and eight divots (3 mm hemispherical holes,
// eq. 4) in the plate frame {P} (origin at the centre, z out of the plate's face), moved
// through the workspace in static poses and dynamic trajectories, and seen at the same
// instants by a simulated reference optical tracker (like the Optotrak CERTUS) that reports
// the markers' frame {M} in its own frame {O}, with a fixed transform O_T_C to the rig that the
// validation has to recover.

#include <array>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "pulsetrack/sim/rasterizer.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::sim {

// A rigid transform x_to = R x_from + t.
struct Pose {
  cv::Matx33d r = cv::Matx33d::eye();
  cv::Vec3d t{0, 0, 0};
  [[nodiscard]] cv::Vec3d operator*(const cv::Vec3d& p) const { return r * p + t; }
  [[nodiscard]] Pose operator*(const Pose& o) const { return {r * o.r, r * o.t + t}; }
  [[nodiscard]] Pose inverse() const { return {r.t(), -(r.t() * t)}; }
};

// Eq. (4): divots 1..8 in {P}, mm. Eq. (5): features 1..6 in {P}, mm.
const std::array<cv::Vec3d, 8>& nominalDivots();
const std::array<cv::Vec3d, 6>& nominalFeatures();

enum class PlateProtocol { kStatic, kDynamic };

struct PlateSpec {
  PlateProtocol protocol = PlateProtocol::kStatic;
  int registration_acquisitions = 10;  // static protocol: the registration set (section 4.B)
  int sets = 4;
  int acquisitions_per_set = 10;
  int frames_per_acquisition = 50;  // dynamic: 5 s at 10 fps (Table I)
  std::vector<double> set_depths_mm = {410.0, 440.0, 470.0, 500.0};
  double depth_spread_mm = 12.0;
  double lateral_range_mm = 25.0;  // +- in x and y (workspace 50 x 50 x 100 mm)
  double max_tilt_deg = 30.0;      // about x and y (60 deg range); any angle about z
  double max_speed_mm_s = 25.0;
  double max_angular_speed_deg_s = 9.7;
  double tracker_noise_mm = 0.1;  // RMS on the divots' positions
  // The cameras and the tracker stand still between sessions: O_T_C and the markers' body come
  // from this seed, so a static and a dynamic session share them (the scene's seed draws the
  // poses and the noise).
  int setup_seed = 1;
  double texture_px_per_mm = 20.0;
};

// One frame of the plate protocol.
struct PlateSample {
  int set = 0;          // 0: registration set (static protocol), 1..sets: test sets
  int acquisition = 0;  // within the set
  int frame_in_acquisition = 0;
  double t = 0.0;  // s
  Pose c_t_p;      // true plate pose in the rig frame {C}
  Pose o_t_m;      // the tracker's measurement of the markers' frame (with noise)
};

class PlateScene {
 public:
  PlateScene(const PlateSpec& spec, double fps, unsigned seed);

  [[nodiscard]] const PlateSpec& spec() const { return spec_; }
  [[nodiscard]] const std::vector<PlateSample>& samples() const { return samples_; }
  // The fixed, unknown transforms: rig -> tracker, and markers' frame on the plate.
  [[nodiscard]] const Pose& oTc() const { return o_t_c_; }
  [[nodiscard]] const Pose& pTm() const { return p_t_m_; }
  // Section 4.A: the divots digitized once in {O} (with the digitizer's noise) and the
  // tracker's O_T_M at that moment.
  [[nodiscard]] const std::array<cv::Vec3d, 8>& digitizedDivots() const { return digitized_; }
  [[nodiscard]] const Pose& digitizationMarkers() const { return digitization_o_t_m_; }

  void render(const vision::StereoRig& rig, const Pose& c_t_p, Rasterizer& raster, cv::Mat& left,
              cv::Mat& right);

 private:
  void buildTexture();
  void buildTrajectory(double fps, unsigned seed);

  PlateSpec spec_;
  Pose o_t_c_;
  Pose p_t_m_;
  std::array<cv::Vec3d, 8> digitized_{};
  Pose digitization_o_t_m_;
  std::vector<PlateSample> samples_;
  cv::Mat texture_;
  std::vector<cv::Vec2d> grid_;  // plate mesh in {P} (x, y)
  std::vector<cv::Vec3i> tris_;
  std::vector<ScreenVertex> screen_;
};

}  // namespace pulsetrack::sim
