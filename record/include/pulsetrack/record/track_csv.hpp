#pragma once
// Track files: the tracker's output, one row per feature and frame, as `pulsetrack track`
// writes it and `evaluate`, `analyze` read it:
//   frame,t,id,xl,yl,xr,yr,x,y,z,ncc,nmi,status
// t in s; xl..yr in px; x, y, z in mm in the left camera frame {C}; status "ok" or the reason
// the feature was not measured and the gate that said so ("occluded:glint", "lost:no_peak",
// "outlier_surface:surface", ...).
//
// Deformation files: the TrackingSession's signal, one row per pair with ok features, as
// `pulsetrack track --deformation` writes it (the same values pulsetrackd publishes on
// rt/pulsetrack/deformation, in mm and s, printed to round-trip exactly) and `analyze` reads:
//   frame,t,dx,dy,dz,vx,vy,vz,velocity_delay,displacement_sigma,velocity_sigma,cx,cy,cz,ok,
//   total,detections,continuous

#include <filesystem>
#include <string>
#include <vector>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::record {

struct TrackRow {
  long frame = 0;
  double t = 0.0;
  int id = 0;
  double xl = 0, yl = 0, xr = 0, yr = 0;
  double x = 0, y = 0, z = 0;
  double ncc = 0, nmi = 0;
  std::string status;
  [[nodiscard]] bool ok() const { return status == "ok"; }
};

inline constexpr const char* kTrackCsvHeader = "frame,t,id,xl,yl,xr,yr,x,y,z,ncc,nmi,status";

// Fails naming file:line on a wrong header, a short row or a value that is not a number.
vision::Result<std::vector<TrackRow>> readTrackCsv(const std::filesystem::path& path);
vision::Result<void> writeTrackCsv(const std::filesystem::path& path,
                                   const std::vector<TrackRow>& rows);

struct DeformationRow {
  long frame = 0;
  double t = 0.0;                                     // s
  double dx = 0, dy = 0, dz = 0;                      // mm
  double vx = 0, vy = 0, vz = 0;                      // mm/s
  double velocity_delay = 0;                          // s
  double displacement_sigma = 0, velocity_sigma = 0;  // mm, mm/s
  double cx = 0, cy = 0, cz = 0;                      // mm, the ok features' centroid
  int ok = 0, total = 0, detections = 0;
  bool continuous = true;
};

inline constexpr const char* kDeformationCsvHeader =
    "frame,t,dx,dy,dz,vx,vy,vz,velocity_delay,displacement_sigma,velocity_sigma,cx,cy,cz,ok,total,"
    "detections,continuous";

vision::Result<std::vector<DeformationRow>> readDeformationCsv(const std::filesystem::path& path);
vision::Result<void> writeDeformationCsv(const std::filesystem::path& path,
                                         const std::vector<DeformationRow>& rows);
// Whether the file starts with the deformation header (else: a track file, or unreadable).
bool isDeformationCsv(const std::filesystem::path& path);

}  // namespace pulsetrack::record
