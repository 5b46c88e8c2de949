#include "pulsetrack/record/track_csv.hpp"

#include <fmt/format.h>

#include <charconv>
#include <fstream>

namespace pulsetrack::record {

using vision::fail;

namespace {

template <class T>
bool parseField(std::string_view s, T& out) {
  const char* end = s.data() + s.size();
  const auto [ptr, ec] = std::from_chars(s.data(), end, out);
  return ec == std::errc() && ptr == end;
}

// Splits a CSV line at commas into `f` (views into `line`).
void splitCsv(const std::string& line, std::vector<std::string_view>& f) {
  f.clear();
  size_t start = 0;
  for (;;) {
    const size_t comma = line.find(',', start);
    f.emplace_back(line.data() + start, (comma == std::string::npos ? line.size() : comma) - start);
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
}

}  // namespace

vision::Result<std::vector<TrackRow>> readTrackCsv(const std::filesystem::path& path) {
  std::ifstream in(path);
  if (!in) return fail(fmt::format("{}: cannot open track file", path.string()));
  std::string line;
  if (!std::getline(in, line))
    return fail(
        fmt::format("{}: empty file, expected the header '{}'", path.string(), kTrackCsvHeader));
  if (!line.empty() && line.back() == '\r') line.pop_back();
  if (line != kTrackCsvHeader) {
    return fail(
        fmt::format("{}:1: header must be '{}', got '{}'", path.string(), kTrackCsvHeader, line));
  }
  std::vector<TrackRow> rows;
  long lineno = 1;
  std::vector<std::string_view> f;
  while (std::getline(in, line)) {
    ++lineno;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty()) continue;
    splitCsv(line, f);
    if (f.size() != 13) {
      return fail(
          fmt::format("{}:{}: expected 13 fields, got {}", path.string(), lineno, f.size()));
    }
    TrackRow r;
    const char* names[] = {"frame", "t", "id", "xl", "yl", "xr", "yr", "x", "y", "z", "ncc", "nmi"};
    bool ok = parseField(f[0], r.frame) && parseField(f[2], r.id);
    // One slot per field, in the header's order; frame and id are the integers parsed above.
    double* doubles[] = {nullptr, &r.t, nullptr, &r.xl, &r.yl,  &r.xr,
                         &r.yr,   &r.x, &r.y,    &r.z,  &r.ncc, &r.nmi};
    size_t bad = ok ? 99 : (parseField(f[0], r.frame) ? 2 : 0);
    for (size_t i = 0; ok && i < 12; ++i) {
      if (doubles[i] != nullptr && !parseField(f[i], *doubles[i])) {
        // from_chars rejects "nan": accept it for rows whose position is unknown.
        if (f[i] == "nan" || f[i] == "NaN") {
          *doubles[i] = std::numeric_limits<double>::quiet_NaN();
        } else {
          ok = false;
          bad = i;
        }
      }
    }
    if (!ok) {
      return fail(fmt::format("{}:{}: field '{}' is not a number: '{}'", path.string(), lineno,
                              names[bad], f[bad]));
    }
    r.status = std::string(f[12]);
    if (r.status.empty()) return fail(fmt::format("{}:{}: empty status", path.string(), lineno));
    rows.push_back(std::move(r));
  }
  return rows;
}

vision::Result<void> writeTrackCsv(const std::filesystem::path& path,
                                   const std::vector<TrackRow>& rows) {
  std::ofstream out(path);
  if (!out) return fail(fmt::format("{}: cannot open for writing", path.string()));
  out << kTrackCsvHeader << '\n';
  for (const TrackRow& r : rows) {
    out << fmt::format(
        "{},{:.6f},{},{:.4f},{:.4f},{:.4f},{:.4f},{:.5f},{:.5f},{:.5f},{:.4f},{:.4f},{}\n", r.frame,
        r.t, r.id, r.xl, r.yl, r.xr, r.yr, r.x, r.y, r.z, r.ncc, r.nmi, r.status);
  }
  if (!out) return fail(fmt::format("{}: write failed", path.string()));
  return {};
}

bool isDeformationCsv(const std::filesystem::path& path) {
  std::ifstream in(path);
  std::string line;
  if (!std::getline(in, line)) return false;
  if (!line.empty() && line.back() == '\r') line.pop_back();
  return line == kDeformationCsvHeader;
}

vision::Result<std::vector<DeformationRow>> readDeformationCsv(const std::filesystem::path& path) {
  std::ifstream in(path);
  if (!in) return fail(fmt::format("{}: cannot open deformation file", path.string()));
  std::string line;
  if (!std::getline(in, line))
    return fail(fmt::format("{}: empty file, expected the header '{}'", path.string(),
                            kDeformationCsvHeader));
  if (!line.empty() && line.back() == '\r') line.pop_back();
  if (line != kDeformationCsvHeader) {
    return fail(fmt::format("{}:1: header must be '{}', got '{}'", path.string(),
                            kDeformationCsvHeader, line));
  }
  static constexpr const char* kNames[] = {"frame",
                                           "t",
                                           "dx",
                                           "dy",
                                           "dz",
                                           "vx",
                                           "vy",
                                           "vz",
                                           "velocity_delay",
                                           "displacement_sigma",
                                           "velocity_sigma",
                                           "cx",
                                           "cy",
                                           "cz",
                                           "ok",
                                           "total",
                                           "detections",
                                           "continuous"};
  constexpr size_t kFields = std::size(kNames);
  std::vector<DeformationRow> rows;
  std::vector<std::string_view> f;
  long lineno = 1;
  while (std::getline(in, line)) {
    ++lineno;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty()) continue;
    splitCsv(line, f);
    if (f.size() != kFields) {
      return fail(fmt::format("{}:{}: expected {} fields, got {}", path.string(), lineno, kFields,
                              f.size()));
    }
    DeformationRow r;
    double* doubles[] = {nullptr,
                         &r.t,
                         &r.dx,
                         &r.dy,
                         &r.dz,
                         &r.vx,
                         &r.vy,
                         &r.vz,
                         &r.velocity_delay,
                         &r.displacement_sigma,
                         &r.velocity_sigma,
                         &r.cx,
                         &r.cy,
                         &r.cz};
    int continuous = 0;
    int* ints[] = {&r.ok, &r.total, &r.detections, &continuous};
    for (size_t i = 0; i < kFields; ++i) {
      const bool ok = i == 0                   ? parseField(f[i], r.frame)
                      : i < std::size(doubles) ? parseField(f[i], *doubles[i])
                                               : parseField(f[i], *ints[i - std::size(doubles)]);
      if (!ok) {
        return fail(fmt::format("{}:{}: field '{}' is not a number: '{}'", path.string(), lineno,
                                kNames[i], f[i]));
      }
    }
    r.continuous = continuous != 0;
    rows.push_back(r);
  }
  return rows;
}

vision::Result<void> writeDeformationCsv(const std::filesystem::path& path,
                                         const std::vector<DeformationRow>& rows) {
  std::ofstream out(path);
  if (!out) return fail(fmt::format("{}: cannot open for writing", path.string()));
  out << kDeformationCsvHeader << '\n';
  for (const DeformationRow& r : rows) {
    out << fmt::format(
        "{},{:.17g},{:.17g},{:.17g},{:.17g},{:.17g},{:.17g},{:.17g},{:.17g},{:.17g},"
        "{:.17g},{:.17g},{:.17g},{:.17g},{},{},{},{}\n",
        r.frame, r.t, r.dx, r.dy, r.dz, r.vx, r.vy, r.vz, r.velocity_delay, r.displacement_sigma,
        r.velocity_sigma, r.cx, r.cy, r.cz, r.ok, r.total, r.detections, r.continuous ? 1 : 0);
  }
  if (!out) return fail(fmt::format("{}: write failed", path.string()));
  return {};
}

}  // namespace pulsetrack::record
