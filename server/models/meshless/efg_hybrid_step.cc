// EfgHybridModel's step (efg_hybrid_model.h): the supports and tools, the region (static factor,
// tool following, adaptivity, a new partition carrying the field over), A's factor and the
// tools' low-rank slots, the loads' far response, then implicit Euler on q and one pass over D.
#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "server/models/meshless/efg_hybrid_internal.h"
#include "server/models/meshless/efg_hybrid_model.h"
#include "server/models/meshless/efg_shared.h"
#include "server/models/meshless/efg_system.h"

namespace somasim::models::meshless {

using hybrid_internal::HybridState;
using hybrid_internal::Index;
using hybrid_internal::Matrix3d;
using hybrid_internal::NonZero;
using hybrid_internal::Vector3d;
using hybrid_internal::VectorXd;

void EfgHybridModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const auto fail = [st] {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
  };
  // 1. Supports (penalty springs and their targets) and the distinct attached nodes.
  if (!GatherSupportsAndTools(inputs, st)) {  // more distinct grasped nodes than slots
    fail();
    return;
  }
  // 2. The static factor of K̃ (when the supports change), then the region.
  if (!UpdateRegion(inputs, st)) {
    fail();
    return;
  }
  // 3. A's factor (per dt and partition) and the attached nodes' slots.
  if (!PrepareStepFactor(inputs.dt, st)) {
    fail();
    return;
  }
  // 4. Loads reaching far parameters: their particular response when they change.
  UpdateFarLoads(inputs, st);
  // 5. b = dt (Dᵀ h - α M_r v - K_r (q + (β + dt) v) - P_r (q + dt v)).
  AssembleRightHandSide(inputs, st);
  // 6. Solve, correct for the attachments, update q, then the positions and velocities.
  st->a_llt.matrixL().solveInPlace(st->b);
  st->a_llt.matrixU().solveInPlace(st->b);
  if (st->slots.num_attached > 0 && !CorrectForAttachments(inputs.dt, st)) {
    fail();
    return;
  }
  ++st->counters.solver_iterations;
  st->vq += st->b;
  st->q += inputs.dt * st->vq;
  const Index rows = 3 * Index(num_nodes());
  double* x = st->positions.data();
  double* v = st->velocities.data();
  const double* x0 = efg_->system_->rest.data();
  const double* o = st->offsets.data();
  for (Index r = 0; r < rows; ++r) {
    const auto row = st->d.row(r);
    x[r] = x0[r] + o[r] + row.dot(st->q);
    v[r] = row.dot(st->vq);
  }
}

bool EfgHybridModel::GatherSupportsAndTools(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const mesh::Points& rest = efg_->system_->rest;
  const double penalty = efg_->system_->penalty;
  for (const int32_t node : st->support_nodes) {
    st->support[size_t(node)] = 0.0;
    st->support_target.col(node).setZero();
    st->support_listed[size_t(node)] = 0;
  }
  st->support_nodes.clear();  // capacity num_nodes: no allocation
  const auto add_support = [st, penalty, &rest](int32_t node, const Vector3d& target) {
    st->support[size_t(node)] += penalty;
    st->support_target.col(node) += penalty * (target - rest.col(node));
    if (st->support_listed[size_t(node)] == 0) {
      st->support_listed[size_t(node)] = 1;
      st->support_nodes.push_back(node);
    }
  };
  ForEachSupport(inputs, st, add_support);
  return st->slots.Gather(inputs.attachments);
}

bool EfgHybridModel::UpdateRegion(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const int32_t n = num_nodes();
  const mesh::Points& rest = efg_->system_->rest;
  bool need_partition = !st->partitioned;
  if (st->cut_pending ||
      !std::equal(st->support.begin(), st->support.end(), st->cached_support.begin())) {
    st->cut_pending = false;
    if (!FactoriseStatic(st)) return false;
    need_partition = true;
  }
  // The tool: the first attached node, else the node with the largest external force.
  int32_t tool = -1;
  if (st->slots.num_attached > 0) {
    tool = st->slots.attached_nodes[0];
  } else if (inputs.external_forces != nullptr) {
    double largest = 0.0;
    for (int32_t i = 0; i < n; ++i) {
      const double f = inputs.external_forces->col(i).squaredNorm();
      if (f > largest) {
        largest = f;
        tool = i;
      }
    }
  }
  Vector3d centre = st->centre;
  if (parameters_.adaptive && st->partitioned &&
      ++st->steps_since_adapt >= parameters_.adapt_interval) {
    st->steps_since_adapt = 0;
    need_partition = Adapt(st) || need_partition;
  }
  if (!st->partitioned) {
    if (parameters_.region_centre.allFinite()) {
      centre = parameters_.region_centre;
    } else if (tool >= 0) {
      centre = rest.col(tool);
    } else {
      Index nearest = 0;
      (rest.colwise() - centroid_).colwise().squaredNorm().minCoeff(&nearest);
      centre = rest.col(nearest);
    }
  } else if (parameters_.follow_tool && tool >= 0 &&
             (rest.col(tool) - st->centre).norm() >
                 parameters_.follow_fraction * parameters_.region_radius) {
    centre = rest.col(tool);
    need_partition = true;
    if (parameters_.adaptive) Adapt(st);  // the refinement follows the tool too
  }
  if (!need_partition) return true;
  // The field carries over by its parameters: the new q are the old û at the new region.
  mesh::Points params, vparams;
  if (st->carry) {  // a cut's: the physical field under the cut Φ
    params = st->carried_params;
    vparams = st->carried_vparams;
    st->carry = false;
  } else if (st->partitioned) {
    params = NodalParameters(*st);
    const VectorXd v = st->t * st->vq;
    vparams = Eigen::Map<const mesh::Points>(v.data(), 3, n);
  }
  Partition(centre, st);
  if (params.size() > 0) {
    for (size_t a = 0; a < st->kept.size(); ++a) {
      st->q.segment<3>(3 * Index(a)) = params.col(st->kept[a]);
      st->vq.segment<3>(3 * Index(a)) = vparams.col(st->kept[a]);
    }
  }
  st->good_q = st->q;
  st->good_vq = st->vq;
  return true;
}

bool EfgHybridModel::PrepareStepFactor(double dt, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const double alpha = efg_->system_->rayleigh_mass, beta = efg_->system_->rayleigh_stiffness;
  if (!st->a_valid || dt != st->cached_dt) {
    st->a = (1.0 + dt * alpha) * st->m_r + (dt * dt + dt * beta) * st->k_r + dt * dt * st->p_r;
    st->a_llt.compute(st->a);
    ++st->factorisations;
    st->a_valid = st->a_llt.info() == Eigen::Success;
    st->cached_dt = dt;
    st->slots.FreeAll();  // Z = A⁻¹ U belongs to the old factor
    if (!st->a_valid) return false;
  }
  st->slots.Assign([this, st](int32_t slot, int32_t node) { FillSlot(slot, node, st); });
  return true;
}

void EfgHybridModel::UpdateFarLoads(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const int32_t n = num_nodes();
  // External forces and support targets at nodes whose MLS row holds a far parameter.
  const mesh::Points* external = inputs.external_forces;
  st->far_loads.setZero();
  bool any_far = false;
  for (int32_t i = 0; i < n; ++i) {
    if (st->touches_far[size_t(i)] == 0) continue;
    Vector3d f = st->support_target.col(i);
    if (external != nullptr) f += external->col(i);
    if (f.isZero(0.0)) continue;
    st->far_loads.col(i) = f;
    any_far = true;
  }
  if (st->far_loads != st->cached_far_loads) {  // NaN after a partition: always different
    if (any_far && st->has_supports && st->shift == 0.0) {
      ParticularResponse(st->far_loads.data(), st->offset_l.data(), st);
      std::copy(st->full_solution.data(), st->full_solution.data() + 3 * size_t(n),
                st->param_offset_l.data());
      ++st->far_solves;
    } else {
      st->offset_l.setZero();
      st->param_offset_l.setZero();
    }
    st->cached_far_loads = st->far_loads;
  }
  st->gravity = inputs.gravity;
  st->offsets = st->offset_l;
  Eigen::Map<VectorXd>(st->offsets.data(), 3 * Index(n)).noalias() += st->offset_g * inputs.gravity;
}

void EfgHybridModel::AssembleRightHandSide(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const int32_t n = num_nodes();
  const mesh::Points& rest = efg_->system_->rest;
  const double dt = inputs.dt;
  const double alpha = efg_->system_->rayleigh_mass, beta = efg_->system_->rayleigh_stiffness;
  const auto k3 = Index(3 * st->kept.size());
  // Dᵀ h: gravity, the external forces, the supports' targets, the tools' springs.
  auto b = st->b.head(k3);
  b.noalias() = st->g_r * inputs.gravity;
  const mesh::Points* external = inputs.external_forces;
  if (external != nullptr) {
    for (int32_t i = 0; i < n; ++i) {
      const double* f = external->col(i).data();
      if (NonZero(f))
        b.noalias() += st->d.middleRows<3>(3 * Index(i)).transpose() * external->col(i);
    }
  }
  for (const int32_t node : st->support_nodes) {
    if (NonZero(st->support_target.col(node).data())) {
      b.noalias() +=
          st->d.middleRows<3>(3 * Index(node)).transpose() * st->support_target.col(node);
    }
  }
  for (const Attachment& grasp : inputs.attachments) {
    const auto di = st->d.middleRows<3>(3 * Index(grasp.node));
    const Vector3d u = di * st->q + st->offsets.col(grasp.node);
    const Vector3d v = di * st->vq;
    const Vector3d f = grasp.stiffness * (grasp.target - rest.col(grasp.node) - u - dt * v);
    b.noalias() += di.transpose() * f;
  }
  // The damping, elastic and support forces of the reduced system.
  b.noalias() -= alpha * (st->m_r * st->vq);
  st->work.head(k3) = st->q + (beta + dt) * st->vq;
  b.noalias() -= st->k_r * st->work.head(k3);
  st->work.head(k3) = st->q + dt * st->vq;
  b.noalias() -= st->p_r * st->work.head(k3);
  b *= dt;
}

void EfgHybridModel::FillSlot(int32_t slot, int32_t node, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  LowRankSlots& slots = st->slots;
  const auto s = Index(slot);
  // Z's columns: A⁻¹ D_Iᵀ.
  const auto di = st->d.middleRows<3>(3 * Index(node));
  for (int c = 0; c < 3; ++c) {
    auto column = slots.z.col(3 * s + c);
    column = di.row(c).transpose();
    st->a_llt.matrixL().solveInPlace(column);
    st->a_llt.matrixU().solveInPlace(column);
  }
  // G's blocks with every held slot t (this one included): D_{I_t} Z_s, mirrored.
  for (size_t t = 0; t < slots.slot_node.size(); ++t) {
    const int32_t other = slots.slot_node[t];
    if (other < 0) continue;
    const auto tt = Index(t);
    Matrix3d block;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) {
        block(r, c) = st->d.row(3 * Index(other) + r).dot(slots.z.col(3 * s + c));
      }
    }
    if (tt == s) block = (0.5 * (block + block.transpose())).eval();
    slots.gram.block<3, 3>(3 * tt, 3 * s) = block;
    slots.gram.block<3, 3>(3 * s, 3 * tt) = block.transpose();
  }
}

bool EfgHybridModel::CorrectForAttachments(double dt, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  LowRankSlots& slots = st->slots;
  // Uᵀ x0: D_I x0 per attached node.
  for (Index i = 0; i < Index(slots.num_attached); ++i) {
    const int32_t node = slots.attached_nodes[size_t(i)];
    for (int c = 0; c < 3; ++c) {
      slots.small_rhs[3 * i + c] = st->d.row(3 * Index(node) + c).dot(st->b);
    }
  }
  return slots.Correct(dt, st->b);
}

}  // namespace somasim::models::meshless
