// The haptic loop's timing record: a histogram of microsecond values (period errors, wake-up
// lateness) with its bins allocated at start-up, so the 1 kHz loop adds to it without
// allocating; percentiles read after the loop has stopped.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace somasim::haptic {

class MicrosecondHistogram {
 public:
  // Bins of 1 µs from 0 to `max_us`; larger values count in the last bin (and in max()).
  explicit MicrosecondHistogram(int64_t max_us = 20000)
      : bins_(static_cast<size_t>(max_us) + 1, 0) {}

  // Adds a value [ns]; negative values count as 0. Allocation-free.
  void Add(int64_t ns) {
    const int64_t us = std::max<int64_t>(0, ns) / 1000;
    const size_t bin = std::min(static_cast<size_t>(us), bins_.size() - 1);
    ++bins_[bin];
    ++count_;
    max_ns_ = std::max(max_ns_, std::max<int64_t>(0, ns));
  }

  uint64_t count() const { return count_; }
  double max_us() const { return 1e-3 * static_cast<double>(max_ns_); }
  // Values above `us` [µs].
  uint64_t CountAbove(int64_t us) const {
    uint64_t n = 0;
    for (size_t b = static_cast<size_t>(std::max<int64_t>(0, us)) + 1; b < bins_.size(); ++b) {
      n += bins_[b];
    }
    return n;
  }
  // The q-quantile (0..1) [µs], to the bin's upper edge; 0 with no values.
  double Quantile(double q) const {
    if (count_ == 0) return 0.0;
    const auto rank = static_cast<uint64_t>(std::ceil(q * static_cast<double>(count_)));
    uint64_t seen = 0;
    for (size_t b = 0; b < bins_.size(); ++b) {
      seen += bins_[b];
      if (seen >= std::max<uint64_t>(rank, 1)) {
        return b + 1 == bins_.size() ? max_us() : static_cast<double>(b + 1);
      }
    }
    return max_us();
  }

 private:
  std::vector<uint64_t> bins_;
  uint64_t count_ = 0;
  int64_t max_ns_ = 0;
};

}  // namespace somasim::haptic
