// The dense deformation field's cost per pair (issue 17): 100 features over a 60x60 mm patch,
// the grid at 1 mm (61x61 = 3721 points). Three cases a pair meets:
//   steady:   the same features ok as in the last pair (one solve with the kept factors, the grid)
//   changing: one feature hidden or back every pair (the system factored again, IRLS)
//   rebuild:  a re-detection pair (new features: the basis and the grid's basis computed again)
// and the query a robot makes (one material point); the motion predictor's step (three
// horizons) and the grid's prediction at one horizon.
#include <benchmark/benchmark.h>

#include <cmath>
#include <random>
#include <vector>

#include "pulsetrack/vision/deformation_field.hpp"
#include "pulsetrack/vision/motion_predictor.hpp"

namespace {

using pulsetrack::vision::DeformationField;
using pulsetrack::vision::Feature;
using pulsetrack::vision::FeatureStatus;
using pulsetrack::vision::FieldConfig;

struct Patch {
  std::vector<cv::Vec2d> uv;
  std::vector<Feature> features;
  explicit Patch(int n) {
    std::mt19937 rng(5);
    std::uniform_real_distribution<double> u(-30.0, 30.0);
    for (int i = 0; i < n; ++i) {
      uv.emplace_back(u(rng), u(rng));
      Feature f;
      f.id = i;
      f.point0 = rest(uv.back());
      f.point = f.point0;
      features.push_back(f);
    }
    // Two features at opposite corners: the grid spans exactly 60x60 mm.
    uv[0] = {-30, -30};
    uv[1] = {30, 30};
    features[0].point0 = features[0].point = rest(uv[0]);
    features[1].point0 = features[1].point = rest(uv[1]);
  }
  static cv::Vec3d rest(const cv::Vec2d& p) {
    return {p[0], p[1], 450.0 - (p[0] * p[0] + p[1] * p[1]) / 140.0};
  }
  void move(double t, std::mt19937& rng) {
    std::normal_distribution<double> g(0.0, 0.01);
    for (size_t i = 0; i < uv.size(); ++i) {
      const double w = 1 + 0.3 * uv[i][0] / 30;
      features[i].point = features[i].point0 +
                          cv::Vec3d(0.05, 0.02, 0.4 * w) * std::sin(2 * M_PI * 0.2 * t) +
                          cv::Vec3d(g(rng), g(rng), g(rng));
    }
  }
};

FieldConfig grid60() {
  FieldConfig c;
  c.margin_mm = 0.0;
  c.spacing_mm = 1.0;
  return c;
}

void BM_FieldSteady(benchmark::State& state) {
  Patch p(100);
  DeformationField field(grid60(), 100);
  (void)field.update(p.features, true, 1);
  std::mt19937 rng(1);
  double t = 0;
  for (auto _ : state) {
    t += 0.033;
    state.PauseTiming();
    p.move(t, rng);
    state.ResumeTiming();
    benchmark::DoNotOptimize(field.update(p.features, false, 1));
  }
  state.counters["grid_points"] = field.points();
  state.counters["factorizations_per_pair"] =
      benchmark::Counter(field.factorizations(), benchmark::Counter::kAvgIterations);
}

void BM_FieldChangingSet(benchmark::State& state) {
  Patch p(100);
  DeformationField field(grid60(), 100);
  (void)field.update(p.features, true, 1);
  std::mt19937 rng(1);
  double t = 0;
  size_t k = 2;
  for (auto _ : state) {
    t += 0.033;
    state.PauseTiming();
    p.move(t, rng);
    p.features[k].status =
        p.features[k].status == FeatureStatus::kOk ? FeatureStatus::kOccluded : FeatureStatus::kOk;
    k = 2 + (k + 7) % 98;
    state.ResumeTiming();
    benchmark::DoNotOptimize(field.update(p.features, false, 1));
  }
  state.counters["grid_points"] = field.points();
  state.counters["factorizations_per_pair"] =
      benchmark::Counter(field.factorizations(), benchmark::Counter::kAvgIterations);
}

void BM_FieldRebuild(benchmark::State& state) {
  Patch p(100);
  DeformationField field(grid60(), 100);
  (void)field.update(p.features, true, 1);
  int next_id = 1000;
  for (auto _ : state) {
    state.PauseTiming();
    for (int i = 90; i < 100; ++i) p.features[static_cast<size_t>(i)].id = next_id++;
    state.ResumeTiming();
    benchmark::DoNotOptimize(field.update(p.features, true, 2));
  }
}

void BM_FieldQuery(benchmark::State& state) {
  Patch p(100);
  DeformationField field(grid60(), 100);
  (void)field.update(p.features, true, 1);
  std::mt19937 rng(1);
  p.move(0.4, rng);
  (void)field.update(p.features, false, 1);
  const cv::Vec3d q = Patch::rest({3.3, -7.1});
  for (auto _ : state) benchmark::DoNotOptimize(field.at(q));
}

void BM_PredictorStep(benchmark::State& state) {
  pulsetrack::vision::MotionPredictor p(pulsetrack::vision::PredictionConfig{});
  double t = 0;
  for (int i = 0; i < 900; ++i, t += 1.0 / 30) {  // warmed up: fitted and scored
    (void)p.add(t, cv::Vec3d(0.05, 0.02, 0.4) * std::sin(2 * M_PI * 0.2 * t) +
                       cv::Vec3d(0, 0.01, 0.15) * std::sin(2 * M_PI * t));
  }
  for (auto _ : state) {
    t += 1.0 / 30;
    benchmark::DoNotOptimize(p.add(t, cv::Vec3d(0.05, 0.02, 0.4) * std::sin(2 * M_PI * 0.2 * t)));
  }
}

void BM_FieldPrediction(benchmark::State& state) {
  const pulsetrack::vision::PredictionConfig pc;
  Patch p(100);
  DeformationField field(grid60(), 100);
  field.enablePrediction(pc.order * pc.step_s + 0.1, 100.0);
  (void)field.update(p.features, true, 1);
  std::mt19937 rng(1);
  double t = 0;
  for (int i = 0; i < 60; ++i, t += 1.0 / 30) {
    p.move(t, rng);
    (void)field.update(p.features, false, 1);
    field.record(t);
  }
  std::vector<double> w(static_cast<size_t>(pc.order), 0.05);
  Eigen::MatrixXd out = Eigen::MatrixXd::Zero(field.points(), 3);
  for (auto _ : state) benchmark::DoNotOptimize(field.predict(w, pc.step_s, out));
  state.counters["grid_points"] = field.points();
}

}  // namespace

BENCHMARK(BM_PredictorStep)->Unit(benchmark::kMicrosecond)->MinTime(0.5);
BENCHMARK(BM_FieldPrediction)->Unit(benchmark::kMicrosecond)->MinTime(1.0);
BENCHMARK(BM_FieldSteady)->Unit(benchmark::kMicrosecond)->MinTime(1.0);
BENCHMARK(BM_FieldChangingSet)->Unit(benchmark::kMicrosecond)->MinTime(1.0);
BENCHMARK(BM_FieldRebuild)->Unit(benchmark::kMicrosecond)->MinTime(1.0);
BENCHMARK(BM_FieldQuery)->Unit(benchmark::kMicrosecond)->MinTime(0.5);

BENCHMARK_MAIN();
