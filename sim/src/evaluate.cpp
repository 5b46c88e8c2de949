#include "pulsetrack/sim/evaluate.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

namespace pulsetrack::sim {

ErrorParts errorParts(const std::vector<RowError>& rows) {
  struct Sums {
    cv::Vec3d sum;
    long n = 0;
    long last_frame = -2;
    cv::Vec3d last;
  };
  std::map<int, Sums> by_id;
  double diff_sq = 0.0;
  ErrorParts p;
  long n = 0;
  double total_sq = 0.0;
  for (const RowError& r : rows) {  // in frame order per feature, as a track CSV is written
    if (std::isnan(r.error_mm)) continue;
    Sums& s = by_id[r.id];
    if (r.frame == s.last_frame + 1) {
      diff_sq += (r.error_vec - s.last).dot(r.error_vec - s.last);
      ++p.pairs;
    }
    s.last_frame = r.frame;
    s.last = r.error_vec;
    s.sum += r.error_vec;
    ++s.n;
    ++n;
    total_sq += r.error_vec.dot(r.error_vec);
  }
  if (n == 0) return p;
  double bias_sq = 0.0;
  for (const auto& [id, s] : by_id) {
    const cv::Vec3d mean = s.sum / static_cast<double>(s.n);
    bias_sq += static_cast<double>(s.n) * mean.dot(mean);
  }
  const double within = std::max(0.0, total_sq - bias_sq) / static_cast<double>(n);
  const double noise = p.pairs > 0 ? 0.5 * diff_sq / static_cast<double>(p.pairs) : 0.0;
  p.bias_mm = std::sqrt(bias_sq / static_cast<double>(n));
  p.noise_mm = std::sqrt(std::min(noise, within));
  p.slow_mm = std::sqrt(std::max(0.0, within - noise));
  return p;
}

vision::Result<Evaluation> evaluateTrack(const StereoSimulator& sim,
                                         const std::vector<record::TrackRow>& rows,
                                         double outlier_threshold_mm, bool fields) {
  Evaluation ev;
  ev.outlier_threshold_mm = outlier_threshold_mm;
  if (fields && sim.cortex() == nullptr)
    return vision::fail("a track from fields (--fields) is scored on cortex scenes only");
  const int frames = sim.frameCount() * (fields ? 2 : 1);
  struct Truth {
    bool found = false;
    cv::Vec2d uv;
    int plate_feature = -1;
  };
  std::map<int, Truth> truth;
  std::map<int, std::vector<double>> errors;
  std::vector<double> all;
  for (const record::TrackRow& r : rows) {
    if (r.frame < 0 || r.frame >= frames) {
      return vision::fail(fmt::format("track row for frame {} but the scene has frames 0..{}",
                                      r.frame, frames - 1));
    }
    Truth& tr = truth[r.id];
    RowError re{r.frame, r.id, std::numeric_limits<double>::quiet_NaN(), {}};
    if (!r.ok()) {
      ++ev.not_ok[r.status];
      ev.rows.push_back(re);
      continue;
    }
    const double t = fields ? sim.frameTime(static_cast<int>(r.frame / 2)) +
                                  static_cast<double>(r.frame % 2) * 0.5 / sim.spec().fps
                            : sim.frameTime(static_cast<int>(r.frame));
    if (!tr.found && tr.plate_feature < -1) {  // already failed to match
      ev.rows.push_back(re);
      continue;
    }
    if (!tr.found) {
      if (const CortexScene* c = sim.cortex()) {
        tr.found = c->materialAt(sim.rig(), {r.xl, r.yl}, t, tr.uv);
      } else if (const PlateScene* p = sim.plate()) {
        const Pose& pose = p->samples()[static_cast<size_t>(r.frame)].c_t_p;
        double best = 2.0;
        for (int k = 0; k < 6; ++k) {
          const double d =
              cv::norm(pose * nominalFeatures()[static_cast<size_t>(k)] - cv::Vec3d(r.x, r.y, r.z));
          if (d < best) {
            best = d;
            tr.plate_feature = k;
          }
        }
        tr.found = tr.plate_feature >= 0;
      }
      if (!tr.found) {
        tr.plate_feature = -2;
        ev.rows.push_back(re);
        continue;
      }
    }
    cv::Vec3d expected;
    if (const CortexScene* c = sim.cortex()) {
      expected = c->position(tr.uv[0], tr.uv[1], t);
    } else {
      expected = sim.plate()->samples()[static_cast<size_t>(r.frame)].c_t_p *
                 nominalFeatures()[static_cast<size_t>(tr.plate_feature)];
    }
    re.error_vec = cv::Vec3d(r.x, r.y, r.z) - expected;
    re.error_mm = cv::norm(re.error_vec);
    errors[r.id].push_back(re.error_mm);
    all.push_back(re.error_mm);
    ev.rows.push_back(re);
  }
  ev.features = static_cast<int>(truth.size());
  for (const auto& [id, tr] : truth) {
    if (!tr.found) ++ev.unmatched;
  }
  ev.rows_ok = static_cast<long>(all.size());
  if (!all.empty()) {
    double sum2 = 0.0;
    for (double e : all) {
      sum2 += e * e;
      if (e > outlier_threshold_mm) ++ev.outliers;
    }
    ev.rms_mm = std::sqrt(sum2 / static_cast<double>(all.size()));
    std::sort(all.begin(), all.end());
    ev.median_mm = all[all.size() / 2];
    ev.p99_mm =
        all[std::min(all.size() - 1, static_cast<size_t>(0.99 * static_cast<double>(all.size())))];
    ev.max_mm = all.back();
  }
  ev.parts = errorParts(ev.rows);
  for (const auto& [id, es] : errors) {
    FeatureScore fs;
    fs.id = id;
    fs.ok_rows = static_cast<int>(es.size());
    double s2 = 0.0;
    for (double e : es) {
      s2 += e * e;
      fs.max_mm = std::max(fs.max_mm, e);
    }
    fs.rms_mm = std::sqrt(s2 / static_cast<double>(es.size()));
    const Truth& tr = truth[id];
    fs.truth = sim.cortex() != nullptr
                   ? fmt::format("material ({:.3f}, {:.3f}) mm", tr.uv[0], tr.uv[1])
                   : fmt::format("plate feature {}", tr.plate_feature + 1);
    ev.per_feature.push_back(fs);
  }
  return ev;
}

}  // namespace pulsetrack::sim
