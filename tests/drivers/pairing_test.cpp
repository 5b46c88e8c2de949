// Frame pairing by timestamp: random streams with missing triggers, frames one camera dropped
// (with and without a gap in its sequence counter), timestamp jitter and one camera delivering
// late. Every pair must hold the same trigger's frames, and every fault must be counted as
// what it was.

#include "pulsetrack/drivers/pairing.hpp"

#include <gtest/gtest.h>

#include <random>
#include <vector>

namespace pulsetrack::drivers {
namespace {

constexpr int64_t kPeriod = 16'666'667;  // 60 Hz

struct Delivery {
  int cam;
  CameraStamp stamp;
};

struct Truth {
  uint64_t both = 0, one = 0, none_between = 0, left_gaps = 0;
  std::vector<Delivery> order;
};

// Triggers 0..n-1. slot = the true trigger number, so a pair can be checked.
Truth makeStream(int n, double p_missing, double p_drop, int max_lag, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  std::uniform_int_distribution<int64_t> jitter(-60'000, 60'000);  // +-60 us
  Truth t;
  std::vector<Delivery> cams[2];
  uint64_t seq[2] = {100, 7};  // the cameras' counters start anywhere
  int first_pair = -1, last_pair = -1;
  std::vector<int> kind(static_cast<size_t>(n));  // 0 none, 1 one camera, 2 both
  for (int k = 0; k < n; ++k) {
    if (u(rng) < p_missing) continue;  // the pulse never came
    const int64_t t0 = 5'000'000'000 + k * kPeriod;
    int produced = 0;
    for (int c = 0; c < 2; ++c) {
      const bool drop = u(rng) < p_drop;
      if (drop && c == 0) {
        ++seq[0];  // the left driver dropped it: its counter shows the gap
        ++t.left_gaps;
        continue;
      }
      if (drop) continue;  // the right camera missed the pulse: no gap in its counter
      cams[c].push_back({c, {seq[c]++, t0 + jitter(rng), k}});
      ++produced;
    }
    kind[static_cast<size_t>(k)] = produced;
    if (produced == 2) {
      ++t.both;
      if (first_pair < 0) first_pair = k;
      last_pair = k;
    }
  }
  for (int k = first_pair + 1; k < last_pair; ++k) {
    const int kd = kind[static_cast<size_t>(k)];
    if (kd == 0) ++t.none_between;
  }
  for (int k = 0; k < n; ++k) t.one += kind[static_cast<size_t>(k)] == 1 ? 1 : 0;
  // Merge the two cameras' deliveries, each in its own order, one lagging up to max_lag frames.
  size_t i[2] = {0, 0};
  std::uniform_int_distribution<int> lag(0, max_lag);
  while (i[0] < cams[0].size() || i[1] < cams[1].size()) {
    int c = u(rng) < 0.5 ? 0 : 1;
    if (i[static_cast<size_t>(c)] >= cams[c].size()) c = 1 - c;
    // Keep the lag bounded: the leading camera waits when it is max_lag triggers ahead.
    const size_t o = i[static_cast<size_t>(1 - c)];
    if (o < cams[1 - c].size() &&
        cams[c][i[static_cast<size_t>(c)]].stamp.slot - cams[1 - c][o].stamp.slot > lag(rng))
      c = 1 - c;
    t.order.push_back(cams[c][i[static_cast<size_t>(c)]++]);
  }
  return t;
}

TEST(FramePairer, CleanStreamPairsEveryTriggerInOrder) {
  FramePairer p({kPeriod, 0});
  for (int k = 0; k < 50; ++k) {
    const int64_t t = 1'000'000'000 + k * kPeriod;
    EXPECT_FALSE(p.offer(0, {static_cast<uint64_t>(k), t, k}).paired);
    const PairEvents ev = p.offer(1, {static_cast<uint64_t>(k + 3), t + 20'000, k});
    ASSERT_TRUE(ev.paired);
    EXPECT_EQ(ev.trigger_seq, static_cast<uint64_t>(k));
    EXPECT_EQ(ev.left.slot, k);
    EXPECT_EQ(ev.right.slot, k);
    EXPECT_EQ(ev.n_released, 0);
  }
  EXPECT_EQ(p.counters().pairs, 50U);
  EXPECT_EQ(p.counters().unpaired + p.counters().missing_triggers + p.counters().dropped[0] +
                p.counters().dropped[1],
            0U);
}

TEST(FramePairer, AMissingPartnerIsReleasedNotPairedWithTheNextTrigger) {
  FramePairer p({kPeriod, 0});
  const int64_t t0 = 1'000'000'000;
  p.offer(0, {0, t0, 10});
  ASSERT_TRUE(p.offer(1, {0, t0, 20}).paired);
  p.offer(0, {1, t0 + kPeriod, 11});  // the right camera never sends trigger 1
  p.offer(0, {2, t0 + 2 * kPeriod, 12});
  const PairEvents ev = p.offer(1, {1, t0 + 2 * kPeriod + 1000, 22});
  ASSERT_TRUE(ev.paired);
  EXPECT_EQ(ev.left.slot, 12);
  EXPECT_EQ(ev.right.slot, 22);
  EXPECT_EQ(ev.trigger_seq, 2U);
  ASSERT_EQ(ev.n_released, 1);
  EXPECT_EQ(ev.released[0], 11);
  EXPECT_EQ(p.counters().unpaired, 1U);
  EXPECT_EQ(p.counters().missing_triggers, 0U);  // trigger 1 came: one camera lost it
  // Two pulses that never came: a gap of two in the numbers, counted as missing triggers.
  p.offer(0, {3, t0 + 5 * kPeriod, 15});
  const PairEvents ev2 = p.offer(1, {2, t0 + 5 * kPeriod, 25});
  ASSERT_TRUE(ev2.paired);
  EXPECT_EQ(ev2.trigger_seq, 5U);
  EXPECT_EQ(p.counters().missing_triggers, 2U);
}

TEST(FramePairer, ADeadCameraFillsNoMoreThanItsRingAndAStaleFrameIsRefused) {
  FramePairer p({kPeriod, 0});
  const int64_t t0 = 1'000'000'000;
  int released = 0;
  for (int k = 0; k < 20; ++k) {
    const PairEvents ev = p.offer(0, {static_cast<uint64_t>(k), t0 + k * kPeriod, k});
    EXPECT_FALSE(ev.paired);
    released += ev.n_released;
    EXPECT_LE(p.pending(0), FramePairer::kDepth);
  }
  EXPECT_EQ(released, 20 - FramePairer::kDepth);
  // The right camera wakes up with a frame of trigger 3, long given up on the left.
  const PairEvents stale = p.offer(1, {0, t0 + 3 * kPeriod, 99});
  EXPECT_FALSE(stale.paired);
  ASSERT_EQ(stale.n_released, 1);
  EXPECT_EQ(stale.released[0], 99);
  EXPECT_EQ(p.counters().out_of_order, 1U);
  // ...and then one of trigger 19, still pending on the left: paired.
  const PairEvents ev = p.offer(1, {1, t0 + 19 * kPeriod, 119});
  ASSERT_TRUE(ev.paired);
  EXPECT_EQ(ev.left.slot, 19);
  const PairEvents r = p.reset();
  EXPECT_EQ(r.n_released, 0);
  EXPECT_EQ(p.pending(0) + p.pending(1), 0);
}

class RandomStreams : public ::testing::TestWithParam<uint32_t> {};

TEST_P(RandomStreams, EveryPairIsOneTriggerAndEveryFaultIsCounted) {
  const Truth t = makeStream(3000, 0.03, 0.04, 2, GetParam());
  FramePairer p({kPeriod, 0});
  uint64_t pairs = 0, released = 0;
  int first = -1;
  for (const Delivery& d : t.order) {
    const PairEvents ev = p.offer(d.cam, d.stamp);
    released += static_cast<uint64_t>(ev.n_released);
    if (!ev.paired) continue;
    ++pairs;
    ASSERT_EQ(ev.left.slot, ev.right.slot) << "paired two triggers' frames";
    if (first < 0) first = ev.left.slot;
    ASSERT_EQ(ev.trigger_seq, static_cast<uint64_t>(ev.left.slot - first));
  }
  const PairEvents tail = p.reset();
  released += static_cast<uint64_t>(tail.n_released);
  EXPECT_EQ(pairs, t.both);
  EXPECT_EQ(released, t.one);  // every frame came back: paired or released
  EXPECT_LE(p.counters().unpaired, t.one);
  EXPECT_GE(p.counters().unpaired + FramePairer::kDepth * 2, t.one);
  EXPECT_EQ(p.counters().missing_triggers, t.none_between);
  EXPECT_EQ(p.counters().dropped[0], t.left_gaps);
  EXPECT_EQ(p.counters().dropped[1], 0U);
  EXPECT_EQ(p.counters().out_of_order, 0U);
  EXPECT_GT(t.one, 100U);  // the stream did exercise the faults
  EXPECT_GT(t.none_between, 50U);
}

INSTANTIATE_TEST_SUITE_P(Seeds, RandomStreams, ::testing::Values(1U, 2U, 3U, 42U, 4242U));

}  // namespace
}  // namespace pulsetrack::drivers
