#include "server/contact/triangle_queries.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>

namespace somasim::contact {
namespace {

using Eigen::Vector3d;

// a·b - c·d with an exact sign (and exactly 0 when the exact value is 0), the 2D edge function of
// the watertight test. The plain difference has error <= 3u (|ab| + |cd|) (u = 2^-53), so when it
// is larger than that its sign is right; otherwise Kahan's algorithm with FMA (relative error
// <= 2u: Jeannerod, Louvet and Muller 2013) decides. Swapping the roles of the two products
// negates the result bit for bit on the filter path, and keeps the exact sign on the other, which
// is what makes neighbouring triangles agree on their shared edge.
inline double DifferenceOfProducts(double a, double b, double c, double d) {
  const double ab = a * b;
  const double cd = c * d;
  const double r = ab - cd;
  if (std::abs(r) > 1e-15 * (std::abs(ab) + std::abs(cd))) return r;
  const double e = std::fma(-c, d, cd);  // cd - c·d exactly
  const double f = std::fma(a, b, -cd);
  return f + e;
}

// The closest points of segments p1q1 and p2q2: s along the first, u along the second, both in
// [0, 1]; returns the squared distance (Ericson §5.1.9, with exact-zero tests for degenerate
// segments and a relative test for parallel ones).
double SegmentSegmentDistanceSquared(const Vector3d& p1, const Vector3d& q1, const Vector3d& p2,
                                     const Vector3d& q2, double* s, double* u) {
  const Vector3d d1 = q1 - p1;
  const Vector3d d2 = q2 - p2;
  const Vector3d r = p1 - p2;
  const double a = d1.squaredNorm();
  const double e = d2.squaredNorm();
  const double f = d2.dot(r);
  double sc = 0.0;
  double uc = 0.0;
  if (a <= 0.0 && e <= 0.0) {
    // Both are points.
  } else if (a <= 0.0) {
    uc = std::clamp(f / e, 0.0, 1.0);
  } else {
    const double c = d1.dot(r);
    if (e <= 0.0) {
      sc = std::clamp(-c / a, 0.0, 1.0);
    } else {
      const double b = d1.dot(d2);
      const double denom = a * e - b * b;  // >= 0; ~0 when parallel: then any s works, take 0
      if (denom > 1e-14 * a * e) sc = std::clamp((b * f - c * e) / denom, 0.0, 1.0);
      uc = (b * sc + f) / e;
      if (uc < 0.0) {
        uc = 0.0;
        sc = std::clamp(-c / a, 0.0, 1.0);
      } else if (uc > 1.0) {
        uc = 1.0;
        sc = std::clamp((b - c) / a, 0.0, 1.0);
      }
    }
  }
  *s = sc;
  *u = uc;
  return ((p1 + sc * d1) - (p2 + uc * d2)).squaredNorm();
}

// Nearest point of segment ab to p as the parameter along ab, in [0, 1].
double ClosestOnSegment(const Vector3d& p, const Vector3d& a, const Vector3d& b) {
  const Vector3d ab = b - a;
  const double len2 = ab.squaredNorm();
  if (!(len2 > 0.0)) return 0.0;
  return std::clamp((p - a).dot(ab) / len2, 0.0, 1.0);
}

// The degenerate triangle's nearest point: the best of its three edges.
Vector3d ClosestPointOnEdges(const Vector3d& p, const Vector3d& a, const Vector3d& b,
                             const Vector3d& c) {
  const double tab = ClosestOnSegment(p, a, b);
  const double tbc = ClosestOnSegment(p, b, c);
  const double tca = ClosestOnSegment(p, c, a);
  const double dab = (p - (a + tab * (b - a))).squaredNorm();
  const double dbc = (p - (b + tbc * (c - b))).squaredNorm();
  const double dca = (p - (c + tca * (a - c))).squaredNorm();
  if (dab <= dbc && dab <= dca) return Vector3d(1.0 - tab, tab, 0.0);
  if (dbc <= dca) return Vector3d(0.0, 1.0 - tbc, tbc);
  return Vector3d(tca, 0.0, 1.0 - tca);
}

}  // namespace

Vector3d ClosestPointBarycentric(const Vector3d& p, const Vector3d& a, const Vector3d& b,
                                 const Vector3d& c) {
  const Vector3d ab = b - a;
  const Vector3d ac = c - a;
  // Ericson §5.1.5: find the Voronoi region of p by signs of dot products, cheapest first. The
  // vertex and edge regions stay right for degenerate triangles (their divisions are guarded);
  // only the face region needs a real triangle, so the degeneracy test waits until there.
  const Vector3d ap = p - a;
  const double d1 = ab.dot(ap);
  const double d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) return Vector3d(1.0, 0.0, 0.0);  // vertex a
  const Vector3d bp = p - b;
  const double d3 = ab.dot(bp);
  const double d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) return Vector3d(0.0, 1.0, 0.0);  // vertex b
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {  // edge ab (d1 - d3 > 0 here)
    const double v = d1 > 0.0 ? std::clamp(d1 / (d1 - d3), 0.0, 1.0) : 0.0;
    return Vector3d(1.0 - v, v, 0.0);
  }
  const Vector3d cp = p - c;
  const double d5 = ab.dot(cp);
  const double d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) return Vector3d(0.0, 0.0, 1.0);  // vertex c
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {  // edge ac
    const double w = d2 > 0.0 ? std::clamp(d2 / (d2 - d6), 0.0, 1.0) : 0.0;
    return Vector3d(1.0 - w, 0.0, w);
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {  // edge bc
    const double w =
        d4 - d3 > 0.0 ? std::clamp((d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0, 1.0) : 0.0;
    return Vector3d(0.0, 1.0 - w, w);
  }
  // Zero or nearly zero area (sin of the angle at a below 1e-10): the face region's division is
  // meaningless; the nearest point is on an edge.
  if (!(ab.cross(ac).squaredNorm() > 1e-20 * ab.squaredNorm() * ac.squaredNorm())) {
    return ClosestPointOnEdges(p, a, b, c);
  }
  // Face: weights proportional to the sub-areas; clamp rounding noise so each stays in [0, 1].
  const double wa = std::max(va, 0.0);
  const double wb = std::max(vb, 0.0);
  const double wc = std::max(vc, 0.0);
  const double sum = wa + wb + wc;
  if (!(sum > 0.0) || !std::isfinite(sum)) return ClosestPointOnEdges(p, a, b, c);
  return Vector3d(wa / sum, wb / sum, wc / sum);
}

double PointTriangleDistanceSquared(const Vector3d& p, const Vector3d& a, const Vector3d& b,
                                    const Vector3d& c, Vector3d* barycentric) {
  const Vector3d w = ClosestPointBarycentric(p, a, b, c);
  *barycentric = w;
  return (p - (w.x() * a + w.y() * b + w.z() * c)).squaredNorm();
}

PreparedSegment::PreparedSegment(const Vector3d& p, const Vector3d& q)
    : p_(p), q_(q), d_(q - p), d_p_(d_.dot(p)), d_q_(d_.dot(q)) {
  const Vector3d& d = d_;
  if (!p.allFinite() || !q.allFinite() || !d.allFinite()) return;
  // Woop et al. 2013 §3: kz = the dominant axis of the direction, so the shear is bounded.
  const Vector3d ad = d.cwiseAbs();
  kz_ = ad.x() >= ad.y() ? (ad.x() >= ad.z() ? 0 : 2) : (ad.y() >= ad.z() ? 1 : 2);
  kx_ = (kz_ + 1) % 3;
  ky_ = (kx_ + 1) % 3;
  if (d[kz_] == 0.0) return;  // a point: crosses nothing
  sx_ = d[kx_] / d[kz_];
  sy_ = d[ky_] / d[kz_];
  sz_ = 1.0 / d[kz_];
  crosses_ = true;
}

bool PreparedSegment::Intersect(const Vector3d& a, const Vector3d& b, const Vector3d& c, double* t,
                                Vector3d* barycentric) const {
  if (!crosses_) return false;
  // Vertices relative to p, sheared so that pq runs along the third axis (Woop et al. eq. 2-3).
  const Vector3d pa = a - p_;
  const Vector3d pb = b - p_;
  const Vector3d pc = c - p_;
  const double ax = pa[kx_] - sx_ * pa[kz_];
  const double ay = pa[ky_] - sy_ * pa[kz_];
  const double bx = pb[kx_] - sx_ * pb[kz_];
  const double by = pb[ky_] - sy_ * pb[kz_];
  const double cx = pc[kx_] - sx_ * pc[kz_];
  const double cy = pc[ky_] - sy_ * pc[kz_];
  // 2D edge functions (eq. 4) with exact signs: u belongs to edge bc (the weight of a), etc.
  const double u = DifferenceOfProducts(cx, by, cy, bx);
  const double v = DifferenceOfProducts(ax, cy, ay, cx);
  const double w = DifferenceOfProducts(bx, ay, by, ax);
  // Inclusive: zero (on an edge) agrees with either sign, so edges and corners count.
  if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) return false;
  const double det = u + v + w;
  if (det == 0.0) return false;  // seen edge-on: pq lies in the plane (or the triangle is flat)
  // Scaled distance along pq (eq. 6); the crossing is inside the segment when 0 <= T/det <= 1.
  const double az = sz_ * pa[kz_];
  const double bz = sz_ * pb[kz_];
  const double cz = sz_ * pc[kz_];
  const double tt = u * az + v * bz + w * cz;
  if (det > 0.0 ? (tt < 0.0 || tt > det) : (tt > 0.0 || tt < det)) return false;
  const double inv = 1.0 / det;
  *t = std::clamp(tt * inv, 0.0, 1.0);
  *barycentric = Vector3d(u * inv, v * inv, w * inv);
  return true;
}

double PreparedSegment::DistanceSquared(const Vector3d& a, const Vector3d& b, const Vector3d& c,
                                        double* s, Vector3d* barycentric) const {
  return DistanceSquaredWithin(a, b, c, std::numeric_limits<double>::infinity(), s, barycentric);
}

double PreparedSegment::DistanceSquaredWithin(const Vector3d& a, const Vector3d& b,
                                              const Vector3d& c, double bound, double* s,
                                              Vector3d* barycentric) const {
  const Vector3d n = (b - a).cross(c - a);
  const double dp = n.dot(p_ - a);
  const double dq = n.dot(q_ - a);
  // Both ends on one side of the plane, farther than `bound`: so is every point of the triangle.
  if (dp * dq > 0.0) {
    const double m = std::min(std::abs(dp), std::abs(dq));
    if (m * m > bound * bound * n.squaredNorm()) return std::numeric_limits<double>::infinity();
  }
  // When no point of the triangle lies ahead of p along d (d·(y - p) <= 0 at its three
  // vertices, hence everywhere on it), p is the segment's nearest point to every point of the
  // triangle, so the answer is p's distance (likewise q when none lies behind q): the common case
  // of a tool shaft pointing away from the surface, one closest-point query instead of six.
  const double da = d_.dot(a);
  const double db = d_.dot(b);
  const double dc = d_.dot(c);
  if (da <= d_p_ && db <= d_p_ && dc <= d_p_) {
    *s = 0.0;
    return PointTriangleDistanceSquared(p_, a, b, c, barycentric);
  }
  if (da >= d_q_ && db >= d_q_ && dc >= d_q_) {
    *s = 1.0;
    return PointTriangleDistanceSquared(q_, a, b, c, barycentric);
  }
  // Both ends strictly on one side of the plane: every point of the triangle is at least as far
  // as the plane, min(|dp|, |dq|) / |n|, so when the nearer end's nearest point is inside the
  // face (not on an edge), that is the answer (the common case of a tool above a surface). They
  // cannot cross then, so the crossing test is skipped too.
  Vector3d w;
  double best = 0.0;
  if (dp * dq > 0.0) {
    const bool p_nearer = std::abs(dp) <= std::abs(dq);
    best = PointTriangleDistanceSquared(p_nearer ? p_ : q_, a, b, c, &w);
    *s = p_nearer ? 0.0 : 1.0;
    *barycentric = w;
    if (w.minCoeff() > 0.0) return best;
    const double other = PointTriangleDistanceSquared(p_nearer ? q_ : p_, a, b, c, &w);
    if (other < best) {
      best = other;
      *s = p_nearer ? 1.0 : 0.0;
      *barycentric = w;
    }
  } else {
    double t = 0.0;
    if (Intersect(a, b, c, &t, &w)) {
      *s = t;
      *barycentric = w;
      return 0.0;
    }
    // Apart: the closest pair has an end of pq or lies on an edge of the triangle.
    best = PointTriangleDistanceSquared(p_, a, b, c, &w);
    *s = 0.0;
    *barycentric = w;
    const double d_q = PointTriangleDistanceSquared(q_, a, b, c, &w);
    if (d_q < best) {
      best = d_q;
      *s = 1.0;
      *barycentric = w;
    }
  }
  double se = 0.0;
  double ue = 0.0;
  const double dab = SegmentSegmentDistanceSquared(p_, q_, a, b, &se, &ue);
  if (dab < best) {
    best = dab;
    *s = se;
    *barycentric = Vector3d(1.0 - ue, ue, 0.0);
  }
  const double dbc = SegmentSegmentDistanceSquared(p_, q_, b, c, &se, &ue);
  if (dbc < best) {
    best = dbc;
    *s = se;
    *barycentric = Vector3d(0.0, 1.0 - ue, ue);
  }
  const double dca = SegmentSegmentDistanceSquared(p_, q_, c, a, &se, &ue);
  if (dca < best) {
    best = dca;
    *s = se;
    *barycentric = Vector3d(ue, 0.0, 1.0 - ue);
  }
  return best;
}

bool SegmentTriangleIntersection(const Vector3d& p, const Vector3d& q, const Vector3d& a,
                                 const Vector3d& b, const Vector3d& c, double* t,
                                 Vector3d* barycentric) {
  return PreparedSegment(p, q).Intersect(a, b, c, t, barycentric);
}

double SegmentTriangleDistanceSquared(const Vector3d& p, const Vector3d& q, const Vector3d& a,
                                      const Vector3d& b, const Vector3d& c, double* s,
                                      Vector3d* barycentric) {
  return PreparedSegment(p, q).DistanceSquared(a, b, c, s, barycentric);
}

Eigen::Vector3d ClosestPointOnSegment(const Eigen::Vector3d& x, const Eigen::Vector3d& p,
                                      const Eigen::Vector3d& q) {
  const Eigen::Vector3d d = q - p;
  const double length2 = d.squaredNorm();
  const double s = length2 > 0.0 ? std::clamp((x - p).dot(d) / length2, 0.0, 1.0) : 0.0;
  return p + s * d;
}

}  // namespace somasim::contact
