// EfgHybridModel's region (efg_hybrid_model.h): the static factor of K̃, the condensation of the
// far region onto the kept nodes (a partition), the loads' particular far responses, and seed
// 001's adaptivity step that decides whether the region changes.
#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/adaptivity.h"
#include "server/models/meshless/efg_hybrid_internal.h"
#include "server/models/meshless/efg_hybrid_model.h"
#include "server/models/meshless/efg_system.h"

namespace somasim::models::meshless {

using hybrid_internal::HybridState;
using hybrid_internal::Index;
using hybrid_internal::kFreeShift;
using hybrid_internal::MatrixXd;
using hybrid_internal::RowMatrix;
using hybrid_internal::Vector3d;
using hybrid_internal::VectorXd;

bool EfgHybridModel::FactoriseStatic(TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  st->has_supports =
      std::any_of(st->support.begin(), st->support.end(), [](double s) { return s > 0.0; });
  const EfgSystem& system = *efg_->system_;
  const EfgValues values = efg_->ValuesOf(st->cut.get());
  st->shift = st->has_supports ? 0.0 : kFreeShift;
  system.AssembleSystem(values, 1.0, st->shift, 1.0, st->support.data(), st->blocks.data(),
                        st->system.values.data());
  st->static_valid = st->static_factor->Factorise(st->system);
  ++st->factorisations;
  if (!st->static_valid && st->shift == 0.0 && st->cut != nullptr) {
    // A cut severed a piece the supports do not hold: condense with the shifted K̃.
    st->shift = kFreeShift;
    system.AssembleSystem(values, 1.0, st->shift, 1.0, st->support.data(), st->blocks.data(),
                          st->system.values.data());
    st->static_valid = st->static_factor->Factorise(st->system);
    ++st->factorisations;
  }
  std::copy(st->support.begin(), st->support.end(), st->cached_support.begin());
  return st->static_valid;
}

// The particular far response of node-point loads L (3N): û = K̃⁻¹ Φᵀ L, q_p = û_k; the
// parameters' offset û - T q_p and the physical one Φ û - D q_p.
void EfgHybridModel::ParticularResponse(const double* node_loads, double* offsets,
                                        TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const EfgSystem& system = *efg_->system_;
  const EfgValues values = efg_->ValuesOf(st->cut.get());
  system.MultiplyRowsTransposed(values, node_loads, st->full_rhs.data());
  st->static_factor->Solve(st->full_rhs.data(), st->full_solution.data());
  const auto k3 = Index(3 * st->kept.size());
  for (size_t a = 0; a < st->kept.size(); ++a) {
    for (int c = 0; c < 3; ++c) {
      st->work[Index(3 * a) + c] = st->full_solution.data()[3 * size_t(st->kept[a]) + size_t(c)];
    }
  }
  system.MultiplyRows(values, st->full_solution.data(), st->full_phi.data());
  const Index rows = 3 * Index(num_nodes());
  const auto q_p = st->work.head(k3);
  for (Index r = 0; r < rows; ++r) {
    offsets[r] = st->full_phi.data()[r] - st->d.row(r).dot(q_p);
    st->full_solution.data()[r] -= st->t.row(r).dot(q_p);  // parameters' offset, kept below
  }
}

void EfgHybridModel::Partition(const Vector3d& centre, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const int32_t n = num_nodes();
  const EfgSystem& system = *efg_->system_;
  const mesh::Points& rest = system.rest;
  // The region: nodes within the radius, nearest first, at most max_region_nodes, at least one.
  std::vector<std::pair<double, int32_t>> by_distance;
  by_distance.reserve(size_t(n));
  for (int32_t i = 0; i < n; ++i) by_distance.emplace_back((rest.col(i) - centre).norm(), i);
  std::sort(by_distance.begin(), by_distance.end());
  st->kept.clear();
  for (const auto& [distance, node] : by_distance) {
    if (st->kept.size() >= size_t(parameters_.max_region_nodes)) break;
    if (st->kept.empty() || distance <= parameters_.region_radius ||
        st->refined[size_t(node)] != 0) {
      st->kept.push_back(node);
    }
  }
  std::fill(st->kept_of.begin(), st->kept_of.end(), -1);
  for (size_t a = 0; a < st->kept.size(); ++a) st->kept_of[size_t(st->kept[a])] = int32_t(a);
  const auto k = Index(st->kept.size());
  const Index k3 = 3 * k, rows = 3 * Index(n);

  // Y = K̃⁻¹ [I_k; 0] (3k solves), S⁻¹ = Y_kk, S = Y_kk⁻¹, T = Y S.
  MatrixXd y = MatrixXd::Zero(rows, k3);
  for (Index j = 0; j < k3; ++j) y(Index(3 * st->kept[size_t(j / 3)]) + j % 3, j) = 1.0;
  st->static_factor->SolveMany(y.data(), y.data(), int32_t(k3));
  st->s_inv.resize(k3, k3);
  for (Index i = 0; i < k3; ++i) {
    st->s_inv.row(i) = y.row(Index(3 * st->kept[size_t(i / 3)]) + i % 3);
  }
  st->s_inv = (0.5 * (st->s_inv + st->s_inv.transpose())).eval();
  const MatrixXd s = st->s_inv.llt().solve(MatrixXd::Identity(k3, k3));
  const MatrixXd s_sym = 0.5 * (s + s.transpose());
  st->t.noalias() = y * s_sym;
  // D = Φ T by node rows.
  const double* phi_value = efg_->ValuesOf(st->cut.get()).rows;
  st->d.setZero(rows, k3);
  for (int32_t i = 0; i < n; ++i) {
    uint8_t far = 0;
    for (int32_t a = system.row_start[size_t(i)]; a < system.row_start[size_t(i) + 1]; ++a) {
      const int32_t j = system.row_col[size_t(a)];
      far |= uint8_t(st->kept_of[size_t(j)] < 0);
      st->d.middleRows<3>(3 * Index(i)) += phi_value[size_t(a)] * st->t.middleRows<3>(3 * Index(j));
    }
    st->touches_far[size_t(i)] = far;
  }
  // M_r = Dᵀ diag(m) D, G_r = Dᵀ (m ⊗ e_c), P_r = Σ_s s_I D_Iᵀ D_I.
  RowMatrix weighted = st->d;
  st->g_r.setZero(k3, 3);
  for (int32_t i = 0; i < n; ++i) {
    const double m = system.mass[size_t(i)];
    for (int c = 0; c < 3; ++c) st->g_r.col(c) += m * st->d.row(3 * Index(i) + c).transpose();
    weighted.middleRows<3>(3 * Index(i)) *= std::sqrt(m);
  }
  st->m_r.noalias() = weighted.transpose() * weighted;
  st->p_r.setZero(k3, k3);
  for (int32_t i = 0; i < n; ++i) {
    const double support = st->support[size_t(i)];
    if (support <= 0.0) continue;
    const auto di = st->d.middleRows<3>(3 * Index(i));
    st->p_r.noalias() += support * (di.transpose() * di);
  }
  st->k_r = s_sym - st->p_r;
  if (st->shift != 0.0) st->k_r -= st->shift * st->m_r;
  // Per-step and low-rank buffers.
  st->q.setZero(k3);
  st->vq.setZero(k3);
  st->good_q.setZero(k3);
  st->good_vq.setZero(k3);
  st->b.setZero(k3);
  st->work.setZero(std::max<Index>(k3, 3));
  st->a.setZero(k3, k3);
  st->local_work.setZero(k3, 3);
  st->slots.z.setZero(k3, 3 * Index(st->slots.slot_node.size()));
  st->a_valid = false;
  st->slots.FreeAll();
  std::fill(st->local_valid.begin(), st->local_valid.end(), uint8_t{0});
  st->centre = centre;
  st->partitioned = true;
  ++st->partitions;
  // Gravity's particular far response, per unit component (none for a free body).
  st->offset_g.setZero(rows, 3);
  st->param_offset_g.setZero(rows, 3);
  if (st->has_supports && st->shift == 0.0) {
    mesh::Points unit_gravity(3, n);
    for (int c = 0; c < 3; ++c) {
      unit_gravity.setZero();
      for (int32_t i = 0; i < n; ++i) unit_gravity(c, i) = system.mass[size_t(i)];
      ParticularResponse(unit_gravity.data(), st->offset_g.col(c).data(), st);
      st->param_offset_g.col(c) = Eigen::Map<const VectorXd>(st->full_solution.data(), rows);
    }
  }
  // Loads reaching far parameters are recomputed for this partition at the next step.
  st->cached_far_loads.setConstant(std::numeric_limits<double>::quiet_NaN());
  st->offset_l.setZero();
  st->param_offset_l.setZero();
}

bool EfgHybridModel::Adapt(TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  ++st->adaptations;
  const CellIntensity cells = intensity_->Compute(NodalParameters(*st), efg_->lambda_, efg_->mu_);
  // Refine: cells at or above refine_threshold; keep: nodes already refined whose cells stay
  // at or above coarsen_threshold.
  std::vector<uint8_t> refined(st->refined.size(), 0);
  for (Eigen::Index t = 0; t < tets_.cols(); ++t) {
    const double eta = cells.normalised[size_t(t)];
    for (int a = 0; a < 4; ++a) {
      const auto node = size_t(tets_(a, t));
      if (eta >= parameters_.refine_threshold ||
          (eta >= parameters_.coarsen_threshold && st->refined[node] != 0)) {
        refined[node] = 1;
      }
    }
  }
  // The region changes when a node joins (refined, not yet kept) or one that joined by
  // refinement outside the ball leaves.
  const bool room = st->kept.size() < size_t(parameters_.max_region_nodes);
  bool changed = false;
  for (size_t i = 0; i < refined.size() && !changed; ++i) {
    const bool kept = st->kept_of[i] >= 0;
    if (!room && refined[i] != 0 && !kept) continue;  // full: no node can join
    const bool in_ball =
        (efg_->system_->rest.col(Index(i)) - st->centre).norm() <= parameters_.region_radius;
    changed = (refined[i] != 0 && !kept) || (kept && !in_ball && refined[i] == 0);
  }
  st->refined = std::move(refined);
  return changed;
}

}  // namespace somasim::models::meshless
