#pragma once
// `pulsetrack validate`: the paper's validation (sections 4-5) on a plate recording and the
// reference tracker's files: the features tracked per acquisition with the blob detector in
// the box the experimenter drew, identified against eq. (5), their frame C_T_F; the divots'
// frame O_T_D from the tracker; O_T_C registered on set 0 (or given); the error of every frame
// of sets 1.. (eqs. 21-22); Table II; the static test across sets and the dynamic test across
// speed populations (Kruskal-Wallis, Dunn-Bonferroni).

#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "pulsetrack/analysis/plate.hpp"
#include "pulsetrack/analysis/reference.hpp"
#include "pulsetrack/analysis/stats.hpp"

namespace pulsetrack::analysis {

struct ValidationInputs {
  std::filesystem::path recording;
  // Default to RECORDING/tracker/{markers,divots,digitization_markers,protocol}.csv.
  std::filesystem::path markers, divots, digitization, protocol;
  std::optional<Pose> o_t_c;  // a registration from an earlier run (a dynamic session has no set 0)
  double depth_tolerance_mm = 20.0;
  int max_features = 8;             // candidates per acquisition; the six are picked by the layout
  double rotation_scale_mm = 10.0;  // eq. (20): rotation residuals times this (mm per rad)
};

struct FrameResult {
  int set = 0, acquisition = 0;
  long frame = 0;
  int64_t t_ns = 0;
  bool measured = false;
  std::string why;  // when not measured
  Pose c_t_f = Pose::Identity(), o_t_d = Pose::Identity();
  double layout_rms_mm = 0;   // the six features' rigid fit to eq. (5)
  Pose e = Pose::Identity();  // eq. (21), sets 1..
  double e_t_mm = 0, e_r_deg = 0;
  double speed_mm_s = -1, angular_speed_deg_s = -1;  // from the tracker (-1: unknown)
};

struct GroupTest {
  std::string name;                 // "static: translation error by set", ...
  std::vector<std::string> groups;  // labels
  std::vector<std::vector<double>> values;
  std::optional<KruskalWallis> kw;
  std::string kw_error;
  std::vector<PairwiseComparison> pairs;
};

struct ValidationResult {
  DivotCalibration divots;
  Summary feature_plane_mm;  // distance of the six features to their plane, every frame
  Pose o_t_c = Pose::Identity();
  std::optional<Registration> registration;  // when computed here
  std::array<Summary, 6> table2{};  // |residual| per axis: x, y, z mm; alpha, beta, gamma deg
  std::vector<FrameResult> frames;
  int frames_measured = 0, frames_missing = 0;
  bool dynamic = false;
  std::vector<double> speed_limits, angular_speed_limits;  // the tertiles
  std::vector<GroupTest> tests;
};

vision::Result<ValidationResult> validate(const ValidationInputs& in,
                                          const std::function<void(size_t, size_t)>& progress = {});

}  // namespace pulsetrack::analysis
