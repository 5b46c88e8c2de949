#pragma once
// The hand-off between two pipeline stages: a triple buffer. The producer always has a slot to
// write (it never waits), the consumer always gets the newest complete item, and an item the
// consumer never took is counted as dropped: "a slow consumer never blocks capture; the newest
// frame wins". One producer thread, one consumer thread; wait-free on both sides (one atomic
// exchange per hand-off), no allocation after construction.
//
// Why it is correct: the three slots are always owned one each by the producer (back), the
// exchange cell (middle) and the consumer (front). publish() swaps back <-> middle and take()
// swaps front <-> middle, each with one atomic exchange, so no slot is ever owned twice; the
// acquire/release pair on the exchange orders the slot's contents before its hand-over.
// tests/rt/latest_slot_test.cpp hammers it from two threads.

#include <array>
#include <atomic>
#include <cstdint>

namespace pulsetrack::rt {

template <class T>
class LatestSlot {
 public:
  LatestSlot() = default;
  // Slots set up by the caller (e.g. frames with preallocated images).
  template <class Init>
  explicit LatestSlot(Init init) {
    for (T& s : slots_) init(s);
  }

  // Producer: the slot to fill, then publish() it. Returns true when the item it replaces in
  // the middle was never taken (one drop).
  T& back() noexcept { return slots_[back_]; }
  bool publish() noexcept {
    const uint8_t prev =
        middle_.exchange(static_cast<uint8_t>(back_ | kFresh), std::memory_order_acq_rel);
    back_ = static_cast<uint8_t>(prev & kIndex);
    const bool dropped = (prev & kFresh) != 0;
    if (dropped) drops_.fetch_add(1, std::memory_order_relaxed);
    return dropped;
  }

  // Consumer: the newest published item, or nullptr when nothing new came since the last take.
  // The pointer stays valid (and the item unchanged) until the next take().
  T* take() noexcept {
    if ((middle_.load(std::memory_order_acquire) & kFresh) == 0) return nullptr;
    const uint8_t prev = middle_.exchange(front_, std::memory_order_acq_rel);
    front_ = static_cast<uint8_t>(prev & kIndex);
    return &slots_[front_];
  }

  [[nodiscard]] uint64_t drops() const noexcept { return drops_.load(std::memory_order_relaxed); }

  // Every slot, for set-up before the threads start (e.g. sizing buffers).
  std::array<T, 3>& slots() noexcept { return slots_; }

 private:
  static constexpr uint8_t kIndex = 0x3;
  static constexpr uint8_t kFresh = 0x4;
  std::array<T, 3> slots_{};
  uint8_t back_ = 0;  // producer's
  alignas(64) std::atomic<uint8_t> middle_{1};
  alignas(64) uint8_t front_ = 2;  // consumer's
  std::atomic<uint64_t> drops_{0};
};

}  // namespace pulsetrack::rt
