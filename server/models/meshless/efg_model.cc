#include "server/models/meshless/efg_model.h"

#include <Eigen/LU>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/efg_internal.h"
#include "server/models/meshless/efg_shared.h"
#include "server/models/meshless/efg_system.h"
#include "server/models/particle_mesh.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

}  // namespace

using efg_internal::EfgState;
using efg_internal::PhiMatrix;
using efg_internal::SolvePhi;
using efg_internal::TrianglesNear;

EfgModel::EfgModel() = default;
EfgModel::~EfgModel() = default;

int32_t EfgModel::num_nodes() const { return system_->num_nodes(); }
const std::vector<double>& EfgModel::masses() const { return system_->mass; }
const mesh::Points& EfgModel::rest_positions() const { return system_->rest; }
double EfgModel::penalty() const { return system_->penalty; }
int64_t EfgModel::stiffness_blocks() const {
  return static_cast<int64_t>(system_->block_row.size());
}

EfgValues EfgModel::ValuesOf(const EfgCutValues* cut) const {
  if (cut == nullptr || cut->phi_value.empty()) return system_->own_values();
  return {cut->phi_value.data(), cut->k_blocks.data(), cut->m_blocks.data()};
}

std::unique_ptr<TissueState> EfgModel::MakeState() const {
  auto state = std::make_unique<EfgState>();
  InitialiseState(system_->rest, state.get());
  system_->SizeState(state.get());
  const int32_t n = num_nodes();
  state->slots.Size(max_low_rank_nodes_, n, n);
  state->slots.z =
      Eigen::MatrixXd::Zero(3 * Eigen::Index{n}, 3 * Eigen::Index{max_low_rank_nodes_});
  state->unit_rhs.assign(3 * size_t(n), 0.0);
  return state;
}

int64_t EfgModel::Factorisations(const TissueState& state) const {
  return static_cast<const EfgState&>(state).factorisations;
}

const mesh::Points& EfgModel::NodalParameters(const TissueState& state) const {
  return static_cast<const EfgState&>(state).params;
}

void EfgModel::NodeDisplacements(const mesh::Points& parameters, mesh::Points* displacements,
                                 const EfgCutValues* cut) const {
  displacements->resize(3, num_nodes());
  system_->MultiplyRows(ValuesOf(cut), parameters.data(), displacements->data());
}

void EfgModel::DisplacementAt(const TissueState& state, const Vector3d& x, Vector3d* u,
                              Matrix3d* gradient) const {
  const auto& st = static_cast<const EfgState&>(state);
  const mesh::Points& params = st.params;
  MlsEvaluation eval;
  std::vector<Vector3d> near;
  if (st.cut != nullptr) {
    TrianglesNear(st.cut->triangles, 0, st.cut->triangles.size(), x, shape_->max_support_radius(),
                  &near);
  }
  shape_->Evaluate(x, gradient != nullptr, near, &eval);
  Vector3d sum = Vector3d::Zero();
  Matrix3d grad = Matrix3d::Zero();
  for (size_t a = 0; a < eval.nodes.size(); ++a) {
    const auto col = static_cast<Eigen::Index>(a);
    sum += eval.values[a] * params.col(eval.nodes[a]);
    if (gradient != nullptr)
      grad += params.col(eval.nodes[a]) * eval.gradients.col(col).transpose();
  }
  if (u != nullptr) *u = sum;
  if (gradient != nullptr) *gradient = grad;
}

Matrix3d EfgModel::LocalStiffness(const TissueState& base, int32_t node) const {
  const auto& st = static_cast<const EfgState&>(base);
  return system_->LocalStiffness(ValuesOf(st.cut.get()), st, node);
}

bool EfgModel::ParametersOfDisplacements(const mesh::Points& displacements,
                                         mesh::Points* parameters, const EfgCutValues* cut) const {
  const Eigen::MatrixXd u = displacements.transpose();  // num_nodes × 3
  Eigen::MatrixXd params;
  if (cut == nullptr || cut->phi_value.empty()) {
    params = system_->lu.solve(u);
  } else if (!SolvePhi(PhiMatrix(num_nodes(), system_->row_start, system_->row_col,
                                 cut->phi_value.data()),
                       false, u, &params)) {
    return false;
  }
  *parameters = params.transpose();
  return true;
}

void EfgModel::ForcesOfParameters(const mesh::Points& params, mesh::Points* forces,
                                  const EfgCutValues* cut) const {
  mesh::Points k_params(3, num_nodes());
  system_->MultiplyStiffness(ValuesOf(cut), params.data(), k_params.data());
  // Φᵀ f = -K û: the physical forces whose virtual work on δu = Φ δû is -δûᵀ K û.
  const Eigen::MatrixXd rhs = -k_params.transpose();
  Eigen::MatrixXd f;
  if (cut == nullptr || cut->phi_value.empty()) {
    f = system_->lu_transposed.solve(rhs);
  } else if (!SolvePhi(PhiMatrix(num_nodes(), system_->row_start, system_->row_col,
                                 cut->phi_value.data()),
                       true, rhs, &f)) {
    f = Eigen::MatrixXd::Zero(num_nodes(), 3);  // cannot happen but for a degenerate cut
  }
  *forces = f.transpose();
}

double EfgModel::ElasticEnergyOfParameters(const mesh::Points& params,
                                           const EfgCutValues* cut) const {
  return system_->ElasticEnergy(ValuesOf(cut), params);
}

void EfgModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  const EfgCutValues* cut = static_cast<const EfgState&>(state).cut.get();
  mesh::Points params;
  if (!ParametersOfDisplacements(state.positions - system_->rest, &params, cut)) {
    params = static_cast<const EfgState&>(state).params;
  }
  ForcesOfParameters(params, forces, cut);
}

EnergyReport EfgModel::Energy(const TissueState& state, const Vector3d& gravity) const {
  EnergyReport report;
  const EfgCutValues* cut = static_cast<const EfgState&>(state).cut.get();
  mesh::Points params;
  if (!ParametersOfDisplacements(state.positions - system_->rest, &params, cut)) {
    params = static_cast<const EfgState&>(state).params;
  }
  report.elastic = ElasticEnergyOfParameters(params, cut);
  AddKineticAndGravity(system_->mass, state, gravity, &report);
  return report;
}

void CheckStaticLoads(const EfgStaticLoads& loads, int32_t n, const std::string& model) {
  const auto refuse = [&model](const std::string& what) {
    throw std::invalid_argument(model + ": SolveStatic: " + what);
  };
  const auto in_range = [n](int32_t node) { return node >= 0 && node < n; };
  if (loads.external_forces != nullptr &&
      (loads.external_forces->cols() != n || !loads.external_forces->allFinite())) {
    refuse("external_forces must be finite, 3 x num_nodes");
  }
  if (loads.parameter_forces != nullptr &&
      (loads.parameter_forces->cols() != n || !loads.parameter_forces->allFinite())) {
    refuse("parameter_forces must be finite, 3 x num_nodes");
  }
  if (!loads.gravity.allFinite()) refuse("gravity must be finite");
  for (const int32_t node : loads.fixed_nodes) {
    if (!in_range(node)) refuse("fixed node " + std::to_string(node) + " out of range");
  }
  for (const int32_t node : loads.prescribed_nodes) {
    if (!in_range(node)) {
      refuse("prescribed node " + std::to_string(node) + " out of range");
    }
  }
  if (!loads.prescribed_nodes.empty() &&
      (loads.prescribed_positions == nullptr ||
       loads.prescribed_positions->cols() !=
           static_cast<Eigen::Index>(loads.prescribed_nodes.size()) ||
       !loads.prescribed_positions->allFinite())) {
    refuse("prescribed_positions must be finite, 3 x prescribed_nodes.size()");
  }
  if (loads.fixed_nodes.empty() && loads.prescribed_nodes.empty()) {
    refuse("needs fixed or prescribed nodes (a free body has no equilibrium)");
  }
}

void EfgModel::SolveStatic(const EfgStaticLoads& loads, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  CheckStaticLoads(loads, num_nodes(), "efg");
  system_->SolveStatic(ValuesOf(st->cut.get()), loads, "efg", st);
}

void EfgModel::GatherSprings(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  // Per node the supports' summed stiffness, every spring's Σ k (target - X_I), and the
  // distinct attached nodes with their summed stiffness (all of them: the capacity is
  // num_nodes).
  GatherSupportSprings(inputs, system_->rest, system_->penalty, st);
  for (const Attachment& grasp : inputs.attachments) {
    st->springs.col(grasp.node) += grasp.stiffness * (grasp.target - system_->rest.col(grasp.node));
  }
  st->slots.Gather(inputs.attachments);
  std::copy(st->support.begin(), st->support.end(), st->stiffness.begin());
  for (size_t j = 0; j < size_t(st->slots.num_attached); ++j) {
    st->stiffness[size_t(st->slots.attached_nodes[j])] += st->slots.attached_stiffness[j];
  }
}

bool EfgModel::PrepareFactors(double dt, bool low_rank, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  // The step's system: A0 (supports only) on the low-rank path, else A with the attachments.
  const EfgValues values = ValuesOf(st->cut.get());
  if (system_->UpdateStepFactor(values, dt, low_rank ? st->support : st->stiffness, st)) {
    st->slots.FreeAll();                  // Z = A0⁻¹ U belongs to the old factor
    if (!st->factor_valid) return false;  // cannot happen for a positive mass
  }
  // The static K_s = K + P_s for LocalStiffness (nothing holds a body without supports).
  system_->UpdateStaticFactor(values, st->cut != nullptr, st);
  if (!low_rank || st->slots.num_attached == 0) return true;
  st->slots.Assign([this, st](int32_t slot, int32_t node) { FillLowRankSlot(slot, node, st); });
  return true;
}

void EfgModel::FillLowRankSlot(int32_t slot, int32_t node, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  LowRankSlots& slots = st->slots;
  const auto s = static_cast<Eigen::Index>(slot);
  const std::vector<int32_t>& start = system_->row_start;
  const std::vector<int32_t>& col = system_->row_col;
  // Z's columns: A0⁻¹ Φ_Iᵀ e_k, three solves.
  const double* phi_value = ValuesOf(st->cut.get()).rows;
  const int32_t begin = start[size_t(node)], end = start[size_t(node) + 1];
  for (int k = 0; k < 3; ++k) {
    for (int32_t a = begin; a < end; ++a) {
      st->unit_rhs[3 * size_t(col[size_t(a)]) + size_t(k)] = phi_value[size_t(a)];
    }
    st->factor->Solve(st->unit_rhs.data(), slots.z.col(3 * s + k).data());
    for (int32_t a = begin; a < end; ++a) {
      st->unit_rhs[3 * size_t(col[size_t(a)]) + size_t(k)] = 0.0;
    }
  }
  // G's blocks with every held slot t (this one included): Φ_{I_t} Z_s (3 × 3), mirrored (G
  // is symmetric; the diagonal block is symmetrised).
  for (size_t t = 0; t < slots.slot_node.size(); ++t) {
    const int32_t other = slots.slot_node[t];
    if (other < 0) continue;
    Matrix3d block = Matrix3d::Zero();
    for (int32_t a = start[size_t(other)]; a < start[size_t(other) + 1]; ++a) {
      const Eigen::Index row = 3 * static_cast<Eigen::Index>(col[size_t(a)]);
      block += phi_value[size_t(a)] * slots.z.block<3, 3>(row, 3 * s);
    }
    const auto tt = static_cast<Eigen::Index>(t);
    if (tt == s) block = 0.5 * (block + block.transpose()).eval();
    slots.gram.block<3, 3>(3 * tt, 3 * s) = block;
    slots.gram.block<3, 3>(3 * s, 3 * tt) = block.transpose();
  }
}

bool EfgModel::CorrectForAttachments(double dt, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  LowRankSlots& slots = st->slots;
  const std::vector<int32_t>& start = system_->row_start;
  const std::vector<int32_t>& col = system_->row_col;
  const double* phi_value = ValuesOf(st->cut.get()).rows;
  // Uᵀ x0: Φ_I x0 per attached node.
  for (Eigen::Index i = 0; i < Eigen::Index{slots.num_attached}; ++i) {
    const int32_t node = slots.attached_nodes[size_t(i)];
    Vector3d ux = Vector3d::Zero();
    for (int32_t a = start[size_t(node)]; a < start[size_t(node) + 1]; ++a) {
      ux += phi_value[size_t(a)] *
            Eigen::Map<const Vector3d>(st->dv.data() + 3 * size_t(col[size_t(a)]));
    }
    slots.small_rhs.segment<3>(3 * i) = ux;
  }
  return slots.Correct(dt, Eigen::Map<Eigen::VectorXd>(st->dv.data(), st->dv.size()));
}

void EfgModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  // 1. Springs at the node points and the distinct attached nodes.
  GatherSprings(inputs, st);
  // 2. The factors: A0 and the attached nodes' slots, or A with the attachments inside.
  const bool low_rank = st->slots.num_attached <= max_low_rank_nodes_;
  if (!PrepareFactors(inputs.dt, low_rank, st)) {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
    return;
  }
  // 3–5. The node-point loads and the right-hand side b.
  const EfgValues values = ValuesOf(st->cut.get());
  system_->StepRightHandSide(values, inputs, st);
  // 6. Solve, correct for the attachments, update the parameters, then the physical positions
  // and velocities.
  st->factor->Solve(st->rhs.data(), st->dv.data());
  if (low_rank && st->slots.num_attached > 0 && !CorrectForAttachments(inputs.dt, st)) {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
    return;
  }
  system_->ApplyVelocityChange(values, inputs.dt, st);
}

}  // namespace somasim::models::meshless
