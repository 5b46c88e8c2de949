#pragma once
// Per-stage latency: a fixed log-linear histogram (HdrHistogram's layout, 16 sub-buckets per
// power of two: at most 6 % relative error) from 1 us to ~67 s. One writer (the stage), any
// number of readers (health): record() is two relaxed atomic operations, no allocation.

#include <array>
#include <atomic>
#include <bit>
#include <cstdint>

namespace pulsetrack::rt {

class LatencyHistogram {
 public:
  static constexpr int kSub = 16;
  static constexpr int kOctaves = 27;  // 2^26 us ~ 67 s
  static constexpr int kBuckets = kSub * kOctaves;

  void record(uint64_t ns) noexcept {
    const uint64_t us = ns / 1000;
    const int b = bucket(us);
    counts_[static_cast<size_t>(b)].fetch_add(1, std::memory_order_relaxed);
    uint64_t m = max_ns_.load(std::memory_order_relaxed);
    if (ns > m) max_ns_.store(ns, std::memory_order_relaxed);  // single writer
    total_.fetch_add(1, std::memory_order_relaxed);
  }

  // The value below which a fraction p of the samples lie, in ns (the bucket's upper edge,
  // capped by the maximum seen); 0 with no samples.
  [[nodiscard]] uint64_t percentileNs(double p) const noexcept {
    const uint64_t n = total_.load(std::memory_order_relaxed);
    if (n == 0) return 0;
    const auto rank = static_cast<uint64_t>(p * static_cast<double>(n));
    uint64_t seen = 0;
    for (int b = 0; b < kBuckets; ++b) {
      seen += counts_[static_cast<size_t>(b)].load(std::memory_order_relaxed);
      if (seen > rank) {
        const uint64_t edge = upperEdgeUs(b) * 1000;
        return edge < maxNs() ? edge : maxNs();
      }
    }
    return maxNs();
  }
  [[nodiscard]] uint64_t maxNs() const noexcept { return max_ns_.load(std::memory_order_relaxed); }
  [[nodiscard]] uint64_t count() const noexcept { return total_.load(std::memory_order_relaxed); }

  static int bucket(uint64_t us) noexcept {
    if (us < kSub) return static_cast<int>(us);
    const int octave = static_cast<int>(std::bit_width(us)) - 4;  // us in [2^(o+3), 2^(o+4))
    if (octave >= kOctaves) return kBuckets - 1;
    const auto sub = static_cast<int>(us >> (octave - 1)) - kSub;  // 0..15
    return octave * kSub + sub;
  }
  static uint64_t upperEdgeUs(int b) noexcept {
    const int octave = b / kSub, sub = b % kSub;
    if (octave == 0) return static_cast<uint64_t>(sub) + 1;
    return (static_cast<uint64_t>(kSub + sub + 1) << (octave - 1));
  }

 private:
  std::array<std::atomic<uint32_t>, kBuckets> counts_{};
  std::atomic<uint64_t> max_ns_{0};
  std::atomic<uint64_t> total_{0};
};

}  // namespace pulsetrack::rt
