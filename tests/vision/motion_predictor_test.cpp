// The motion predictor as radiotherapy's motion-prediction literature scores one: relative RMS =
// RMS(prediction error) / RMS(error of holding the last value), per horizon, against the true
// (noise-free) motion, with a linear-extrapolation baseline in the same run. The motion: the
// simulator's (sim::OscillationClock, the cortex scenes' motion model, each case with its
// truth): vasomotor, breathing with harmonics, cardiac with a harmonic, a slow sag, measured at
// 30 Hz with 2 % of the pairs dropped and the tracker's noise on the mean displacement
// (0.003 mm per axis, docs/ros2.md); breathing 12-20 per minute, amplitude drift, irregular
// breaths, cardiac rate changes, a sudden change of rate.

#include "pulsetrack/vision/motion_predictor.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <random>

#include "pulsetrack/sim/cortex.hpp"

namespace pulsetrack::vision {
namespace {

struct Motion {
  std::vector<sim::Oscillation> oscillations;
  std::vector<sim::OscillationClock> clocks;
  double sag_mm = 0.8, sag_tau_s = 240.0;
  void build() {
    clocks.clear();
    for (const sim::Oscillation& o : oscillations) clocks.emplace_back(o, 400.0);
  }
  // The patch's mean displacement (mm): each component along its direction.
  [[nodiscard]] cv::Vec3d at(double t) const {
    cv::Vec3d d(0, 0, -sag_mm * (1.0 - std::exp(-t / sag_tau_s)));
    for (size_t i = 0; i < oscillations.size(); ++i)
      d += cv::normalize(oscillations[i].direction) * clocks[i].value(t);
    return d;
  }
};

Motion paper() {
  Motion m;
  m.oscillations = sim::paperMotion();
  // cortex-60s's directions (its motion in {S}).
  for (sim::Oscillation& o : m.oscillations) {
    if (o.name == "breathing") o.direction = {0.15, 0.1, 1.0};
    if (o.name == "cardiac") o.direction = {0.0, 0.1, 1.0};
    if (o.name == "vasomotor") o.direction = {0.1, 0.0, 1.0};
  }
  return m;
}

sim::Oscillation& component(Motion& m, const char* name) {
  for (sim::Oscillation& o : m.oscillations)
    if (o.name == name) return o;
  throw std::runtime_error(name);
}

struct Score {
  std::array<double, kMaxHorizons> model{}, hold{}, linear{}, relative{}, relative_linear{};
  std::array<double, kMaxHorizons> sigma_ratio{};  // stated sigma / actual RMS per axis
  std::array<double, kMaxHorizons>
      worst_window{};  // the worst 2 s window's relative RMS after t_change
  std::array<double, kMaxHorizons> adapted_s{};  // after t_change, until every window <= 0.5
};

// Runs the predictor over [0, duration) at 30 Hz; scores from `warmup` on.
Score run(const Motion& m, double duration, double warmup, double t_change = -1.0,
          const PredictionConfig& pc = PredictionConfig{}) {
  MotionPredictor p(pc);
  const int horizons = static_cast<int>(pc.horizons_s.size());
  std::mt19937 rng(9);
  std::normal_distribution<double> noise(0.0, 0.003);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  Score s;
  std::array<double, kMaxHorizons> em{}, eh{}, el{}, sig{};
  std::array<int, kMaxHorizons> n{};
  // Windows after the change: 2 s each, squared errors of model and hold.
  struct Win {
    double m = 0, h = 0;
  };
  std::array<std::vector<Win>, kMaxHorizons> windows;
  std::vector<std::pair<double, cv::Vec3d>> recent;  // for the linear baseline (0.1 s)
  for (int i = 0; i < static_cast<int>(duration * 30.0); ++i) {
    if (u(rng) < 0.02) continue;  // a dropped pair
    const double t = i / 30.0;
    const cv::Vec3d measured = m.at(t) + cv::Vec3d(noise(rng), noise(rng), noise(rng));
    const Prediction& pr = p.add(t, measured);
    recent.emplace_back(t, measured);
    while (recent.front().first < t - 0.1) recent.erase(recent.begin());
    // Linear extrapolation: the least-squares line through the last 0.1 s (4 pairs), at t + h.
    double st = 0, stt = 0;
    cv::Vec3d sd(0, 0, 0), std_(0, 0, 0);
    for (const auto& [tt, dd] : recent) {
      st += tt;
      sd += dd;
    }
    const double k = static_cast<double>(recent.size());
    const double tm = st / k;
    const cv::Vec3d dm = sd / k;
    for (const auto& [tt, dd] : recent) {
      stt += (tt - tm) * (tt - tm);
      std_ += (tt - tm) * (dd - dm);
    }
    const cv::Vec3d slope = stt > 0 ? std_ / stt : cv::Vec3d(0, 0, 0);
    if (t < warmup) continue;
    for (int h = 0; h < horizons; ++h) {
      const auto hh = static_cast<size_t>(h);
      const double th = t + pc.horizons_s[hh];
      const cv::Vec3d truth = m.at(th);
      const cv::Vec3d lin = dm + slope * (th - tm);
      const double e_model = (pr.displacement[hh] - truth).dot(pr.displacement[hh] - truth);
      const double e_hold = (measured - truth).dot(measured - truth);
      em[hh] += e_model;
      eh[hh] += e_hold;
      el[hh] += (lin - truth).dot(lin - truth);
      sig[hh] += pr.sigma_mm[hh] * pr.sigma_mm[hh];
      ++n[hh];
      if (t_change >= 0 && t >= t_change) {
        const auto w = static_cast<size_t>((t - t_change) / 2.0);
        if (windows[hh].size() <= w) windows[hh].resize(w + 1);
        windows[hh][w].m += e_model;
        windows[hh][w].h += e_hold;
      }
    }
  }
  for (int h = 0; h < horizons; ++h) {
    const auto hh = static_cast<size_t>(h);
    s.model[hh] = std::sqrt(em[hh] / n[hh] / 3.0);
    s.hold[hh] = std::sqrt(eh[hh] / n[hh] / 3.0);
    s.linear[hh] = std::sqrt(el[hh] / n[hh] / 3.0);
    s.relative[hh] = s.model[hh] / s.hold[hh];
    s.relative_linear[hh] = s.linear[hh] / s.hold[hh];
    s.sigma_ratio[hh] = std::sqrt(sig[hh] / n[hh]) / s.model[hh];
    double last_bad = 0.0;
    for (size_t w = 0; w < windows[hh].size(); ++w) {
      const double r = std::sqrt(windows[hh][w].m / windows[hh][w].h);
      s.worst_window[hh] = std::max(s.worst_window[hh], r);
      if (r > 0.5) last_bad = 2.0 * static_cast<double>(w + 1);
    }
    s.adapted_s[hh] = last_bad;
  }
  return s;
}

void print(const char* name, const Score& s) {
  const PredictionConfig pc;
  for (size_t h = 0; h < pc.horizons_s.size(); ++h) {
    std::cout << name << " " << pc.horizons_s[h] * 1e3 << " ms: relative RMS " << s.relative[h]
              << " (linear extrapolation " << s.relative_linear[h] << "), RMS " << s.model[h]
              << " mm per axis, holding " << s.hold[h] << "; stated sigma / actual "
              << s.sigma_ratio[h];
    if (s.worst_window[h] > 0)
      std::cout << "; after the change: worst 2 s window " << s.worst_window[h]
                << ", every window <= 0.5 after " << s.adapted_s[h] << " s";
    std::cout << "\n";
  }
}

TEST(MotionPredictor, SteadyBreathingAndCardiac) {
  Motion m = paper();
  m.build();
  const Score s = run(m, 120.0, 30.0);
  print("steady", s);
  EXPECT_LE(s.relative[1], 0.3);  // the aim at 100 ms
  for (int h = 0; h < 3; ++h) {
    EXPECT_LT(s.relative[static_cast<size_t>(h)], s.relative_linear[static_cast<size_t>(h)]);
    EXPECT_LT(s.relative[static_cast<size_t>(h)], 1.0);
    // The stated error is the actual one's size.
    EXPECT_GT(s.sigma_ratio[static_cast<size_t>(h)], 0.5);
    EXPECT_LT(s.sigma_ratio[static_cast<size_t>(h)], 2.0);
  }
}

TEST(MotionPredictor, BreathingRateAndCardiacRateChange) {
  Motion m = paper();
  sim::Oscillation& b = component(m, "breathing");
  b.frequency_end_hz = 20.0 / 60.0;  // 12 -> 20 breaths per minute over 40-70 s
  b.change_start_s = 40.0;
  b.change_duration_s = 30.0;
  sim::Oscillation& c = component(m, "cardiac");
  c.frequency_end_hz = 1.3;  // 60 -> 78 per minute
  c.change_start_s = 40.0;
  c.change_duration_s = 30.0;
  m.build();
  const Score s = run(m, 120.0, 30.0, 40.0);
  print("rate 12->20/min", s);
  EXPECT_LE(s.relative[1], 0.3);
  EXPECT_LE(s.worst_window[1], 1.0);  // never worse than holding
}

TEST(MotionPredictor, AmplitudeDriftAndIrregularBreaths) {
  Motion m = paper();
  sim::Oscillation& b = component(m, "breathing");
  b.amplitude_end_mm = 0.9;  // doubles over 40-70 s
  b.change_start_s = 40.0;
  b.change_duration_s = 30.0;
  b.irregularity = 0.15;  // each breath's length and depth +-15 % (1 sigma)
  component(m, "cardiac").irregularity = 0.05;
  m.build();
  const Score s = run(m, 120.0, 30.0, 40.0);
  print("amplitude x2, irregular", s);
  EXPECT_LE(s.relative[1], 0.35);
  EXPECT_LE(s.worst_window[1], 1.0);
}

TEST(MotionPredictor, ASuddenChangeOfRateIsFollowed) {
  Motion m = paper();
  sim::Oscillation& b = component(m, "breathing");
  b.frequency_end_hz = 20.0 / 60.0;  // 12 -> 20 per minute within 2 s, at 60 s
  b.change_start_s = 60.0;
  b.change_duration_s = 2.0;
  b.amplitude_end_mm = 0.3;
  m.build();
  const Score s = run(m, 120.0, 30.0, 60.0);
  print("sudden 12->20/min", s);
  EXPECT_LE(s.worst_window[1], 1.0);
  EXPECT_LE(s.adapted_s[1], 20.0);
  EXPECT_LE(s.relative[1], 0.35);
}

TEST(MotionPredictor, ItsConfigCheckNamesTheKey) {
  PredictionConfig c;
  EXPECT_TRUE(checkPredictionConfig(c));
  c.horizons_s = {0.05, 0.1, 0.2, 0.3, 0.4};
  auto r = checkPredictionConfig(c);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("[prediction] horizons_ms: 1 to 4 horizons"), std::string::npos);
  c = PredictionConfig{};
  c.order = 40;
  r = checkPredictionConfig(c);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("[prediction] order = 40"), std::string::npos);
}

}  // namespace
}  // namespace pulsetrack::vision
