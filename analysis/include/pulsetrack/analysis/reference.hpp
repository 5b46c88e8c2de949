#pragma once
// Inputs of the validation besides the recording (docs/validation.md documents the formats):
// the reference tracker's poses, the digitized divots and the experimenter's protocol log.
// Every reader fails naming file:line and what was wrong.

#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "pulsetrack/analysis/plate.hpp"
#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::analysis {

// A CSV file with a header line: cells as text, with their line numbers for messages.
struct CsvTable {
  std::string file;
  std::vector<std::string> header;  // lower-cased, trimmed
  std::vector<std::vector<std::string>> rows;
  std::vector<int> lines;
  // The column named one of `names`, or -1.
  [[nodiscard]] int column(std::initializer_list<const char*> names) const;
  // Cell (row, col) as a number; fails with file:line and the column's name.
  [[nodiscard]] vision::Result<double> number(size_t row, int col) const;
  // ... as a whole number in [lo, hi] (a cell past what the column can hold is named, not cast).
  [[nodiscard]] vision::Result<int64_t> integer(size_t row, int col, int64_t lo, int64_t hi) const;
};
vision::Result<CsvTable> readCsv(const std::filesystem::path& path);

struct TimedPose {
  long frame = -1;  // -1 when the file has no frame column
  int64_t t_ns = 0;
  Pose pose = Pose::Identity();
};

struct PoseSeries {
  std::vector<TimedPose> poses;
  int missing = 0;     // rows the tracker marked missing (NDI: "MISSING", empty cells), skipped
  bool timed = false;  // the file has a time column
};

// Timestamped rigid-body poses, as NDI tools export them or as 4x4 matrices:
//   time: t_ns (ns) or t / time / timestamp (s); frame (either is needed to match camera frames)
//   pose: q0|qw, qx, qy, qz with tx, ty, tz (mm), or m00 .. m23 (row-major, 3x4 or 4x4)
vision::Result<PoseSeries> readPoses(const std::filesystem::path& path);

// divot,x,y,z: the eight divots digitized in the tracker's frame, mm.
vision::Result<std::array<Vec3, 8>> readDivots(const std::filesystem::path& path);

// One acquisition of the protocol: its set (0 = registration), its frames and the box the
// experimenter drew around the six features on its first frame.
struct Acquisition {
  int set = 0;
  int acquisition = 0;
  long first_frame = 0, last_frame = 0;
  std::array<int, 4> roi_left{}, roi_right{};  // x, y, width, height
};
vision::Result<std::vector<Acquisition>> readProtocol(const std::filesystem::path& path);

}  // namespace pulsetrack::analysis
