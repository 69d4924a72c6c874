#include "common/mesh_gen/implicit.h"

#include <cassert>
#include <cmath>

namespace somasim::mesh_gen {

Eigen::Vector3d ImplicitGradient(const ImplicitSolid& solid, const Eigen::Vector3d& p, double h) {
  Eigen::Vector3d gradient;
  for (int axis = 0; axis < 3; ++axis) {
    Eigen::Vector3d forward = p;
    Eigen::Vector3d backward = p;
    forward[axis] += h;
    backward[axis] -= h;
    gradient[axis] = (solid.Value(forward) - solid.Value(backward)) / (2.0 * h);
  }
  return gradient;
}

Eigen::Vector3d ProjectToSurface(const ImplicitSolid& solid, const Eigen::Vector3d& p,
                                 double tolerance, int max_iterations) {
  Eigen::Vector3d x = p;
  for (int iteration = 0; iteration < max_iterations; ++iteration) {
    const double value = solid.Value(x);
    if (std::abs(value) < tolerance) break;
    const Eigen::Vector3d gradient = ImplicitGradient(solid, x);
    const double norm2 = gradient.squaredNorm();
    if (!(norm2 > 1e-24)) break;
    Eigen::Vector3d step = -value * gradient / norm2;
    // Damping: a distance-like function never needs a step much longer than |value|.
    const double limit = 2.0 * std::abs(value) + 1e-12;
    if (step.norm() > limit) step *= limit / step.norm();
    x += step;
  }
  return x;
}

Eigen::Vector3d FindSegmentRoot(const ImplicitSolid& solid, const Eigen::Vector3d& a,
                                const Eigen::Vector3d& b, double tolerance) {
  double fa = solid.Value(a);
  double fb = solid.Value(b);
  assert((fa < 0.0) != (fb < 0.0));
  // Parameter t in [0, 1] along a→b; the bracket [lo, hi] always holds the sign change.
  double lo = 0.0;
  double hi = 1.0;
  const double length = (b - a).norm();
  int side = 0;  // Illinois: which end was kept twice in a row
  for (int iteration = 0; iteration < 200 && (hi - lo) * length > tolerance; ++iteration) {
    double t = (lo * fb - hi * fa) / (fb - fa);
    // Fall back to bisection when the secant leaves the bracket or stalls at an end.
    if (!(t > lo && t < hi)) t = 0.5 * (lo + hi);
    if (iteration % 4 == 3) t = 0.5 * (lo + hi);  // guarantees halving at least every 4 steps
    const double ft = solid.Value(a + t * (b - a));
    if (ft == 0.0) return a + t * (b - a);
    if ((ft < 0.0) == (fa < 0.0)) {
      lo = t;
      fa = ft;
      if (side == -1) fb *= 0.5;
      side = -1;
    } else {
      hi = t;
      fb = ft;
      if (side == 1) fa *= 0.5;
      side = 1;
    }
  }
  return a + 0.5 * (lo + hi) * (b - a);
}

Ellipsoid::Ellipsoid(const Eigen::Vector3d& centre, const Eigen::Vector3d& semi_axes)
    : centre_(centre), semi_axes_(semi_axes) {
  assert(semi_axes.minCoeff() > 0.0);
}

double Ellipsoid::Value(const Eigen::Vector3d& p) const {
  const Eigen::Vector3d scaled = (p - centre_).cwiseQuotient(semi_axes_);
  return (scaled.norm() - 1.0) * semi_axes_.minCoeff();
}

mesh::BoundingBox Ellipsoid::Bounds() const {
  mesh::BoundingBox box;
  box.min = centre_ - semi_axes_;
  box.max = centre_ + semi_axes_;
  box.empty = false;
  return box;
}

}  // namespace somasim::mesh_gen
