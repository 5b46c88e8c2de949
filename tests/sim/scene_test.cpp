// Scene files: the shipped ones load; every mistake names file:line and the key.

#include "pulsetrack/sim/scene.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <opencv2/core/persistence.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <regex>
#include <vector>

#include "pulsetrack/sim/evaluate.hpp"
#include "pulsetrack/sim/paper_rig.hpp"
#include "test_util.hpp"

namespace pulsetrack::sim {
namespace {

std::string configDir() { return test::sourceDir() + "/config"; }

TEST(SceneFile, ShippedScenesLoad) {
  for (const char* name : {"cortex-60s", "cortex-hard", "cortex-1h", "cortex-1h-compressed",
                           "plate-static", "plate-dynamic"}) {
    auto s = loadScene(configDir() + "/scenes/" + name + ".toml");
    ASSERT_TRUE(s) << s.error().message;
    EXPECT_EQ(s->name, name);
    auto rig = vision::loadRig(s->rig_path);
    ASSERT_TRUE(rig) << rig.error().message;
  }
  auto cortex = loadScene(configDir() + "/scenes/cortex-60s.toml");
  ASSERT_EQ(cortex->cortex.oscillations.size(), 3U);
  EXPECT_EQ(cortex->cortex.oscillations[1].name, "breathing");
  EXPECT_DOUBLE_EQ(cortex->cortex.oscillations[1].frequency_hz, 0.2);
  ASSERT_EQ(cortex->cortex.oscillations[1].harmonics.size(), 2U);
  EXPECT_DOUBLE_EQ(cortex->cortex.oscillations[1].harmonics[1].multiple, 3.0);
  EXPECT_NEAR(cortex->cortex.oscillations[1].harmonics[0].phase_rad, 29.0 * CV_PI / 180.0, 1e-12);
  EXPECT_TRUE(cortex->cortex.sag.enabled);
  EXPECT_TRUE(cortex->cortex.instrument.enabled);
  EXPECT_EQ(cortex->frames, 600);
  auto hour = loadScene(configDir() + "/scenes/cortex-1h.toml");
  EXPECT_DOUBLE_EQ(hour->cortex.sag.rotation_deg, 4.0);
  EXPECT_DOUBLE_EQ(hour->cortex.sag.rotation_axis[1], 0.6);
  EXPECT_DOUBLE_EQ(hour->cortex.instrument.period_s, 120.0);
  EXPECT_EQ(hour->cortex.instrument.repeats, 0);
  auto dynamic = loadScene(configDir() + "/scenes/plate-dynamic.toml");
  EXPECT_EQ(dynamic->plate.protocol, PlateProtocol::kDynamic);
}

TEST(SceneFile, PaperRigYamlIsThePaperRig) {
  auto rig = vision::loadRig(configDir() + "/rigs/paper-rig.yaml");
  ASSERT_TRUE(rig) << rig.error().message;
  const vision::StereoRig ref = paperRig();
  EXPECT_LT(cv::norm(rig->left.k() - ref.left.k()), 1e-9);
  EXPECT_LT(cv::norm(rig->r - ref.r), 1e-12);
  EXPECT_LT(cv::norm(rig->t - ref.t), 1e-9);
  EXPECT_EQ(rig->left.imageSize(), cv::Size(1360, 1024));
  EXPECT_NEAR(rig->left.fx(), 25.0 / 4.65e-3, 5.0);  // 25 mm lens, 4.65 um pixels
  EXPECT_NEAR(rig->baseline(), 60.0, 0.1);
  // Both views see the whole of a 55 mm craniotomy centred on the left axis from 40 to 50 cm.
  for (double z : {400.0, 450.0, 500.0}) {
    for (int k = 0; k < 36; ++k) {
      const double a = k * CV_PI / 18;
      const cv::Vec3d p(27.5 * std::cos(a), 27.5 * std::sin(a), z);
      for (const cv::Vec2d& px : {rig->projectLeft(p), rig->projectRight(p)}) {
        EXPECT_GT(px[0], 0.0);
        EXPECT_GT(px[1], 0.0);
        EXPECT_LT(px[0], 1359.0);
        EXPECT_LT(px[1], 1023.0);
      }
    }
  }
}

void expectError(const std::string& text, const std::string& pattern) {
  auto s = parseScene(text, "/x/scene.toml");
  ASSERT_FALSE(s) << "accepted:\n" << text;
  EXPECT_TRUE(std::regex_search(s.error().message, std::regex(pattern)))
      << "message: " << s.error().message << "\nexpected: " << pattern;
}

const std::string kHead = "kind = \"cortex\"\nrig = \"r.yaml\"\n";

TEST(SceneFile, MistakesNameFileLineAndKey) {
  expectError(kHead + "[cortex.sag]\nrotation_axis = [0, 0, 0]\n",
              "scene.toml:4: cortex.sag.rotation_axis: must not be zero");
  expectError(kHead + "[cortex.instrument]\nduration_s = 8\nperiod_s = 5\n",
              "scene.toml:5: cortex.instrument.period_s: must be 0 \\(once\\) or at least "
              "duration_s");
  expectError("rig = \"r.yaml\"\n", "scene.toml: key 'kind' is missing");
  expectError("kind = \"cortex\"\n", "scene.toml: key 'rig' is missing");
  expectError("kind = \"brain\"\nrig = \"r\"\n",
              "scene.toml:1: kind: expected one of cortex, plate");
  expectError(kHead + "fps = \"ten\"\n", "scene.toml:3: fps: expected a number");
  expectError(kHead + "fps = 0.0\n",
              "scene.toml:3: fps: expected a number in \\[0.1, 1000\\], got 0");
  expectError(kHead + "frames = 2.5\n", "scene.toml:3: frames: expected an integer");
  expectError(kHead + "framez = 3\n", "scene.toml:3: unknown key 'framez'");
  expectError(kHead + "[camera]\nnoise_sigma = -1\n",
              "scene.toml:4: camera.noise_sigma: expected a number in \\[0, 50\\]");
  expectError(kHead + "[cortex]\ntilt = 3\n", "scene.toml:4: unknown key 'cortex.tilt'");
  expectError(kHead + "[[cortex.motion]]\nname = \"b\"\ngradient = [1]\n",
              "scene.toml:5: cortex.motion\\[0\\].gradient: expected 2 to 2 numbers");
  expectError(kHead + "[[cortex.motion]]\nharmonics = [{ multiple = 0.5 }]\n",
              "scene.toml:4: cortex.motion\\[0\\].harmonics\\[0\\].multiple: expected a number in "
              "\\[1, 20\\]");
  expectError(kHead + "[cortex.sag]\nenabled = 1\n",
              "scene.toml:4: cortex.sag.enabled: expected true or false");
  expectError(kHead + "cortex = 5\n", "scene.toml:3: cortex: expected a table");
  expectError(kHead + "[plate]\nprotocol = \"wobbly\"\n",
              "scene.toml:4: plate.protocol: expected one of dynamic, static");
  expectError(kHead + "fps = [\n", "scene.toml:3:");  // TOML syntax error
  // fuzz_scene's finding: a table or array of small floats where a number was expected was
  // printed through toml++'s formatter, which casts log10(0.2) to size_t (undefined behaviour).
  // The message says what it got, briefly.
  expectError(kHead + "fps = [0.2, 0.1]\n",
              "scene.toml:3: fps: expected a number in \\[0.1, 1000\\], got an array of 2");
  expectError(kHead + "fps = { a = 0.2 }\n", "scene.toml:3: fps: expected a number.*got a table");
}

// A motion that changes (the predictor's cases): rate and amplitude ramps, irregular cycles.
TEST(SceneFile, AMotionCanChangeRateAndAmplitudeAndBeIrregular) {
  auto s = parseScene(kHead +
                          "[[cortex.motion]]\nname = \"breathing\"\namplitude_mm = 0.45\n"
                          "frequency_hz = 0.2\nfrequency_end_hz = 0.3333\namplitude_end_mm = 0.9\n"
                          "change_start_s = 40\nchange_duration_s = 30\nirregularity = 0.1\n"
                          "irregularity_seed = 4\n",
                      "/x/scene.toml");
  ASSERT_TRUE(s) << s.error().message;
  ASSERT_EQ(s->cortex.oscillations.size(), 1U);
  const Oscillation& o = s->cortex.oscillations[0];
  EXPECT_EQ(o.frequency_end_hz, 0.3333);
  EXPECT_EQ(o.amplitude_end_mm, 0.9);
  EXPECT_EQ(o.irregularity, 0.1);
  const OscillationClock clock(o, 200.0);
  EXPECT_DOUBLE_EQ(clock.frequency(10.0), 0.2);
  EXPECT_DOUBLE_EQ(clock.frequency(55.0), 0.2 + 0.5 * (0.3333 - 0.2));
  EXPECT_DOUBLE_EQ(clock.frequency(100.0), 0.3333);
  EXPECT_DOUBLE_EQ(clock.amplitude(100.0), 0.9);
  // The signal is continuous through the ramp and the irregular cycles' joins.
  double prev = clock.value(0.0), jump = 0.0;
  for (double t = 0.001; t < 100.0; t += 0.001) {
    const double v = clock.value(t);
    jump = std::max(jump, std::abs(v - prev));
    prev = v;
  }
  EXPECT_LT(jump, 0.01);  // continuous: 1 ms steps of a <= 1.5 Hz, <= 1.5 mm signal
  // Without changes the closed form is kept (the shipped scenes' truth, bit for bit).
  Oscillation plain = o;
  plain.frequency_end_hz = plain.amplitude_end_mm = std::numeric_limits<double>::quiet_NaN();
  plain.irregularity = 0.0;
  const OscillationClock plain_clock(plain);
  EXPECT_EQ(plain_clock.value(12.345), 0.45 * std::sin(2.0 * CV_PI * 0.2 * 12.345));
  expectError(kHead + "[[cortex.motion]]\nirregularity = 0.9\n",
              "scene.toml:4: cortex.motion\\[0\\].irregularity: expected a number in \\[0, 0.5\\]");
  expectError(kHead + "[[cortex.motion]]\nfrequency_end_hz = -1\n",
              "scene.toml:4: cortex.motion\\[0\\].frequency_end_hz");
}

// Unequal cameras (issue 14): [camera.right] overrides [camera]'s keys for the right camera only;
// its mistakes are named like the others'.
TEST(SceneFile, TheRightCameraCanDiffer) {
  auto s = parseScene(kHead +
                          "[camera]\nnoise_sigma = 3.0\ngain_amplitude = 0.3\n"
                          "[camera.right]\ngain = 0.8\ngain_phase_deg = 120.0\n"
                          "vignetting_centre_px = [120.0, -80.0]\n"
                          "[cortex.instrument]\nhold_fraction = 0.7\n",
                      "/x/scene.toml");
  ASSERT_TRUE(s) << s.error().message;
  EXPECT_DOUBLE_EQ(s->camera.gain, 1.0);
  ASSERT_TRUE(s->camera_right.has_value());
  const CameraEffectsSpec right_spec = s->camera_right.value_or(CameraEffectsSpec{});
  EXPECT_DOUBLE_EQ(right_spec.gain, 0.8);
  EXPECT_DOUBLE_EQ(right_spec.noise_sigma, 3.0);     // inherited
  EXPECT_DOUBLE_EQ(right_spec.gain_amplitude, 0.3);  // inherited
  EXPECT_DOUBLE_EQ(right_spec.gain_phase_deg, 120.0);
  EXPECT_DOUBLE_EQ(right_spec.vignetting_centre_px[0], 120.0);
  EXPECT_DOUBLE_EQ(s->cortex.instrument.hold_fraction, 0.7);
  // The gains as the cameras apply them: 20 % apart at t = 0 (phase 0 and 120 deg).
  CameraEffects left(s->camera, {64, 48}, 1), right(right_spec, {64, 48}, 2);
  EXPECT_NEAR(left.gain(0.0), 1.0, 1e-12);
  EXPECT_NEAR(right.gain(0.0), 0.8 * (1.0 + 0.3 * std::sin(120.0 * CV_PI / 180.0)), 1e-12);
  auto plain = parseScene(kHead, "/x/scene.toml");
  ASSERT_TRUE(plain);
  EXPECT_FALSE(plain->camera_right.has_value());  // both cameras use [camera]
  expectError(kHead + "[camera.right]\ngainn = 1\n",
              "scene.toml:4: unknown key 'camera.right.gainn'");
  expectError(kHead + "[camera.right]\ngain = 9\n",
              "scene.toml:4: camera.right.gain: expected a number in \\[0.2, 5\\]");
}

// The half-resolution rig as OpenCV's own FileStorage reads it (what a user's OpenCV tools and
// the real-texture scenes' consumers meet; pulsetrack's reader is yaml-cpp): the paper rig's
// lenses and baseline at 680x512, focal lengths halved, principal points (c + 0.5) / 2 - 0.5.
TEST(SceneFile, HalfResolutionRigIsThePaperRigHalvedForOpenCv) {
  cv::FileStorage full(configDir() + "/rigs/paper-rig.yaml", cv::FileStorage::READ);
  cv::FileStorage half(configDir() + "/rigs/paper-rig-half.yaml", cv::FileStorage::READ);
  ASSERT_TRUE(full.isOpened());
  ASSERT_TRUE(half.isOpened());
  std::vector<int> size;
  half["image_size"] >> size;
  EXPECT_EQ(size, (std::vector<int>{680, 512}));
  for (const char* m : {"M1", "M2"}) {
    cv::Mat a, b;
    full[m] >> a;
    half[m] >> b;
    ASSERT_EQ(a.size(), cv::Size(3, 3)) << m;
    ASSERT_EQ(b.size(), cv::Size(3, 3)) << m;
    EXPECT_NEAR(b.at<double>(0, 0), a.at<double>(0, 0) / 2.0, 1e-9) << m;
    EXPECT_NEAR(b.at<double>(1, 1), a.at<double>(1, 1) / 2.0, 1e-9) << m;
    EXPECT_NEAR(b.at<double>(0, 2), (a.at<double>(0, 2) + 0.5) / 2.0 - 0.5, 1e-9) << m;
    EXPECT_NEAR(b.at<double>(1, 2), (a.at<double>(1, 2) + 0.5) / 2.0 - 0.5, 1e-9) << m;
  }
  for (const char* m : {"D1", "D2", "R", "T"}) {
    cv::Mat a, b;
    full[m] >> a;
    half[m] >> b;
    ASSERT_FALSE(a.empty()) << m;
    ASSERT_EQ(a.size(), b.size()) << m;
    EXPECT_EQ(cv::norm(a, b, cv::NORM_INF), 0.0) << m;
  }
}

// Truth on real texture (issue 32): the shipped real-texture scenes wear a real in-vivo frame
// from ../shared/data; a texture image that is not there, or not given, is a named error.
TEST(SceneFile, ARealPhotographAsTheTexture) {
  expectError(kHead + "[cortex]\ntexture = \"image\"\n",
              "scene.toml: cortex.texture = \"image\" needs cortex.texture_image");
  expectError(kHead + "[cortex]\ntexture = \"image\"\ntexture_image = \"nowhere.png\"\n",
              "scene.toml: cortex.texture_image /x/nowhere.png: cannot read it as an image");
  expectError(kHead + "[cortex]\ntexture_image_mm = 0.5\n",
              "scene.toml:4: cortex.texture_image_mm: expected a number in \\[1, 500\\]");
  expectError(kHead + "[camera]\njpeg_quality = 101\n",
              "scene.toml:4: camera.jpeg_quality: expected an integer in \\[0, 100\\]");
  const auto data = data::shared("hamlyn-invivo-tpsnet");
  PULSETRACK_SKIP_WITHOUT_DATA(data);
  for (const char* name : {"real-texture", "real-texture-sd", "real-texture-hard"}) {
    auto s = loadScene(configDir() + "/scenes/" + name + ".toml");
    ASSERT_TRUE(s) << s.error().message;
    EXPECT_EQ(s->cortex.texture, "image");
    EXPECT_EQ(s->cortex.texture_image_grey.size(), cv::Size(360, 288)) << name;
    auto rig = vision::loadRig(s->rig_path);
    ASSERT_TRUE(rig) << rig.error().message;
  }
  // Through the cameras: the photograph's detail is in the rendered patch, and JPEG leaves its
  // blocks (a change of a few grey levels, not a different picture).
  auto spec = loadScene(configDir() + "/scenes/real-texture-sd.toml");
  ASSERT_TRUE(spec);
  auto rig = vision::loadRig(spec->rig_path);
  ASSERT_TRUE(rig);
  EXPECT_EQ(rig->left.imageSize(), cv::Size(680, 512));
  cv::Mat l_jpeg, r_jpeg, l_raw, r_raw;
  {
    StereoSimulator sim(*spec, *rig);
    sim.render(0, l_jpeg, r_jpeg);
  }
  spec->camera.jpeg_quality = 0;
  {
    StereoSimulator sim(*spec, *rig);
    sim.render(0, l_raw, r_raw);
  }
  const cv::Rect centre(290, 206, 100, 100);
  cv::Scalar mean, sd;
  cv::meanStdDev(l_raw(centre), mean, sd);
  EXPECT_GT(sd[0], 15.0);  // the heart's texture, not a flat patch
  const double diff = cv::mean(cv::abs(l_jpeg - l_raw) + cv::abs(l_raw - l_jpeg))[0];
  std::cout << "real-texture-sd, frame 0: patch SD " << sd[0] << " grey, JPEG 60 changes it by "
            << diff << " grey on average\n";
  EXPECT_GT(diff, 0.5);
  EXPECT_LT(diff, 8.0);
}

// A recording of a scene wearing a photograph carries it: texture.png beside scene.toml, which
// names it and parses back to the same scene (evaluate reads the scene from the recording).
TEST(SceneFile, ARecordingCarriesItsTexture) {
  test::TempDir dir;
  cv::Mat photo(48, 64, CV_8UC1);
  cv::randu(photo, 40, 200);
  ASSERT_TRUE(cv::imwrite(dir / "photo.png", photo));
  const std::string text = "kind = \"cortex\"\nrig = \"" + configDir() +
                           "/rigs/paper-rig-half.yaml\"\nframes = 2\nsupersample = 1\n"
                           "[cortex]\ntexture = \"image\"\ntexture_image = \"photo.png\"\n"
                           "texture_image_mm = 2.0\n[[cortex.motion]]\nname = \"beat\"\n"
                           "amplitude_mm = 0.2\nfrequency_hz = 1.1\n"
                           "harmonics = [{ multiple = 2.0, relative_amplitude = 0.3 }]\n";
  auto spec = parseScene(text, dir.path() / "scene.toml");
  ASSERT_TRUE(spec) << spec.error().message;
  auto rig = vision::loadRig(spec->rig_path);
  ASSERT_TRUE(rig) << rig.error().message;
  StereoSimulator sim(*spec, *rig);  // 2 mm mirrored over the whole patch: no hang, no gap
  ASSERT_TRUE(writeSimulation(sim, dir.path() / "rec"));
  auto again = loadScene(dir.path() / "rec" / "scene.toml");
  ASSERT_TRUE(again) << again.error().message;
  EXPECT_EQ(again->cortex.texture, "image");
  EXPECT_EQ(again->cortex.texture_image, dir.path() / "rec" / "texture.png");
  EXPECT_EQ(cv::norm(again->cortex.texture_image_grey, photo, cv::NORM_INF), 0.0);
  ASSERT_EQ(again->cortex.oscillations.size(), 1U);
  EXPECT_DOUBLE_EQ(again->cortex.oscillations[0].frequency_hz, 1.1);
  ASSERT_EQ(again->cortex.oscillations[0].harmonics.size(), 1U);
  EXPECT_DOUBLE_EQ(again->cortex.oscillations[0].harmonics[0].relative_amplitude, 0.3);
  EXPECT_EQ(again->frames, 2);
}

// An interlaced camera: each frame's even rows are the scene at the frame's time, its odd rows
// the scene half a frame later, as a progressive camera at twice the rate sees them: each
// field blurred by the lens on its own (no noise, gain drift or compression here, so the rows
// compare exactly).
TEST(SceneFile, AnInterlacedFrameWeavesTwoInstants) {
  const std::string body = "rig = \"" + configDir() +
                           "/rigs/paper-rig-half.yaml\"\nframes = 4\nsupersample = 1\n"
                           "[camera]\nblur_sigma_px = 0.7\nnoise_sigma = 0\nvignetting = 0\n"
                           "[[cortex.motion]]\nname = \"beat\"\namplitude_mm = 1.5\n"
                           "frequency_hz = 1.2\n";
  auto woven =
      parseScene("kind = \"cortex\"\nfps = 25\ninterlaced = true\n" + body, "/x/scene.toml");
  auto doubled = parseScene("kind = \"cortex\"\nfps = 50\n" + body, "/x/scene.toml");
  ASSERT_TRUE(woven) << woven.error().message;
  ASSERT_TRUE(doubled) << doubled.error().message;
  EXPECT_TRUE(woven->interlaced);
  auto rig = vision::loadRig(woven->rig_path);
  ASSERT_TRUE(rig) << rig.error().message;
  StereoSimulator interlaced(*woven, *rig), progressive(*doubled, *rig);
  cv::Mat l, r, l0, r0, l1, r1;
  interlaced.render(1, l, r);
  progressive.render(2, l0, r0);  // the same instant
  progressive.render(3, l1, r1);  // half a frame later
  double even_diff = 0.0, odd_diff = 0.0, odd_vs_first = 0.0;
  for (int y = 0; y < l.rows; ++y) {
    const double d = cv::norm(l.row(y), (y % 2 == 0 ? l0 : l1).row(y), cv::NORM_INF) +
                     cv::norm(r.row(y), (y % 2 == 0 ? r0 : r1).row(y), cv::NORM_INF);
    (y % 2 == 0 ? even_diff : odd_diff) = std::max(y % 2 == 0 ? even_diff : odd_diff, d);
    if (y % 2 == 1)
      odd_vs_first = std::max(odd_vs_first, cv::norm(l.row(y), l0.row(y), cv::NORM_INF));
  }
  EXPECT_EQ(even_diff, 0.0);
  EXPECT_EQ(odd_diff, 0.0);
  EXPECT_GT(odd_vs_first, 20.0);  // the surface moved between the fields
  expectError("kind = \"plate\"\nrig = \"r.yaml\"\ninterlaced = true\n",
              "scene.toml: interlaced = true needs kind = \"cortex\"");
}

TEST(SceneFile, MissingFileIsNamed) {
  auto s = loadScene("/nonexistent/scene.toml");
  ASSERT_FALSE(s);
  EXPECT_EQ(s.error().message,
            "/nonexistent/scene.toml: cannot open the scene file: No such file or directory");
}

// evaluate's error parts on rows made with known parts: each feature a constant bias, white noise
// and a slow sine, some rows not ok (their neighbours are no consecutive pair). Each part comes
// back within its sampling error, and the three squares add up to the RMS's square.
TEST(ErrorParts, SeparateABiasASlowChangeAndWhiteNoise) {
  std::mt19937 rng(7);
  std::normal_distribution<double> white(0.0, 0.05);
  std::vector<RowError> rows;
  double bias_sq = 0.0, total_sq = 0.0;
  long n = 0;
  constexpr int kFeatures = 20, kFrames = 400;
  for (long frame = 0; frame < kFrames; ++frame) {
    const double slow =
        0.03 * std::sqrt(2.0) * std::sin(2.0 * M_PI * static_cast<double>(frame) / 100.0);
    for (int id = 0; id < kFeatures; ++id) {
      RowError r{frame, id, std::numeric_limits<double>::quiet_NaN(), {}};
      if ((frame + id) % 37 != 0) {  // about 3 % not ok
        const double bias = 0.02 * (id % 5 - 2);
        r.error_vec = {0.5 * bias, 0.0, bias + slow + white(rng)};
        r.error_mm = cv::norm(r.error_vec);
        total_sq += r.error_vec.dot(r.error_vec);
        bias_sq += 1.25 * bias * bias;
        ++n;
      }
      rows.push_back(r);
    }
  }
  const ErrorParts p = errorParts(rows);
  EXPECT_NEAR(p.bias_mm, std::sqrt(bias_sq / static_cast<double>(n)), 0.005);
  EXPECT_NEAR(p.noise_mm, 0.05, 0.003);
  EXPECT_NEAR(p.slow_mm, 0.03, 0.005);
  EXPECT_LT(p.pairs, n);  // a gap breaks the pair
  EXPECT_GT(p.pairs, n - kFeatures - kFrames * kFeatures / 37 * 2);
  EXPECT_NEAR(p.bias_mm * p.bias_mm + p.slow_mm * p.slow_mm + p.noise_mm * p.noise_mm,
              total_sq / static_cast<double>(n), 1e-9);
  // Nothing scored: all zero.
  const ErrorParts none =
      errorParts({RowError{0, 1, std::numeric_limits<double>::quiet_NaN(), {}}});
  EXPECT_EQ(none.pairs, 0);
  EXPECT_EQ(none.bias_mm + none.slow_mm + none.noise_mm, 0.0);
}

}  // namespace
}  // namespace pulsetrack::sim
