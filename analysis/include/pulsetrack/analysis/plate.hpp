#pragma once
// The validation plate's frames and the registration of the paper's sections 3.B-4.D, on
// measured data (a real reference tracker's or the simulator's):
//   divots digitized once -> their plane -> p_D,P in the markers' frame (sec. 4.A, eqs. 6-7)
//   eight divots in {O} -> the divots' frame O_T_D (eqs. 8-12)
//   six features in {C} -> the features' frame C_T_F (eqs. 14-18, see featureFrame)
//   ten registration acquisitions -> O_T_C by Levenberg-Marquardt (eq. 20)
//   every other acquisition -> error matrix E (eq. 21), E_T (eq. 22), E_R (axis-angle angle)

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <array>
#include <vector>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::analysis {

using Pose = Eigen::Isometry3d;
using Vec3 = Eigen::Vector3d;

// Eq. (4): divots 1..8, eq. (5): features 1..6, in the plate's frame {P}, mm.
const std::array<Vec3, 8>& plateDivots();
const std::array<Vec3, 6>& plateFeatures();

struct PlaneFit {
  Vec3 centroid = Vec3::Zero();
  Vec3 normal = Vec3::UnitZ();
  // Distances of the points to the plane (the paper's "plane fitting error").
  double mean_mm = 0, sd_mm = 0, max_mm = 0;
};
PlaneFit fitPlane(const std::vector<Vec3>& points);
Vec3 projectOntoPlane(const PlaneFit& plane, const Vec3& p);

// Section 4.A: the divots digitized in {O} with the markers' pose at that moment -> the divots
// in the markers' frame, projected onto their least-squares plane (eq. 6 and the plane).
struct DivotCalibration {
  std::array<Vec3, 8> in_markers{};
  PlaneFit plane;
};
DivotCalibration calibrateDivots(const std::array<Vec3, 8>& digitized_o, const Pose& o_t_m);

// Eqs. (8)-(12): the divots' frame from the eight divots (order of Fig. 5).
Pose divotFrame(const std::array<Vec3, 8>& p);
// Eqs. (14)-(18): the features' frame from the six features. Eq. (14) and (18) as printed (x from
// p6, origin from p2, p4, p5, p6) give an x axis 53 deg and an origin 2.8 mm away from {P} for
// the layout of eq. (5), contradicting eq. (13); the intended reading is used:
//   f0 = (p3 + p4 + p5 + p6) / 4,  f_xx = (p1 + p2) / 2 - f0,  f'_yy = (p3 + p4) / 2 - p5.
Pose featureFrame(const std::array<Vec3, 6>& p);

// Which measured point is plate feature 1..6: every 6-subset, every 4-subset of it as the line
// of features 3-6, oriented by the plate's normal facing the camera (origin of {C}), scored by
// the rigid fit to eq. (5). Fails when no assignment fits within `max_rms_mm`.
struct FeatureIdentification {
  std::array<int, 6> index{};  // into the input
  double rms_mm = 0;           // rigid fit to the layout
};
vision::Result<FeatureIdentification> identifyPlateFeatures(const std::vector<Vec3>& points,
                                                            double max_rms_mm = 0.5);

// Kabsch: the rigid transform taking `from` onto `to`, least squares.
Pose fitRigid(const std::vector<Vec3>& from, const std::vector<Vec3>& to);

// Eq. (21) and the two error figures.
Pose errorMatrix(const Pose& o_t_d, const Pose& o_t_c, const Pose& c_t_f);
double translationError(const Pose& e);  // eq. (22), mm
double rotationErrorDeg(const Pose& e);  // the axis-angle angle

struct Registration {
  Pose o_t_c = Pose::Identity();
  std::vector<Pose> residuals;  // E of each registration acquisition
  double lever_mm = 0;          // rotation residuals are scaled by it (mm per rad)
  int evaluations = 0;
};
// Eq. (20): O_T_C minimising, over the acquisitions, the translation of E and its rotation
// vector times `lever_mm` (the same order of magnitude: the displacement a rotation error
// causes at the features' span, 10 mm). Initialised by Kabsch on the frames' origins and axes.
vision::Result<Registration> registerFrames(const std::vector<Pose>& o_t_d,
                                            const std::vector<Pose>& c_t_f, double lever_mm = 10.0);

}  // namespace pulsetrack::analysis
