// Exact point, segment and sphere queries against one triangle (double precision), the leaf
// tests of the AABB tree (aabb_tree.h) and of the god-object proxy. Pure.
#pragma once

#include <Eigen/Core>

namespace somasim::contact {

// The point of triangle (a, b, c) nearest to p, as barycentric weights (w_a, w_b, w_c), each in
// [0, 1], summing to 1 (Ericson, Real-Time Collision Detection §5.1.5). Degenerate triangles
// (zero area) give the nearest point of their longest edge.
Eigen::Vector3d ClosestPointBarycentric(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                        const Eigen::Vector3d& b, const Eigen::Vector3d& c);

// Where segment pq meets triangle (a, b, c): the parameter t in [0, 1] along pq (point p + t (q
// - p)) and the barycentric weights of the meeting point. Edges and corners of the triangle and
// the segment's ends count as meeting; a segment lying in the triangle's plane does not (it
// never passes from one side to the other). False when they do not meet.
bool SegmentTriangleIntersection(const Eigen::Vector3d& p, const Eigen::Vector3d& q,
                                 const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                 const Eigen::Vector3d& c, double* t,
                                 Eigen::Vector3d* barycentric);

// The squared distance [m²] between segment pq and triangle (a, b, c) (0 when they meet), with
// the closest points: s in [0, 1] along pq and the barycentric weights on the triangle.
double SegmentTriangleDistanceSquared(const Eigen::Vector3d& p, const Eigen::Vector3d& q,
                                      const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                      const Eigen::Vector3d& c, double* s,
                                      Eigen::Vector3d* barycentric);

}  // namespace somasim::contact
