#include "server/cutting/tet_cutter.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"

namespace somasim::cutting {

namespace {

using Eigen::Vector3d;

constexpr int kTetEdges[6][2] = {{0, 1}, {0, 2}, {0, 3}, {1, 2}, {1, 3}, {2, 3}};

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

// Whether edge ab passes from one side of triangle (t0, t1, t2) to the other through it: both
// ends off its plane by more than `tolerance` [m], on opposite sides, the crossing point within
// the triangle. An end on the plane does not count: the vertices seed 003 relocated onto the
// sweep (or its boundary) lie there, and the edges joining them to their own side separate
// nothing.
bool Crosses(const Vector3d& a, const Vector3d& b, const Vector3d& t0, const Vector3d& t1,
             const Vector3d& t2, double tolerance) {
  const Vector3d normal = (t1 - t0).cross(t2 - t0);
  const double norm = normal.norm();
  if (!(norm > 0.0)) return false;
  const Vector3d m = normal / norm;
  const double da = m.dot(a - t0), db = m.dot(b - t0);
  if (!((da > tolerance && db < -tolerance) || (da < -tolerance && db > tolerance))) return false;
  const Vector3d y = a + (da / (da - db)) * (b - a);
  // Inside the triangle: the same side of each edge as the normal says.
  return (t1 - t0).cross(y - t0).dot(m) >= 0.0 && (t2 - t1).cross(y - t1).dot(m) >= 0.0 &&
         (t0 - t2).cross(y - t2).dot(m) >= 0.0;
}

// The sweep's unit normal (the quad's diagonals' cross product), zero when it has no area.
Vector3d SweepNormal(const models::SweptQuad& s) {
  const Vector3d n = (s.q1 - s.p0).cross(s.p1 - s.q0);
  const double scale = std::max(
      {(s.q1 - s.p0).squaredNorm(), (s.p1 - s.q0).squaredNorm(), (s.q0 - s.p0).squaredNorm()});
  if (!(n.norm() > 1e-9 * scale) || scale <= 0.0) return Vector3d::Zero();
  return n.normalized();
}

}  // namespace

TetCutter::TetCutter(const mesh::Tetrahedra& tets, const mesh::Points& positions,
                     const CutSettings& settings)
    : tets_(tets), num_nodes_(static_cast<int32_t>(positions.cols())), settings_(settings) {
  if (!(settings_.min_volume_fraction > 0.0 && settings_.min_volume_fraction < 1.0)) {
    throw std::invalid_argument("cutter: min_volume_fraction must be within (0, 1)");
  }
  const auto num_tets = static_cast<size_t>(tets_.cols());
  for (Eigen::Index t = 0; t < tets_.cols(); ++t) {
    for (int k = 0; k < 4; ++k) {
      if (tets_(k, t) < 0 || tets_(k, t) >= num_nodes_) {
        throw std::invalid_argument("cutter: tetrahedron " + std::to_string(t) + " has node " +
                                    std::to_string(tets_(k, t)) + ", outside 0.." +
                                    std::to_string(num_nodes_ - 1));
      }
    }
  }
  alive_.assign(num_tets, 1);
  num_alive_ = static_cast<int32_t>(num_tets);
  const mesh::Adjacency adjacency = mesh::NodeToTets(num_nodes_, tets_);
  node_tet_offsets_ = adjacency.offsets;
  node_tet_entries_ = adjacency.entries;
  node_alive_.resize(static_cast<size_t>(num_nodes_));
  for (int32_t v = 0; v < num_nodes_; ++v)
    node_alive_[static_cast<size_t>(v)] = adjacency.Count(static_cast<size_t>(v));
  surface_ = CutSurface(num_nodes_, tets_);
  on_surface_.assign(static_cast<size_t>(num_nodes_), 0);
  for (Eigen::Index t = 0; t < tets_.cols(); ++t) {
    for (int f = 0; f < 4; ++f) {
      if (surface_.neighbour(f, t) != -1) continue;
      for (int k = 0; k < 3; ++k) on_surface_[static_cast<size_t>(tets_(kTetFaces[f][k], t))] = 1;
    }
  }
  cut_.reserve(num_tets);
  pending_.resize(num_tets);
  pending_mark_.assign(num_tets, 0);
  tet_stamp_.assign(num_tets, 0);
  removed_.resize(4 * num_tets);  // a tetrahedron may be removed, put back, removed again
  moved_.resize(static_cast<size_t>(num_nodes_));
  stamp_.assign(static_cast<size_t>(num_nodes_), 0);
  losing_.assign(static_cast<size_t>(num_nodes_), 0);
  volume_before_.assign(num_tets, 0.0);
}

void TetCutter::BeginIncision() {
  num_quads_ = 0;
  pending_count_ = 0;
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
      const int a = tets_(kTetFaces[f][0], t), b = tets_(kTetFaces[f][1], t),
                c = tets_(kTetFaces[f][2], t);
      if (a != node && b != node && c != node) continue;
      m += (x.col(b) - x.col(a)).cross(x.col(c) - x.col(a));  // 2 × area × outward normal
    }
  }
  const double norm = m.norm();
  return norm > 0.0 ? Vector3d(m / norm) : Vector3d::Zero();
}

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

bool TetCutter::Remove(int32_t t) {
  if (removed_count_ == removed_.size()) return false;  // this step's list is full
  alive_[static_cast<size_t>(t)] = 0;
  for (int k = 0; k < 4; ++k) --node_alive_[static_cast<size_t>(tets_(k, t))];
  removed_[removed_count_++] = t;
  return true;
}

bool TetCutter::SplitPinch(int32_t v, int32_t w, bool dry_run) {
  // The alive tetrahedra around v (and w, for an edge).
  int32_t m = 0;
  for (int32_t j = node_tet_offsets_[static_cast<size_t>(v)];
       j < node_tet_offsets_[static_cast<size_t>(v) + 1]; ++j) {
    const int32_t t = node_tet_entries_[static_cast<size_t>(j)];
    if (alive_[static_cast<size_t>(t)] == 0) continue;
    if (w >= 0 && tets_(0, t) != w && tets_(1, t) != w && tets_(2, t) != w && tets_(3, t) != w) {
      continue;
    }
    if (m == kMaxFan) return false;  // a fan this large: left alone
    fan_[static_cast<size_t>(m)] = t;
    group_[static_cast<size_t>(m)] = m;
    ++m;
  }
  if (m < 2) return false;
  const auto find = [&](int32_t i) {
    while (group_[static_cast<size_t>(i)] != i) i = group_[static_cast<size_t>(i)];
    return i;
  };
  for (int32_t i = 0; i < m; ++i) {
    const int32_t t = fan_[static_cast<size_t>(i)];
    for (int f = 0; f < 4; ++f) {
      // Only faces holding v (and w): the face opposite corner f holds every other corner.
      if (tets_(f, t) == v || (w >= 0 && tets_(f, t) == w)) continue;
      const int32_t nb = surface_.neighbour(f, t);
      if (nb < 0 || alive_[static_cast<size_t>(nb)] == 0) continue;
      for (int32_t j = 0; j < m; ++j) {
        if (fan_[static_cast<size_t>(j)] != nb) continue;
        const int32_t a = find(i), b = find(j);
        if (a != b) group_[static_cast<size_t>(std::max(a, b))] = std::min(a, b);
      }
    }
  }
  // One group stays, the largest whose keeping lets all the others' tetrahedra go without
  // orphaning a vertex (all or none: a half-removed group would leave the pinch).
  int32_t roots[kMaxFan];
  int32_t sizes[kMaxFan];
  int32_t groups = 0;
  for (int32_t i = 0; i < m; ++i) {
    if (find(i) != i) continue;
    roots[groups] = i;
    sizes[groups] = 0;
    for (int32_t j = 0; j < m; ++j) sizes[groups] += find(j) == i ? 1 : 0;
    ++groups;
  }
  if (groups < 2) return false;
  if (dry_run) return true;
  for (int32_t tries = 0; tries < groups; ++tries) {
    int32_t pick = -1;
    for (int32_t g = 0; g < groups; ++g) {
      if (sizes[g] >= 0 && (pick < 0 || sizes[g] > sizes[pick])) pick = g;
    }
    const int32_t keep = roots[pick];
    sizes[pick] = -1;  // tried
    // Every other group's tetrahedra go, all or none.
    int32_t count = 0;
    for (int32_t i = 0; i < m; ++i) {
      if (find(i) != keep) chosen_[static_cast<size_t>(count++)] = fan_[static_cast<size_t>(i)];
    }
    if (!RemoveAllOrNone(count)) continue;
    return true;
  }
  return false;  // every choice would orphan a vertex: the pinch stays (counted by the caller)
}

bool TetCutter::RemoveAllOrNone(int32_t count) {
  // Would removing them all orphan a vertex? Count what each vertex would lose.
  bool orphans = false;
  for (int32_t i = 0; i < count; ++i) {
    const int32_t t = chosen_[static_cast<size_t>(i)];
    for (int k = 0; k < 4; ++k) ++losing_[static_cast<size_t>(tets_(k, t))];
  }
  for (int32_t i = 0; i < count; ++i) {
    const int32_t t = chosen_[static_cast<size_t>(i)];
    for (int k = 0; k < 4; ++k) {
      const auto node = static_cast<size_t>(tets_(k, t));
      orphans = orphans || losing_[node] >= node_alive_[node];
    }
  }
  for (int32_t i = 0; i < count; ++i) {
    const int32_t t = chosen_[static_cast<size_t>(i)];
    for (int k = 0; k < 4; ++k) losing_[static_cast<size_t>(tets_(k, t))] = 0;
  }
  if (orphans) return false;
  for (int32_t i = 0; i < count; ++i) {
    if (!Remove(chosen_[static_cast<size_t>(i)])) break;
  }
  return true;
}

bool TetCutter::Pinched(int32_t v) { return SplitPinch(v, -1, true) || SplitLink(v, true); }

bool TetCutter::RestoreAround(int32_t v) {
  for (size_t i = 0; i < removed_count_; ++i) {
    const int32_t t = removed_[i];
    if (alive_[static_cast<size_t>(t)] != 0) continue;
    if (tets_(0, t) != v && tets_(1, t) != v && tets_(2, t) != v && tets_(3, t) != v) continue;
    alive_[static_cast<size_t>(t)] = 1;
    for (int k = 0; k < 4; ++k) ++node_alive_[static_cast<size_t>(tets_(k, t))];
    if (!Pinched(v)) return true;
    alive_[static_cast<size_t>(t)] = 0;
    for (int k = 0; k < 4; ++k) --node_alive_[static_cast<size_t>(tets_(k, t))];
  }
  // No single one: all of them around v (v as it was before this step, when it was sound).
  bool any = false;
  for (size_t i = 0; i < removed_count_; ++i) {
    const int32_t t = removed_[i];
    if (alive_[static_cast<size_t>(t)] != 0) continue;
    if (tets_(0, t) != v && tets_(1, t) != v && tets_(2, t) != v && tets_(3, t) != v) continue;
    alive_[static_cast<size_t>(t)] = 1;
    for (int k = 0; k < 4; ++k) ++node_alive_[static_cast<size_t>(tets_(k, t))];
    any = true;
  }
  return any && !Pinched(v);
}

bool TetCutter::SplitLink(int32_t v, bool dry_run) {
  // The alive tetrahedra around v, and the boundary triangles holding v: each gives an edge
  // (a, b) of v's link on the surface. Their connected components are v's fans.
  int32_t m = 0;
  for (int32_t j = node_tet_offsets_[static_cast<size_t>(v)];
       j < node_tet_offsets_[static_cast<size_t>(v) + 1]; ++j) {
    const int32_t t = node_tet_entries_[static_cast<size_t>(j)];
    if (alive_[static_cast<size_t>(t)] == 0) continue;
    if (m == kMaxFan) return false;
    fan_[static_cast<size_t>(m++)] = t;
  }
  int32_t nv = 0;  // link vertices in link_
  const auto link_index = [&](int32_t node) {
    for (int32_t i = 0; i < nv; ++i) {
      if (link_[static_cast<size_t>(i)] == node) return i;
    }
    link_[static_cast<size_t>(nv)] = node;
    link_parent_[static_cast<size_t>(nv)] = nv;
    return nv++;
  };
  const auto find = [&](int32_t i) {
    while (link_parent_[static_cast<size_t>(i)] != i) i = link_parent_[static_cast<size_t>(i)];
    return i;
  };
  for (int32_t i = 0; i < m; ++i) {
    const int32_t t = fan_[static_cast<size_t>(i)];
    for (int f = 0; f < 4; ++f) {
      if (tets_(f, t) == v) continue;  // the face opposite v does not hold it
      const int32_t nb = surface_.neighbour(f, t);
      if (nb >= 0 && alive_[static_cast<size_t>(nb)] != 0) continue;
      int32_t ends[2];
      int32_t e = 0;
      for (int k = 0; k < 3; ++k) {
        const int32_t node = tets_(kTetFaces[f][k], t);
        if (node != v) ends[e++] = node;
      }
      if (nv + 2 > 3 * kMaxFan) return false;
      const int32_t a = find(link_index(ends[0])), b = find(link_index(ends[1]));
      if (a != b) link_parent_[static_cast<size_t>(std::max(a, b))] = std::min(a, b);
    }
  }
  int32_t fans = 0;
  int32_t first = -1;
  for (int32_t i = 0; i < nv; ++i) {
    if (find(i) != i) continue;
    ++fans;
    if (first < 0) first = i;
  }
  if (fans < 2) return false;
  if (dry_run) return true;
  // Which fan each tetrahedron's boundary triangles at v belong to: 1 the first, 2 another.
  for (int32_t i = 0; i < m; ++i) {
    const int32_t t = fan_[static_cast<size_t>(i)];
    int32_t touches = 0;
    for (int f = 0; f < 4; ++f) {
      if (tets_(f, t) == v) continue;
      const int32_t nb = surface_.neighbour(f, t);
      if (nb >= 0 && alive_[static_cast<size_t>(nb)] != 0) continue;
      const int32_t node =
          tets_(kTetFaces[f][0], t) != v ? tets_(kTetFaces[f][0], t) : tets_(kTetFaces[f][1], t);
      touches |= find(link_index(node)) == first ? 1 : 2;
    }
    group_[static_cast<size_t>(i)] = touches;
    dist_[static_cast<size_t>(i)] = (touches & 1) != 0 ? 0 : -1;
    parent_[static_cast<size_t>(i)] = -1;
  }
  // The shortest chain of tetrahedra (across faces holding v) from the first fan to another:
  // removing it joins the fans into one.
  int32_t goal = -1;
  for (int32_t i = 0; i < m && goal < 0; ++i) {
    if (dist_[static_cast<size_t>(i)] == 0 && (group_[static_cast<size_t>(i)] & 2) != 0) goal = i;
  }
  for (int32_t d = 0; goal < 0 && d < m; ++d) {
    bool grew = false;
    for (int32_t i = 0; i < m && goal < 0; ++i) {
      if (dist_[static_cast<size_t>(i)] != d) continue;
      const int32_t t = fan_[static_cast<size_t>(i)];
      for (int f = 0; f < 4 && goal < 0; ++f) {
        if (tets_(f, t) == v) continue;
        const int32_t nb = surface_.neighbour(f, t);
        if (nb < 0 || alive_[static_cast<size_t>(nb)] == 0) continue;
        for (int32_t j = 0; j < m; ++j) {
          if (fan_[static_cast<size_t>(j)] != nb || dist_[static_cast<size_t>(j)] >= 0) continue;
          dist_[static_cast<size_t>(j)] = d + 1;
          parent_[static_cast<size_t>(j)] = i;
          grew = true;
          if ((group_[static_cast<size_t>(j)] & 2) != 0) goal = j;
        }
      }
    }
    if (!grew) break;
  }
  if (goal < 0) return false;
  // All of the chain or none.
  int32_t count = 0;
  for (int32_t i = goal; i >= 0; i = parent_[static_cast<size_t>(i)]) {
    chosen_[static_cast<size_t>(count++)] = fan_[static_cast<size_t>(i)];
  }
  return RemoveAllOrNone(count);
}

CutStepResult TetCutter::Step(const models::SweptQuad& sweep, mesh::Points* positions) {
  CutStepResult result;
  removed_count_ = 0;
  moved_count_ = 0;
  if (!sweep.AllFinite() || positions->cols() != num_nodes_) return result;
  const Vector3d n = SweepNormal(sweep);
  if (n.isZero()) return result;
  quads_[static_cast<size_t>(num_quads_ % kHistory)] = sweep;
  ++num_quads_;
  mesh::Points& x = *positions;

  // 1. The cut set, after a bounding-box cull: tetrahedra the current quad crosses, and those
  // crossed before but not yet severed (pending).
  Vector3d lo = sweep.p0.cwiseMin(sweep.q0).cwiseMin(sweep.p1).cwiseMin(sweep.q1);
  Vector3d hi = sweep.p0.cwiseMax(sweep.q0).cwiseMax(sweep.p1).cwiseMax(sweep.q1);
  // Vertices within this of the sweep's plane lie on it (relocated there before) [m].
  const double tolerance = 1e-9 * (hi - lo).norm();
  const double inside_tolerance = 1e-6 * (sweep.q1 - sweep.p1).norm();
  ++pending_epoch_;
  cut_.clear();
  for (size_t i = 0; i < pending_count_; ++i) {
    const int32_t t = pending_[i];
    if (alive_[static_cast<size_t>(t)] == 0) continue;
    pending_mark_[static_cast<size_t>(t)] = pending_epoch_;
    cut_.push_back(t);
  }
  for (Eigen::Index t = 0; t < tets_.cols(); ++t) {
    if (alive_[static_cast<size_t>(t)] == 0 ||
        pending_mark_[static_cast<size_t>(t)] == pending_epoch_) {
      continue;
    }
    Vector3d tlo = x.col(tets_(0, t)), thi = tlo;
    for (int k = 1; k < 4; ++k) {
      tlo = tlo.cwiseMin(x.col(tets_(k, t)));
      thi = thi.cwiseMax(x.col(tets_(k, t)));
    }
    if ((tlo.array() > hi.array()).any() || (thi.array() < lo.array()).any()) continue;
    for (const auto& e : kTetEdges) {
      const Vector3d a = x.col(tets_(e[0], t)), b = x.col(tets_(e[1], t));
      if (Crosses(a, b, sweep.p0, sweep.q0, sweep.q1, tolerance) ||
          Crosses(a, b, sweep.p0, sweep.q1, sweep.p1, tolerance)) {
        cut_.push_back(static_cast<int32_t>(t));
        break;
      }
    }
  }
  std::sort(cut_.begin(), cut_.end());
  result.cut = static_cast<int32_t>(cut_.size());
  if (cut_.empty()) return result;
  // Severed: every edge from one side of the sweep's plane to the other crosses it within the
  // swept region, or below the tip's path (nearer to it than to the blade: the bottom of a
  // partial-depth cut, whose vertices eq. 2 brings up onto the tip's path) — so the wound opens
  // behind the blade, never ahead of it. The others wait.
  pending_count_ = 0;
  size_t severed = 0;
  for (const int32_t t : cut_) {
    bool all = true;
    for (const auto& e : kTetEdges) {
      const Vector3d a = x.col(tets_(e[0], t)), b = x.col(tets_(e[1], t));
      const double da = n.dot(a - sweep.p1), db = n.dot(b - sweep.p1);
      if (!((da > tolerance && db < -tolerance) || (da < -tolerance && db > tolerance))) continue;
      const Vector3d crossing = a + (da / (da - db)) * (b - a);
      Vector3d s0, s1;
      if (!InsideSwept(crossing, inside_tolerance) &&
          !NearestIsTipPath(crossing, sweep, &s0, &s1)) {
        all = false;
        break;
      }
    }
    if (all) {
      cut_[severed++] = t;
    } else {
      pending_[pending_count_++] = t;
    }
  }
  result.pending = static_cast<int32_t>(pending_count_);
  cut_.resize(severed);

  // 2. The removed set: no vertex left in no element.
  for (const int32_t t : cut_) {
    bool orphans = false;
    for (int k = 0; k < 4; ++k) {
      orphans = orphans || node_alive_[static_cast<size_t>(tets_(k, t))] <= 1;
    }
    if (orphans) {
      ++result.kept;
      continue;
    }
    if (!Remove(t)) break;
  }
  const size_t severed_removed = removed_count_;
  // 2b. Keep the boundary a manifold: around each vertex and edge of a removed tetrahedron the
  // alive tetrahedra must form one group (linked across faces holding that vertex or edge);
  // otherwise two parts of the mesh touch only there, a pinch no vertex-preserving cut can
  // open. The smaller groups' tetrahedra there are removed too (when that orphans no vertex).
  for (int pass = 0; pass < 6; ++pass) {
    bool changed = false;
    const size_t end = removed_count_;
    for (size_t i = 0; i < end; ++i) {
      const int32_t t = removed_[i];
      for (const auto& e : kTetEdges) {
        changed = SplitPinch(tets_(e[0], t), tets_(e[1], t), false) || changed;
      }
      for (int k = 0; k < 4; ++k) {
        const int32_t u = tets_(k, t);
        if (!Pinched(u)) continue;
        // Split it by removing more; where that would orphan a vertex, put back a tetrahedron
        // this step removed (the wound stays closed there).
        changed = SplitPinch(u, -1, false) || SplitLink(u, false) || RestoreAround(u) || changed;
      }
    }
    if (!changed) break;
  }
  // Anything still pinched around this step's changes: the step is undone (every tetrahedron
  // it removed put back; the severed ones wait for a later step, when the blade has moved on).
  for (size_t i = 0; i < removed_count_ && result.unresolved == 0; ++i) {
    const int32_t t = removed_[i];
    for (int k = 0; k < 4; ++k) result.unresolved += Pinched(tets_(k, t)) ? 1 : 0;
    for (const auto& e : kTetEdges) {
      result.unresolved += SplitPinch(tets_(e[0], t), tets_(e[1], t), true) ? 1 : 0;
    }
  }
  if (result.unresolved > 0) {
    for (size_t i = 0; i < removed_count_; ++i) {
      const int32_t t = removed_[i];
      if (alive_[static_cast<size_t>(t)] != 0) continue;
      alive_[static_cast<size_t>(t)] = 1;
      for (int k = 0; k < 4; ++k) ++node_alive_[static_cast<size_t>(tets_(k, t))];
      if (i < severed_removed && pending_count_ < pending_.size()) {
        pending_[pending_count_++] = t;
      }
    }
    removed_count_ = 0;
    result.removed = 0;
    result.undone = true;
    return result;
  }
  // The tetrahedra put back leave the list (in order); the severed ones stay first.
  size_t kept_entries = 0, kept_severed = 0;
  ++tet_epoch_;
  for (size_t i = 0; i < removed_count_; ++i) {
    const auto t = static_cast<size_t>(removed_[i]);
    if (alive_[t] != 0 || tet_stamp_[t] == tet_epoch_) continue;  // put back, or listed twice
    tet_stamp_[t] = tet_epoch_;
    if (i < severed_removed) ++kept_severed;
    removed_[kept_entries++] = removed_[i];
  }
  removed_count_ = kept_entries;
  const size_t severed_count = kept_severed;
  result.removed = static_cast<int32_t>(removed_count_);
  result.repaired = static_cast<int32_t>(removed_count_ - severed_count);
  num_alive_ -= result.removed;
  if (removed_count_ == 0) return result;
  ++topology_version_;

  // 3. Relocation of the severed tetrahedra's vertices, ascending, with the inversion guard.
  if (++epoch_ == 0) {
    std::fill(stamp_.begin(), stamp_.end(), 0);
    epoch_ = 1;
  }
  for (size_t i = 0; i < severed_count; ++i) {
    for (int k = 0; k < 4; ++k) {
      const int32_t v = tets_(k, removed_[i]);
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
      volume_before_[static_cast<size_t>(t)] = mesh::TetSignedVolume(
          x.col(tets_(0, t)), x.col(tets_(1, t)), x.col(tets_(2, t)), x.col(tets_(3, t)));
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
        const double volume = mesh::TetSignedVolume(x.col(tets_(0, t)), x.col(tets_(1, t)),
                                                    x.col(tets_(2, t)), x.col(tets_(3, t)));
        ok = volume >= settings_.min_volume_fraction * volume_before_[static_cast<size_t>(t)];
      }
    }
    if (!ok) x.col(v) = from;
    if (!ok || attempt > 1) ++result.shortened;
    if (ok && (x.col(v) - from).squaredNorm() > 0.0) moved_[kept_moves++] = v;
  }
  moved_count_ = kept_moves;
  result.relocated = static_cast<int32_t>(moved_count_);
  return result;
}

void TetCutter::ExtractSurface(mesh::Triangles* triangles, std::vector<uint8_t>* inner) const {
  ExtractSurface(alive_, triangles, inner);
}

void TetCutter::ExtractSurface(std::span<const uint8_t> alive, mesh::Triangles* triangles,
                               std::vector<uint8_t>* inner) const {
  surface_.Extract(alive, triangles, inner);
}

}  // namespace somasim::cutting
