// A single-producer single-consumer ring of fixed capacity between two threads: the server's
// session events (physics → publisher) and tool commands (intake → physics), the haptic node's
// rendered forces (1 kHz loop → the thread that writes them to a file). Push never waits and
// fails when full (the caller counts the loss); Pop never waits. No lock, no allocation after
// construction.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>

namespace somasim::lockfree {

template <typename T, uint32_t kCapacity>
class SpscRing {
  static_assert(kCapacity > 0 && (kCapacity & (kCapacity - 1)) == 0, "a power of two");

 public:
  // Producer: false when the ring is full (nothing written).
  bool Push(const T& item) {
    const uint32_t head = head_.load(std::memory_order_relaxed);
    if (head - tail_.load(std::memory_order_acquire) == kCapacity) return false;
    items_[head % kCapacity] = item;
    head_.store(head + 1, std::memory_order_release);
    return true;
  }
  // Consumer: false when empty (`item` untouched).
  bool Pop(T* item) {
    const uint32_t tail = tail_.load(std::memory_order_relaxed);
    if (tail == head_.load(std::memory_order_acquire)) return false;
    *item = items_[tail % kCapacity];
    tail_.store(tail + 1, std::memory_order_release);
    return true;
  }

 private:
  std::array<T, kCapacity> items_{};
  alignas(64) std::atomic<uint32_t> head_{0};
  alignas(64) std::atomic<uint32_t> tail_{0};
};

}  // namespace somasim::lockfree
