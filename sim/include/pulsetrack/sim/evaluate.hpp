#pragma once
// Scores a track (record/track_csv.hpp) against a simulated scene's ground truth: the 3D error
// of every row with status ok, per feature and overall, outliers above a threshold, and what
// happened to the rows that are not ok.
//
// Cortex: a feature is the material point under its left pixel in the first frame it is ok
// (ray cast on the true surface); its truth in later frames is that material point's position.
// Plate: a feature is the nearest of the six features of eq. (5) in its first ok frame (within
// 2 mm; farther ones are counted unmatched).

#include <map>
#include <string>
#include <vector>

#include "pulsetrack/record/track_csv.hpp"
#include "pulsetrack/sim/scene.hpp"

namespace pulsetrack::sim {

struct FeatureScore {
  int id = 0;
  int ok_rows = 0;
  double rms_mm = 0.0;
  double max_mm = 0.0;
  std::string truth;  // "material (u, v)" or "plate feature k"
};

struct RowError {
  long frame = 0;
  int id = 0;
  double error_mm = 0.0;  // NaN when not scored
  cv::Vec3d error_vec;
};

// The ok rows' 3D error in three parts whose squares add up to the RMS's square: what each feature
// carries all along (the RMS of its mean error vector, e.g. a stereo match's bias), what changes
// from one pair to the next (white noise: half the mean square of a feature's error change between
// consecutive ok frames), and the slow rest (changes over many pairs: drift, a bias that follows
// the motion). Averaging pairs removes only the second; a better measurement per pair the others.
struct ErrorParts {
  double bias_mm = 0.0;
  double slow_mm = 0.0;
  double noise_mm = 0.0;
  long pairs = 0;  // consecutive ok rows of one feature that the noise comes from
};
ErrorParts errorParts(const std::vector<RowError>& rows);

struct Evaluation {
  int features = 0;
  int unmatched = 0;  // never ok, or no truth found
  long rows_ok = 0;
  double rms_mm = 0.0;
  double median_mm = 0.0;
  double p99_mm = 0.0;
  double max_mm = 0.0;
  long outliers = 0;  // ok rows with error above the threshold
  double outlier_threshold_mm = 0.5;
  std::map<std::string, long> not_ok;  // status -> rows
  ErrorParts parts;
  std::vector<FeatureScore> per_feature;
  std::vector<RowError> rows;
};

// `fields`: the track was made from the recording's fields (`pulsetrack track --fields`): row
// frame 2i + k is frame i's k-th field, k/2 of a frame later (a cortex scene).
vision::Result<Evaluation> evaluateTrack(const StereoSimulator& sim,
                                         const std::vector<record::TrackRow>& rows,
                                         double outlier_threshold_mm = 0.5, bool fields = false);

}  // namespace pulsetrack::sim
