#include "pulsetrack/analysis/report.hpp"

#include <fmt/format.h>

#include <fstream>

#include "pulsetrack/analysis/plot.hpp"

namespace pulsetrack::analysis {

using vision::fail;

namespace {

vision::Result<void> writeFile(const std::filesystem::path& p, const std::string& s,
                               std::vector<std::filesystem::path>& written) {
  std::ofstream f(p);
  f << s;
  f.close();
  if (!f) return fail(fmt::format("{}: cannot write", p.string()));
  written.push_back(p);
  return {};
}

std::string html(const std::string& s) {
  std::string o;
  for (const char c : s) {
    if (c == '<')
      o += "&lt;";
    else if (c == '>')
      o += "&gt;";
    else if (c == '&')
      o += "&amp;";
    else
      o += c;
  }
  return o;
}

std::string htmlTable(const std::vector<std::string>& head,
                      const std::vector<std::vector<std::string>>& rows) {
  std::string s = "<table><tr>";
  for (const auto& h : head) s += "<th>" + html(h) + "</th>";
  s += "</tr>\n";
  for (const auto& r : rows) {
    s += "<tr>";
    for (const auto& c : r) s += "<td>" + html(c) + "</td>";
    s += "</tr>\n";
  }
  return s + "</table>\n";
}

const char* kStyle =
    "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
    "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:3px 8px;"
    "text-align:right}th{background:#eee}img{max-width:100%;border:1px solid #ddd}</style>";

std::string poseColumns(const Pose& p) {
  const Eigen::Quaterniond q(p.linear());
  return fmt::format("{:.6f},{:.6f},{:.6f},{:.12f},{:.12f},{:.12f},{:.12f}", p.translation().x(),
                     p.translation().y(), p.translation().z(), q.w(), q.x(), q.y(), q.z());
}

const char* kAxes[6] = {"X (mm)", "Y (mm)", "Z (mm)", "alpha (deg)", "beta (deg)", "gamma (deg)"};

std::vector<std::vector<std::string>> table2Rows(const ValidationResult& r) {
  std::vector<std::vector<std::string>> rows;
  for (size_t k = 0; k < 6; ++k) {
    const Summary& s = r.table2[k];
    rows.push_back({kAxes[k], fmt::format("{:.3f}", s.mean), fmt::format("{:.3f}", s.sd),
                    fmt::format("{:.3f}", s.max)});
  }
  return rows;
}

std::vector<std::vector<std::string>> testRows(const GroupTest& t) {
  std::vector<std::vector<std::string>> rows;
  for (size_t g = 0; g < t.groups.size(); ++g) {
    const Summary s = summarize(t.values[g]);
    rows.push_back({t.groups[g], std::to_string(s.n), fmt::format("{:.3f}", s.median),
                    fmt::format("{:.3f}", s.q1), fmt::format("{:.3f}", s.q3),
                    fmt::format("{:.3f}", s.max)});
  }
  return rows;
}

std::string kwLine(const GroupTest& t) {
  if (!t.kw) return "Kruskal-Wallis: " + t.kw_error;
  std::string s = fmt::format(
      "Kruskal-Wallis H = {:.4f}, {} dof, p = {:.4g}{}", t.kw->h, t.kw->dof, t.kw->p,
      t.kw->p < 0.05 ? " (the groups differ, p < 0.05)" : " (no difference at p < 0.05)");
  for (const PairwiseComparison& c : t.pairs) {
    if (c.significant)
      s += fmt::format("; {} vs {}: Dunn z = {:.2f}, Bonferroni p = {:.3g} *",
                       t.groups[static_cast<size_t>(c.a)], t.groups[static_cast<size_t>(c.b)], c.z,
                       c.p_adjusted);
  }
  return s;
}

void boxAxes(Axes& ax, const GroupTest& t, const std::string& title, const std::string& ylabel) {
  ax.title = title;
  ax.ylabel = ylabel;
  for (size_t g = 0; g < t.groups.size(); ++g) ax.boxes.push_back({t.groups[g], t.values[g]});
  for (const PairwiseComparison& c : t.pairs) {
    if (c.significant) ax.brackets.push_back({c.a, c.b, "*"});
  }
}

}  // namespace

std::string formatValidation(const ValidationResult& r) {
  std::string s;
  s += fmt::format("frames measured: {} ({} not: see frames.csv)\n", r.frames_measured,
                   r.frames_missing);
  s += fmt::format("divot plane fit: mean {:.3f} mm, sd {:.3f}, max {:.3f}\n",
                   r.divots.plane.mean_mm, r.divots.plane.sd_mm, r.divots.plane.max_mm);
  s += fmt::format("feature plane fit (every frame): mean {:.3f} mm, sd {:.3f}, max {:.3f}\n",
                   r.feature_plane_mm.mean, r.feature_plane_mm.sd, r.feature_plane_mm.max);
  const Eigen::AngleAxisd aa(r.o_t_c.linear());
  s += fmt::format(
      "O_T_C: t = ({:.3f}, {:.3f}, {:.3f}) mm, rotation {:.3f} deg about ({:.4f}, {:.4f}, "
      "{:.4f})\n",
      r.o_t_c.translation().x(), r.o_t_c.translation().y(), r.o_t_c.translation().z(),
      aa.angle() * 180 / M_PI, aa.axis().x(), aa.axis().y(), aa.axis().z());
  if (r.registration) {
    s += fmt::format("Table II, registration residuals ({} acquisitions)\n",
                     r.registration->residuals.size());
    s += fmt::format("  {:12} {:>8} {:>8} {:>8}\n", "", "mean", "sigma", "max");
    for (const auto& row : table2Rows(r))
      s += fmt::format("  {:12} {:>8} {:>8} {:>8}\n", row[0], row[1], row[2], row[3]);
  }
  for (const GroupTest& t : r.tests) {
    s += t.name + "\n";
    s += fmt::format("  {:24} {:>5} {:>8} {:>8} {:>8} {:>8}\n", "group", "n", "median", "q1", "q3",
                     "max");
    for (const auto& row : testRows(t))
      s += fmt::format("  {:24} {:>5} {:>8} {:>8} {:>8} {:>8}\n", row[0], row[1], row[2], row[3],
                       row[4], row[5]);
    s += "  " + kwLine(t) + "\n";
  }
  return s;
}

vision::Result<std::vector<std::filesystem::path>> writeValidationReport(
    const ValidationResult& r, const std::filesystem::path& out, const std::string& title) {
  std::error_code ec;
  std::filesystem::create_directories(out, ec);
  if (ec) return fail(fmt::format("{}: {}", out.string(), ec.message()));
  std::vector<std::filesystem::path> w;
  std::string frames =
      "set,acquisition,frame,t_ns,measured,e_t_mm,e_r_deg,ex_mm,ey_mm,ez_mm,speed_mm_s,"
      "angular_speed_deg_s,layout_rms_mm,note\n";
  for (const FrameResult& f : r.frames) {
    const Vec3 t = f.e.translation();
    std::string note = f.why;
    std::replace(note.begin(), note.end(), ',', ';');
    frames += fmt::format(
        "{},{},{},{},{},{:.5f},{:.5f},{:.5f},{:.5f},{:.5f},{:.4f},{:.4f},{:.4f},{}\n", f.set,
        f.acquisition, f.frame, f.t_ns, f.measured ? 1 : 0, f.e_t_mm, f.e_r_deg, t.x(), t.y(),
        t.z(), f.speed_mm_s, f.angular_speed_deg_s, f.layout_rms_mm, note);
  }
  if (auto ok = writeFile(out / "frames.csv", frames, w); !ok) return std::unexpected(ok.error());
  if (auto ok = writeFile(out / "registration.csv",
                          "tx,ty,tz,qw,qx,qy,qz\n" + poseColumns(r.o_t_c) + "\n", w);
      !ok)
    return std::unexpected(ok.error());
  std::string t2 = "axis,mean,sigma,max\n";
  for (const auto& row : table2Rows(r))
    t2 += fmt::format("{},{},{},{}\n", row[0], row[1], row[2], row[3]);
  if (r.registration) {
    if (auto ok = writeFile(out / "table2.csv", t2, w); !ok) return std::unexpected(ok.error());
  }
  std::string st = "test,h,dof,p,group_a,group_b,dunn_z,p_bonferroni,significant\n";
  for (const GroupTest& t : r.tests) {
    if (!t.kw) continue;
    st += fmt::format("{},{:.9g},{},{:.9g},,,,,{}\n", t.name, t.kw->h, t.kw->dof, t.kw->p,
                      t.kw->p < 0.05 ? 1 : 0);
    for (const PairwiseComparison& c : t.pairs)
      st +=
          fmt::format("{},,,,{},{},{:.6f},{:.6g},{}\n", t.name, t.groups[static_cast<size_t>(c.a)],
                      t.groups[static_cast<size_t>(c.b)], c.z, c.p_adjusted, c.significant ? 1 : 0);
  }
  if (auto ok = writeFile(out / "statistics.csv", st, w); !ok) return std::unexpected(ok.error());

  std::string page = fmt::format(
      "<!doctype html><html><head><meta charset=\"utf-8\"><title>{}</title>{}</head><body>\n",
      html(title), kStyle);
  page += "<h1>" + html(title) + "</h1>\n<pre>" + html(formatValidation(r)) + "</pre>\n";
  if (r.registration)
    page += "<h2>Table II: registration residuals</h2>\n" +
            htmlTable({"", "mean", "sigma", "max"}, table2Rows(r));
  // Fig. 7: the tests by set; Fig. 8: by speed.
  std::vector<const GroupTest*> by_set, by_speed;
  for (const GroupTest& t : r.tests)
    (t.name.find("by set") != std::string::npos ? by_set : by_speed).push_back(&t);
  const auto figure = [&](const std::vector<const GroupTest*>& tests, const std::string& name,
                          const std::string& caption) -> vision::Result<void> {
    if (tests.empty()) return {};
    Figure fig(1100, 480, 1, static_cast<int>(tests.size()), caption);
    for (size_t i = 0; i < tests.size(); ++i) {
      const bool rot = tests[i]->name.find("rotation") != std::string::npos;
      boxAxes(fig.at(0, static_cast<int>(i)), *tests[i],
              tests[i]->name.substr(tests[i]->name.find(':') + 2),
              rot ? "rotation error (deg)" : "translation error (mm)");
    }
    if (auto ok = fig.save(out / name); !ok) return ok;
    w.push_back(out / name);
    page += "<h2>" + html(caption) + "</h2>\n<img src=\"" + name + "\" alt=\"" + html(caption) +
            "\">\n";
    for (const GroupTest* t : tests)
      page += "<h3>" + html(t->name) + "</h3>\n" +
              htmlTable({"group", "n", "median", "q1", "q3", "max"}, testRows(*t)) + "<p>" +
              html(kwLine(*t)) + "</p>\n";
    return {};
  };
  if (auto ok = figure(by_set, "fig7_static.png",
                       r.dynamic ? "Errors of the moving plate by set"
                                 : "Fig. 7 style: detection error of the immobile plate by set");
      !ok)
    return std::unexpected(ok.error());
  if (auto ok = figure(by_speed, "fig8_dynamic.png",
                       "Fig. 8 style: tracking error by linear and angular speed");
      !ok)
    return std::unexpected(ok.error());
  page += "</body></html>\n";
  if (auto ok = writeFile(out / "report.html", page, w); !ok) return std::unexpected(ok.error());
  return w;
}

vision::Result<Pose> readRegistration(const std::filesystem::path& path) {
  auto csv = readCsv(path);
  if (!csv) return std::unexpected(csv.error());
  if (csv->rows.size() != 1) return fail(fmt::format("{}: expected one pose row", path.string()));
  const char* names[] = {"tx", "ty", "tz", "qw", "qx", "qy", "qz"};
  std::array<double, 7> v{};
  for (size_t k = 0; k < 7; ++k) {
    const int c = csv->column({names[k]});
    if (c < 0) return fail(fmt::format("{}: no column '{}'", path.string(), names[k]));
    auto x = csv->number(0, c);
    if (!x) return std::unexpected(x.error());
    v[k] = *x;
  }
  Pose p = Pose::Identity();
  const Eigen::Quaterniond q(v[3], v[4], v[5], v[6]);
  if (std::fabs(q.norm() - 1) > 1e-3)
    return fail(fmt::format("{}: the quaternion is not a unit one", path.string()));
  p.linear() = q.normalized().toRotationMatrix();
  p.translation() = Vec3(v[0], v[1], v[2]);
  return p;
}

std::string formatMotion(const NamedMotion& n) {
  const MotionAnalysis& m = n.motion;
  std::string s = fmt::format(
      "{}: {} features, {} frames ({} measured, {} missing filled), period {:.4f} s\n"
      "  displacement along the principal axis ({:.3f}, {:.3f}, {:.3f}): {:.3f} mm peak to peak; "
      "trend {:.4f} mm/min\n",
      n.name, m.features, m.frames_expected, m.frames_measured, m.frames_filled, m.period_s,
      m.principal_axis.x(), m.principal_axis.y(), m.principal_axis.z(), m.peak_to_peak_mm,
      m.trend_mm_per_s.norm() * 60.0);
  s += fmt::format("  feature speeds: mean {:.3f} mm/s, sigma {:.3f}, max {:.3f}\n",
                   m.feature_speed_mm_s.mean, m.feature_speed_mm_s.sd, m.feature_speed_mm_s.max);
  s += fmt::format("  {:>10} {:>12}  {}\n", "Hz", "amplitude mm", "component");
  for (const SpectralPeak& p : m.peaks)
    s += fmt::format("  {:>10.4f} {:>12.4f}  {}\n", p.frequency_hz, p.amplitude_mm, p.name);
  return s;
}

vision::Result<std::vector<std::filesystem::path>> writeMotionReport(
    const std::vector<NamedMotion>& acq, const std::filesystem::path& out) {
  std::error_code ec;
  std::filesystem::create_directories(out, ec);
  if (ec) return fail(fmt::format("{}: {}", out.string(), ec.message()));
  std::vector<std::filesystem::path> w;
  std::string peaks = "acquisition,frequency_hz,amplitude_mm,component\n";
  std::string page = fmt::format(
      "<!doctype html><html><head><meta charset=\"utf-8\"><title>Brain "
      "motion</title>{}</head><body>\n"
      "<h1>Brain motion</h1>\n",
      kStyle);
  Figure fig(1200, 300 * static_cast<int>(std::max<size_t>(1, acq.size())) + 30,
             static_cast<int>(std::max<size_t>(1, acq.size())), 2,
             "Fig. 9 style: the cloud's displacement (DC and trend removed) and its spectrum");
  for (size_t i = 0; i < acq.size(); ++i) {
    const MotionAnalysis& m = acq[i].motion;
    std::string d =
        "t_s,dx_mm,dy_mm,dz_mm,detrended_x_mm,detrended_y_mm,detrended_z_mm,along_axis_mm\n";
    for (size_t k = 0; k < m.t.size(); ++k)
      d += fmt::format("{:.4f},{:.5f},{:.5f},{:.5f},{:.5f},{:.5f},{:.5f},{:.5f}\n", m.t[k],
                       m.displacement[k].x(), m.displacement[k].y(), m.displacement[k].z(),
                       m.detrended[k].x(), m.detrended[k].y(), m.detrended[k].z(), m.along_axis[k]);
    if (auto ok = writeFile(out / ("displacement_" + acq[i].name + ".csv"), d, w); !ok)
      return std::unexpected(ok.error());
    std::string sp = "frequency_hz,amplitude_mm\n";
    for (size_t k = 0; k < m.frequency_hz.size(); ++k)
      sp += fmt::format("{:.5f},{:.6f}\n", m.frequency_hz[k], m.amplitude_mm[k]);
    if (auto ok = writeFile(out / ("spectrum_" + acq[i].name + ".csv"), sp, w); !ok)
      return std::unexpected(ok.error());
    std::vector<std::vector<std::string>> rows;
    for (const SpectralPeak& p : m.peaks) {
      peaks +=
          fmt::format("{},{:.5f},{:.5f},{}\n", acq[i].name, p.frequency_hz, p.amplitude_mm, p.name);
      rows.push_back(
          {fmt::format("{:.4f}", p.frequency_hz), fmt::format("{:.4f}", p.amplitude_mm), p.name});
    }
    Axes& left = fig.at(static_cast<int>(i), 0);
    left.title = acq[i].name + ": displacement";
    left.xlabel = "time (s)";
    left.ylabel = "displacement (mm)";
    left.lines.push_back(
        {m.t, m.along_axis, cv::Scalar(180, 90, 30), "along the principal axis", 1});
    Axes& right = fig.at(static_cast<int>(i), 1);
    right.title = acq[i].name + ": spectrum (3D amplitude)";
    right.xlabel = "frequency (Hz)";
    right.ylabel = "amplitude (mm)";
    right.xmin = 0;
    right.xmax = std::min(2.5, m.frequency_hz.empty() ? 2.5 : m.frequency_hz.back());
    right.lines.push_back({m.frequency_hz, m.amplitude_mm, cv::Scalar(40, 40, 200), "", 1});
    for (const SpectralPeak& p : m.peaks) {
      if (!p.name.empty() && p.frequency_hz <= right.xmax)
        right.annotations.push_back({p.frequency_hz, fmt::format("{} {:.2f} Hz, {:.3f} mm", p.name,
                                                                 p.frequency_hz, p.amplitude_mm)});
    }
    page += "<h2>" + html(acq[i].name) + "</h2>\n<pre>" + html(formatMotion(acq[i])) + "</pre>\n" +
            htmlTable({"Hz", "amplitude (mm)", "component"}, rows);
  }
  if (auto ok = writeFile(out / "peaks.csv", peaks, w); !ok) return std::unexpected(ok.error());
  if (auto ok = fig.save(out / "fig9_motion.png"); !ok) return std::unexpected(ok.error());
  w.push_back(out / "fig9_motion.png");
  page +=
      "<h2>Figure</h2>\n<img src=\"fig9_motion.png\" alt=\"displacement and "
      "spectrum\">\n</body></html>\n";
  if (auto ok = writeFile(out / "report.html", page, w); !ok) return std::unexpected(ok.error());
  return w;
}

}  // namespace pulsetrack::analysis
