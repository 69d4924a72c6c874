#include "server/runner/step_time_histogram.h"

#include <cmath>

namespace somasim::runner {

double StepTimeHistogram::Quantile(double q) const {
  if (count_ == 0) return 0.0;
  const auto target = static_cast<uint64_t>(std::ceil(q * static_cast<double>(count_)));
  uint64_t seen = 0;
  for (int i = 0; i < kBins; ++i) {
    seen += bins_[static_cast<size_t>(i)];
    if (seen >= target) return std::min(max_, std::pow(1.02, i + 1));
  }
  return max_;
}

int StepTimeHistogram::Bin(double microseconds) {
  if (!(microseconds > 1.0)) return 0;
  const int bin = static_cast<int>(std::log(microseconds) / std::log(1.02));
  return std::clamp(bin, 0, kBins - 1);
}

}  // namespace somasim::runner
