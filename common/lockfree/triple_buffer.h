// A lock-free triple buffer of a value sized at start-up (an organ's positions, its topology
// after a cut, the rigid bodies' poses) from one writer thread (the physics) to one reader (the
// publisher): the writer never waits for the reader, the reader always gets the newest complete
// value. The writer fills back() in place and publishes it; nothing is allocated after
// construction as long as the writer keeps each buffer's sizes.
#pragma once

#include <array>
#include <atomic>

namespace somasim::lockfree {

template <typename T>
class TripleBuffer {
 public:
  // Three copies of `initial` (the sizes every later value keeps).
  explicit TripleBuffer(const T& initial) : buffers_{initial, initial, initial} {}

  // Writer: the buffer to fill (it holds an older value), then Publish().
  T& back() { return buffers_[back_]; }
  void Publish() {
    const int previous = middle_.exchange(back_ | kFresh, std::memory_order_acq_rel);
    back_ = previous & kIndex;
  }
  // Reader: true when a value newer than the last Take arrived (then front() shows it).
  bool Take() {
    if ((middle_.load(std::memory_order_acquire) & kFresh) == 0) return false;
    const int previous = middle_.exchange(front_, std::memory_order_acq_rel);
    front_ = previous & kIndex;
    return true;
  }
  // Reader: the value last taken (the initial one before any).
  const T& front() const { return buffers_[front_]; }

 private:
  static constexpr int kIndex = 3;
  static constexpr int kFresh = 4;
  std::array<T, 3> buffers_;
  int back_ = 0;                // the writer's
  int front_ = 2;               // the reader's
  std::atomic<int> middle_{1};  // the one in between, with kFresh when unread
};

}  // namespace somasim::lockfree
