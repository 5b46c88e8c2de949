// Video matching of 100 features in both cameras (15x15 templates, +-8 px windows) on a
// rendered cortex frame pair, against what a user would assemble from OpenCV on the same
// windows: cv::matchTemplate(TM_CCOEFF_NORMED) + cv::minMaxLoc, and cv::calcOpticalFlowPyrLK
// for the same points (frame to frame, as a KLT user would). One core. Prints the ratios at the
// end, and each method's error against the simulator's ground truth in the left camera (the
// material point under the frame-0 pixel, projected at the later frame's time).
//
// "ours_video_match" is what the tracker does per camera: the translation refinement from the
// last position (one Highway pass per iteration), the SIMD NCC search only when that fails.

#include <benchmark/benchmark.h>

#include <cmath>
#include <iostream>
#include <limits>
#include <map>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "pulsetrack/sim/paper_rig.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/affine_refiner.hpp"
#include "pulsetrack/vision/ncc.hpp"

namespace {

constexpr int kHalf = 7;    // 15x15
constexpr int kSearch = 8;  // +-8 px
constexpr int kSide = 2 * kSearch + 1;

// Templates from frame 0; the features were tracked to frame 5 (`last`); the matching under
// test finds them in frame 6, in +-8 px windows around `last`, as the tracker does at 30 fps.
struct Fixture {
  cv::Mat prev[2], before[2], next[2];  // frames 0, 5 and 6
  std::vector<cv::Point> points[2];     // integer feature positions in frame 0 (the templates)
  std::vector<cv::Point> last[2];       // their positions in the previous frame, rounded
  std::vector<cv::Point2f> last_f[2];   // ... and not rounded (KLT's starting points)
  std::vector<pulsetrack::vision::NccTemplate> templates[2];
  std::vector<cv::Mat> cv_templates[2];
  std::vector<pulsetrack::vision::ShiftTemplate> shift[2];
  std::vector<cv::Vec2d> truth;  // left camera: the true position in `next`, NaN if unknown

  Fixture() {
    cv::setNumThreads(1);
    pulsetrack::sim::SceneSpec spec;
    spec.kind = pulsetrack::sim::SceneKind::kCortex;
    spec.supersample = 2;
    spec.fps = 30.0;
    spec.frames = 10;
    spec.cortex.oscillations = pulsetrack::sim::paperMotion();
    pulsetrack::sim::StereoSimulator sim(spec, pulsetrack::sim::paperRig());
    sim.render(0, prev[0], prev[1]);
    sim.render(5, before[0], before[1]);
    sim.render(6, next[0], next[1]);
    const double t0 = sim.frameTime(0), t6 = sim.frameTime(6);
    for (int c = 0; c < 2; ++c) {
      // Like the tracker's detection: inside the craniotomy, away from glints.
      std::vector<cv::Point2f> corners;
      cv::Mat mask(prev[c].size(), CV_8UC1, cv::Scalar(0));
      mask(cv::Rect(400, 250, 560, 520)).setTo(255);
      cv::Mat glints = prev[c] >= 215;
      cv::dilate(glints, glints, cv::getStructuringElement(cv::MORPH_ELLIPSE, {27, 27}));
      mask.setTo(0, glints);
      cv::goodFeaturesToTrack(prev[c], corners, 100, 0.01, 20, mask);
      for (const auto& p : corners) {
        const cv::Point q(cvRound(p.x), cvRound(p.y));
        pulsetrack::vision::NccTemplate t;
        t.set(prev[c].ptr(q.y - kHalf, q.x - kHalf), prev[c].step, 15, 15);
        pulsetrack::vision::ShiftTemplate st;
        st.set(prev[c].data, prev[c].step, prev[c].cols, prev[c].rows, cv::Vec2d(q.x, q.y));
        // Where the tracker left it in frame 5: the template's own refinement there.
        const auto ar = st.refine(before[c].data, before[c].step, before[c].cols, before[c].rows,
                                  cv::Vec2d(q.x, q.y));
        if (!ar.converged) continue;
        points[c].push_back(q);
        last[c].emplace_back(cvRound(ar.warp.centre[0]), cvRound(ar.warp.centre[1]));
        last_f[c].emplace_back(static_cast<float>(ar.warp.centre[0]),
                               static_cast<float>(ar.warp.centre[1]));
        templates[c].push_back(t);
        cv_templates[c].push_back(prev[c](cv::Rect(q.x - kHalf, q.y - kHalf, 15, 15)).clone());
        shift[c].push_back(st);
        if (c == 0) {
          cv::Vec2d uv;
          const double nan = std::numeric_limits<double>::quiet_NaN();
          truth.push_back(sim.cortex()->materialAt(sim.rig(), cv::Vec2d(q.x, q.y), t0, uv)
                              ? sim.rig().projectLeft(sim.cortex()->position(uv[0], uv[1], t6))
                              : cv::Vec2d(nan, nan));
        }
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
        const cv::Point& p = f.last[c][i];
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

// The exhaustive search with the quadratic peak, as a position.
cv::Vec2d nccSearch(const Fixture& f, int c, size_t i, float* scores) {
  const cv::Point& p = f.last[c][i];
  const uint8_t* region = f.next[c].ptr(p.y - kHalf - kSearch, p.x - kHalf - kSearch);
  pulsetrack::vision::nccScores(f.templates[c][i], region, f.next[c].step, kSide, kSide, scores);
  const int best = static_cast<int>(std::max_element(scores, scores + kSide * kSide) - scores);
  const int bx = std::clamp(best % kSide, 1, kSide - 2),
            by = std::clamp(best / kSide, 1, kSide - 2);
  float n3[9];
  for (int j = 0; j < 3; ++j) {
    for (int k = 0; k < 3; ++k) n3[j * 3 + k] = scores[(by - 1 + j) * kSide + bx - 1 + k];
  }
  const auto sub = pulsetrack::vision::quadraticPeak(n3);
  return {p.x - kSearch + bx + sub.dx, p.y - kSearch + by + sub.dy};
}

// What the tracker does per camera and feature (StereoTracker::trackCamera).
cv::Vec2d videoMatch(const Fixture& f, int c, size_t i, float* scores) {
  const cv::Mat& img = f.next[c];
  const cv::Vec2d last(f.last[c][i].x, f.last[c][i].y);
  const auto& t = f.shift[c][i];
  auto ar = t.refine(img.data, img.step, img.cols, img.rows, last);
  if (ar.converged && ar.ncc >= 0.75 && cv::norm(ar.warp.centre - last) <= kSearch)
    return ar.warp.centre;
  const cv::Vec2d start = nccSearch(f, c, i, scores);
  ar = t.refine(img.data, img.step, img.cols, img.rows, start);
  return ar.converged ? ar.warp.centre : start;
}

void BM_OurVideoMatch(benchmark::State& state) {
  Fixture& f = fixture();
  float scores[kSide * kSide];
  for (auto _ : state) {
    for (int c = 0; c < 2; ++c) {
      for (size_t i = 0; i < f.points[c].size(); ++i)
        benchmark::DoNotOptimize(videoMatch(f, c, i, scores));
    }
  }
  state.SetItemsProcessed(state.iterations() *
                          static_cast<int64_t>(f.points[0].size() + f.points[1].size()));
}
BENCHMARK(BM_OurVideoMatch)->Name("ours_video_match")->Unit(benchmark::kMicrosecond);

// The translation refinement alone, from the last position: the Highway kernel against its
// scalar reference (the ratio that says what the SIMD target buys, on x86 and under emulation).
template <bool kSimd>
void BM_OurRefine(benchmark::State& state) {
  Fixture& f = fixture();
  for (auto _ : state) {
    for (int c = 0; c < 2; ++c) {
      const cv::Mat& img = f.next[c];
      for (size_t i = 0; i < f.points[c].size(); ++i) {
        benchmark::DoNotOptimize(f.shift[c][i].refine(img.data, img.step, img.cols, img.rows,
                                                      cv::Vec2d(f.last[c][i].x, f.last[c][i].y), 10,
                                                      2e-3, /*scalar=*/!kSimd));
      }
    }
  }
  state.SetItemsProcessed(state.iterations() *
                          static_cast<int64_t>(f.points[0].size() + f.points[1].size()));
}
BENCHMARK_TEMPLATE(BM_OurRefine, true)->Name("ours_simd_refine")->Unit(benchmark::kMicrosecond);
BENCHMARK_TEMPLATE(BM_OurRefine, false)->Name("ours_scalar_refine")->Unit(benchmark::kMicrosecond);

void BM_MatchTemplate(benchmark::State& state) {
  Fixture& f = fixture();
  cv::Mat result;
  for (auto _ : state) {
    for (int c = 0; c < 2; ++c) {
      for (size_t i = 0; i < f.points[c].size(); ++i) {
        const cv::Point& p = f.last[c][i];
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
  std::vector<cv::Point2f> from[2] = {f.last_f[0], f.last_f[1]}, to[2];
  std::vector<uchar> st;
  std::vector<float> err;
  for (auto _ : state) {
    for (int c = 0; c < 2; ++c) {
      cv::calcOpticalFlowPyrLK(f.before[c], f.next[c], from[c], to[c], st, err, cv::Size(15, 15),
                               2);
      benchmark::DoNotOptimize(to[c].data());
    }
  }
  state.SetItemsProcessed(state.iterations() *
                          static_cast<int64_t>(from[0].size() + from[1].size()));
}
BENCHMARK(BM_Klt)->Name("opencv_calcOpticalFlowPyrLK")->Unit(benchmark::kMicrosecond);

// Left-camera error against the truth of each method, run once on the same features.
void printAccuracy() {
  Fixture& f = fixture();
  float scores[kSide * kSide];
  std::vector<cv::Point2f> from = f.last_f[0], klt;
  std::vector<uchar> st;
  std::vector<float> err;
  cv::calcOpticalFlowPyrLK(f.before[0], f.next[0], from, klt, st, err, cv::Size(15, 15), 2);
  cv::Mat result;
  double ss[4] = {}, mx[4] = {};
  int n = 0;
  for (size_t i = 0; i < f.points[0].size(); ++i) {
    if (!std::isfinite(f.truth[i][0])) continue;
    const cv::Point& p = f.last[0][i];
    const cv::Mat window = f.next[0](
        cv::Rect(p.x - kHalf - kSearch, p.y - kHalf - kSearch, 15 + 2 * kSearch, 15 + 2 * kSearch));
    cv::matchTemplate(window, f.cv_templates[0][i], result, cv::TM_CCOEFF_NORMED);
    cv::Point loc;
    cv::minMaxLoc(result, nullptr, nullptr, nullptr, &loc);
    const cv::Vec2d at[4] = {videoMatch(f, 0, i, scores), nccSearch(f, 0, i, scores),
                             cv::Vec2d(p.x - kSearch + loc.x, p.y - kSearch + loc.y),
                             cv::Vec2d(klt[i].x, klt[i].y)};
    for (int m = 0; m < 4; ++m) {
      const double e = cv::norm(at[m] - f.truth[i]);
      ss[m] += e * e;
      mx[m] = std::max(mx[m], e);
    }
    ++n;
  }
  const char* names[4] = {"ours_video_match (refined)", "ours NCC + quadratic peak",
                          "matchTemplate + minMaxLoc (integer)", "calcOpticalFlowPyrLK"};
  std::cout << "left-camera error against the truth, " << n << " features (px):\n";
  for (int m = 0; m < 4; ++m) {
    std::cout << "  " << names[m] << ": RMS " << std::sqrt(ss[m] / std::max(n, 1)) << ", max "
              << mx[m] << "\n";
  }
}

class RatioReporter : public benchmark::ConsoleReporter {
 public:
  void ReportRuns(const std::vector<Run>& runs) override {
    for (const Run& r : runs) times_[r.benchmark_name()] = r.GetAdjustedRealTime();
    ConsoleReporter::ReportRuns(runs);
  }
  void Finalize() override {
    ConsoleReporter::Finalize();
    const auto get = [&](const char* n) { return times_.count(n) != 0U ? times_[n] : 0.0; };
    const double ours = get("ours_video_match");
    std::cout << "\nSIMD target: " << pulsetrack::vision::nccTarget() << "\n";
    std::cout << "per frame pair (" << fixture().points[0].size() << "+"
              << fixture().points[1].size() << " features, 15x15, +-8 px), time and its ratio "
              << "to ours_video_match:\n";
    for (const char* n : {"ours_video_match", "ours_simd_ncc_exhaustive",
                          "ours_scalar_ncc_exhaustive", "ours_simd_refine", "ours_scalar_refine",
                          "opencv_matchTemplate_minMaxLoc", "opencv_calcOpticalFlowPyrLK"}) {
      if (get(n) > 0 && ours > 0)
        std::cout << "  " << n << ": " << get(n) << " us, " << get(n) / ours << "x\n";
    }
    // Under qemu (preset arm64) only these ratios mean anything, not the times.
    std::cout << "SIMD (" << pulsetrack::vision::nccTarget() << ") vs the scalar reference:\n";
    for (const auto& [simd, scalar] :
         {std::pair{"ours_simd_ncc_exhaustive", "ours_scalar_ncc_exhaustive"},
          std::pair{"ours_simd_refine", "ours_scalar_refine"}}) {
      if (get(simd) > 0 && get(scalar) > 0)
        std::cout << "  " << scalar << " / " << simd << ": " << get(scalar) / get(simd) << "x\n";
    }
    printAccuracy();
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
