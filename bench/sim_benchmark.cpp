// Frame pairs the simulator renders per second at full resolution (1360x1024 x 2), on one core
// (OpenCV's thread pool limited to 1), with all camera effects: the live simulated rig must
// sustain the paper's 10 fps at supersample 1; recordings for accuracy work use 2.

#include <benchmark/benchmark.h>

#include <opencv2/core.hpp>

#include "pulsetrack/sim/paper_rig.hpp"
#include "pulsetrack/sim/scene.hpp"

namespace {

pulsetrack::sim::SceneSpec cortexScene(int supersample) {
  pulsetrack::sim::SceneSpec spec;
  spec.name = "bench";
  spec.kind = pulsetrack::sim::SceneKind::kCortex;
  spec.supersample = supersample;
  spec.frames = 1'000'000;
  spec.cortex.oscillations = pulsetrack::sim::paperMotion();
  spec.cortex.instrument.enabled = true;
  spec.cortex.instrument.start_s = 0.0;
  spec.cortex.instrument.duration_s = 1e6;
  return spec;
}

void BM_CortexFramePair(benchmark::State& state) {
  cv::setNumThreads(1);
  pulsetrack::sim::StereoSimulator sim(cortexScene(static_cast<int>(state.range(0))),
                                       pulsetrack::sim::paperRig());
  cv::Mat left, right;
  int i = 0;
  for (auto _ : state) {
    sim.render(i++, left, right);
    benchmark::DoNotOptimize(left.data);
  }
  state.counters["pairs_per_s"] =
      benchmark::Counter(static_cast<double>(state.iterations()), benchmark::Counter::kIsRate);
}
BENCHMARK(BM_CortexFramePair)->Arg(1)->Arg(2)->Arg(3)->Unit(benchmark::kMillisecond)->UseRealTime();

void BM_PlateFramePair(benchmark::State& state) {
  cv::setNumThreads(1);
  pulsetrack::sim::SceneSpec spec;
  spec.kind = pulsetrack::sim::SceneKind::kPlate;
  spec.supersample = static_cast<int>(state.range(0));
  spec.plate.protocol = pulsetrack::sim::PlateProtocol::kDynamic;
  pulsetrack::sim::StereoSimulator sim(spec, pulsetrack::sim::paperRig());
  cv::Mat left, right;
  int i = 0;
  for (auto _ : state) {
    sim.render(i++ % sim.frameCount(), left, right);
    benchmark::DoNotOptimize(left.data);
  }
  state.counters["pairs_per_s"] =
      benchmark::Counter(static_cast<double>(state.iterations()), benchmark::Counter::kIsRate);
}
BENCHMARK(BM_PlateFramePair)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
