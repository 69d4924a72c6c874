// The cutter's relocation (Step's stage 3, seed 003 eq. 1 and 2): the severed tetrahedra's
// vertices moved onto the sweep or the boundary of the swept region, each move guarded so that no
// alive tetrahedron is inverted.
#include <algorithm>
#include <cmath>

#include "common/mesh/geometry.h"
#include "server/cutting/tet_cutter.h"

namespace somasim::cutting {

namespace {

using Eigen::Vector3d;

// The point of segment ab nearest to x.
Vector3d ClosestOnSegment(const Vector3d& x, const Vector3d& a, const Vector3d& b) {
  const Vector3d d = b - a;
  const double dd = d.squaredNorm();
  if (dd <= 0.0) return a;
  const double s = std::clamp((x - a).dot(d) / dd, 0.0, 1.0);
  return a + s * d;
}

// The point of triangle (a, b, c) nearest to p (Ericson, Real-Time Collision Detection 5.1.5).
Vector3d ClosestOnTriangle(const Vector3d& p, const Vector3d& a, const Vector3d& b,
                           const Vector3d& c) {
  const Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) return a;
  const Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return a + (d1 / (d1 - d3)) * ab;
  const Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return a + (d2 / (d2 - d6)) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b);
  }
  const double denom = 1.0 / (va + vb + vc);
  return a + ab * (vb * denom) + ac * (vc * denom);
}

// The parameter s of the line x0 + s d nearest to segment ab (d unit).
double LineParameterNearestSegment(const Vector3d& x0, const Vector3d& d, const Vector3d& a,
                                   const Vector3d& b) {
  // Minimise |x0 + s d − (a + u (b − a))|² over s and u ∈ [0, 1]: for fixed u, s = d·(a_u − x0).
  const Vector3d e = b - a;
  const double ee = e.squaredNorm();
  double u = 0.0;
  if (ee > 0.0) {
    // The unconstrained optimum in u, with s eliminated: minimise |P (a − x0 + u e)|², P the
    // projector orthogonal to d.
    const Vector3d pe = e - d.dot(e) * d;
    const Vector3d pa = (a - x0) - d.dot(a - x0) * d;
    const double pee = pe.squaredNorm();
    u = pee > 1e-30 ? std::clamp(-pa.dot(pe) / pee, 0.0, 1.0) : 0.0;
  }
  return d.dot(a + u * e - x0);
}

}  // namespace

// The vertices of the severed tetrahedra (the first severed_count of removed_), in ascending
// order, each moved by Relocate. Guard (beyond the seed, which is silent on it): a move never
// takes an alive tetrahedron below settings_.min_volume_fraction of its signed volume before the
// step; a move that would is shortened (halved up to 8 times, else dropped). So no element is
// ever inverted. moved_ keeps the vertices that moved.
void TetCutter::RelocateVertices(const models::SweptQuad& sweep, const Vector3d& n,
                                 size_t severed_count, mesh::Points* positions,
                                 CutStepResult* result) {
  mesh::Points& x = *positions;
  if (++epoch_ == 0) {
    std::fill(stamp_.begin(), stamp_.end(), 0);
    epoch_ = 1;
  }
  for (size_t i = 0; i < severed_count; ++i) {
    for (int k = 0; k < 4; ++k) {
      const int32_t v = tet_node(k, removed_[i]);
      if (stamp_[static_cast<size_t>(v)] == epoch_) continue;
      stamp_[static_cast<size_t>(v)] = epoch_;
      moved_[moved_count_++] = v;
    }
  }
  std::sort(moved_.begin(), moved_.begin() + static_cast<std::ptrdiff_t>(moved_count_));
  // The alive tets around the moving vertices, their volumes before the step.
  for (size_t i = 0; i < moved_count_; ++i) {
    const int32_t v = moved_[i];
    for (int32_t j = node_tet_offsets_[static_cast<size_t>(v)];
         j < node_tet_offsets_[static_cast<size_t>(v) + 1]; ++j) {
      const int32_t t = node_tet_entries_[static_cast<size_t>(j)];
      volume_before_[static_cast<size_t>(t)] =
          mesh::TetSignedVolume(x.col(tet_node(0, t)), x.col(tet_node(1, t)), x.col(tet_node(2, t)),
                                x.col(tet_node(3, t)));
    }
  }
  size_t kept_moves = 0;
  for (size_t i = 0; i < moved_count_; ++i) {
    const int32_t v = moved_[i];
    const Vector3d from = x.col(v);
    const Vector3d target = Relocate(v, from, n, sweep, x);
    if (!target.allFinite()) continue;
    bool ok = false;
    int attempt = 0;
    for (double fraction = 1.0; attempt <= 8 && !ok; ++attempt, fraction *= 0.5) {
      x.col(v) = from + fraction * (target - from);
      ok = true;
      for (int32_t j = node_tet_offsets_[static_cast<size_t>(v)];
           ok && j < node_tet_offsets_[static_cast<size_t>(v) + 1]; ++j) {
        const int32_t t = node_tet_entries_[static_cast<size_t>(j)];
        if (alive_[static_cast<size_t>(t)] == 0) continue;
        const double volume = mesh::TetSignedVolume(x.col(tet_node(0, t)), x.col(tet_node(1, t)),
                                                    x.col(tet_node(2, t)), x.col(tet_node(3, t)));
        ok = volume >= settings_.min_volume_fraction * volume_before_[static_cast<size_t>(t)];
      }
    }
    if (!ok) x.col(v) = from;
    if (!ok || attempt > 1) ++result->shortened;
    if (ok && (x.col(v) - from).squaredNorm() > 0.0) moved_[kept_moves++] = v;
  }
  moved_count_ = kept_moves;
  result->relocated = static_cast<int32_t>(moved_count_);
}

bool TetCutter::InsideSwept(const Vector3d& x, double tolerance) const {
  const int32_t n = std::min(num_quads_, kHistory);
  for (int32_t i = 0; i < n; ++i) {
    const models::SweptQuad& s = quads_[static_cast<size_t>((num_quads_ - 1 - i) % kHistory)];
    if ((ClosestOnTriangle(x, s.p0, s.q0, s.q1) - x).norm() <= tolerance) return true;
    if ((ClosestOnTriangle(x, s.p0, s.q1, s.p1) - x).norm() <= tolerance) return true;
  }
  return false;
}

Vector3d TetCutter::SurfaceNormal(int32_t node, const mesh::Points& x) const {
  Vector3d m = Vector3d::Zero();
  for (int32_t i = node_tet_offsets_[static_cast<size_t>(node)];
       i < node_tet_offsets_[static_cast<size_t>(node) + 1]; ++i) {
    const int32_t t = node_tet_entries_[static_cast<size_t>(i)];
    for (int f = 0; f < 4; ++f) {
      if (surface_.neighbour(f, t) != -1) continue;  // the original outer surface only
      const int a = tet_node(kTetFaces[f][0], t), b = tet_node(kTetFaces[f][1], t),
                c = tet_node(kTetFaces[f][2], t);
      if (a != node && b != node && c != node) continue;
      m += (x.col(b) - x.col(a)).cross(x.col(c) - x.col(a));  // 2 × area × outward normal
    }
  }
  const double norm = m.norm();
  return norm > 0.0 ? Vector3d(m / norm) : Vector3d::Zero();
}

// Where vertex `node`, at v, goes (seed 003 eq. 1):
//   interior vertex  v ← v − {n·(v − p_t)} n, n the sweep's unit normal;
//   surface vertex   (on the original outer surface) onto the line where its tangent plane
//                    (normal: the area-weighted normal of its boundary faces) meets the
//                    sweep's plane, at the point nearest to v (seed 003 §3: keeps the
//                    outline); when the two planes are nearly parallel (|n × m| < 0.2) it
//                    does not move;
// then, when the new position lies outside every sweep quad of this cut (the last kHistory
// kept), onto the nearest boundary segment of the swept region when that is the tip's path
// {p_k, p_k−1} (seed 003 eq. 2; a surface vertex stays on its line, at the point of the line
// nearest to that segment). When the blade p_t q_t is nearer (the vertex is ahead of the blade)
// it stays: projected onto the blade's line it would join the two sides of the wound behind the
// blade for good, as no vertex may be added to split them (the seed's eq. 2 there, a deliberate
// departure).
Vector3d TetCutter::Relocate(int32_t node, const Vector3d& v, const Vector3d& n,
                             const models::SweptQuad& sweep, const mesh::Points& x) const {
  const double scale = std::max((sweep.q1 - sweep.p1).norm(), (sweep.p1 - sweep.p0).norm());
  const double tolerance = 1e-9 * std::max(scale, 1e-12);
  // The boundary segment of the swept region nearest to a point: the tip's path or the blade.
  // True when it is the tip's path (the bottom of the wound, where both sides meet); false when
  // the blade itself is nearer: a vertex ahead of the blade is left where it is until the blade
  // has passed it (projected onto the blade's line, it would join the two sides of the wound
  // behind the blade for good, since no vertex may be added to split it).
  const auto nearest_boundary = [&](const Vector3d& y, Vector3d* a, Vector3d* b) {
    return NearestIsTipPath(y, sweep, a, b);
  };
  if (on_surface_[static_cast<size_t>(node)] == 0) {
    // Seed 003 eq. 1: onto the sweep's plane; eq. 2: outside the swept region, onto its boundary.
    Vector3d y = v - n.dot(v - sweep.p1) * n;
    if (!InsideSwept(y, tolerance)) {
      Vector3d a, b;
      if (!nearest_boundary(y, &a, &b)) return v;
      y = ClosestOnSegment(y, a, b);
    }
    return y;
  }
  // A surface vertex: on the line where its tangent plane meets the sweep's plane.
  const Vector3d m = SurfaceNormal(node, x);
  const Vector3d d = n.cross(m);
  if (!(d.norm() >= 0.2)) return v;  // the planes nearly parallel: it stays
  const Vector3d u = d.normalized();
  // The line's point nearest to v: x0 = v − α n − β m with n·x0 = n·p, m·x0 = m·v.
  const double nm = n.dot(m);
  const double det = 1.0 - nm * nm;
  const double r = n.dot(v - sweep.p1);
  const double alpha = r / det;
  const double beta = -nm * r / det;
  Vector3d x0 = v - alpha * n - beta * m;
  if (InsideSwept(x0, tolerance)) return x0;
  Vector3d a, b;
  if (!nearest_boundary(x0, &a, &b)) return v;
  return x0 + LineParameterNearestSegment(x0, u, a, b) * u;
}

bool TetCutter::NearestIsTipPath(const Vector3d& y, const models::SweptQuad& sweep, Vector3d* a,
                                 Vector3d* b) const {
  double best = (ClosestOnSegment(y, sweep.p1, sweep.q1) - y).squaredNorm();
  bool tip = false;
  const int32_t count = std::min(num_quads_, kHistory);
  for (int32_t i = 0; i < count; ++i) {
    const models::SweptQuad& s = quads_[static_cast<size_t>((num_quads_ - 1 - i) % kHistory)];
    const double d = (ClosestOnSegment(y, s.p0, s.p1) - y).squaredNorm();
    if (d < best) {
      best = d;
      *a = s.p0;
      *b = s.p1;
      tip = true;
    }
  }
  return tip;
}

}  // namespace somasim::cutting
