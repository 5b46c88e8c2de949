#pragma once
// The reports of `pulsetrack validate` and `pulsetrack analyze`: tables as CSV, figures as PNG
// (the paper's Figs. 7-9 in style) and one HTML page that shows them, plus the same tables as
// text for the terminal.

#include <filesystem>
#include <string>
#include <vector>

#include "pulsetrack/analysis/motion.hpp"
#include "pulsetrack/analysis/validation.hpp"

namespace pulsetrack::analysis {

// Table II, the plane fits and every group test, as the terminal shows them.
std::string formatValidation(const ValidationResult& r);
// frames.csv, registration.csv, table2.csv, statistics.csv, fig7_static.png, fig8_dynamic.png
// (dynamic sessions), report.html. Returns the files written.
vision::Result<std::vector<std::filesystem::path>> writeValidationReport(
    const ValidationResult& r, const std::filesystem::path& out_dir, const std::string& title);

// O_T_C as written to registration.csv (tx,ty,tz,qw,qx,qy,qz), read back for a dynamic session.
vision::Result<Pose> readRegistration(const std::filesystem::path& path);

struct NamedMotion {
  std::string name;  // the acquisition's (track file's) name
  MotionAnalysis motion;
};
std::string formatMotion(const NamedMotion& m);
// displacement_<name>.csv, spectrum_<name>.csv, peaks.csv, fig9_motion.png, report.html.
vision::Result<std::vector<std::filesystem::path>> writeMotionReport(
    const std::vector<NamedMotion>& acquisitions, const std::filesystem::path& out_dir);

}  // namespace pulsetrack::analysis
