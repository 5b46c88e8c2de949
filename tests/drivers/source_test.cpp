// The camera sources without hardware: the simulator on a software trigger, and replay of a
// real recording file (paced or fast, sequence gaps counted, looping, bad paths).

#include "pulsetrack/drivers/source.hpp"

#include <gtest/gtest.h>

#include <set>
#include <thread>

#include "pulsetrack/rt/heartbeat.hpp"
#include "pulsetrack/sim/paper_rig.hpp"
#include "test_util.hpp"

namespace pulsetrack::drivers {
namespace {

// The default cortex scene, `frames` long, rendered fast (no supersampling).
sim::SceneSpec cortex(int frames) {
  sim::SceneSpec spec;
  spec.kind = sim::SceneKind::kCortex;
  spec.supersample = 1;
  spec.frames = frames;
  return spec;
}

// A recording's manifest for the paper rig's images.
record::Manifest paperManifest() {
  record::Manifest m;
  m.source = "test";
  m.rig_id = "rig-t";
  m.width = sim::paperRig().left.imageSize().width;
  m.height = sim::paperRig().left.imageSize().height;
  m.nominal_fps = 10;
  return m;
}

TEST(SimSource, SoftwareTriggerAtTheRateWithTheSimulatorsFrames) {
  const sim::SceneSpec spec = cortex(10);
  sim::StereoSimulator reference(spec, sim::paperRig());
  auto src = makeSimSource(spec, sim::paperRig(), 10.0, /*loop=*/true);
  ASSERT_TRUE(src->start());
  StereoFrame f;
  cv::Mat l, r;
  int64_t first = 0;
  std::vector<StereoFrame> got(3);
  for (auto& g : got) ASSERT_EQ(src->next(g, std::chrono::milliseconds(1000)), Next::kFrame);
  for (uint64_t i = 0; i < 3; ++i) {
    f = got[i];
    if (i == 0) first = f.t_left_ns;
    // 10 Hz: each trigger 100 ms after the one before (a slow render, e.g. under a sanitizer,
    // skips triggers: the sequence number says which).
    EXPECT_EQ(f.t_left_ns - first,
              static_cast<int64_t>(f.trigger_seq - got[0].trigger_seq) * 100'000'000);
    EXPECT_LE(f.t_left_ns, rt::monotonicNs());  // the trigger time has passed
    reference.render(static_cast<int>(f.trigger_seq % 10), l, r);
    EXPECT_EQ(cv::norm(f.left, l, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(f.right, r, cv::NORM_INF), 0.0);
  }
  EXPECT_EQ(src->counters().frames, 3U);
  // A consumer that comes late: the triggers it missed are counted, not queued.
  std::this_thread::sleep_for(std::chrono::milliseconds(450));
  ASSERT_EQ(src->next(f, std::chrono::milliseconds(1000)), Next::kFrame);
  EXPECT_GE(src->counters().overruns, 2U);
  EXPECT_EQ(src->counters().missing_triggers, 0U);  // the pulses did fire
  EXPECT_GE(f.trigger_seq, 5U);
}

TEST(SimSource, InjectedTriggerAndCameraFaultsAreCountedAndNeverPairedWrongly) {
  const sim::SceneSpec spec = cortex(40);
  sim::StereoSimulator reference(spec, sim::paperRig());
  SimFaults faults;
  faults.missing_trigger_every = 5;  // triggers 4, 9, 14, ...
  faults.left_drop_every = 7;        // 6, 13, 20, ...
  faults.right_miss_every = 11;      // 10, 21, ...
  auto src = makeSimSource(spec, sim::paperRig(), 10.0, /*loop=*/false, faults);
  ASSERT_TRUE(src->start());
  EXPECT_EQ(src->triggerState(), "software 10 Hz");
  StereoFrame f;
  cv::Mat l, r;
  int pairs = 0;
  while (src->next(f, std::chrono::milliseconds(1000)) == Next::kFrame) {
    // The first trigger (0) is whole, so the pair's number is the trigger's.
    const uint64_t k = f.trigger_seq;
    EXPECT_FALSE(k % 5 == 4 || k % 7 == 6 || k % 11 == 10) << "trigger " << k << " was faulty";
    reference.render(static_cast<int>(k), l, r);
    EXPECT_EQ(cv::norm(f.left, l, cv::NORM_INF), 0.0) << "trigger " << k;
    EXPECT_EQ(cv::norm(f.right, r, cv::NORM_INF), 0.0) << "trigger " << k;
    ++pairs;
  }
  const SourceCounters c = src->counters();
  EXPECT_EQ(c.frames, static_cast<uint64_t>(pairs));
  // Of 40 triggers: 8 never fired (4 9 ... 39), the left driver dropped 6 13 20 27 (34 never
  // fired), the right camera missed 10 21 32: 25 whole pairs, each either handed over or, when
  // the render was late, an overrun. Every count is exact whatever the machine's speed.
  EXPECT_EQ(c.frames + c.overruns, 25U);
  EXPECT_GT(pairs, 0);  // how many of the 25 were handed over depends on the render speed
  EXPECT_EQ(c.missing_triggers, 7U);  // 4 ... 34 lie between pairs; 39 comes after the last
  EXPECT_EQ(c.unpaired, 7U);          // the partners of the 7 frames lost by one camera
  EXPECT_EQ(c.dropped, 4U);           // the left counter's gaps
}

// An injected outage: the source says kFault (as a driver whose camera vanished) for its length,
// the trigger's pulses meanwhile are missing triggers, and the cameras come back by themselves.
TEST(SimSource, AnInjectedOutageIsAFaultAndTheCamerasComeBack) {
  const sim::SceneSpec spec = cortex(10);
  SimFaults faults;
  faults.outage_every_s = 1.0;
  faults.outage_s = 0.45;  // pulses 10 ... 14 (1.0 ... 1.4 s) fall in it
  auto src = makeSimSource(spec, sim::paperRig(), 10.0, /*loop=*/true, faults);
  ASSERT_TRUE(src->start());
  const int64_t t0 = rt::monotonicNs();
  StereoFrame f;
  int faults_seen = 0;
  std::vector<uint64_t> after;  // pairs after the first fault
  uint64_t last = 0;
  // Pulse k (10 Hz) falls in an outage: 1.0 ... 1.4 s, 2.0 ... 2.4 s, ...
  const auto inOutage = [](uint64_t k) { return k >= 10 && k % 10 <= 4; };
  while (after.size() < 3 && rt::monotonicNs() - t0 < 60'000'000'000) {
    const Next n = src->next(f, std::chrono::milliseconds(1000));
    if (n == Next::kFault) {
      ++faults_seen;
      EXPECT_EQ(src->lastFault(), kInjectedOutage);
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      continue;
    }
    ASSERT_EQ(n, Next::kFrame);
    EXPECT_FALSE(inOutage(f.trigger_seq)) << "pulse " << f.trigger_seq;
    last = f.trigger_seq;
    EXPECT_EQ(src->lastFault(), "");
    if (faults_seen > 0) after.push_back(f.trigger_seq);
  }
  EXPECT_GT(faults_seen, 0);
  ASSERT_EQ(after.size(), 3U) << "the cameras did not come back";
  EXPECT_GE(after[0], 15U);
  // The outages' pulses (five each second: a slow render, under a sanitizer, lives through more
  // than one) gave no frame from either camera: missing triggers, none unpaired.
  uint64_t outage_pulses = 0;
  for (uint64_t k = 0; k < last; ++k) outage_pulses += inOutage(k) ? 1 : 0;
  EXPECT_GE(outage_pulses, 5U);
  EXPECT_EQ(src->counters().missing_triggers, outage_pulses);
  EXPECT_EQ(src->counters().unpaired, 0U);
}

TEST(ReplaySource, AtARateMissingTriggersAndOutagesAsALiveCameraShowsThem) {
  test::TempDir dir;
  const auto path = dir.path() / "rec";
  const vision::StereoRig rig = sim::paperRig();
  const record::Manifest m = paperManifest();
  auto w = record::Writer::create(path, m, rig, 0);
  ASSERT_TRUE(w) << w.error().message;
  for (uint64_t i = 0; i < 5; ++i) {
    const cv::Mat l(rig.left.imageSize(), CV_8UC1, cv::Scalar(static_cast<double>(i)));
    ASSERT_TRUE(w->write(
        {i, i, static_cast<int64_t>(i) * 100'000'000, static_cast<int64_t>(i) * 100'000'000, 0}, l,
        l));
  }
  ASSERT_TRUE(w->close());
  ReplayOptions rate;
  rate.pace = ReplayOptions::Pace::kRate;
  rate.fps = 50.0;
  rate.loop = true;
  rate.preload = true;
  SimFaults faults;
  faults.missing_trigger_every = 7;  // pulses 6, 13, 20, ...
  faults.outage_every_s = 0.2;
  faults.outage_s = 0.09;  // pulses 10 ... 14 (0.20 ... 0.28 s)
  auto src = makeReplaySource(path, rate, faults);
  ASSERT_TRUE(src) << src.error().message;
  ASSERT_TRUE((*src)->start());
  StereoFrame f;
  std::set<uint64_t> got;
  int faults_seen = 0;
  const int64_t t0 = rt::monotonicNs();
  while ((got.empty() || *got.rbegin() < 19) && rt::monotonicNs() - t0 < 30'000'000'000) {
    const Next n = (*src)->next(f, std::chrono::milliseconds(1000));
    if (n == Next::kFault) {
      ++faults_seen;
      EXPECT_EQ((*src)->lastFault(), kInjectedOutage);
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
      continue;
    }
    ASSERT_EQ(n, Next::kFrame);
    got.insert(f.trigger_seq);
    // The scene moves on with time: pulse k shows the recording's frame k mod 5.
    EXPECT_EQ(f.left.at<uint8_t>(0, 0), f.trigger_seq % 5) << "pulse " << f.trigger_seq;
  }
  const std::set<uint64_t> expected = {0, 1, 2, 3, 4, 5, 7, 8, 9, 15, 16, 17, 18, 19};
  EXPECT_EQ(got, expected);
  EXPECT_EQ((*src)->counters().missing_triggers, 6U);  // 6, 10 ... 14 (13 both)
  // Faults that need two cameras' frames, or a pace that is not a live camera's, are refused.
  SimFaults drops;
  drops.left_drop_every = 3;
  EXPECT_FALSE(makeReplaySource(path, rate, drops));
  EXPECT_FALSE(makeReplaySource(path, {}, faults));
  EXPECT_GT(faults_seen, 0);  // a consumer calling on time meets the outage as a fault
}

TEST(ReplaySource, FramesAsRecordedGapsCountedEndAndLoop) {
  test::TempDir dir;
  const auto path = dir.path() / "rec";
  const vision::StereoRig rig = sim::paperRig();
  const record::Manifest m = paperManifest();
  auto w = record::Writer::create(path, m, rig);
  ASSERT_TRUE(w) << w.error().message;
  std::vector<cv::Mat> lefts;
  const uint64_t seqs[] = {0, 1, 3, 4};  // trigger 2 never arrived
  for (int i = 0; i < 4; ++i) {
    cv::Mat l(rig.left.imageSize(), CV_8UC1), r(rig.left.imageSize(), CV_8UC1);
    cv::randu(l, 0, 255);
    cv::randu(r, 0, 255);
    lefts.push_back(l);
    record::FrameMeta meta;
    meta.frame = seqs[i];
    meta.trigger_seq = seqs[i];
    meta.t_left_ns = meta.t_right_ns = 1'000'000'000 + static_cast<int64_t>(seqs[i]) * 40'000'000;
    ASSERT_TRUE(w->write(meta, l, r));
  }
  ASSERT_TRUE(w->close());

  auto src = makeReplaySource(path, {});  // at the recorded pace, once
  ASSERT_TRUE(src) << src.error().message;
  ASSERT_TRUE((*src)->start());
  StereoFrame f;
  const int64_t t0 = rt::monotonicNs();
  for (int i = 0; i < 4; ++i) {
    ASSERT_EQ((*src)->next(f, std::chrono::milliseconds(1000)), Next::kFrame);
    EXPECT_EQ(f.trigger_seq, seqs[i]);
    EXPECT_EQ(cv::norm(f.left, lefts[static_cast<size_t>(i)], cv::NORM_INF), 0.0);
  }
  // Paced by the recorded timestamps: 4 triggers of 40 ms after the first.
  EXPECT_GE(rt::monotonicNs() - t0, 150'000'000);
  EXPECT_EQ((*src)->counters().missing_triggers, 1U);
  EXPECT_EQ((*src)->next(f, std::chrono::milliseconds(10)), Next::kEnd);

  ReplayOptions fast_loop;
  fast_loop.pace = ReplayOptions::Pace::kFast;
  fast_loop.loop = true;
  auto fast = makeReplaySource(path, fast_loop);
  ASSERT_TRUE(fast);
  ASSERT_TRUE((*fast)->start());
  for (int i = 0; i < 5; ++i)
    ASSERT_EQ((*fast)->next(f, std::chrono::milliseconds(10)), Next::kFrame);
  EXPECT_EQ(f.trigger_seq, 5U);  // looped to the start; the sequence goes on past the end (4)
  EXPECT_EQ(cv::norm(f.left, lefts[0], cv::NORM_INF), 0.0);

  // From memory, at a rate, restamped as a live camera would (the latency benchmark's source).
  ReplayOptions rate;
  rate.pace = ReplayOptions::Pace::kRate;
  rate.fps = 50.0;
  rate.loop = true;
  rate.preload = true;
  auto live = makeReplaySource(path, rate);
  ASSERT_TRUE(live) << live.error().message;
  ASSERT_TRUE((*live)->start());
  int64_t first = 0;
  for (int i = 0; i < 6; ++i) {
    ASSERT_EQ((*live)->next(f, std::chrono::milliseconds(1000)), Next::kFrame);
    EXPECT_EQ(f.trigger_seq, static_cast<uint64_t>(i));
    EXPECT_LE(f.t_left_ns, rt::monotonicNs());
    if (i == 0) first = f.t_left_ns;
    EXPECT_EQ(cv::norm(f.left, lefts[static_cast<size_t>(i % 4)], cv::NORM_INF), 0.0);
  }
  EXPECT_EQ(f.t_left_ns - first, 5 * 20'000'000);  // 50 Hz, stamped at the trigger

  auto missing = makeReplaySource(dir.path() / "nothing", {});
  ASSERT_FALSE(missing);
  EXPECT_NE(missing.error().message.find("nothing"), std::string::npos) << missing.error().message;
}

}  // namespace
}  // namespace pulsetrack::drivers
