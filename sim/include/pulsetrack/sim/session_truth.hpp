#pragma once
// The simulator's truth for a TrackingSession's output, written independently of the session
// (the tests and bench/gate_eval score the session against it):
// - SessionTruth: each feature's material point (the surface point under its left pixel in the
//   pair it first appeared) and the true deformation by the session's documented rule
//   (tracking_session.hpp: a hidden feature moved by its neighbours' motion since it was seen, a
//   new one entering at the mean), applied to the true displacements. So an error against it is
//   the measurement's, not the definition's.
// - heldOutPoints: material points for the dense field that are not features: a grid of left
//   pixels over the whole ROI (edges and corners included), none within 1 mm of a feature.

#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <span>
#include <vector>

#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/tracking_session.hpp"

namespace pulsetrack::sim {

struct MaterialTruth {
  cv::Vec2d uv;
  double t_ref = 0;  // the time of its reference position (when it appeared)
  bool found = false;
};

class SessionTruth {
 public:
  explicit SessionTruth(const StereoSimulator& s) : s_(s), scene_(*s.cortex()) {}

  // After the session's process() of the pair at time t. Returns false when no feature of the
  // signal is ok with a truth (the signal is then undefined).
  bool update(const vision::PairResult& pr, double t) {
    // This pair's own true displacements of the signal's features that are ok. In a pair that
    // re-detected, the session measured with the features it had (new ids are not in yet).
    std::map<int, cv::Vec3d> own;
    for (const vision::Feature& f : pr.features) {
      const bool member = first_ || members_.contains(f.id);
      if (!member) continue;
      MaterialTruth& tr = at(f, t);
      if (f.status != vision::FeatureStatus::kOk || !tr.found) continue;
      own[f.id] =
          scene_.position(tr.uv[0], tr.uv[1], t) - scene_.position(tr.uv[0], tr.uv[1], tr.t_ref);
    }
    if (first_) {
      for (const vision::Feature& f : pr.features) {
        Member& m = members_[f.id];
        m.ok = own.contains(f.id);
        m.last_own = m.ok ? own[f.id] : cv::Vec3d(0, 0, 0);
        m.birth = -m.last_own;
      }
    }
    if (own.empty()) return false;
    // The session's rule (tracking_session.hpp), on the truth: a hidden feature moves with its
    // nearest features when it was last seen, or with the mean increment of those ok in both
    // pairs while none of them is seen.
    cv::Vec3d inc(0, 0, 0);
    int common = 0;
    for (const auto& [id, v] : own) {
      const Member& m = members_[id];
      if (!m.ok) continue;
      inc += v - m.last_own;
      ++common;
    }
    if (common > 0) inc /= common;
    std::map<int, cv::Vec3d> point;  // this pair's reported positions
    for (const vision::Feature& f : pr.features) point[f.id] = f.point;
    cv::Vec3d sum(0, 0, 0);
    for (auto& [id, m] : members_) {
      const auto o = own.find(id);
      if (o != own.end()) {
        m.dhat = m.birth + o->second;
      } else {
        if (m.ok && point.contains(id)) {  // hidden from this pair: its nearest, seen with it
          std::vector<std::pair<double, int>> near;
          for (const auto& [jd, mj] : members_) {
            if (jd == id || !mj.ok || !point.contains(jd)) continue;
            near.emplace_back(cv::norm(point[jd] - point[id]), jd);
          }
          std::sort(near.begin(), near.end());
          m.nb.clear();
          for (size_t k = 0; k < near.size() && k < kNeighbours; ++k)
            m.nb.emplace_back(near[k].second, members_[near[k].second].last_own);
        }
        cv::Vec3d moved(0, 0, 0);
        int seen = 0;
        for (const auto& [jd, snap] : m.nb) {
          const auto oj = own.find(jd);
          if (oj == own.end()) continue;
          moved += oj->second - snap;
          ++seen;
        }
        m.dhat = seen > 0 ? m.birth + m.last_own + moved / seen : m.dhat + inc;
      }
      sum += m.dhat;
    }
    const cv::Vec3d mean = sum / static_cast<double>(members_.size());
    if (first_) offset_ = -mean;
    out_ = mean + offset_;
    for (auto& [id, m] : members_) {
      const auto o = own.find(id);
      m.ok = o != own.end();
      if (m.ok) m.last_own = o->second;
    }
    if (pr.detected && !first_) {  // a re-detection: new features enter at the mean, retired leave
      std::map<int, Member> next;
      cv::Vec3d next_sum(0, 0, 0);
      for (const vision::Feature& f : pr.features) {
        const auto m = members_.find(f.id);
        Member nm;
        if (m != members_.end()) {
          nm = m->second;
        } else {
          at(f, t);
          nm.nb.clear();
          nm.birth = mean;  // its own displacement is zero here
          nm.dhat = mean;
          nm.ok = f.status == vision::FeatureStatus::kOk && find(f.id) != nullptr;
        }
        next_sum += nm.dhat;
        next[f.id] = nm;
      }
      members_ = std::move(next);
      offset_ += mean - next_sum / static_cast<double>(members_.size());
      ++redetections_;
    }
    true_d_ = std::move(own);
    first_ = false;
    return true;
  }

  // The true deformation at the last update, mm.
  [[nodiscard]] const cv::Vec3d& displacement() const { return out_; }
  // The ok features' true displacements from their references at the last update.
  [[nodiscard]] const std::map<int, cv::Vec3d>& featureDisplacements() const { return true_d_; }
  [[nodiscard]] int redetections() const { return redetections_; }
  [[nodiscard]] const MaterialTruth* find(int id) const {
    const auto it = truth_.find(id);
    return it == truth_.end() || !it->second.found ? nullptr : &it->second;
  }

 private:
  static constexpr size_t kNeighbours = 6;  // TrackerConfig::reacquire_neighbours
  struct Member {
    bool ok = false;
    cv::Vec3d last_own{0, 0, 0}, birth{0, 0, 0}, dhat{0, 0, 0};
    std::vector<std::pair<int, cv::Vec3d>> nb;  // while hidden: neighbours and their own then
  };
  MaterialTruth& at(const vision::Feature& f, double t) {
    MaterialTruth& tr = truth_[f.id];
    if (!tr.found) {
      tr.found = scene_.materialAt(s_.rig(), f.left, t, tr.uv);
      tr.t_ref = t;
    }
    return tr;
  }

  const StereoSimulator& s_;
  const CortexScene& scene_;
  std::map<int, MaterialTruth> truth_;
  std::map<int, Member> members_;
  std::map<int, cv::Vec3d> true_d_;
  cv::Vec3d out_{0, 0, 0}, offset_{0, 0, 0};
  bool first_ = true;
  int redetections_ = 0;
};

struct HeldOutPoint {
  cv::Vec2d uv;
  cv::Vec3d p0;  // its position at t0, {C} mm
  bool edge = false;
};

inline std::vector<HeldOutPoint> heldOutPoints(const StereoSimulator& s, const cv::Rect& roi,
                                               double t0,
                                               std::span<const vision::Feature> features) {
  const CortexScene& scene = *s.cortex();
  std::vector<HeldOutPoint> held;
  for (int j = 0; j <= 14; ++j) {
    for (int i = 0; i <= 14; ++i) {
      const cv::Vec2d px(roi.x + roi.width * i / 14.0, roi.y + roi.height * j / 14.0);
      cv::Vec2d uv;
      if (!scene.materialAt(s.rig(), px, t0, uv)) continue;
      const cv::Vec3d p0 = scene.position(uv[0], uv[1], t0);
      const bool near_feature =
          std::any_of(features.begin(), features.end(),
                      [&](const vision::Feature& f) { return cv::norm(f.point0 - p0) < 1.0; });
      if (near_feature) continue;
      held.push_back({uv, p0, i == 0 || j == 0 || i == 14 || j == 14});
    }
  }
  return held;
}

}  // namespace pulsetrack::sim
