// Internal to the AABB tree: the outward rounding of double boxes to float that the build, Refit
// and the queries share (aabb_tree.cc, aabb_tree_refit.cc, aabb_tree_queries.cc).
#pragma once

#include <cmath>
#include <limits>

namespace somasim::contact::aabb_internal {

inline constexpr double kInf = std::numeric_limits<double>::infinity();

// Double to float rounded down / up, whatever the rounding mode, without branches: move x
// outwards by 2^-22 |x| + 1e-37 first (in double), then convert. A conversion errs by less than
// one float ulp <= 2^-23 |y| + 2^-149 in any rounding mode, which that step exceeds, so the result
// is <= x (>= x). Costs at most ~3 float ulps (3.6e-7 relative) of looseness.
inline constexpr double kOutwardRelative = 0x1p-22;
inline constexpr double kOutwardAbsolute = 1e-37;
inline float RoundDown(double x) {
  return static_cast<float>(x - (std::abs(x) * kOutwardRelative + kOutwardAbsolute));
}
inline float RoundUp(double x) {
  return static_cast<float>(x + (std::abs(x) * kOutwardRelative + kOutwardAbsolute));
}

}  // namespace somasim::contact::aabb_internal
