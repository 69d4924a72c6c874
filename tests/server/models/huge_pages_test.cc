// Huge pages for the large arrays of the explicit mass-spring pass: where large arrays start,
// that vectors on them behave as any vector, and which ranges can be advised.
#include "server/models/huge_pages.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <numeric>
#include <vector>

namespace somasim::models {
namespace {

bool OnHugePageBoundary(const void* data) {
  return reinterpret_cast<uintptr_t>(data) % kHugePageSize == 0;
}

TEST(HugePages, LargeArraysStartOnAHugePageBoundary) {
  HugePageVector<double> large(kHugePageThreshold / sizeof(double), 1.5);
  EXPECT_TRUE(OnHugePageBoundary(large.data()));
  HugePageVector<int32_t> larger(3 * kHugePageSize / sizeof(int32_t) + 7, -2);
  EXPECT_TRUE(OnHugePageBoundary(larger.data()));
  EXPECT_EQ(larger.back(), -2);
  // Small arrays are not worth a huge page: allocated as usual, aligned for their type.
  HugePageVector<double> small(100, 2.0);
  EXPECT_EQ(reinterpret_cast<uintptr_t>(small.data()) % alignof(double), 0U);
  EXPECT_EQ(small[99], 2.0);
}

TEST(HugePages, VectorsOnHugePagesCopyGrowAndShrinkLikeAnyVector) {
  HugePageVector<int64_t> values;
  // Growth takes the array from ordinary memory to huge pages and back (shrink_to_fit).
  for (int64_t k = 0; k < 200000; ++k) values.push_back(3 * k);
  ASSERT_EQ(values.size(), 200000U);
  EXPECT_TRUE(OnHugePageBoundary(values.data()));
  const HugePageVector<int64_t> copy = values;
  EXPECT_TRUE(OnHugePageBoundary(copy.data()));
  EXPECT_EQ(copy, values);
  EXPECT_EQ(std::accumulate(copy.begin(), copy.end(), int64_t{0}), 3 * (199999LL * 200000 / 2));
  values.resize(10);
  values.shrink_to_fit();
  EXPECT_EQ(values.size(), 10U);
  EXPECT_EQ(values[9], 27);
}

TEST(HugePages, OnlyRangesHoldingAWholeAlignedHugePageAreAdvised) {
  std::vector<double> small(1000, 0.0);
  EXPECT_FALSE(AdviseHugePages(small.data(), small.size() * sizeof(double)));
  EXPECT_FALSE(AdviseHugePages(nullptr, 0));
  // 6 MiB hold at least two whole aligned 2 MiB pages wherever they start.
  std::vector<double> large(6 * (size_t{1} << 20) / sizeof(double), 1.0);
#if defined(__linux__)
  EXPECT_TRUE(AdviseHugePages(large.data(), large.size() * sizeof(double)));
#else
  EXPECT_FALSE(AdviseHugePages(large.data(), large.size() * sizeof(double)));
#endif
  // Advice changes no value.
  EXPECT_EQ(std::accumulate(large.begin(), large.end(), 0.0), static_cast<double>(large.size()));
}

}  // namespace
}  // namespace somasim::models
