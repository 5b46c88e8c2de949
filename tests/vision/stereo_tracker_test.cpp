// The tracker against the simulator's ground truth (issue: tracking core, accuracy).

#include "pulsetrack/vision/stereo_tracker.hpp"

#include <gtest/gtest.h>

#include <iostream>
#include <opencv2/imgproc.hpp>

#include "pulsetrack/record/track_csv.hpp"
#include "pulsetrack/sim/evaluate.hpp"
#include "pulsetrack/sim/paper_rig.hpp"
#include "pulsetrack/sim/scene.hpp"

namespace pulsetrack::vision {
namespace {

// The bounding box of the craniotomy's projection (radius r mm around the patch centre).
Roi roiFor(const sim::StereoSimulator& s, double r) {
  const sim::CortexScene& c = *s.cortex();
  std::vector<cv::Point2f> l, rr;
  for (int k = 0; k < 36; ++k) {
    const double a = k * CV_PI / 18;
    const cv::Vec3d p = c.position(r * std::cos(a), r * std::sin(a), 0.0);
    const cv::Vec2d pl = s.rig().projectLeft(p), pr = s.rig().projectRight(p);
    l.emplace_back(static_cast<float>(pl[0]), static_cast<float>(pl[1]));
    rr.emplace_back(static_cast<float>(pr[0]), static_cast<float>(pr[1]));
  }
  return {cv::boundingRect(l), cv::boundingRect(rr)};
}

struct TrackRun {
  sim::Evaluation ev;
  int initial_ok = 0;
};

TrackRun trackScene(const sim::SceneSpec& spec, int frames) {
  sim::StereoSimulator s(spec, sim::paperRig());
  StereoTracker tracker(s.rig(), TrackerConfig{});
  cv::Mat l, r;
  s.render(0, l, r);
  TrackRun run;
  // The ROI on the brain, inside the craniotomy (29.5 mm): its corners stay off the bone rim.
  auto ok = tracker.initialize(l, r, roiFor(s, 19.0), 20.0);
  EXPECT_TRUE(ok) << ok.error().message;
  run.initial_ok = ok.value_or(0);
  std::vector<record::TrackRow> rows;
  for (int i = 0; i < frames; ++i) {
    if (i > 0) {
      s.render(i, l, r);
      tracker.track(l, r);
    }
    for (const Feature& f : tracker.features()) {
      rows.push_back({i, s.frameTime(i), f.id, f.left[0], f.left[1], f.right[0], f.right[1],
                      f.point[0], f.point[1], f.point[2], f.ncc, f.nmi, toString(f.status)});
    }
  }
  auto ev = sim::evaluateTrack(s, rows, 0.5);
  EXPECT_TRUE(ev) << ev.error().message;
  run.ev = ev.value_or(sim::Evaluation{});
  return run;
}

sim::SceneSpec staticCortex() {
  sim::SceneSpec spec;
  spec.kind = sim::SceneKind::kCortex;
  spec.supersample = 2;
  spec.fps = 10.0;
  spec.camera.noise_sigma = 2.0;
  spec.camera.blur_sigma_px = 0.7;
  spec.cortex.oscillations.clear();  // static
  spec.cortex.instrument.enabled = true;
  spec.cortex.instrument.start_s = 0.6;
  spec.cortex.instrument.duration_s = 1.6;
  return spec;
}

void report(const char* what, const TrackRun& run, double& worst_feature, long& occluded) {
  const sim::Evaluation& ev = run.ev;
  worst_feature = 0.0;
  for (const auto& f : ev.per_feature) worst_feature = std::max(worst_feature, f.rms_mm);
  occluded = ev.not_ok.count("occluded") != 0U ? ev.not_ok.at("occluded") : 0;
  std::cout << what << ": " << run.initial_ok << " features; 3D error RMS " << ev.rms_mm
            << " mm, worst feature RMS " << worst_feature << " mm, max " << ev.max_mm << " mm, "
            << ev.outliers << " ok rows > 0.5 mm; " << occluded << " rows occluded\n";
}

// The figure is a per-feature RMS <= 0.05 mm. Measured here: met on a matte cortex
// (worst feature 0.088 mm, overall 0.046 mm: close), not on the glossy one, where the
// sub-saturation sheen of glints differs between the two views and biases the stereo match of
// some features by up to 0.3 px (worst feature 0.19 mm). These tests hold what is achieved;
// the issue stays open until the target is.
TEST(StereoTracker, StaticMatteCortexAt45cm) {
  sim::SceneSpec spec = staticCortex();
  spec.cortex.specular_strength = 0.0;
  const TrackRun run = trackScene(spec, 30);
  double worst = 0;
  long occluded = 0;
  report("static matte cortex, 45 cm, 30 frames, noise 2 grey levels, instrument", run, worst,
         occluded);
  EXPECT_GE(run.initial_ok, 80);
  EXPECT_LE(run.ev.rms_mm, 0.05);
  EXPECT_LE(worst, 0.1);
  EXPECT_LE(run.ev.max_mm, 0.25);
  EXPECT_EQ(run.ev.outliers, 0);
}

TEST(StereoTracker, StaticGlossyCortexAt45cm) {
  const TrackRun run = trackScene(staticCortex(), 30);
  double worst = 0;
  long occluded = 0;
  report("static glossy cortex (glints), 45 cm, 30 frames, noise 2 grey levels, instrument", run,
         worst, occluded);
  EXPECT_GE(run.initial_ok, 60);
  EXPECT_LE(run.ev.rms_mm, 0.07);
  EXPECT_LE(worst, 0.22);
  EXPECT_LE(run.ev.max_mm, 0.5);  // the issue: no ok feature off by more than 0.5 mm in any frame
  EXPECT_EQ(run.ev.outliers, 0);
  EXPECT_GT(occluded,
            0);  // the instrument and the glints were seen and reported, not tracked through
}

}  // namespace
}  // namespace pulsetrack::vision
