#pragma once
// `pulsetrack analyze`: the brain-motion analysis of the paper's section 6 on a track
// (record/track_csv.hpp):
//   - the cloud's displacement per frame: the mean of the ok features' displacements from their
//     reference positions (occluded features dropped; a feature that appears later, after a
//     re-detection, joins at the current displacement, so the cloud's membership changing does
//     not move its centre);
//   - missing frames found from the timestamps (the nominal period is the median step) and
//     filled by a natural cubic spline through the measured frames;
//   - DC and linear trend removed (the trend, the brain's slow shift or sag, is reported);
//   - spectrum per axis by FFT (Hann window, zero padding), its 3D amplitude
//     sqrt(Ax^2 + Ay^2 + Az^2) in mm, peaks located by parabolic interpolation and named:
//     breathing (strongest in 0.1-0.6 Hz), cardiac (strongest remaining in 0.6-2.5 Hz) and its
//     harmonic, breathing's harmonics 2-4, vasomotor (0.025-0.07 Hz);
//   - per-feature speeds between consecutive frames (mean, sigma, max), as section 6.

#include <string>
#include <vector>

#include "pulsetrack/analysis/plate.hpp"
#include "pulsetrack/analysis/stats.hpp"
#include "pulsetrack/record/track_csv.hpp"

namespace pulsetrack::analysis {

struct MotionOptions {
  int zero_padding = 8;        // FFT length: this many times the samples (rounded up)
  double min_peak_mm = 0.005;  // peaks below this amplitude are not reported
  double floor_factor = 6.0;   // ... nor below this many times the spectrum's median
};

struct SpectralPeak {
  double frequency_hz = 0;
  double amplitude_mm = 0;  // 3D amplitude of the sinusoid
  std::string name;         // "breathing", "breathing harmonic 2", "cardiac", ... or ""
};

struct MotionAnalysis {
  double period_s = 0;
  int frames_expected = 0;  // grid points from the first to the last frame
  int frames_measured = 0;
  int frames_filled = 0;  // by the spline
  int features = 0;
  std::vector<double> t;           // s from the first frame, uniform
  std::vector<Vec3> displacement;  // mm, the cloud's, filled
  std::vector<Vec3> detrended;     // mm, DC and trend removed
  Vec3 trend_mm_per_s = Vec3::Zero();
  Vec3 principal_axis = Vec3::UnitZ();
  std::vector<double> along_axis;  // detrended, projected on the principal axis, mm
  double peak_to_peak_mm = 0;      // of the detrended displacement's norm along the axis
  std::vector<double> frequency_hz, amplitude_mm;  // the 3D amplitude spectrum
  std::vector<SpectralPeak> peaks;
  Summary feature_speed_mm_s;  // every feature, consecutive frames
};

vision::Result<MotionAnalysis> analyzeMotion(const std::vector<record::TrackRow>& rows,
                                             const MotionOptions& options = {});
// The same analysis on the TrackingSession's deformation (`pulsetrack track --deformation`, the
// signal pulsetrackd publishes): no feature speeds (they need the track).
vision::Result<MotionAnalysis> analyzeMotion(const std::vector<record::DeformationRow>& rows,
                                             const MotionOptions& options = {});
// The analysis of a displacement series (t in s, increasing; mm).
vision::Result<MotionAnalysis> analyzeSeries(const std::vector<double>& t,
                                             const std::vector<Vec3>& displacement, int features,
                                             const std::vector<double>& speeds,
                                             const MotionOptions& options = {});

// A natural cubic spline through (x, y), x increasing, evaluated at `at`.
std::vector<double> naturalCubicSpline(const std::vector<double>& x, const std::vector<double>& y,
                                       const std::vector<double>& at);

}  // namespace pulsetrack::analysis
