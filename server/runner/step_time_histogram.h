// Step times: a histogram of 2 %-wide bins from 1 µs to ~10 s, so percentiles cost nothing to
// keep on the physics thread (no allocation, no sorting) and are exact to 2 %.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>

namespace somasim::runner {

class StepTimeHistogram {
 public:
  void Add(double microseconds) {
    ++count_;
    max_ = std::max(max_, microseconds);
    ++bins_[static_cast<size_t>(Bin(microseconds))];
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

}  // namespace somasim::runner
