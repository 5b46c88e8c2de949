#pragma once
// `pulsetrack track --field FIELD.csv [--field-every N] [--targets POINTS.csv]`: the dense
// deformation field pulsetrackd publishes (vision::DeformationField, the same code), written for
// the lab, with its figures; and the robot's question ("where is the material point that was at
// P in the reference pair now?") answered for every pair of a recording.
//
// FIELD.csv, every N-th pair with a field (docs/tools.md):
//   frame,t,signal,row,col,x,y,z,dx,dy,dz,confidence
//   x y z: where the grid point is in this pair; dx dy dz: since the signal's first pair (mm,
//   left camera frame); confidence 0: beyond the features' reach (x..dz empty).
// FIELD-map.png: the displacement along the surface normal over the grid, at the pair where the
// field's mean displacement was largest; FIELD-points.png: the normal displacement over time at
// the grid's centre and four points halfway to its corners, and the features' mean.
// POINTS.csv: one point per line, x,y,z in mm in the reference pair (a header line is allowed);
// TARGETS.csv (beside --out, NAME-targets.csv): frame,t,target,x,y,z,dx,dy,dz,confidence.

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "pulsetrack/vision/deformation_field.hpp"

namespace pulsetrack::tools {

// Reads POINTS.csv; the error names the file and line.
vision::Result<std::vector<cv::Vec3d>> readPoints(const std::filesystem::path& path);

class FieldOutput {
 public:
  // `field_csv` empty: no field file or figures; `targets` empty: no targets file.
  static vision::Result<FieldOutput> open(const std::string& field_csv, int every,
                                          const std::vector<cv::Vec3d>& targets,
                                          const std::string& targets_csv,
                                          const vision::FieldConfig& config, int max_features);
  // One pair's session result.
  vision::Result<void> add(long frame, double t, std::span<const vision::Feature> features,
                           bool detected, uint32_t detections, const cv::Vec3d& mean_displacement);
  // Flushes the files and draws the figures; returns what was written, one line each.
  vision::Result<std::vector<std::string>> finish();

 private:
  FieldOutput(const vision::FieldConfig& config, int max_features) : field_(config, max_features) {}
  vision::DeformationField field_;
  std::string field_path_, targets_path_;
  std::ofstream field_out_, targets_out_;
  int every_ = 10;
  long with_field_ = 0, field_rows_pairs_ = 0, target_rows_ = 0;
  std::vector<cv::Vec3d> targets_;
  // For the figures.
  struct Series {
    std::vector<double> t, mean;
    std::vector<std::vector<double>> at;  // per probe point
  } series_;
  uint32_t signal_ = 0;
  double best_mean_ = -1.0, best_t_ = 0.0;
  std::vector<double> best_map_;  // normal displacement per grid point (NaN beyond reach)
  int best_cols_ = 0, best_rows_ = 0;
  double spacing_ = 1.0;
};

}  // namespace pulsetrack::tools
