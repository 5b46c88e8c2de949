// The cortex scene against its own ground truth: rendered points land on the model's
// projection, the motion's spectrum holds exactly the configured components, material points
// round-trip through ray casting, the instrument occludes what is under it.

#include "pulsetrack/sim/cortex.hpp"

#include <gtest/gtest.h>

#include <iostream>
#include <opencv2/core.hpp>

#include "pulsetrack/sim/paper_rig.hpp"
#include "sim/image_probe.hpp"

namespace pulsetrack::sim {
namespace {

// The probe is the darkness centroid of a 0.8 mm dot, which is only an unbiased estimate of
// the projected centre where the surface is smooth at the dot's scale: on the default gyri
// (0.8 mm high, 16 mm long: 8 mm radius of curvature) the dot's own image is asymmetric by up
// to 0.1 px. Flat, the same renderer puts dots 0.004 px RMS from the projection; here a 70 mm
// curvature, 0.2 mm gyri, a 30 deg tilt and the motion.
CortexSpec dotsSpec() {
  CortexSpec spec;
  spec.texture = "dots";
  spec.gyri_amplitude_mm = 0.2;
  spec.wrinkle_slope = 0.0;
  spec.specular_strength = 0.0;
  spec.illumination_gradient = 0.0;
  spec.oscillations = paperMotion();
  spec.sag = {1.0, 60.0, true};
  return spec;
}

TEST(CortexRender, DotCentroidsLandOnTheirProjection) {
  const vision::StereoRig rig = paperRig();
  CortexScene scene(dotsSpec());
  Rasterizer raster(rig.left.imageSize(), 3);
  cv::Mat left, right;
  double worst = 0.0, sum2 = 0.0;
  int n = 0;
  for (double t : {0.0, 3.3}) {
    scene.render(rig, t, raster, left, right);
    for (int cam = 0; cam < 2; ++cam) {
      const cv::Mat& img = cam == 0 ? left : right;
      for (double v = -24; v <= 24; v += 4) {
        for (double u = -24; u <= 24; u += 4) {
          if (u * u + v * v > 24 * 24) continue;
          const cv::Vec3d p = scene.position(u, v, t);
          const cv::Vec2d proj = cam == 0 ? rig.projectLeft(p) : rig.projectRight(p);
          const cv::Vec2d c = test::darkCentroid(img, proj, 9);
          ASSERT_TRUE(std::isfinite(c[0])) << "no dot at material (" << u << ", " << v << ")";
          const double e = cv::norm(c - proj);
          worst = std::max(worst, e);
          sum2 += e * e;
          ++n;
        }
      }
    }
  }
  std::cout << n << " rendered cortex dots (both cameras, at rest and moving): RMS "
            << std::sqrt(sum2 / n) << " px, max " << worst << " px from the model's projection\n";
  EXPECT_GT(n, 300);
  EXPECT_LT(worst, 0.05);
}

// Ground-truth centre of mass of the patch over 60 s at 10 fps: its spectrum must hold exactly
// the configured lines (each component's amplitude along each axis) and nothing else.
TEST(CortexMotion, SpectrumHoldsExactlyTheConfiguredComponents) {
  CortexSpec spec;
  spec.oscillations = paperMotion();
  const CortexScene scene(spec);
  const int n = 600;
  const double fps = 10.0;
  std::vector<cv::Vec2d> material;
  for (double v = -29; v <= 29; v += 1.0) {
    for (double u = -29; u <= 29; u += 1.0) {
      if (u * u + v * v <= 29 * 29) material.emplace_back(u, v);
    }
  }
  cv::Mat signal(3, n, CV_64FC1);
  for (int i = 0; i < n; ++i) {
    cv::Vec3d com(0, 0, 0);
    for (const cv::Vec2d& m : material) com += scene.position(m[0], m[1], i / fps);
    com *= 1.0 / static_cast<double>(material.size());
    for (int a = 0; a < 3; ++a) signal.at<double>(a, i) = com[a];
  }
  // Expected single-sided amplitude per axis and bin.
  std::map<int, cv::Vec3d> expected;
  for (const Oscillation& o : spec.oscillations) {
    const cv::Vec3d dir_c = scene.rotation() * cv::normalize(o.direction);
    const auto add = [&](double f, double amp) {
      const int bin = static_cast<int>(std::lround(f * n / fps));
      ASSERT_NEAR(bin, f * n / fps, 1e-9) << "component off the FFT grid";
      for (int a = 0; a < 3; ++a) expected[bin][a] += amp * std::abs(dir_c[a]);
    };
    add(o.frequency_hz, o.amplitude_mm);
    for (const Harmonic& h : o.harmonics)
      add(h.multiple * o.frequency_hz, o.amplitude_mm * h.relative_amplitude);
  }
  for (int a = 0; a < 3; ++a) {
    cv::Mat row = signal.row(a).clone();
    row -= cv::mean(row)[0];
    cv::Mat spectrum;
    cv::dft(row, spectrum, cv::DFT_COMPLEX_OUTPUT);
    double stray = 0.0;
    for (int k = 1; k < n / 2; ++k) {
      const cv::Vec2d c = spectrum.at<cv::Vec2d>(0, k);
      const double amp = 2.0 * std::hypot(c[0], c[1]) / n;
      const auto it = expected.find(k);
      if (it != expected.end()) {
        EXPECT_NEAR(amp, it->second[a], 1e-9) << "axis " << a << " at " << k * fps / n << " Hz";
      } else {
        stray = std::max(stray, amp);
      }
    }
    EXPECT_LT(stray, 1e-9) << "axis " << a << ": energy where no component was configured";
  }
  EXPECT_EQ(expected.size(), 6U);  // vasomotor, breathing x3, cardiac x2
}

TEST(CortexMotion, SagSinksTheCentreAsConfigured) {
  CortexSpec spec;
  spec.oscillations.clear();
  spec.sag = {2.0, 100.0, true};
  const CortexScene scene(spec);
  const cv::Vec3d normal = scene.rotation() * cv::Vec3d(0, 0, 1);
  for (double t : {0.0, 50.0, 100.0, 400.0}) {
    const double sink = (scene.position(0, 0, 0) - scene.position(0, 0, t)).dot(normal);
    EXPECT_NEAR(sink, 2.0 * (1.0 - std::exp(-t / 100.0)), 1e-9);
  }
  // Half as much at the rim.
  const double rim = (scene.position(30, 0, 0) - scene.position(30, 0, 1e9)).dot(normal);
  EXPECT_NEAR(rim, 1.0, 1e-9);
}

// Brain shift's turn (cortex-1h): the deformed surface turns rigidly about the axis through the
// patch centre, by rotation_deg * (1 - exp(-t / tau)); the material points follow it exactly.
TEST(CortexMotion, ShiftTurnsTheSurfaceAboutItsCentre) {
  CortexSpec spec;
  spec.oscillations.clear();
  spec.sag = {0.0, 100.0, true, 6.0, {0.0, 1.0, 0.0}};
  const CortexScene scene(spec);
  const vision::StereoRig rig = paperRig();
  for (double t : {50.0, 100.0, 1e4}) {
    const double angle = 6.0 * (1.0 - std::exp(-t / 100.0));
    // Two points along u (their offset is perpendicular to the v axis): the offset keeps its
    // length and turns by the angle.
    const cv::Vec3d a0 = scene.position(20, 0, 0) - scene.position(0, 0, 0);
    const cv::Vec3d a1 = scene.position(20, 0, t) - scene.position(0, 0, t);
    EXPECT_NEAR(cv::norm(a1), cv::norm(a0), 1e-9);
    EXPECT_NEAR(std::acos(a0.dot(a1) / (cv::norm(a0) * cv::norm(a1))) * 180.0 / CV_PI, angle, 1e-6);
    // Material points still round-trip through the image.
    cv::Vec2d found;
    ASSERT_TRUE(scene.materialAt(rig, rig.projectLeft(scene.position(8.0, -5.0, t)), t, found));
    EXPECT_NEAR(found[0], 8.0, 1e-6);
    EXPECT_NEAR(found[1], -5.0, 1e-6);
  }
}

TEST(CortexScene, MaterialPointsRoundTripThroughTheLeftImage) {
  const vision::StereoRig rig = paperRig();
  CortexSpec spec;
  spec.oscillations = paperMotion();
  const CortexScene scene(spec);
  for (double t : {0.0, 1.7}) {
    for (const cv::Vec2d& uv : {cv::Vec2d(0, 0), cv::Vec2d(12.3, -7.9), cv::Vec2d(-20.1, 15.2)}) {
      cv::Vec2d found;
      ASSERT_TRUE(
          scene.materialAt(rig, rig.projectLeft(scene.position(uv[0], uv[1], t)), t, found));
      EXPECT_NEAR(found[0], uv[0], 1e-6);
      EXPECT_NEAR(found[1], uv[1], 1e-6);
    }
  }
  cv::Vec2d off;
  EXPECT_FALSE(scene.materialAt(rig, {5, 5}, 0.0, off));  // the image corner sees bone, not cortex
}

TEST(CortexScene, InstrumentOccludesWhatIsBeneathIt) {
  CortexSpec spec;
  spec.instrument.enabled = true;
  spec.instrument.start_s = 10;
  spec.instrument.duration_s = 4;
  const CortexScene scene(spec);
  const cv::Vec3d camera(0, 0, 0);
  // At mid-crossing the tip is over `to_mm`; the point of the surface on the camera ray
  // through the tip's axis is hidden.
  const double t_mid = 12.0;
  const cv::Vec3d tip =
      scene.rotation() * cv::Vec3d(spec.instrument.to_mm[0] - 10.0, spec.instrument.to_mm[1],
                                   spec.instrument.height_mm) +
      scene.translation();
  const cv::Vec3d behind = tip * 1.05;  // further along the same camera ray
  EXPECT_TRUE(scene.occluded(behind, camera, t_mid));
  EXPECT_FALSE(scene.occluded(behind, camera, 9.0));                           // before it enters
  EXPECT_FALSE(scene.occluded(behind, camera, 14.5));                          // after it left
  EXPECT_FALSE(scene.occluded(scene.position(25, 20, t_mid), camera, t_mid));  // far from the rod

  // Repeated crossings (cortex-1h): the same crossing every period, `repeats` times.
  spec.instrument.period_s = 30.0;
  spec.instrument.repeats = 3;
  const CortexScene again(spec);
  for (int k = 0; k < 3; ++k) {
    EXPECT_TRUE(again.occluded(behind, camera, t_mid + 30.0 * k)) << "crossing " << k;
    EXPECT_FALSE(again.occluded(behind, camera, 9.0 + 30.0 * k)) << "before crossing " << k;
    EXPECT_FALSE(again.occluded(behind, camera, 14.5 + 30.0 * k)) << "after crossing " << k;
  }
  EXPECT_FALSE(again.occluded(behind, camera, t_mid + 90.0));  // three were asked for
}

}  // namespace
}  // namespace pulsetrack::sim
