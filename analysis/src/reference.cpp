#include "pulsetrack/analysis/reference.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <fstream>
#include <sstream>

namespace pulsetrack::analysis {

using vision::fail;

namespace {

std::string trim(const std::string& s) {
  const auto b = s.find_first_not_of(" \t\r\"");
  const auto e = s.find_last_not_of(" \t\r\"");
  return b == std::string::npos ? "" : s.substr(b, e - b + 1);
}

std::vector<std::string> split(const std::string& line) {
  std::vector<std::string> cells;
  std::stringstream ss(line);
  for (std::string c; std::getline(ss, c, ',');) cells.push_back(trim(c));
  if (!line.empty() && line.back() == ',') cells.emplace_back();
  return cells;
}

}  // namespace

int CsvTable::column(std::initializer_list<const char*> names) const {
  for (const char* n : names) {
    const auto it = std::find(header.begin(), header.end(), n);
    if (it != header.end()) return static_cast<int>(it - header.begin());
  }
  return -1;
}

namespace {
// A frame index (and a protocol's set, acquisition and ROI numbers) no recording reaches.
constexpr int64_t kMaxFrame = (int64_t{1} << 31) - 1;
}  // namespace

vision::Result<double> CsvTable::number(size_t row, int col) const {
  const std::string& cell = rows[row][static_cast<size_t>(col)];
  double v = 0;
  const auto [ptr, ec] = std::from_chars(cell.data(), cell.data() + cell.size(), v);
  if (ec != std::errc() || ptr != cell.data() + cell.size() || cell.empty())
    return fail(fmt::format("{}:{}: column '{}': '{}' is not a number", file, lines[row],
                            header[static_cast<size_t>(col)], cell));
  return v;
}

vision::Result<int64_t> CsvTable::integer(size_t row, int col, int64_t lo, int64_t hi) const {
  const std::string& cell = rows[row][static_cast<size_t>(col)];
  // Read as an integer, not through a double (a stamp in ns past 2^53 would be rounded); a cell
  // written as a whole double ("12.0", "1e3") is taken when it is exact.
  int64_t v = 0;
  const auto [ptr, ec] = std::from_chars(cell.data(), cell.data() + cell.size(), v);
  bool whole = ec == std::errc() && ptr == cell.data() + cell.size() && !cell.empty();
  if (!whole) {
    auto d = number(row, col);
    if (!d) return std::unexpected(d.error());
    // Compared as doubles before the cast: a double past int64's range does not convert.
    whole = *d == std::floor(*d) && *d >= -9.0e18 && *d <= 9.0e18;
    if (whole) v = static_cast<int64_t>(*d);
  }
  if (!whole || v < lo || v > hi) {
    return fail(fmt::format("{}:{}: column '{}': '{}' is not a whole number from {} to {}", file,
                            lines[row], header[static_cast<size_t>(col)], cell, lo, hi));
  }
  return v;
}

vision::Result<CsvTable> readCsv(const std::filesystem::path& path) {
  std::ifstream in(path);
  if (!in) return fail(fmt::format("{}: cannot open", path.string()));
  CsvTable t;
  t.file = path.string();
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (trim(line).empty() || line[0] == '#') continue;
    std::vector<std::string> cells = split(line);
    if (t.header.empty()) {
      for (std::string& c : cells) {
        std::transform(c.begin(), c.end(), c.begin(),
                       [](unsigned char ch) { return std::tolower(ch); });
      }
      t.header = cells;
      continue;
    }
    if (cells.size() != t.header.size())
      return fail(fmt::format("{}:{}: {} cells, the header has {}", t.file, n, cells.size(),
                              t.header.size()));
    t.rows.push_back(std::move(cells));
    t.lines.push_back(n);
  }
  if (t.header.empty()) return fail(fmt::format("{}: empty (no header line)", t.file));
  return t;
}

vision::Result<PoseSeries> readPoses(const std::filesystem::path& path) {
  auto csv = readCsv(path);
  if (!csv) return std::unexpected(csv.error());
  const CsvTable& t = *csv;
  const int c_ns = t.column({"t_ns"}), c_s = t.column({"t", "time", "timestamp"});
  const int c_frame = t.column({"frame"});
  const std::array<int, 4> cq = {t.column({"q0", "qw"}), t.column({"qx"}), t.column({"qy"}),
                                 t.column({"qz"})};
  const std::array<int, 3> ct = {t.column({"tx"}), t.column({"ty"}), t.column({"tz"})};
  std::array<int, 12> cm{};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c)
      cm[(4 * static_cast<size_t>(r)) + c] = t.column({fmt::format("m{}{}", r, c).c_str()});
  const bool quat = std::all_of(cq.begin(), cq.end(), [](int c) { return c >= 0; }) &&
                    std::all_of(ct.begin(), ct.end(), [](int c) { return c >= 0; });
  const bool matrix = std::all_of(cm.begin(), cm.end(), [](int c) { return c >= 0; });
  if (!quat && !matrix)
    return fail(fmt::format(
        "{}: no pose columns: expected q0 (or qw), qx, qy, qz, tx, ty, tz, or m00 .. m23", t.file));
  PoseSeries out;
  out.timed = c_ns >= 0 || c_s >= 0;
  for (size_t i = 0; i < t.rows.size(); ++i) {
    const auto& row = t.rows[i];
    const bool missing = std::any_of(row.begin(), row.end(), [](const std::string& c) {
      return c.empty() || c == "MISSING" || c == "missing" || c == "nan" || c == "NaN";
    });
    if (missing) {
      ++out.missing;
      continue;
    }
    TimedPose p;
    if (c_frame >= 0) {
      auto f = t.integer(i, c_frame, 0, kMaxFrame);
      if (!f) return std::unexpected(f.error());
      p.frame = static_cast<long>(*f);
    }
    if (c_ns >= 0) {
      // Stamps up to 2^62 ns (146 years), in either direction.
      auto tv = t.integer(i, c_ns, -(int64_t{1} << 62), int64_t{1} << 62);
      if (!tv) return std::unexpected(tv.error());
      p.t_ns = *tv;
    } else if (c_s >= 0) {
      auto tv = t.number(i, c_s);
      if (!tv) return std::unexpected(tv.error());
      if (!(std::abs(*tv) <= 4.6e9)) {
        return fail(fmt::format("{}:{}: column '{}': {} s is not a time (at most 4.6e9 s)", t.file,
                                t.lines[i], t.header[static_cast<size_t>(c_s)], *tv));
      }
      p.t_ns = static_cast<int64_t>(std::llround(*tv * 1e9));
    }
    if (quat) {
      std::array<double, 7> v{};
      for (size_t k = 0; k < 4; ++k) {
        auto x = t.number(i, cq[k]);
        if (!x) return std::unexpected(x.error());
        v[k] = *x;
      }
      for (size_t k = 0; k < 3; ++k) {
        auto x = t.number(i, ct[k]);
        if (!x) return std::unexpected(x.error());
        v[4 + k] = *x;
      }
      Eigen::Quaterniond q(v[0], v[1], v[2], v[3]);
      if (std::fabs(q.norm() - 1.0) > 1e-3)
        return fail(fmt::format("{}:{}: the quaternion's norm is {:.6f}, not 1", t.file, t.lines[i],
                                q.norm()));
      p.pose.linear() = q.normalized().toRotationMatrix();
      p.pose.translation() = Vec3(v[4], v[5], v[6]);
    } else {
      Eigen::Matrix<double, 3, 4> m;
      for (int k = 0; k < 12; ++k) {
        auto x = t.number(i, cm[static_cast<size_t>(k)]);
        if (!x) return std::unexpected(x.error());
        m(k / 4, k % 4) = *x;
      }
      const Eigen::Matrix3d r = m.leftCols<3>();
      if ((r * r.transpose() - Eigen::Matrix3d::Identity()).norm() > 1e-3 || r.determinant() < 0)
        return fail(fmt::format("{}:{}: the 3x3 part is not a rotation", t.file, t.lines[i]));
      p.pose.linear() = r;
      p.pose.translation() = m.col(3);
    }
    out.poses.push_back(p);
  }
  if (out.poses.empty()) return fail(fmt::format("{}: no pose in the file", t.file));
  return out;
}

vision::Result<std::array<Vec3, 8>> readDivots(const std::filesystem::path& path) {
  auto csv = readCsv(path);
  if (!csv) return std::unexpected(csv.error());
  const CsvTable& t = *csv;
  const int cd = t.column({"divot"}), cx = t.column({"x"}), cy = t.column({"y"}),
            cz = t.column({"z"});
  if (cd < 0 || cx < 0 || cy < 0 || cz < 0)
    return fail(fmt::format("{}: expected the columns divot,x,y,z", t.file));
  std::array<Vec3, 8> d{};
  std::array<bool, 8> seen{};
  for (size_t i = 0; i < t.rows.size(); ++i) {
    auto k = t.number(i, cd), x = t.number(i, cx), y = t.number(i, cy), z = t.number(i, cz);
    for (const auto* v : {&k, &x, &y, &z}) {
      if (!*v) return std::unexpected(v->error());
    }
    if (!(*k >= 1 && *k <= 8) || *k != std::floor(*k))
      return fail(
          fmt::format("{}:{}: divot {} (they are numbered 1 to 8)", t.file, t.lines[i], *k));
    const int id = static_cast<int>(*k);
    d[static_cast<size_t>(id - 1)] = Vec3(*x, *y, *z);
    seen[static_cast<size_t>(id - 1)] = true;
  }
  for (size_t i = 0; i < 8; ++i) {
    if (!seen[i]) return fail(fmt::format("{}: divot {} is missing", t.file, i + 1));
  }
  return d;
}

vision::Result<std::vector<Acquisition>> readProtocol(const std::filesystem::path& path) {
  auto csv = readCsv(path);
  if (!csv) return std::unexpected(csv.error());
  const CsvTable& t = *csv;
  const char* names[] = {"set",         "acquisition", "first_frame", "last_frame",
                         "roi_left_x",  "roi_left_y",  "roi_left_w",  "roi_left_h",
                         "roi_right_x", "roi_right_y", "roi_right_w", "roi_right_h"};
  std::array<int, 12> col{};
  for (size_t k = 0; k < 12; ++k) {
    col[k] = t.column({names[k]});
    if (col[k] < 0) return fail(fmt::format("{}: no column '{}'", t.file, names[k]));
  }
  std::vector<Acquisition> out;
  for (size_t i = 0; i < t.rows.size(); ++i) {
    std::array<long, 12> v{};
    for (size_t k = 0; k < 12; ++k) {
      auto x = t.integer(i, col[k], 0, kMaxFrame);
      if (!x) return std::unexpected(x.error());
      v[k] = static_cast<long>(*x);
    }
    Acquisition a{static_cast<int>(v[0]), static_cast<int>(v[1]), v[2], v[3], {}, {}};
    for (size_t k = 0; k < 4; ++k) {
      a.roi_left[k] = static_cast<int>(v[4 + k]);
      a.roi_right[k] = static_cast<int>(v[8 + k]);
    }
    if (a.last_frame < a.first_frame)
      return fail(fmt::format("{}:{}: last_frame before first_frame", t.file, t.lines[i]));
    if (a.roi_left[2] < 16 || a.roi_left[3] < 16 || a.roi_right[2] < 16 || a.roi_right[3] < 16)
      return fail(fmt::format("{}:{}: a box smaller than 16 px", t.file, t.lines[i]));
    out.push_back(a);
  }
  if (out.empty()) return fail(fmt::format("{}: no acquisition", t.file));
  return out;
}

}  // namespace pulsetrack::analysis
