// Issue 14: robust outside the project's own simulator. Each gate's false-reject and
// false-accept rates against ground truth, on two real photographed stereo pairs with true
// disparity (Middlebury 2003 teddy and cones, ../shared/data/middlebury-*) beside a plain OpenCV
// matcher on the same pair, and on the hard cortex scene (config/scenes/cortex-hard.toml: glossy,
// view- dependent glints, gains 20 % apart drifting +-30 % independently, different vignetting, an
// instrument resting over the ROI for 5 s, a shadow). The tables are printed (docs/gates.md's gate
// table comes from them); the assertions are the aims this tracker meets, and guards at
// today's level for those it does not yet meet (see the comments).

#include <gtest/gtest.h>

#include <iostream>
#include <string>

#include "pulsetrack/sim/gate_eval.hpp"
#include "test_util.hpp"

namespace pulsetrack::sim {
namespace {

TEST(Robustness, RealPhotographsWithTrueDisparity) {
  for (const auto& photo : data::middlebury()) {
    PULSETRACK_SKIP_WITHOUT_DATA(photo.dir);
    auto pair = loadPhotoPair(photo.dir, photo.disparity, photo.scale);
    ASSERT_TRUE(pair) << pair.error().message;
    const std::string name = pair->name;
    auto e = evaluatePhotoPair(*pair, vision::TrackerConfig{}, 4, 60);
    ASSERT_TRUE(e) << e.error().message;
    std::cout << formatGateTable(e->table, "photograph " + name + ":");
    const double right = 100.0 * e->accepted_good / std::max(1, e->accepted_judged);
    const double plain_right = 100.0 * e->plain.accepted_good / std::max(1, e->plain.judged);
    std::cout << "  pulsetrack " << e->accepted << " accepted of " << e->candidates << ", " << right
              << " % within 1 px; plain OpenCV matcher " << e->plain.accepted << " of "
              << e->plain.candidates << ", " << plain_right << " % within 1 px\n";
    // The issue: at least as many accepted as the plain matcher, never fewer than 50, >= 95 %
    // within 1 px. teddy: 100 accepted at 97.0 % (plain 94 at 71.9 %), cones: 100 at 100 %
    // (plain 93 at 75.8 %); the epipolar-spread gate took teddy from 95.0 and cones from 98.0.
    EXPECT_GE(e->accepted, e->plain.accepted) << name;
    EXPECT_GE(e->accepted, 50) << name;
    EXPECT_GE(right, 95.0) << name;
    EXPECT_GT(right, plain_right + 5.0) << name;
    // Every gate was evaluated on right and wrong matches, so its rates mean something.
    for (vision::Gate g :
         {vision::Gate::kNcc, vision::Gate::kStereoNcc, vision::Gate::kLeftRight,
          vision::Gate::kNotConverged, vision::Gate::kEpipolar, vision::Gate::kDepthEdge}) {
      const GateRates& r = e->table.gates[static_cast<size_t>(g)];
      EXPECT_GT(r.good, 40) << name << " " << vision::toString(g);
      EXPECT_GT(r.bad, 10) << name << " " << vision::toString(g);
    }
    // The glint gate at 250 rejects few right matches on photographs (at 215: 43 %).
    const GateRates& glint = e->table.gates[static_cast<size_t>(vision::Gate::kGlint)];
    EXPECT_LE(glint.good_rejected, glint.good / 8) << name;
    // The depth-edge gate (corner blocks matched on their own): few right ones rejected (0.9 %
    // and 6.9 % at 0.5), a third or more of the wrong ones caught (37 % and 56 %).
    const GateRates& edge = e->table.gates[static_cast<size_t>(vision::Gate::kDepthEdge)];
    EXPECT_LE(edge.good_rejected * 10, edge.good) << name;
    EXPECT_GE((edge.bad - edge.bad_passed) * 3, edge.bad) << name;
  }
}

TEST(Robustness, HardCortexSceneKeepsFeaturesAndTheirIds) {
  auto spec = loadScene(std::string(PULSETRACK_SOURCE_DIR) + "/config/scenes/cortex-hard.toml");
  ASSERT_TRUE(spec) << spec.error().message;
  auto rig = vision::loadRig(spec->rig_path);
  ASSERT_TRUE(rig) << rig.error().message;
  StereoSimulator s(*spec, *rig);
  SceneRunOptions opt;
  auto run = runScene(s, opt);
  ASSERT_TRUE(run) << run.error().message;
  std::cout << formatGateTable(run->detection, "cortex-hard: detections") << "\n"
            << formatGateTable(run->tracking, "cortex-hard: tracking, every pair") << "\n";
  int at50 = 0;
  for (int ok : run->ok_per_pair) at50 += ok >= 50 ? 1 : 0;
  const double frac50 = static_cast<double>(at50) / std::max(1, run->pairs);
  std::cout << "cortex-hard: " << run->pairs << " pairs, first " << run->first_ok
            << " ok, textured cells " << run->textured_cells << " (empty "
            << run->empty_textured_cells << "), detections " << run->detections << ", distinct ids "
            << run->distinct_ids << ", >= 50 ok in " << 100 * frac50
            << " % of pairs; instrument hid " << run->hidden << ", back within 1 s "
            << run->back_within_1s << "; 3D RMS " << run->rms_3d_mm << " mm, max " << run->max_3d_mm
            << ", above 0.5 mm " << run->above_half_mm << "; mean displacement "
            << run->displacement_rms_mm << " mm RMS; breathing " << 100 * run->breathing_error
            << " %, cardiac " << 100 * run->cardiac_error << " %; track "
            << run->ms_per_pair_tracking << " ms/pair, refresh " << run->ms_per_pair_refresh
            << " ms/pair\n";
  // Detection under glints and unequal gains: >= 80 of the ceiling of 100 (100: the detector
  // matches corners until the ceiling passes its gates). The "no textured cell empty" is
  // not met: 5 of 22 cells whose right candidates are all under glints or fail the stereo NCC
  // gate in their sheen. Guarded at today's level.
  EXPECT_GE(run->first_ok, 80);
  EXPECT_GE(run->textured_cells, 15);
  EXPECT_LE(run->empty_textured_cells, 6);
  // Identity: the features keep their ids through the instrument, shadow and glints.
  EXPECT_LE(run->distinct_ids, 110);
  EXPECT_LE(run->detections, 3);
  // Re-acquisition: >= 90 % of the features the instrument hid are back within 1 s.
  EXPECT_GE(run->hidden, 20);
  EXPECT_GE(run->back_within_1s, (9 * run->hidden + 9) / 10);
  // The instrument covers "30 % of the ROI" as the issue has it (24.8 %: hidden from either
  // camera, over the ROI's circle, mid-rest; 23.1 % of the left ROI box). Not yet the issue's
  // aim: >= 50 features accepted in >= 80 % of the pairs (75.0 %). The features gather where
  // the tissue is matchable, outside the specular zone, which is where the instrument rests:
  // by the truth 48 of the 100 are behind it and 6 more have it in their patch, and the ceiling
  // counts the hidden ones, so 46-47 stay ok for the 5.5 s it rests (27 % of the pairs).
  // Meeting it takes features added in the visible part while the hidden ones wait, beyond the
  // ceiling (the next step). Guarded at today's level.
  EXPECT_GE(run->instrument_covers, 0.2);
  EXPECT_LE(run->instrument_covers, 0.35);
  EXPECT_GE(frac50, 0.7);
  // Breathing and cardiac amplitudes within 1 %; no accepted sample above 0.5 mm (the motion
  // gate took the one at 0.86 mm: a right match sliding onto the instrument's edge);
  // the mean-displacement signal within 0.005 mm RMS per axis (0.0037).
  EXPECT_LE(run->breathing_error, 0.01);
  EXPECT_LE(run->cardiac_error, 0.01);
  EXPECT_EQ(run->above_half_mm, 0);
  EXPECT_LE(run->displacement_rms_mm, 0.005);
  // Not yet the aim: 3D RMS <= 0.03 mm (0.036: 0.020 mm of it each feature's own
  // constant depth bias, 0.028 mm per-pair depth noise, white: bench/gate_eval --samples-csv).
  // Guarded at today's level.
  EXPECT_LE(run->rms_3d_mm, 0.04);
  EXPECT_LE(run->max_3d_mm, 0.4);
  // The tracking glint gate tells a glint from tissue a camera's gain saturated: it rejects
  // almost no right video match (7 % before glint_excess) and the motion gate none.
  const GateRates& glint = run->tracking.gates[static_cast<size_t>(vision::Gate::kGlint)];
  EXPECT_LE(glint.good_rejected * 100, glint.good);
  const GateRates& motion = run->tracking.gates[static_cast<size_t>(vision::Gate::kMotion)];
  EXPECT_LE(motion.good_rejected * 1000, motion.good);
  // Accepted matches are right (both views within 0.3 px of the truth) in >= 98 % of cases.
  EXPECT_GE(run->tracking.accepted_good, run->tracking.accepted * 98 / 100);
}

}  // namespace
}  // namespace pulsetrack::sim
