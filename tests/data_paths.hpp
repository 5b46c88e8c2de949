#pragma once
// Where the data that is not the project's lives (issue 35): OpenCV's sample images, from
// Debian's opencv-doc package (scripts/bootstrap installs it), and the real data sets beside the
// checkout (../shared/data; its README.md says where each came from), and the ROS message
// definitions Debian packages (ros-sensor-msgs, ros-geometry-msgs). Nothing fetched is
// committed to the project. The folders come from CMake (PULSETRACK_OPENCV_SAMPLES,
// PULSETRACK_SHARED_DATA, PULSETRACK_ROS_MSGS: the top CMakeLists.txt names them); environment
// variables of the same names override them at run time. The tests and benchmarks read them
// only through here and skip loudly, naming the folder, where one is absent.

#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

namespace pulsetrack::data {

inline std::filesystem::path fromEnvOr(const char* var, const char* built_in) {
  const char* v = std::getenv(var);
  return (v != nullptr && *v != '\0') ? std::filesystem::path(v) : std::filesystem::path(built_in);
}

// OpenCV's samples: left01..14.jpg, right01..14.jpg (13 stereo chessboard pairs, 9x6), aloe...
inline std::filesystem::path opencvSamples() {
  return fromEnvOr("PULSETRACK_OPENCV_SAMPLES", PULSETRACK_OPENCV_SAMPLES_DIR);
}

// A real data set: ../shared/data/NAME (middlebury-teddy, middlebury-cones, ...).
inline std::filesystem::path shared(const std::string& name) {
  return fromEnvOr("PULSETRACK_SHARED_DATA", PULSETRACK_SHARED_DATA_DIR) / name;
}

// The Middlebury 2003 photographs with true disparity, as ../shared/data holds them: teddy with
// Middlebury's disp2 (quarter pixels), cones with its disparity rounded to whole pixels.
struct PhotoWithTruth {
  std::filesystem::path dir;
  std::string disparity;  // the file in dir
  double scale;           // grey / scale = px
};
inline std::vector<PhotoWithTruth> middlebury() {
  return {{shared("middlebury-teddy"), "disparity.pgm", 4.0},
          {shared("middlebury-cones"), "gt.pgm", 1.0}};
}

// A ROS message definition from Debian's ROS packages (ros-sensor-msgs, ros-geometry-msgs):
// <PULSETRACK_ROS_MSGS>/<package>/msg/<name>.msg.
inline std::filesystem::path rosMsg(const std::string& package, const std::string& name) {
  return fromEnvOr("PULSETRACK_ROS_MSGS", PULSETRACK_ROS_MSGS_DIR) / package / "msg" /
         (name + ".msg");
}

// Why a folder is missing, for a loud skip or an error: empty when it is there.
inline std::string absent(const std::filesystem::path& dir) {
  std::error_code ec;
  if (std::filesystem::is_directory(dir, ec)) return {};
  return "data folder " + dir.string() +
         " is absent (OpenCV's samples: apt install opencv-doc, scripts/bootstrap; a real data "
         "set: ../shared/data beside the checkout, or PULSETRACK_SHARED_DATA)";
}

}  // namespace pulsetrack::data
