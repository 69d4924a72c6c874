#include "server/models/meshless/efg_model.h"

#include <Eigen/LU>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/efg_internal.h"
#include "server/models/meshless/efg_shared.h"
#include "server/models/meshless/small_cholesky.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

// σ [1/s²]: the mass shift of the static K_s when a cut has severed an unsupported piece.
constexpr double kSeveredShift = 1.0;

}  // namespace

using efg_internal::EfgState;
using efg_internal::PhiMatrix;
using efg_internal::SolvePhi;
using efg_internal::TrianglesNear;

EfgModel::EfgModel() = default;
EfgModel::~EfgModel() = default;

EfgModel::Values EfgModel::ValuesOf(const EfgCutValues* cut) const {
  if (cut == nullptr || cut->phi_value.empty()) {
    return {phi_value_.data(), k_blocks_.data(), m_blocks_.data()};
  }
  return {cut->phi_value.data(), cut->k_blocks.data(), cut->m_blocks.data()};
}

int64_t EfgModel::BlockIndex(int32_t row, int32_t col) const {
  const auto begin = block_row_.begin() + block_start_[size_t(col)];
  const auto end = block_row_.begin() + block_start_[size_t(col) + 1];
  const auto it = std::lower_bound(begin, end, row);
  return it != end && *it == row ? static_cast<int64_t>(it - block_row_.begin()) : -1;
}

std::unique_ptr<TissueState> EfgModel::MakeState() const {
  auto state = std::make_unique<EfgState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = num_nodes();
  for (mesh::Points* p :
       {&state->params, &state->vparams, &state->good_params, &state->good_vparams, &state->u,
        &state->v, &state->h, &state->rhs, &state->dv, &state->work, &state->springs}) {
    *p = mesh::Points::Zero(3, n);
  }
  state->anchor = rest_;
  state->fixed_now.assign(size_t(n), 0);
  state->fixed_prev.assign(size_t(n), 0);
  state->support.assign(size_t(n), 0.0);
  state->stiffness.assign(size_t(n), 0.0);
  state->attached_nodes.assign(size_t(n), 0);
  state->attached_stiffness.assign(size_t(n), 0.0);
  state->attached_sum.assign(size_t(n), 0.0);
  state->cached_stiffness.assign(size_t(n), 0.0);
  state->cached_support.assign(size_t(n), 0.0);
  const auto slots = static_cast<Eigen::Index>(max_low_rank_nodes_);
  state->z = Eigen::MatrixXd::Zero(3 * n, 3 * slots);
  state->gram = Eigen::MatrixXd::Zero(3 * slots, 3 * slots);
  state->small = Eigen::MatrixXd::Zero(3 * slots, 3 * slots);
  state->small_rhs = Eigen::VectorXd::Zero(3 * slots);
  state->slot_node.assign(size_t(slots), -1);
  state->slot_of_node.assign(size_t(n), -1);
  state->attached_slot.assign(size_t(slots), -1);
  state->slot_stamp.assign(size_t(slots), -1);
  state->unit_rhs.assign(3 * size_t(n), 0.0);
  state->a_blocks.assign(k_blocks_.size(), 0.0);
  state->system.size = 3 * static_cast<int32_t>(n);
  state->system.col_start = csc_col_start_;
  state->system.rows = csc_rows_;
  state->system.values.assign(csc_rows_.size(), 0.0);
  state->factor = std::make_unique<fem::SparseCholesky>();
  state->factor->Analyse(state->system);
  state->static_factor = std::make_unique<fem::SparseCholesky>();
  state->static_factor->Analyse(state->system);
  state->local_rhs.assign(3 * size_t(n), 0.0);
  state->local_solution.assign(3 * size_t(n), 0.0);
  state->local_stiffness.assign(9 * size_t(n), 0.0);
  state->local_valid.assign(size_t(n), 0);
  return state;
}

int64_t EfgModel::Factorisations(const TissueState& state) const {
  return static_cast<const EfgState&>(state).factorisations;
}

const mesh::Points& EfgModel::NodalParameters(const TissueState& state) const {
  return static_cast<const EfgState&>(state).params;
}

void EfgModel::MultiplyStiffness(const Values& values, const double* x, double* y) const {
  const double* k_blocks = values.k;
  const auto n = size_t(num_nodes());
  std::fill(y, y + 3 * n, 0.0);
  for (size_t c = 0; c < n; ++c) {
    const Eigen::Map<const Vector3d> xc(x + 3 * c);
    Eigen::Map<Vector3d> yc(y + 3 * c);
    const auto begin = size_t(block_start_[c]), end = size_t(block_start_[c + 1]);
    yc.noalias() += Eigen::Map<const Matrix3d>(k_blocks + 9 * begin) * xc;  // diagonal
    for (size_t slot = begin + 1; slot < end; ++slot) {
      const auto r = size_t(block_row_[slot]);
      const Eigen::Map<const Matrix3d> block(k_blocks + 9 * slot);
      Eigen::Map<Vector3d>(y + 3 * r).noalias() += block * xc;
      yc.noalias() += block.transpose() * Eigen::Map<const Vector3d>(x + 3 * r);
    }
  }
}

void EfgModel::MultiplyPhi(const Values& values, const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  const double* phi_value = values.phi;
  for (size_t i = 0; i < n; ++i) {
    Vector3d sum = Vector3d::Zero();
    for (auto k = size_t(phi_start_[i]); k < size_t(phi_start_[i + 1]); ++k) {
      sum += phi_value[k] * Eigen::Map<const Vector3d>(x + 3 * size_t(phi_node_[k]));
    }
    Eigen::Map<Vector3d>(y + 3 * i) = sum;
  }
}

void EfgModel::MultiplyPhiTransposed(const Values& values, const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  const double* phi_value = values.phi;
  std::fill(y, y + 3 * n, 0.0);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Map<const Vector3d> xi(x + 3 * i);
    for (auto k = size_t(phi_start_[i]); k < size_t(phi_start_[i + 1]); ++k) {
      Eigen::Map<Vector3d>(y + 3 * size_t(phi_node_[k])) += phi_value[k] * xi;
    }
  }
}

void EfgModel::AssembleSystem(const Values& matrices, double k_scale, double m_scale,
                              double s_scale, const double* s, double* blocks,
                              double* values) const {
  const double* phi_value = matrices.phi;
  // Blocks first (k_scale K + m_scale M̂ + s_scale Σ s_I Φ_Iᵀ Φ_I), then gathered into the scalar
  // CSC.
  const size_t num_blocks = block_row_.size();
  for (size_t b = 0; b < num_blocks; ++b) {
    Eigen::Map<Matrix3d> block(blocks + 9 * b);
    block = k_scale * Eigen::Map<const Matrix3d>(matrices.k + 9 * b);
    block.diagonal().array() += m_scale * matrices.m[b];
  }
  const auto n = num_nodes();
  for (int32_t i = 0; i < n; ++i) {
    if (s[size_t(i)] == 0.0) continue;
    const int32_t begin = phi_start_[size_t(i)], end = phi_start_[size_t(i) + 1];
    for (int32_t b = begin; b < end; ++b) {
      for (int32_t a = b; a < end; ++a) {
        const int64_t slot = BlockIndex(phi_node_[size_t(a)], phi_node_[size_t(b)]);
        Eigen::Map<Matrix3d>(blocks + 9 * slot).diagonal().array() +=
            s_scale * s[size_t(i)] * phi_value[size_t(a)] * phi_value[size_t(b)];
      }
    }
  }
  for (size_t k = 0; k < csc_source_.size(); ++k) values[k] = blocks[size_t(csc_source_[k])];
}

void EfgModel::NodeDisplacements(const mesh::Points& parameters, mesh::Points* displacements,
                                 const EfgCutValues* cut) const {
  displacements->resize(3, num_nodes());
  MultiplyPhi(ValuesOf(cut), parameters.data(), displacements->data());
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
  if (!st.static_valid || node < 0 || node >= num_nodes()) return Matrix3d::Zero();
  double* cached = st.local_stiffness.data() + 9 * size_t(node);
  if (st.local_valid[size_t(node)] != 0) return Eigen::Map<const Matrix3d>(cached);
  // Column k of the compliance Φ_I K_s⁻¹ Φ_Iᵀ: a unit force along k at the node point.
  const double* phi_value = ValuesOf(st.cut.get()).phi;
  const int32_t begin = phi_start_[size_t(node)], end = phi_start_[size_t(node) + 1];
  Matrix3d compliance;
  for (int k = 0; k < 3; ++k) {
    for (int32_t a = begin; a < end; ++a) {
      st.local_rhs[3 * size_t(phi_node_[size_t(a)]) + size_t(k)] = phi_value[size_t(a)];
    }
    st.static_factor->Solve(st.local_rhs.data(), st.local_solution.data());
    Vector3d sum = Vector3d::Zero();
    for (int32_t a = begin; a < end; ++a) {
      const auto j = 3 * size_t(phi_node_[size_t(a)]);
      sum += phi_value[size_t(a)] * Eigen::Map<const Vector3d>(st.local_solution.data() + j);
      st.local_rhs[j + size_t(k)] = 0.0;
    }
    compliance.col(k) = sum;
  }
  const Matrix3d stiffness = compliance.inverse();
  Eigen::Map<Matrix3d> out(cached);
  out = 0.5 * (stiffness + stiffness.transpose());
  st.local_valid[size_t(node)] = 1;
  return Eigen::Map<const Matrix3d>(cached);
}

bool EfgModel::ParametersOfDisplacements(const mesh::Points& displacements,
                                         mesh::Points* parameters, const EfgCutValues* cut) const {
  const Eigen::MatrixXd u = displacements.transpose();  // num_nodes × 3
  Eigen::MatrixXd params;
  if (cut == nullptr || cut->phi_value.empty()) {
    params = factors_->phi.solve(u);
  } else if (!SolvePhi(PhiMatrix(num_nodes(), phi_start_, phi_node_, cut->phi_value.data()), false,
                       u, &params)) {
    return false;
  }
  *parameters = params.transpose();
  return true;
}

void EfgModel::ForcesOfParameters(const mesh::Points& params, mesh::Points* forces,
                                  const EfgCutValues* cut) const {
  mesh::Points k_params(3, num_nodes());
  MultiplyStiffness(ValuesOf(cut), params.data(), k_params.data());
  // Φᵀ f = -K û: the physical forces whose virtual work on δu = Φ δû is -δûᵀ K û.
  const Eigen::MatrixXd rhs = -k_params.transpose();
  Eigen::MatrixXd f;
  if (cut == nullptr || cut->phi_value.empty()) {
    f = factors_->phi_transposed.solve(rhs);
  } else if (!SolvePhi(PhiMatrix(num_nodes(), phi_start_, phi_node_, cut->phi_value.data()), true,
                       rhs, &f)) {
    f = Eigen::MatrixXd::Zero(num_nodes(), 3);  // cannot happen but for a degenerate cut
  }
  *forces = f.transpose();
}

double EfgModel::ElasticEnergyOfParameters(const mesh::Points& params,
                                           const EfgCutValues* cut) const {
  mesh::Points k_params(3, num_nodes());
  MultiplyStiffness(ValuesOf(cut), params.data(), k_params.data());
  return 0.5 * params.cwiseProduct(k_params).sum();
}

void EfgModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  const EfgCutValues* cut = static_cast<const EfgState&>(state).cut.get();
  mesh::Points params;
  if (!ParametersOfDisplacements(state.positions - rest_, &params, cut)) {
    params = static_cast<const EfgState&>(state).params;
  }
  ForcesOfParameters(params, forces, cut);
}

EnergyReport EfgModel::Energy(const TissueState& state, const Vector3d& gravity) const {
  EnergyReport report;
  const EfgCutValues* cut = static_cast<const EfgState&>(state).cut.get();
  mesh::Points params;
  if (!ParametersOfDisplacements(state.positions - rest_, &params, cut)) {
    params = static_cast<const EfgState&>(state).params;
  }
  report.elastic = ElasticEnergyOfParameters(params, cut);
  for (Eigen::Index i = 0; i < state.positions.cols(); ++i) {
    const double m = mass_[size_t(i)];
    report.kinetic += 0.5 * m * state.velocities.col(i).squaredNorm();
    report.gravity -= m * gravity.dot(state.positions.col(i));
    report.momentum += m * state.velocities.col(i);
  }
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
  const int32_t n = num_nodes();
  CheckStaticLoads(loads, n, "efg");
  // Penalty springs κ: fixed at rest (target displacement 0), prescribed at their positions.
  std::vector<double> s(size_t(n), 0.0);
  mesh::Points h = mesh::Points::Zero(3, n);
  for (const int32_t node : loads.fixed_nodes) s[size_t(node)] += penalty_;
  for (size_t k = 0; k < loads.prescribed_nodes.size(); ++k) {
    const int32_t node = loads.prescribed_nodes[k];
    s[size_t(node)] += penalty_;
    h.col(node) += penalty_ * (loads.prescribed_positions->col(static_cast<Eigen::Index>(k)) -
                               rest_.col(node));
  }
  for (int32_t i = 0; i < n; ++i) h.col(i) += mass_[size_t(i)] * loads.gravity;
  if (loads.external_forces != nullptr) h += *loads.external_forces;
  const Values values = ValuesOf(st->cut.get());
  mesh::Points rhs(3, n), solution(3, n);
  MultiplyPhiTransposed(values, h.data(), rhs.data());
  if (loads.parameter_forces != nullptr) rhs += *loads.parameter_forces;

  fem::LowerCsc system;
  system.size = 3 * n;
  system.col_start = csc_col_start_;
  system.rows = csc_rows_;
  system.values.assign(csc_rows_.size(), 0.0);
  std::vector<double> blocks(k_blocks_.size());
  AssembleSystem(values, 1.0, 0.0, 1.0, s.data(), blocks.data(), system.values.data());
  fem::SparseCholesky cholesky;
  cholesky.Analyse(system);
  if (!cholesky.Factorise(system)) {
    throw std::runtime_error(
        "efg: SolveStatic: K + penalties is not positive definite "
        "(too few held nodes to remove the rigid motions)");
  }
  cholesky.Solve(rhs.data(), solution.data());
  st->params = solution;
  st->vparams.setZero();
  MultiplyPhi(values, st->params.data(), st->u.data());
  st->positions = rest_ + st->u;
  st->velocities.setZero();
}

bool EfgModel::PrepareFactors(double dt, bool low_rank, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const double alpha = rayleigh_mass_, beta = rayleigh_stiffness_;
  // The step's system: A0 (supports only) on the low-rank path, else A with the attachments.
  const std::vector<double>& key = low_rank ? st->support : st->stiffness;
  const Values values = ValuesOf(st->cut.get());
  if (!st->factor_valid || dt != st->cached_dt ||
      !std::equal(key.begin(), key.end(), st->cached_stiffness.begin())) {
    AssembleSystem(values, dt * dt + dt * beta, 1.0 + dt * alpha, dt * dt, key.data(),
                   st->a_blocks.data(), st->system.values.data());
    st->factor_valid = st->factor->Factorise(st->system);
    ++st->factorisations;
    st->cached_dt = dt;
    std::copy(key.begin(), key.end(), st->cached_stiffness.begin());
    // Z = A0⁻¹ U belongs to the old factor: every slot is free again.
    for (int32_t& node : st->slot_node) {
      if (node >= 0) st->slot_of_node[size_t(node)] = -1;
      node = -1;
    }
    std::fill(st->slot_stamp.begin(), st->slot_stamp.end(), int64_t{-1});
    if (!st->factor_valid) return false;  // cannot happen for a positive mass
  }
  // The static K_s = K + P_s for LocalStiffness (nothing holds a body without supports).
  if (!st->static_current ||
      !std::equal(st->support.begin(), st->support.end(), st->cached_support.begin())) {
    st->static_valid = false;
    if (std::any_of(st->support.begin(), st->support.end(), [](double s) { return s > 0; })) {
      AssembleSystem(values, 1.0, 0.0, 1.0, st->support.data(), st->a_blocks.data(),
                     st->system.values.data());
      st->static_valid = st->static_factor->Factorise(st->system);
      ++st->factorisations;
      if (!st->static_valid && st->cut != nullptr) {
        // A cut severed a piece the supports do not hold (K_s singular): K_s + σ M̂, σ = 1 /s²
        // (the held piece's stiffness changes by σ/ω² of its own, ~1 % for a liver).
        AssembleSystem(values, 1.0, kSeveredShift, 1.0, st->support.data(), st->a_blocks.data(),
                       st->system.values.data());
        st->static_valid = st->static_factor->Factorise(st->system);
        ++st->factorisations;
      }
    }
    st->static_current = true;
    std::copy(st->support.begin(), st->support.end(), st->cached_support.begin());
    std::fill(st->local_valid.begin(), st->local_valid.end(), uint8_t{0});
  }
  if (!low_rank || st->num_attached == 0) return true;
  // The attached nodes' slots: those already cached are kept (stamped), each new node takes the
  // least recently used slot, which no node of this step holds (num_attached <= slots).
  ++st->stamp;
  const auto m = size_t(st->num_attached);
  for (size_t j = 0; j < m; ++j) {
    const int32_t slot = st->slot_of_node[size_t(st->attached_nodes[j])];
    st->attached_slot[j] = slot;
    if (slot >= 0) st->slot_stamp[size_t(slot)] = st->stamp;
  }
  for (size_t j = 0; j < m; ++j) {
    if (st->attached_slot[j] >= 0) continue;
    const auto oldest = std::min_element(st->slot_stamp.begin(), st->slot_stamp.end());
    const auto slot = static_cast<int32_t>(oldest - st->slot_stamp.begin());
    if (st->slot_node[size_t(slot)] >= 0) {
      st->slot_of_node[size_t(st->slot_node[size_t(slot)])] = -1;
    }
    FillLowRankSlot(slot, st->attached_nodes[j], st);
    st->slot_stamp[size_t(slot)] = st->stamp;
    st->attached_slot[j] = slot;
  }
  return true;
}

void EfgModel::FillLowRankSlot(int32_t slot, int32_t node, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const auto s = static_cast<Eigen::Index>(slot);
  // Z's columns: A0⁻¹ Φ_Iᵀ e_k, three solves.
  const double* phi_value = ValuesOf(st->cut.get()).phi;
  const int32_t begin = phi_start_[size_t(node)], end = phi_start_[size_t(node) + 1];
  for (int k = 0; k < 3; ++k) {
    for (int32_t a = begin; a < end; ++a) {
      st->unit_rhs[3 * size_t(phi_node_[size_t(a)]) + size_t(k)] = phi_value[size_t(a)];
    }
    st->factor->Solve(st->unit_rhs.data(), st->z.col(3 * s + k).data());
    for (int32_t a = begin; a < end; ++a) {
      st->unit_rhs[3 * size_t(phi_node_[size_t(a)]) + size_t(k)] = 0.0;
    }
  }
  st->slot_node[size_t(slot)] = node;
  st->slot_of_node[size_t(node)] = slot;
  // G's blocks with every held slot t (this one included): Φ_{I_t} Z_s (3 × 3), mirrored (G
  // is symmetric; the diagonal block is symmetrised).
  for (size_t t = 0; t < st->slot_node.size(); ++t) {
    const int32_t other = st->slot_node[t];
    if (other < 0) continue;
    Matrix3d block = Matrix3d::Zero();
    for (int32_t a = phi_start_[size_t(other)]; a < phi_start_[size_t(other) + 1]; ++a) {
      const Eigen::Index row = 3 * static_cast<Eigen::Index>(phi_node_[size_t(a)]);
      block += phi_value[size_t(a)] * st->z.block<3, 3>(row, 3 * s);
    }
    const auto tt = static_cast<Eigen::Index>(t);
    if (tt == s) block = 0.5 * (block + block.transpose()).eval();
    st->gram.block<3, 3>(3 * tt, 3 * s) = block;
    st->gram.block<3, 3>(3 * s, 3 * tt) = block.transpose();
  }
}

bool EfgModel::CorrectForAttachments(double dt, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const auto m = static_cast<Eigen::Index>(st->num_attached);
  const Eigen::Index r = 3 * m;
  const double* phi_value = ValuesOf(st->cut.get()).phi;
  // W Uᵀ x0 (W = S^½: dt √k_j per node) and the lower triangle of I + W G W.
  for (Eigen::Index i = 0; i < m; ++i) {
    const int32_t node = st->attached_nodes[size_t(i)];
    const double wi = dt * std::sqrt(st->attached_stiffness[size_t(i)]);
    Vector3d ux = Vector3d::Zero();
    for (int32_t a = phi_start_[size_t(node)]; a < phi_start_[size_t(node) + 1]; ++a) {
      ux += phi_value[size_t(a)] *
            Eigen::Map<const Vector3d>(st->dv.data() + 3 * size_t(phi_node_[size_t(a)]));
    }
    st->small_rhs.segment<3>(3 * i) = wi * ux;
    const auto si = static_cast<Eigen::Index>(st->attached_slot[size_t(i)]);
    for (Eigen::Index j = 0; j <= i; ++j) {
      const double wj = dt * std::sqrt(st->attached_stiffness[size_t(j)]);
      const auto sj = static_cast<Eigen::Index>(st->attached_slot[size_t(j)]);
      st->small.block<3, 3>(3 * i, 3 * j) = (wi * wj) * st->gram.block<3, 3>(3 * si, 3 * sj);
    }
    st->small.block<3, 3>(3 * i, 3 * i).diagonal().array() += 1.0;
  }
  const auto ld = static_cast<int>(st->small.rows());
  if (!CholeskyInPlace(st->small.data(), static_cast<int>(r), ld)) return false;
  CholeskySolveInPlace(st->small.data(), static_cast<int>(r), ld, st->small_rhs.data());
  // dv = x0 - Σ_j Z_j (W y)_j.
  Eigen::Map<Eigen::VectorXd> dv(st->dv.data(), st->dv.size());
  for (Eigen::Index j = 0; j < m; ++j) {
    const double wj = dt * std::sqrt(st->attached_stiffness[size_t(j)]);
    const auto sj = static_cast<Eigen::Index>(st->attached_slot[size_t(j)]);
    const Vector3d y = wj * st->small_rhs.segment<3>(3 * j);
    dv.noalias() -= st->z.middleCols<3>(3 * sj) * y;
  }
  return true;
}

void EfgModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const auto n = size_t(num_nodes());
  const double dt = inputs.dt;
  const double alpha = rayleigh_mass_, beta = rayleigh_stiffness_;

  // 1. Springs at the node points: per node the supports' summed stiffness, every spring's
  // Σ k (target - X_I), and the distinct attached nodes with their summed stiffness.
  GatherSupportSprings(inputs, rest_, penalty_, st);
  for (const Attachment& grasp : inputs.attachments) {
    st->attached_sum[size_t(grasp.node)] += grasp.stiffness;
    st->springs.col(grasp.node) += grasp.stiffness * (grasp.target - rest_.col(grasp.node));
  }
  std::copy(st->support.begin(), st->support.end(), st->stiffness.begin());
  st->num_attached = 0;
  for (const Attachment& grasp : inputs.attachments) {  // in order; each node once
    const auto i = size_t(grasp.node);
    const double k = st->attached_sum[i];
    if (k > 0.0) {
      st->attached_nodes[size_t(st->num_attached)] = grasp.node;
      st->attached_stiffness[size_t(st->num_attached)] = k;
      ++st->num_attached;
      st->stiffness[i] += k;
    }
    st->attached_sum[i] = 0.0;  // marks the node taken and leaves the sums zero
  }

  // 2. The factors: A0 and the attached nodes' slots, or A with the attachments inside.
  const bool low_rank = st->num_attached <= max_low_rank_nodes_;
  if (!PrepareFactors(dt, low_rank, st)) {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
    return;
  }

  // 3. Physical displacements and velocities at the nodes.
  const Values values = ValuesOf(st->cut.get());
  MultiplyPhi(values, st->params.data(), st->u.data());
  MultiplyPhi(values, st->vparams.data(), st->v.data());

  // 4. Node-point forces h_I = f_ext + m_I (g - α v_I) + Σ k (t - X_I) - s_I (u_I + dt v_I).
  const mesh::Points* external = inputs.external_forces;
  for (size_t i = 0; i < n; ++i) {
    const auto c = static_cast<Eigen::Index>(i);
    Vector3d f = mass_[i] * (inputs.gravity - alpha * st->v.col(c)) + st->springs.col(c) -
                 st->stiffness[i] * (st->u.col(c) + dt * st->v.col(c));
    if (external != nullptr) f += external->col(c);
    st->h.col(c) = f;
  }
  // 5. b = dt (Φᵀ h - K (û + (β + dt) v̂)).
  st->work = st->params + (beta + dt) * st->vparams;
  MultiplyStiffness(values, st->work.data(), st->dv.data());
  MultiplyPhiTransposed(values, st->h.data(), st->rhs.data());
  st->rhs = dt * (st->rhs - st->dv);

  // 6. Solve, update the parameters, then the physical positions and velocities.
  st->factor->Solve(st->rhs.data(), st->dv.data());
  if (low_rank && st->num_attached > 0 && !CorrectForAttachments(dt, st)) {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
    return;
  }
  ++st->counters.solver_iterations;
  st->vparams += st->dv;
  st->params += dt * st->vparams;
  MultiplyPhi(values, st->params.data(), st->u.data());
  MultiplyPhi(values, st->vparams.data(), st->velocities.data());
  st->positions = rest_ + st->u;
}

}  // namespace somasim::models::meshless
