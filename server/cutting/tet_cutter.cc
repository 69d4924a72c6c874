// The cutter's construction and its blade step (Step) in stages: the cut set (crossed, then
// severed) and the removed set here; keeping its boundary a manifold (or undoing the step) in
// tet_cutter_pinch.cc; the relocation in tet_cutter_relocation.cc.
#include "server/cutting/tet_cutter.h"

#include <algorithm>
#include <stdexcept>
#include <string>

#include "common/mesh/topology.h"

namespace somasim::cutting {

namespace {

using Eigen::Vector3d;

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
    : num_nodes_(static_cast<int32_t>(positions.cols())), settings_(settings) {
  if (!(settings_.min_volume_fraction > 0.0 && settings_.min_volume_fraction < 1.0)) {
    throw std::invalid_argument("cutter: min_volume_fraction must be within (0, 1)");
  }
  const auto num_tets = static_cast<size_t>(tets.cols());
  for (Eigen::Index t = 0; t < tets.cols(); ++t) {
    for (int k = 0; k < 4; ++k) {
      if (tets(k, t) < 0 || tets(k, t) >= num_nodes_) {
        throw std::invalid_argument("cutter: tetrahedron " + std::to_string(t) + " has node " +
                                    std::to_string(tets(k, t)) + ", outside 0.." +
                                    std::to_string(num_nodes_ - 1));
      }
    }
  }
  surface_ = CutSurface(num_nodes_, tets);  // the cutter's tetrahedra and their face neighbours
  alive_.assign(num_tets, 1);
  num_alive_ = static_cast<int32_t>(num_tets);
  const mesh::Adjacency adjacency = mesh::NodeToTets(num_nodes_, tets);
  node_tet_offsets_ = adjacency.offsets;
  node_tet_entries_ = adjacency.entries;
  node_alive_.resize(static_cast<size_t>(num_nodes_));
  for (int32_t v = 0; v < num_nodes_; ++v)
    node_alive_[static_cast<size_t>(v)] = adjacency.Count(static_cast<size_t>(v));
  on_surface_.assign(static_cast<size_t>(num_nodes_), 0);
  for (Eigen::Index t = 0; t < tets.cols(); ++t) {
    for (int f = 0; f < 4; ++f) {
      if (surface_.neighbour(f, t) != -1) continue;
      for (int k = 0; k < 3; ++k)
        on_surface_[static_cast<size_t>(tet_node(kTetFaces[f][k], t))] = 1;
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

  // 1. The cut set: what the sweep crosses, then which of it is severed.
  const Vector3d lo = sweep.p0.cwiseMin(sweep.q0).cwiseMin(sweep.p1).cwiseMin(sweep.q1);
  const Vector3d hi = sweep.p0.cwiseMax(sweep.q0).cwiseMax(sweep.p1).cwiseMax(sweep.q1);
  // Vertices within this of the sweep's plane lie on it (relocated there before) [m].
  const double tolerance = 1e-9 * (hi - lo).norm();
  const double inside_tolerance = 1e-6 * (sweep.q1 - sweep.p1).norm();
  FindCrossed(sweep, lo, hi, tolerance, x);
  result.cut = static_cast<int32_t>(cut_.size());
  if (cut_.empty()) return result;
  KeepSevered(sweep, n, tolerance, inside_tolerance, x);
  result.pending = static_cast<int32_t>(pending_count_);

  // 2. The removed set, its boundary kept a manifold, or the step undone.
  RemoveSevered(&result);
  const size_t severed_removed = removed_count_;
  RepairPinches();
  if (UndoIfPinched(severed_removed, &result)) return result;
  const size_t severed_count = CompactRemoved(severed_removed);
  result.removed = static_cast<int32_t>(removed_count_);
  result.repaired = static_cast<int32_t>(removed_count_ - severed_count);
  num_alive_ -= result.removed;
  if (removed_count_ == 0) return result;
  ++topology_version_;

  // 3. Relocation of the severed tetrahedra's vertices.
  RelocateVertices(sweep, n, severed_count, &x, &result);
  return result;
}

// The cut set, after a bounding-box cull (the sweep's box lo, hi): tetrahedra the current quad
// crosses (an edge passing through one of its triangles p0 q0 q1 and p0 q1 p1 from one side to
// the other; an edge with an end on the sweep's plane does not cross: earlier steps relocated
// vertices there), and those crossed before but not yet severed (pending). Ascending.
void TetCutter::FindCrossed(const models::SweptQuad& sweep, const Vector3d& lo, const Vector3d& hi,
                            double tolerance, const mesh::Points& x) {
  ++pending_epoch_;
  cut_.clear();
  for (size_t i = 0; i < pending_count_; ++i) {
    const int32_t t = pending_[i];
    if (alive_[static_cast<size_t>(t)] == 0) continue;
    pending_mark_[static_cast<size_t>(t)] = pending_epoch_;
    cut_.push_back(t);
  }
  for (Eigen::Index t = 0; t < surface_.num_tets(); ++t) {
    if (alive_[static_cast<size_t>(t)] == 0 ||
        pending_mark_[static_cast<size_t>(t)] == pending_epoch_) {
      continue;
    }
    Vector3d tlo = x.col(tet_node(0, t)), thi = tlo;
    for (int k = 1; k < 4; ++k) {
      tlo = tlo.cwiseMin(x.col(tet_node(k, t)));
      thi = thi.cwiseMax(x.col(tet_node(k, t)));
    }
    if ((tlo.array() > hi.array()).any() || (thi.array() < lo.array()).any()) continue;
    for (const auto& e : kTetEdges) {
      const Vector3d a = x.col(tet_node(e[0], t)), b = x.col(tet_node(e[1], t));
      if (Crosses(a, b, sweep.p0, sweep.q0, sweep.q1, tolerance) ||
          Crosses(a, b, sweep.p0, sweep.q1, sweep.p1, tolerance)) {
        cut_.push_back(static_cast<int32_t>(t));
        break;
      }
    }
  }
  std::sort(cut_.begin(), cut_.end());
}

// Keeps in cut_ the severed tetrahedra: every edge from one side of the sweep's plane to the other
// crosses it within the swept region, or below the tip's path (nearer to it than to the blade:
// the bottom of a partial-depth cut, whose vertices eq. 2 brings up onto the tip's path) — so the
// wound opens behind the blade, never ahead of it. The others wait in pending_.
void TetCutter::KeepSevered(const models::SweptQuad& sweep, const Vector3d& n, double tolerance,
                            double inside_tolerance, const mesh::Points& x) {
  pending_count_ = 0;
  size_t severed = 0;
  for (const int32_t t : cut_) {
    bool all = true;
    for (const auto& e : kTetEdges) {
      const Vector3d a = x.col(tet_node(e[0], t)), b = x.col(tet_node(e[1], t));
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
  cut_.resize(severed);
}

// The severed tetrahedra are removed, in ascending order, unless that leaves a vertex in no
// element (seed 003 §4: the stiffness would be singular); those are counted as kept.
void TetCutter::RemoveSevered(CutStepResult* result) {
  for (const int32_t t : cut_) {
    bool orphans = false;
    for (int k = 0; k < 4; ++k) {
      orphans = orphans || node_alive_[static_cast<size_t>(tet_node(k, t))] <= 1;
    }
    if (orphans) {
      ++result->kept;
      continue;
    }
    if (!Remove(t)) break;
  }
}

// The tetrahedra put back leave the removed list (in order), and those listed twice; the severed
// ones stay first. Returns how many of them are severed.
size_t TetCutter::CompactRemoved(size_t severed_removed) {
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
  return kept_severed;
}

void TetCutter::ExtractSurface(mesh::Triangles* triangles, std::vector<uint8_t>* inner) const {
  ExtractSurface(alive_, triangles, inner);
}

void TetCutter::ExtractSurface(std::span<const uint8_t> alive, mesh::Triangles* triangles,
                               std::vector<uint8_t>* inner) const {
  surface_.Extract(alive, triangles, inner);
}

}  // namespace somasim::cutting
