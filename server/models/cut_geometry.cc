#include "server/models/cut_geometry.h"

#include <cmath>

namespace somasim::models {

using Eigen::Vector3d;

bool SegmentCrossesTriangle(const Vector3d& a, const Vector3d& b, const Vector3d& t0,
                            const Vector3d& t1, const Vector3d& t2) {
  // Möller & Trumbore 1997 on the segment a + s (b - a), s in [0, 1].
  const Vector3d direction = b - a;
  const Vector3d e1 = t1 - t0;
  const Vector3d e2 = t2 - t0;
  const Vector3d h = direction.cross(e2);
  const double det = e1.dot(h);
  // Parallel to the plane (or a degenerate triangle or segment): no crossing. The scale makes
  // the test independent of units.
  const double scale = direction.norm() * e1.norm() * e2.norm();
  if (!(std::abs(det) > 1e-12 * scale)) return false;
  const double inverse = 1.0 / det;
  const Vector3d s = a - t0;
  const double u = inverse * s.dot(h);
  if (u < 0.0 || u > 1.0) return false;
  const Vector3d q = s.cross(e1);
  const double v = inverse * direction.dot(q);
  if (v < 0.0 || u + v > 1.0) return false;
  const double t = inverse * e2.dot(q);
  return t >= 0.0 && t <= 1.0;
}

bool SegmentCrossesSweep(const Vector3d& a, const Vector3d& b, const SweptQuad& sweep) {
  return SegmentCrossesTriangle(a, b, sweep.p0, sweep.q0, sweep.q1) ||
         SegmentCrossesTriangle(a, b, sweep.p0, sweep.q1, sweep.p1);
}

}  // namespace somasim::models
