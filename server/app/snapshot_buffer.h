// A lock-free triple buffer of one organ's positions from the physics thread (one writer) to
// the publisher thread (one reader): the writer never waits for the reader, the reader always
// gets the newest complete snapshot. Buffers are sized at start-up; Write allocates nothing.
#pragma once

#include <algorithm>
#include <array>
#include <atomic>
#include <cstdint>
#include <span>
#include <vector>

namespace somasim::server {

class SnapshotBuffer {
 public:
  explicit SnapshotBuffer(size_t size) {
    for (auto& b : buffers_) b.assign(size, 0.0);
  }
  // Physics thread: copies `values` (size() of them) with its time [s] and hands it over.
  void Write(std::span<const double> values, double time) {
    std::copy_n(values.begin(), std::min(values.size(), buffers_[back_].size()),
                buffers_[back_].begin());
    times_[back_] = time;
    const int previous = middle_.exchange(back_ | kFresh, std::memory_order_acq_rel);
    back_ = previous & kIndex;
  }
  // Publisher thread: true when a snapshot newer than the last Take arrived (then values()
  // and time() show it).
  bool Take() {
    if ((middle_.load(std::memory_order_acquire) & kFresh) == 0) return false;
    const int previous = middle_.exchange(front_, std::memory_order_acq_rel);
    front_ = previous & kIndex;
    return true;
  }
  std::span<const double> values() const { return buffers_[front_]; }
  double time() const { return times_[front_]; }
  size_t size() const { return buffers_[0].size(); }

 private:
  static constexpr int kIndex = 3;
  static constexpr int kFresh = 4;
  std::array<std::vector<double>, 3> buffers_;
  std::array<double, 3> times_{};
  int back_ = 0;                // the writer's
  int front_ = 2;               // the reader's
  std::atomic<int> middle_{1};  // the one in between, with kFresh when unread
};

// Step times: a histogram of 2 %-wide bins from 1 µs to ~10 s, so percentiles cost nothing to
// keep (no allocation, no sorting) and are exact to 2 %.
class StepTimeHistogram {
 public:
  void Add(double microseconds) {
    ++count_;
    max_ = std::max(max_, microseconds);
    ++bins_[Bin(microseconds)];
  }
  void Clear() {
    bins_.fill(0);
    count_ = 0;
    max_ = 0.0;
  }
  uint64_t count() const { return count_; }
  double max() const { return max_; }
  // The q-quantile (0 < q <= 1) [µs]: the upper edge of the bin it falls in (0 when empty).
  double Quantile(double q) const;

 private:
  static constexpr int kBins = 820;  // 1.02^820 µs ≈ 11 s
  static int Bin(double microseconds);
  std::array<uint64_t, kBins> bins_{};
  uint64_t count_ = 0;
  double max_ = 0.0;
};

}  // namespace somasim::server
