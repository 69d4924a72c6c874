// Exact point, segment and sphere queries against one triangle (double precision), the leaf
// tests of the AABB tree (aabb_tree.h) and of the god-object proxy. Pure.
#pragma once

#include <Eigen/Core>

namespace somasim::contact {

// The point of segment pq nearest to x (p when the segment has no length).
Eigen::Vector3d ClosestPointOnSegment(const Eigen::Vector3d& x, const Eigen::Vector3d& p,
                                      const Eigen::Vector3d& q);

// The point of triangle (a, b, c) nearest to p, as barycentric weights (w_a, w_b, w_c), each in
// [0, 1], summing to 1 (Ericson, Real-Time Collision Detection §5.1.5). Degenerate triangles
// (zero area, or sin of the angle at a below 1e-10) give the nearest point of their three edges
// (for a zero-area triangle: of its longest edge).
Eigen::Vector3d ClosestPointBarycentric(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                        const Eigen::Vector3d& b, const Eigen::Vector3d& c);

// The squared distance [m²] from p to triangle (a, b, c) and the barycentric weights of the
// nearest point (ClosestPointBarycentric). The AABB tree's Nearest and SphereQuery use exactly
// this computation, so a brute-force loop over it reproduces them bit for bit.
double PointTriangleDistanceSquared(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                    const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                    Eigen::Vector3d* barycentric);

// Where segment pq meets triangle (a, b, c): the parameter t in [0, 1] along pq (point p + t (q
// - p)) and the barycentric weights of the meeting point. Edges and corners of the triangle and
// the segment's ends count as meeting; a segment lying in the triangle's plane does not (it
// never passes from one side to the other). False when they do not meet.
//
// Watertight: Woop, Benthin and Wald 2013 ("Watertight ray/triangle intersection", JCGT 2(1)):
// the vertices are moved into a frame where pq runs along an axis (the same transform for every
// triangle, so a shared vertex lands on the same point), and the three 2D edge functions there
// are evaluated with exact signs (a floating-point filter, then Kahan's FMA difference of
// products, relative error < 2 ulp, hence exact sign and exact zero). A shared edge therefore
// gets the same signed answer from both of its triangles, so a segment crossing a closed
// surface always meets at least one triangle, through edges and corners too.
bool SegmentTriangleIntersection(const Eigen::Vector3d& p, const Eigen::Vector3d& q,
                                 const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                 const Eigen::Vector3d& c, double* t, Eigen::Vector3d* barycentric);

// The squared distance [m²] between segment pq and triangle (a, b, c) (0 when they meet), with
// the closest points: s in [0, 1] along pq and the barycentric weights on the triangle.
// (Minimum of the crossing test, the two ends against the triangle and pq against the three
// edges; Ericson §5.1.5, §5.1.9.) A zero-length segment is the point p.
double SegmentTriangleDistanceSquared(const Eigen::Vector3d& p, const Eigen::Vector3d& q,
                                      const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                      const Eigen::Vector3d& c, double* s,
                                      Eigen::Vector3d* barycentric);

// Segment pq prepared once for many triangle tests (the per-segment part of Woop et al.'s
// transform). Intersect and DistanceSquared give bit-identical results to the free functions
// above for the same p, q; the AABB tree uses this form. Trivially copyable, allocation-free.
class PreparedSegment {
 public:
  PreparedSegment(const Eigen::Vector3d& p, const Eigen::Vector3d& q);

  bool Intersect(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                 double* t, Eigen::Vector3d* barycentric) const;
  double DistanceSquared(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                         const Eigen::Vector3d& c, double* s, Eigen::Vector3d* barycentric) const;
  // DistanceSquared, or +infinity (s and barycentric untouched) when both ends of pq lie on one
  // side of the triangle's plane farther than `bound` [m] from it (then so is the triangle). The
  // tree's pruning test, folded in so the plane is computed once.
  double DistanceSquaredWithin(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                               const Eigen::Vector3d& c, double bound, double* s,
                               Eigen::Vector3d* barycentric) const;

  const Eigen::Vector3d& p() const { return p_; }
  const Eigen::Vector3d& q() const { return q_; }

 private:
  Eigen::Vector3d p_;
  Eigen::Vector3d q_;
  Eigen::Vector3d d_;  // q - p
  double d_p_;         // d·p, d·q
  double d_q_;
  int kx_ = 0;  // the frame's axes: kz is the longest component of q - p
  int ky_ = 1;
  int kz_ = 2;
  double sx_ = 0.0;  // shear (Woop et al. eq. 2): d[kx]/d[kz], d[ky]/d[kz], 1/d[kz]
  double sy_ = 0.0;
  double sz_ = 0.0;
  bool crosses_ = false;  // false for a zero-length or non-finite segment: it crosses nothing
};

}  // namespace somasim::contact
