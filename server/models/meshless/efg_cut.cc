// EfgModel's cutting by the visibility criterion (docs/models.md, "The EFG model in detail"):
// the sweep pulled back to the reference configuration, the points whose segments it crosses
// re-evaluated.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <utility>
#include <vector>

#include "server/models/meshless/efg_internal.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/meshless/efg_system.h"

namespace somasim::models::meshless {

using efg_internal::EfgState;
using efg_internal::PhiMatrix;
using efg_internal::SolvePhi;
using efg_internal::TrianglesNear;
using Eigen::Vector3d;

const EfgCutValues* EfgModel::CutOf(const TissueState& state) const {
  return static_cast<const EfgState&>(state).cut.get();
}

SweptQuad EfgModel::PullBack(const SweptQuad& sweep, const mesh::Points& positions) const {
  // Each corner p moves back by the inverse-distance mean displacement of the 4 nodes nearest
  // to it in the current configuration (a blade corner outside the body has no MLS field).
  constexpr int kNearest = 4;
  const auto back = [&](const Vector3d& p) {
    std::array<std::pair<double, int32_t>, kNearest> best;
    best.fill({std::numeric_limits<double>::infinity(), -1});
    for (int32_t i = 0; i < num_nodes(); ++i) {
      const double d = (positions.col(i) - p).squaredNorm();
      if (d < best.back().first) {
        best.back() = {d, i};
        std::sort(best.begin(), best.end());
      }
    }
    Vector3d u = Vector3d::Zero();
    double total = 0.0;
    for (const auto& [d2, i] : best) {
      if (i < 0) continue;
      const double w = 1.0 / (std::sqrt(d2) + 1e-9);
      u += w * (positions.col(i) - system_->rest.col(i));
      total += w;
    }
    return Vector3d(p - u / total);
  };
  return {back(sweep.p0), back(sweep.q0), back(sweep.p1), back(sweep.q1)};
}

int64_t EfgModel::ApplyCut(const SweptQuad& sweep, EfgCutValues* cut) const {
  if (!sweep.AllFinite()) return 0;
  const EfgSystem& system = *system_;
  const mesh::Points& rest = system.rest;
  if (cut->phi_value.empty()) {
    cut->phi_value = system.row_value;
    cut->k_blocks = system.k_blocks;
    cut->m_blocks = system.m_blocks;
    cut->dropped.assign(size_t(num_gauss_), 0);
    cut->detached.assign(size_t(num_nodes()), 0);
  }
  // The sweep's two triangles, without degenerate ones (a blade that did not move).
  std::vector<Vector3d> fresh;
  const auto add = [&](const Vector3d& a, const Vector3d& b, const Vector3d& c) {
    const double scale = std::max({(b - a).squaredNorm(), (c - a).squaredNorm(), 1e-300});
    if ((b - a).cross(c - a).norm() > 1e-9 * scale) fresh.insert(fresh.end(), {a, b, c});
  };
  add(sweep.p0, sweep.q0, sweep.q1);
  add(sweep.p0, sweep.q1, sweep.p1);
  if (fresh.empty()) return 0;
  const auto crosses_fresh = [&](const Vector3d& a, const Vector3d& b) {
    for (size_t k = 0; k + 2 < fresh.size(); k += 3) {
      if (SegmentCrossesTriangle(a, b, fresh[k], fresh[k + 1], fresh[k + 2])) return true;
    }
    return false;
  };
  Vector3d lo = fresh[0], hi = fresh[0];
  for (const Vector3d& p : fresh) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  const double reach = shape_->max_support_radius();
  const auto near_fresh = [&](const Vector3d& x) {
    return !(((x - hi).array() > reach).any() || ((lo - x).array() > reach).any());
  };
  const size_t old_end = cut->triangles.size();
  int64_t hidden = 0;
  std::vector<Vector3d> near;
  std::vector<int32_t> covering;
  MlsEvaluation before, after;
  // Whether a segment from x to a node covering it crosses the fresh triangles (else nothing
  // at x changes): the cheap test before any evaluation.
  const auto may_change = [&](const Vector3d& x) {
    covering.clear();
    shape_->CoveringNodes(x, &covering);
    return std::any_of(covering.begin(), covering.end(),
                       [&](int32_t j) { return crosses_fresh(rest.col(j), x); });
  };

  // Gauss points: old contribution out, new in (or the point dropped).
  for (int64_t g = 0; g < num_gauss_; ++g) {
    const Vector3d x = gauss_x_.col(g);
    if (cut->dropped[size_t(g)] != 0 || !near_fresh(x) || !may_change(x)) continue;
    near.clear();
    TrianglesNear(cut->triangles, 0, old_end, x, reach, &near);
    shape_->Evaluate(x, true, near, &before);  // evaluated like this before: cannot throw
    const bool changed = std::any_of(before.nodes.begin(), before.nodes.end(),
                                     [&](int32_t j) { return crosses_fresh(rest.col(j), x); });
    if (!changed) continue;
    near.insert(near.end(), fresh.begin(), fresh.end());
    const double w = gauss_w_[size_t(g)];
    AddGaussPoint(before, w, -1.0, cut->k_blocks.data());
    try {
      shape_->Evaluate(x, true, near, &after);
      AddGaussPoint(after, w, 1.0, cut->k_blocks.data());
      hidden += static_cast<int64_t>(before.nodes.size() - after.nodes.size());
    } catch (const std::invalid_argument&) {
      cut->dropped[size_t(g)] = 1;
      ++cut->dropped_points;
      hidden += static_cast<int64_t>(before.nodes.size());
    }
  }

  // Node points: Φ's row and its share of M̂ = Φᵀ diag(m) Φ.
  const std::vector<int32_t>& phi_start = system.row_start;
  const std::vector<int32_t>& phi_node = system.row_col;
  std::vector<double> row;
  for (int32_t i = 0; i < num_nodes(); ++i) {
    const Vector3d x = rest.col(i);
    if (cut->detached[size_t(i)] != 0 || !near_fresh(x)) continue;
    const int32_t begin = phi_start[size_t(i)], end = phi_start[size_t(i) + 1];
    bool changed = false;
    for (int32_t a = begin; a < end && !changed; ++a) {
      changed = cut->phi_value[size_t(a)] != 0.0 && crosses_fresh(rest.col(phi_node[size_t(a)]), x);
    }
    if (!changed) continue;
    row.assign(size_t(end - begin), 0.0);
    near.clear();
    TrianglesNear(cut->triangles, 0, old_end, x, reach, &near);
    near.insert(near.end(), fresh.begin(), fresh.end());
    try {
      shape_->Evaluate(x, false, near, &after);
      size_t k = 0;  // after.nodes ⊆ the row's pattern, both increasing
      for (int32_t a = begin; a < end && k < after.nodes.size(); ++a) {
        if (phi_node[size_t(a)] == after.nodes[k]) row[size_t(a - begin)] = after.values[k++];
      }
    } catch (const std::invalid_argument&) {
      for (int32_t a = begin; a < end; ++a) {
        if (phi_node[size_t(a)] == i) row[size_t(a - begin)] = 1.0;
      }
      cut->detached[size_t(i)] = 1;
      ++cut->detached_rows;
    }
    const double m = system.mass[size_t(i)];
    for (int32_t b = begin; b < end; ++b) {
      const double old_b = cut->phi_value[size_t(b)], new_b = row[size_t(b - begin)];
      int64_t slot = system.block_start[size_t(phi_node[size_t(b)])];
      for (int32_t a = b; a < end; ++a) {
        while (system.block_row[size_t(slot)] != phi_node[size_t(a)]) ++slot;
        cut->m_blocks[size_t(slot)] +=
            m * (row[size_t(a - begin)] * new_b - cut->phi_value[size_t(a)] * old_b);
      }
    }
    for (int32_t a = begin; a < end; ++a) {
      const bool was = cut->phi_value[size_t(a)] != 0.0, is = row[size_t(a - begin)] != 0.0;
      if (was && !is) ++hidden;
      cut->phi_value[size_t(a)] = row[size_t(a - begin)];
    }
  }
  // A sweep that hid nothing never will (the points and their pairs are fixed, and hidden
  // pairs stay hidden): only the others are kept.
  if (hidden == 0) return 0;
  cut->triangles.insert(cut->triangles.end(), fresh.begin(), fresh.end());
  cut->hidden_pairs += hidden;
  ++cut->version;
  return hidden;
}

int32_t EfgModel::Cut(const SweptQuad& sweep, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  if (!sweep.AllFinite()) return 0;
  if (st->cut == nullptr) st->cut = std::make_unique<EfgCutValues>();
  const int64_t hidden = ApplyCut(PullBack(sweep, st->positions), st->cut.get());
  if (hidden == 0) return 0;
  // The physical field stays; the parameters follow under the new Φ (one LU for both).
  const Eigen::Index n = num_nodes();
  mesh::Points field(3, 2 * n), params;
  field.leftCols(n) = st->positions - system_->rest;
  field.rightCols(n) = st->velocities;
  Eigen::MatrixXd stacked(n, 6), solved;
  stacked.leftCols<3>() = field.leftCols(n).transpose();
  stacked.rightCols<3>() = field.rightCols(n).transpose();
  if (SolvePhi(
          PhiMatrix(int32_t(n), system_->row_start, system_->row_col, st->cut->phi_value.data()),
          false, stacked, &solved)) {
    st->params = solved.leftCols<3>().transpose();
    st->vparams = solved.rightCols<3>().transpose();
  } else {  // a singular cut Φ (cannot happen but for a degenerate cut): the field follows Φ
    system_->MultiplyRows(ValuesOf(st->cut.get()), st->params.data(), st->u.data());
    system_->MultiplyRows(ValuesOf(st->cut.get()), st->vparams.data(), st->velocities.data());
    st->positions = system_->rest + st->u;
  }
  st->good_params = st->params;
  st->good_vparams = st->vparams;
  st->factor_valid = false;    // the next step factorises A0 again (and frees the slots)
  st->static_current = false;  // and K_s
  return static_cast<int32_t>(std::min<int64_t>(hidden, std::numeric_limits<int32_t>::max()));
}

}  // namespace somasim::models::meshless
