// The per-frame step allocates nothing, locks nothing and throws nothing: every heap entry point
// (malloc, calloc, realloc, memalign, posix_memalign, aligned_alloc, operator new) and
// pthread_mutex_lock is interposed in this executable and counted while track() runs.
// Its own executable, built without sanitizers (they own these symbols).

#include <dlfcn.h>
#include <gtest/gtest.h>
#include <pthread.h>

#include <atomic>
#include <cstdlib>
#include <new>

#include "pulsetrack/sim/paper_rig.hpp"
#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"

namespace {
std::atomic<bool> g_counting{false};
std::atomic<long> g_allocations{0};
std::atomic<long> g_locks{0};
void count() {
  if (g_counting.load(std::memory_order_relaxed))
    g_allocations.fetch_add(1, std::memory_order_relaxed);
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
  if (g_counting.load(std::memory_order_relaxed)) g_locks.fetch_add(1, std::memory_order_relaxed);
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
  g_allocations = 0;
  g_locks = 0;
  g_counting = true;
  for (int i = 2; i < 13; ++i)
    tracker.track(left[static_cast<size_t>(i)], right[static_cast<size_t>(i)]);
  g_counting = false;
  EXPECT_EQ(g_allocations.load(), 0) << "heap allocations in 11 calls of track()";
  EXPECT_EQ(g_locks.load(), 0) << "mutex locks in 11 calls of track()";
  EXPECT_GT(tracker.okCount(), 10);
}

}  // namespace
}  // namespace pulsetrack::vision
