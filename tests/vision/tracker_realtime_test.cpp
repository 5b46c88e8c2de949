// The per-frame path allocates nothing, locks nothing and throws nothing: every heap entry point
// (malloc, calloc, realloc, memalign, posix_memalign, aligned_alloc, operator new) and
// pthread_mutex_lock is interposed in this executable and counted, on the calling thread only,
// while track(), the frame pairer and the live recorder's offer() run.
// Its own executable, built without sanitizers (they own these symbols).

#include <dlfcn.h>
#include <gtest/gtest.h>
#include <pthread.h>

#include <atomic>
#include <cstdlib>
#include <cstring>
#include <iostream>
#include <new>

#include "pulsetrack/daemon/preview.hpp"
#include "pulsetrack/drivers/pairing.hpp"
#include "pulsetrack/record/live_recorder.hpp"
#include "pulsetrack/sim/paper_rig.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/deformation_field.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"
#include "pulsetrack/vision/tracking_session.hpp"
#include "test_util.hpp"

namespace {
thread_local bool g_counting = false;  // this thread's calls only (the recorder's writer allocates)
std::atomic<long> g_allocations{0};
std::atomic<long> g_locks{0};
void count() {
  if (g_counting) g_allocations.fetch_add(1, std::memory_order_relaxed);
}
}  // namespace

// glibc's own allocator entry points, which the interposed functions forward to.
// NOLINTBEGIN(bugprone-reserved-identifier)
extern "C" {
void* __libc_malloc(size_t);
void* __libc_calloc(size_t, size_t);
void* __libc_realloc(void*, size_t);
void* __libc_memalign(size_t, size_t);
void __libc_free(void*);

void* malloc(size_t n) {
  count();
  return __libc_malloc(n);
}
void* calloc(size_t n, size_t m) {
  count();
  return __libc_calloc(n, m);
}
void* realloc(void* p, size_t n) {
  count();
  return __libc_realloc(p, n);
}
void* memalign(size_t a, size_t n) {
  count();
  return __libc_memalign(a, n);
}
void* aligned_alloc(size_t a, size_t n) {
  count();
  return __libc_memalign(a, n);
}
int posix_memalign(void** out, size_t a, size_t n) {
  count();
  *out = __libc_memalign(a, n);
  return *out != nullptr ? 0 : ENOMEM;
}
void free(void* p) { __libc_free(p); }

int pthread_mutex_lock(pthread_mutex_t* m) {
  using Fn = int (*)(pthread_mutex_t*);
  static Fn real = reinterpret_cast<Fn>(dlsym(RTLD_NEXT, "pthread_mutex_lock"));
  if (g_counting) g_locks.fetch_add(1, std::memory_order_relaxed);
  return real(m);
}
}
// NOLINTEND(bugprone-reserved-identifier)

void* operator new(size_t n) {
  count();
  if (void* p = __libc_malloc(n != 0 ? n : 1)) return p;
  throw std::bad_alloc();
}
void* operator new[](size_t n) { return operator new(n); }
void operator delete(void* p) noexcept { __libc_free(p); }
void operator delete[](void* p) noexcept { __libc_free(p); }
void operator delete(void* p, size_t) noexcept { __libc_free(p); }
void operator delete[](void* p, size_t) noexcept { __libc_free(p); }

namespace pulsetrack::vision {
namespace {

TEST(TrackerRealtime, TheCounterSeesAllocationsAndLocks) {
  g_allocations = 0;
  g_locks = 0;
  g_counting = true;
  {
    std::vector<int> v(100);
    v[5] = 1;
    void* p = std::malloc(10);
    std::free(p);
    pthread_mutex_t m = PTHREAD_MUTEX_INITIALIZER;
    pthread_mutex_lock(&m);
    pthread_mutex_unlock(&m);
  }
  g_counting = false;
  EXPECT_GE(g_allocations.load(), 2);
  EXPECT_EQ(g_locks.load(), 1);
}

TEST(TrackerRealtime, TrackAllocatesNothingAndLocksNothing) {
  static_assert(noexcept(std::declval<StereoTracker&>().track(std::declval<const cv::Mat&>(),
                                                              std::declval<const cv::Mat&>())),
                "the per-frame step must be noexcept");
  static_assert(noexcept(std::declval<StereoTracker&>().refreshStereo(
                    std::declval<const cv::Mat&>(), std::declval<const cv::Mat&>())),
                "the stereo refresh runs on the tracking thread too");
  sim::SceneSpec spec;
  spec.kind = sim::SceneKind::kCortex;
  spec.supersample = 1;
  spec.cortex.oscillations = sim::paperMotion();
  spec.cortex.instrument.enabled = true;  // occlusions and re-acquisitions on the path too
  spec.cortex.instrument.start_s = 0.2;
  spec.cortex.instrument.duration_s = 1.0;
  sim::StereoSimulator s(spec, sim::paperRig());
  StereoTracker tracker(s.rig(), TrackerConfig{});
  std::vector<cv::Mat> left(13), right(13);
  for (int i = 0; i < 13; ++i)
    s.render(i, left[static_cast<size_t>(i)], right[static_cast<size_t>(i)]);
  const Roi roi{{560, 380, 260, 220}, {540, 370, 260, 220}};
  auto ok = tracker.initialize(left[0], right[0], roi, 20.0);
  ASSERT_TRUE(ok) << ok.error().message;
  ASSERT_GT(*ok, 20);
  tracker.track(left[1], right[1]);  // warm-up (first-use initialisation in libraries)
  (void)tracker.refreshStereo(left[1], right[1]);
  g_allocations = 0;
  g_locks = 0;
  g_counting = true;
  int refreshed = 0;
  for (int i = 2; i < 13; ++i) {
    tracker.track(left[static_cast<size_t>(i)], right[static_cast<size_t>(i)]);
    refreshed += tracker.refreshStereo(left[static_cast<size_t>(i)], right[static_cast<size_t>(i)]);
  }
  g_counting = false;
  EXPECT_EQ(g_allocations.load(), 0) << "heap allocations in 11 calls of track() + refreshStereo()";
  EXPECT_EQ(g_locks.load(), 0) << "mutex locks in 11 calls of track() + refreshStereo()";
  EXPECT_GT(tracker.okCount(), 10);
  EXPECT_GT(refreshed, 50);  // the refresh ran (25 per pair at most)
}

// The session's per-pair path (track, deformation, refresh) allocates nothing either; and with
// an ROI that cannot work, or one that finds no features, pairs between the rate-limited
// detection attempts cost no allocation: a bad ROI never turns the real-time thread into a
// detector running on every pair.
TEST(TrackerRealtime, TheSessionAllocatesNothingPerPairEvenWithABadRoi) {
  sim::SceneSpec spec;
  spec.kind = sim::SceneKind::kCortex;
  spec.supersample = 1;
  spec.cortex.oscillations = sim::paperMotion();
  sim::StereoSimulator s(spec, sim::paperRig());
  std::vector<cv::Mat> left(12), right(12);
  for (int i = 0; i < 12; ++i)
    s.render(i, left[static_cast<size_t>(i)], right[static_cast<size_t>(i)]);
  const auto t_ns = [](int i) { return int64_t{i} * 100'000'000; };  // 10 Hz
  DeformationField field(FieldConfig{}, TrackerConfig{}.max_features);
  field.enablePrediction(1.0, 100.0);
  Eigen::MatrixXd predicted;
  int fields = 0, predictions = 0, grid_predictions = 0;
  const auto run = [&](TrackingSession& session, int from, int to) {
    g_allocations = 0;
    g_locks = 0;
    g_counting = true;
    for (int i = from; i < to; ++i) {
      const auto k = static_cast<size_t>(i);
      const PairResult& pr = session.process(left[k], right[k], static_cast<uint64_t>(i), t_ns(i));
      if (pr.state == SessionState::kTracking &&
          field.update(pr.features, pr.detected, pr.deformation.detections)) {
        ++fields;
        (void)field.at(field.rest(field.points() / 2));
        // The prediction: the session's (in process()), and the grid's with its weights.
        field.record(static_cast<double>(t_ns(i)) * 1e-9);
        predictions += pr.deformation.prediction.horizons == 3 ? 1 : 0;
        const std::span<const double> w(pr.deformation.prediction_weights[1].data(),
                                        static_cast<size_t>(pr.deformation.prediction_order));
        grid_predictions += field.predict(w, pr.deformation.prediction_step_s, predicted) ? 1 : 0;
      }
      session.afterPublish(left[k], right[k]);
    }
    g_counting = false;
  };
  {  // a good ROI: detection at pair 0 (allocates), then tracking
    SessionConfig c;
    c.roi = {{560, 380, 260, 220}, {540, 370, 260, 220}};
    TrackingSession session(s.rig(), c);
    const PairResult& first = session.process(left[0], right[0], 0, t_ns(0));
    ASSERT_EQ(session.last().state, SessionState::kTracking) << session.reason();
    // The dense field too: it allocates its grid at the detection, nothing per pair after.
    ASSERT_TRUE(field.update(first.features, first.detected, first.deformation.detections));
    const PairResult& second = session.process(left[1], right[1], 1, t_ns(1));  // warm-up
    ASSERT_TRUE(field.update(second.features, second.detected, second.deformation.detections));
    predicted.setZero(field.points(), 3);  // sized once for the grid, as the daemon does
    const int factorizations = field.factorizations();
    run(session, 2, 12);
    EXPECT_EQ(g_allocations.load(), 0) << "allocations in 10 tracked pairs (and their field)";
    EXPECT_EQ(g_locks.load(), 0);
    EXPECT_TRUE(session.last().deformation.valid);
    EXPECT_EQ(fields, 10);
    EXPECT_EQ(predictions, 10);
    EXPECT_GT(grid_predictions, 0);  // the lags reach back far enough after 0.9 s of pairs
    EXPECT_GT(field.points(), 400);
    std::cout << "field: " << field.cols() << "x" << field.rows() << " grid, "
              << field.factorizations() - factorizations << " factorizations in 10 pairs\n";
    // The stereo refresh in parts, as pulsetrackd's track and refresh stages run it: the job and
    // its outcome sized once, then nothing per pair.
    RefreshJob job(c.tracker);
    RefreshOutcome outcome(c.tracker);
    int taken = 0;
    g_allocations = 0;
    g_locks = 0;
    g_counting = true;
    for (int i = 11; i >= 2; --i) {
      const auto k = static_cast<size_t>(i);
      (void)session.process(left[k], right[k], static_cast<uint64_t>(24 - i), t_ns(24 - i));
      session.prepareRefresh(left[k], right[k], job);
      measureRefresh(job, outcome);
      taken += session.applyRefresh(outcome);
    }
    g_counting = false;
    EXPECT_EQ(g_allocations.load(), 0) << "allocations in 10 pairs' refresh in parts";
    EXPECT_EQ(g_locks.load(), 0);
    EXPECT_GT(taken, 50);
  }
  {  // tracked at half the images' size: each pair resampled into buffers sized at detection,
     // the features mapped back to the images' pixels in a vector reserved at construction
    SessionConfig c;
    c.roi = {{560, 380, 260, 220}, {540, 370, 260, 220}};
    c.scale = 0.5;
    TrackingSession session(s.rig(), c);
    const PairResult& first = session.process(left[0], right[0], 0, t_ns(0));
    ASSERT_EQ(session.last().state, SessionState::kTracking) << session.reason();
    EXPECT_EQ(session.scale(), 0.5);
    ASSERT_TRUE(field.update(first.features, first.detected, first.deformation.detections));
    session.afterPublish(left[0], right[0]);
    const PairResult& second = session.process(left[1], right[1], 1, t_ns(1));  // warm-up
    ASSERT_TRUE(field.update(second.features, second.detected, second.deformation.detections));
    predicted.setZero(field.points(), 3);
    session.afterPublish(left[1], right[1]);
    run(session, 2, 12);
    EXPECT_EQ(g_allocations.load(), 0) << "allocations in 10 pairs tracked at half size";
    EXPECT_EQ(g_locks.load(), 0);
    ASSERT_TRUE(session.last().deformation.valid);
    for (const Feature& f : session.last().features) {  // in the full-size ROI, not the half's
      if (f.status != FeatureStatus::kOk) continue;
      EXPECT_TRUE(cv::Rect(540, 360, 300, 260).contains(cv::Point(f.left)))
          << f.left[0] << "," << f.left[1];
    }
  }
  {  // an ROI outside the image: refused with its reason, every pair free
    SessionConfig c;
    c.roi = {{1300, 1000, 200, 200}, {540, 370, 260, 220}};
    TrackingSession session(s.rig(), c);
    run(session, 0, 12);
    EXPECT_EQ(g_allocations.load(), 0) << "allocations in 12 pairs with an ROI outside the image";
    EXPECT_EQ(session.last().state, SessionState::kNoFeatures);
    EXPECT_NE(session.reason().find("left ROI 1300,1000 200x200: not inside"), std::string::npos)
        << session.reason();
    EXPECT_EQ(session.detectionAttempts(), 0);
  }
  {  // a 40x40 ROI in the image's corner (the rig's black surround): no feature; detection is
     // tried at pair 0 and again one retry interval (1 s) later, never in between
    SessionConfig c;
    c.roi = {{10, 10, 40, 40}, {10, 10, 40, 40}};
    TrackingSession session(s.rig(), c);
    (void)session.process(left[0], right[0], 0, t_ns(0));
    EXPECT_EQ(session.detectionAttempts(), 1);
    run(session, 1, 10);
    EXPECT_EQ(g_allocations.load(), 0) << "allocations between detection attempts";
    EXPECT_EQ(session.detectionAttempts(), 1);
    (void)session.process(left[10], right[10], 10, t_ns(10));
    EXPECT_EQ(session.detectionAttempts(), 2);
    EXPECT_EQ(session.last().state, SessionState::kNoFeatures);
    EXPECT_NE(session.reason().find("ROI 10,10 40x40"), std::string::npos) << session.reason();
    EXPECT_NE(session.reason().find("tried again every 1 s"), std::string::npos)
        << session.reason();
  }
}

TEST(TrackerRealtime, PairingAndTheRecordersOfferAllocateNothingAndLockNothing) {
  drivers::FramePairer pairer({33'333'333, 0});
  test::TempDir tmp;
  const cv::Size size(640, 480);
  record::LiveRecorderOptions o;
  o.dir = tmp.path() / "rec";
  o.manifest.source = "test";
  o.manifest.rig_id = "rig";
  o.manifest.width = size.width;
  o.manifest.height = size.height;
  o.manifest.nominal_fps = 30;
  o.slots = 8;
  vision::StereoRig rig = sim::paperRig();
  auto rec = record::LiveRecorder::start(o, rig);
  ASSERT_TRUE(rec) << rec.error().message;
  cv::Mat l(size, CV_8UC1, cv::Scalar(10)), r(size, CV_8UC1, cv::Scalar(20));
  (void)(*rec)->offer({0, 0, 0, 0, 0}, l, r);  // warm-up
  g_allocations = 0;
  g_locks = 0;
  g_counting = true;
  int paired = 0, offered = 0;
  for (int k = 1; k < 200; ++k) {
    const int64_t t = int64_t{k} * 33'333'333;
    (void)pairer.offer(0, {static_cast<uint64_t>(k), t, k});
    if (k % 9 != 0)
      paired += pairer.offer(1, {static_cast<uint64_t>(k), t + 5000, k}).paired ? 1 : 0;
    offered +=
        (*rec)->offer({static_cast<uint64_t>(k), static_cast<uint64_t>(k), t, t, 0}, l, r) ? 1 : 0;
  }
  g_counting = false;
  (*rec)->stop();
  EXPECT_EQ(g_allocations.load(), 0) << "heap allocations in 199 offers";
  EXPECT_EQ(g_locks.load(), 0) << "mutex locks in 199 offers";
  EXPECT_GT(paired, 150);
  EXPECT_GT(offered, 0);
}

// The capture stage's preview hand-off (daemon::PreviewTap): a copy into a preallocated slot at
// most every period, the rest passed by; nothing allocated or locked, and what the preview stage
// takes is the pair as it was.
TEST(TrackerRealtime, ThePreviewsCopyAllocatesNothingAndLocksNothing) {
  const cv::Size size(1360, 1024);
  daemon::PreviewTap tap(size, 200'000'000);  // 5 Hz
  static_assert(noexcept(tap.offer(std::declval<const drivers::StereoFrame&>(), 0)));
  drivers::StereoFrame pair;
  pair.left.create(size, CV_8UC1);
  pair.right.create(size, CV_8UC1);
  g_allocations = 0;
  g_locks = 0;
  g_counting = true;
  int copied = 0;
  for (int k = 0; k < 60; ++k) {                        // 2 s at 30 Hz
    std::memset(pair.left.data, k, pair.left.total());  // (setTo would allocate its scalar)
    std::memset(pair.right.data, 255 - k, pair.right.total());
    pair.trigger_seq = static_cast<uint64_t>(k);
    pair.t_left_ns = pair.t_right_ns = int64_t{k} * 33'333'333;
    // Handed over late, and later for some: the schedule follows the exposures.
    copied += tap.offer(pair, pair.t_left_ns + (k % 4 == 0 ? 90'000'000 : 5'000'000)) ? 1 : 0;
  }
  g_counting = false;
  EXPECT_EQ(g_allocations.load(), 0) << "heap allocations in 60 offers";
  EXPECT_EQ(g_locks.load(), 0) << "mutex locks in 60 offers";
  EXPECT_EQ(copied, 10);  // every 6th pair: 5 a second
  const daemon::PreviewFrame* p = tap.take();
  ASSERT_NE(p, nullptr);
  EXPECT_EQ(p->trigger_seq, 54U);  // the newest copy
  EXPECT_EQ(cv::countNonZero(p->left != 54), 0);
  EXPECT_EQ(cv::countNonZero(p->right != 255 - 54), 0);
  EXPECT_EQ(tap.take(), nullptr);  // nothing newer
}

}  // namespace
}  // namespace pulsetrack::vision
