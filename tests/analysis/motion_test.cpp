// The brain-motion analysis on synthetic tracks whose motion is known exactly: sinusoids along
// a direction, per-frame noise, dropped frames, an occlusion and a re-detection with new ids.

#include "pulsetrack/analysis/motion.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

namespace pulsetrack::analysis {
namespace {

TEST(Spline, NaturalCubicThroughLinesExactlyAndSinesClosely) {
  const std::vector<double> x = {0, 1, 2.5, 3, 4.2, 6};
  std::vector<double> y, s;
  for (const double v : x) {
    y.push_back(2 * v - 1);
    s.push_back(std::sin(v));
  }
  std::vector<double> at;
  for (double v = 0; v <= 6; v += 0.1) at.push_back(v);
  const auto line = naturalCubicSpline(x, y, at);
  for (size_t i = 0; i < at.size(); ++i) EXPECT_NEAR(line[i], 2 * at[i] - 1, 1e-12);
  std::vector<double> fine_x, fine_y;
  for (double v = 0; v <= 6.001; v += 0.1) {
    fine_x.push_back(v);
    fine_y.push_back(std::sin(v));
  }
  const auto sine = naturalCubicSpline(fine_x, fine_y, {1.05, 2.55, 4.45});
  EXPECT_NEAR(sine[0], std::sin(1.05), 1e-5);
  EXPECT_NEAR(sine[2], std::sin(4.45), 1e-5);
}

struct Component {
  double f, amplitude, phase;
};

// 60 s at 10 fps, 50 features, motion along one direction, noise 0.03 mm per coordinate,
// 2 % of frames dropped, features 0-9 occluded at 20-24 s, all features replaced by new ids at
// 40 s (a re-detection), and a sag of 0.2 mm/min.
std::vector<record::TrackRow> syntheticTrack(const std::vector<Component>& comps, int* dropped) {
  std::mt19937 rng(21);
  std::normal_distribution<double> noise(0, 0.03);
  std::uniform_real_distribution<double> u(0, 1);
  const Vec3 dir = Vec3(0.2, 0.1, 1.0).normalized();
  std::vector<Vec3> base;
  base.reserve(50);
  for (int i = 0; i < 50; ++i)
    base.emplace_back(40 * u(rng) - 20, 40 * u(rng) - 20, 440 + 10 * u(rng));
  std::vector<record::TrackRow> rows;
  *dropped = 0;
  for (int k = 0; k < 600; ++k) {
    if (k > 0 && k < 599 && u(rng) < 0.02) {
      ++*dropped;
      continue;
    }
    const double t = 0.1 * k;
    double s = 0.2 / 60.0 * t;
    for (const Component& c : comps) s += c.amplitude * std::sin(2 * M_PI * c.f * t + c.phase);
    for (int i = 0; i < 50; ++i) {
      record::TrackRow r;
      r.frame = k;
      r.t = 12.5 + t;  // the recording's clock needs not start at 0
      r.id = k >= 400 ? 100 + i : i;
      const Vec3 p =
          base[static_cast<size_t>(i)] + s * dir + Vec3(noise(rng), noise(rng), noise(rng));
      r.x = p.x();
      r.y = p.y();
      r.z = p.z();
      r.status = i < 10 && t >= 20 && t < 24 ? "occluded" : "ok";
      rows.push_back(r);
    }
  }
  return rows;
}

TEST(Motion, FindsAndNamesThePeaksWithTheirAmplitudes) {
  const std::vector<Component> comps = {{0.05, 0.12, 0.4}, {0.2, 0.45, 0.0}, {0.4, 0.135, 0.5},
                                        {0.6, 0.054, 1.1}, {1.0, 0.15, 1.3}, {2.0, 0.0375, 0.7}};
  int dropped = 0;
  const auto rows = syntheticTrack(comps, &dropped);
  auto m = analyzeMotion(rows);
  ASSERT_TRUE(m) << m.error().message;
  for (const SpectralPeak& p : m->peaks)
    std::cout << p.frequency_hz << " " << p.amplitude_mm << " " << p.name << "\n";
  std::cout << "trend " << m->trend_mm_per_s.transpose() * 60 << "\n";
  EXPECT_EQ(m->frames_expected, 600);
  EXPECT_EQ(m->frames_filled, dropped);
  EXPECT_GT(dropped, 5);
  EXPECT_NEAR(m->period_s, 0.1, 1e-9);
  EXPECT_EQ(m->features, 100);
  EXPECT_NEAR((m->trend_mm_per_s * 60.0 - Vec3(0.2, 0.1, 1.0).normalized() * 0.2).norm(), 0.0,
              0.03);
  const auto find = [&](const std::string& name) -> const SpectralPeak* {
    for (const SpectralPeak& p : m->peaks) {
      if (p.name == name) return &p;
    }
    return nullptr;
  };
  const std::pair<const char*, Component> expected[] = {{"vasomotor", comps[0]},
                                                        {"breathing", comps[1]},
                                                        {"breathing harmonic 2", comps[2]},
                                                        {"breathing harmonic 3", comps[3]},
                                                        {"cardiac", comps[4]},
                                                        {"cardiac harmonic 2", comps[5]}};
  for (const auto& [name, c] : expected) {
    const SpectralPeak* p = find(name);
    ASSERT_NE(p, nullptr) << name;
    EXPECT_NEAR(p->frequency_hz, c.f, 0.005) << name;
    // The vasomotor wave has three periods in 60 s and shares them with the trend fit.
    EXPECT_NEAR(p->amplitude_mm, c.amplitude,
                (std::string(name) == "vasomotor" ? 0.1 : 0.02) * c.amplitude)
        << name;
  }
  // The along-axis peak to peak of the sum of the components (its true value from the model).
  double lo = 1e9, hi = -1e9;
  for (int k = 0; k < 6000; ++k) {
    double s = 0;
    for (const Component& c : comps)
      s += c.amplitude * std::sin(2 * M_PI * c.f * 0.01 * k + c.phase);
    lo = std::min(lo, s);
    hi = std::max(hi, s);
  }
  EXPECT_NEAR(m->peak_to_peak_mm, hi - lo, 0.1 * (hi - lo));
}

TEST(Motion, RefusesTooShortOrUnorderedTracks) {
  std::vector<record::TrackRow> rows(5);
  for (int i = 0; i < 5; ++i) {
    rows[static_cast<size_t>(i)].frame = i;
    rows[static_cast<size_t>(i)].t = 0.1 * i;
    rows[static_cast<size_t>(i)].status = "ok";
  }
  auto m = analyzeMotion(rows);
  ASSERT_FALSE(m);
  EXPECT_NE(m.error().message.find("too few"), std::string::npos);
}

}  // namespace
}  // namespace pulsetrack::analysis
