// Video matching of 100 features in both cameras (15x15 templates, +-8 px windows) on a
// rendered cortex frame pair, against what a user would assemble from OpenCV on the same
// windows: cv::matchTemplate(TM_CCOEFF_NORMED) + cv::minMaxLoc, and cv::calcOpticalFlowPyrLK
// for the same points. One core. Prints the ratios at the end.

#include <benchmark/benchmark.h>

#include <iostream>
#include <map>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "pulsetrack/sim/paper_rig.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/ncc.hpp"

namespace {

constexpr int kHalf = 7;    // 15x15
constexpr int kSearch = 8;  // +-8 px
constexpr int kSide = 2 * kSearch + 1;

struct Fixture {
  cv::Mat prev[2], next[2];
  std::vector<cv::Point> points[2];  // integer feature positions in frame 0
  std::vector<pulsetrack::vision::NccTemplate> templates[2];
  std::vector<cv::Mat> cv_templates[2];

  Fixture() {
    cv::setNumThreads(1);
    pulsetrack::sim::SceneSpec spec;
    spec.kind = pulsetrack::sim::SceneKind::kCortex;
    spec.supersample = 2;
    spec.frames = 10;
    spec.cortex.oscillations = pulsetrack::sim::paperMotion();
    for (auto& o : spec.cortex.oscillations) o.amplitude_mm *= 4.0;  // a few px of motion
    pulsetrack::sim::StereoSimulator sim(spec, pulsetrack::sim::paperRig());
    sim.render(0, prev[0], prev[1]);
    sim.render(3, next[0], next[1]);
    for (int c = 0; c < 2; ++c) {
      std::vector<cv::Point2f> corners;
      cv::Mat mask(prev[c].size(), CV_8UC1, cv::Scalar(0));
      mask(cv::Rect(400, 250, 560, 520)).setTo(255);
      cv::goodFeaturesToTrack(prev[c], corners, 100, 0.01, 20, mask);
      for (const auto& p : corners) {
        const cv::Point q(cvRound(p.x), cvRound(p.y));
        points[c].push_back(q);
        pulsetrack::vision::NccTemplate t;
        t.set(prev[c].ptr(q.y - kHalf, q.x - kHalf), prev[c].step, 15, 15);
        templates[c].push_back(t);
        cv_templates[c].push_back(prev[c](cv::Rect(q.x - kHalf, q.y - kHalf, 15, 15)).clone());
      }
    }
  }
};

Fixture& fixture() {
  static Fixture f;
  return f;
}

template <bool kSimd>
void BM_OurNcc(benchmark::State& state) {
  Fixture& f = fixture();
  float scores[kSide * kSide];
  for (auto _ : state) {
    for (int c = 0; c < 2; ++c) {
      for (size_t i = 0; i < f.points[c].size(); ++i) {
        const cv::Point& p = f.points[c][i];
        const uint8_t* region = f.next[c].ptr(p.y - kHalf - kSearch, p.x - kHalf - kSearch);
        if constexpr (kSimd) {
          pulsetrack::vision::nccScores(f.templates[c][i], region, f.next[c].step, kSide, kSide,
                                        scores);
        } else {
          pulsetrack::vision::nccScoresScalar(f.templates[c][i], region, f.next[c].step, kSide,
                                              kSide, scores);
        }
        const int best =
            static_cast<int>(std::max_element(scores, scores + kSide * kSide) - scores);
        const int bx = std::clamp(best % kSide, 1, kSide - 2),
                  by = std::clamp(best / kSide, 1, kSide - 2);
        float n3[9];
        for (int j = 0; j < 3; ++j) {
          for (int k = 0; k < 3; ++k) n3[j * 3 + k] = scores[(by - 1 + j) * kSide + bx - 1 + k];
        }
        benchmark::DoNotOptimize(pulsetrack::vision::quadraticPeak(n3));
      }
    }
  }
  state.SetItemsProcessed(state.iterations() *
                          static_cast<int64_t>(f.points[0].size() + f.points[1].size()));
}
BENCHMARK_TEMPLATE(BM_OurNcc, true)
    ->Name("ours_simd_ncc_exhaustive")
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_TEMPLATE(BM_OurNcc, false)
    ->Name("ours_scalar_ncc_exhaustive")
    ->Unit(benchmark::kMicrosecond);

void BM_MatchTemplate(benchmark::State& state) {
  Fixture& f = fixture();
  cv::Mat result;
  for (auto _ : state) {
    for (int c = 0; c < 2; ++c) {
      for (size_t i = 0; i < f.points[c].size(); ++i) {
        const cv::Point& p = f.points[c][i];
        const cv::Mat window = f.next[c](cv::Rect(p.x - kHalf - kSearch, p.y - kHalf - kSearch,
                                                  15 + 2 * kSearch, 15 + 2 * kSearch));
        cv::matchTemplate(window, f.cv_templates[c][i], result, cv::TM_CCOEFF_NORMED);
        double mx = 0;
        cv::Point loc;
        cv::minMaxLoc(result, nullptr, &mx, nullptr, &loc);
        benchmark::DoNotOptimize(loc);
      }
    }
  }
  state.SetItemsProcessed(state.iterations() *
                          static_cast<int64_t>(f.points[0].size() + f.points[1].size()));
}
BENCHMARK(BM_MatchTemplate)->Name("opencv_matchTemplate_minMaxLoc")->Unit(benchmark::kMicrosecond);

void BM_Klt(benchmark::State& state) {
  Fixture& f = fixture();
  std::vector<cv::Point2f> from[2], to[2];
  for (int c = 0; c < 2; ++c) {
    for (const auto& p : f.points[c])
      from[c].emplace_back(static_cast<float>(p.x), static_cast<float>(p.y));
  }
  std::vector<uchar> st;
  std::vector<float> err;
  for (auto _ : state) {
    for (int c = 0; c < 2; ++c) {
      cv::calcOpticalFlowPyrLK(f.prev[c], f.next[c], from[c], to[c], st, err, cv::Size(15, 15), 2);
      benchmark::DoNotOptimize(to[c].data());
    }
  }
  state.SetItemsProcessed(state.iterations() *
                          static_cast<int64_t>(from[0].size() + from[1].size()));
}
BENCHMARK(BM_Klt)->Name("opencv_calcOpticalFlowPyrLK")->Unit(benchmark::kMicrosecond);

class RatioReporter : public benchmark::ConsoleReporter {
 public:
  void ReportRuns(const std::vector<Run>& runs) override {
    for (const Run& r : runs) times_[r.benchmark_name()] = r.GetAdjustedRealTime();
    ConsoleReporter::ReportRuns(runs);
  }
  void Finalize() override {
    ConsoleReporter::Finalize();
    const auto get = [&](const char* n) { return times_.count(n) != 0U ? times_[n] : 0.0; };
    const double simd = get("ours_simd_ncc_exhaustive");
    if (simd <= 0) return;
    std::cout << "\nNCC kernel target: " << pulsetrack::vision::nccTarget() << "\n";
    std::cout << "per frame pair (100 features x 2 cameras, 15x15, +-8 px):\n";
    for (const char* n : {"ours_simd_ncc_exhaustive", "ours_scalar_ncc_exhaustive",
                          "opencv_matchTemplate_minMaxLoc", "opencv_calcOpticalFlowPyrLK"}) {
      if (get(n) > 0)
        std::cout << "  " << n << ": " << get(n) << " us, " << get(n) / simd << "x ours (SIMD)\n";
    }
  }

 private:
  std::map<std::string, double> times_;
};

}  // namespace

int main(int argc, char** argv) {
  benchmark::Initialize(&argc, argv);
  RatioReporter reporter;
  benchmark::RunSpecifiedBenchmarks(&reporter);
  benchmark::Shutdown();
  return 0;
}
