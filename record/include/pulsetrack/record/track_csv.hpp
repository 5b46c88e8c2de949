#pragma once
// Track files: the tracker's output, one row per feature and frame, as `pulsetrack track`
// writes it and `evaluate`, `analyze` read it:
//   frame,t,id,xl,yl,xr,yr,x,y,z,ncc,nmi,status
// t in s; xl..yr in px; x, y, z in mm in the left camera frame {C}; status "ok" or the reason
// the feature was not measured (occluded, lost, outlier, ...).

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

}  // namespace pulsetrack::record
