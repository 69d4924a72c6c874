#include "server/models/meshless/efg_hybrid_model.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/checks/finite.h"
#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/adaptivity.h"
#include "server/models/meshless/efg_hybrid_internal.h"
#include "server/models/meshless/efg_shared.h"
#include "server/models/meshless/efg_system.h"
#include "server/models/particle_mesh.h"

namespace somasim::models::meshless {
namespace {

using hybrid_internal::HybridState;
using hybrid_internal::Index;
using hybrid_internal::kFreeShift;
using hybrid_internal::Matrix3d;
using hybrid_internal::MatrixXd;
using hybrid_internal::NonZero;
using hybrid_internal::RowMatrix;
using hybrid_internal::Vector3d;
using hybrid_internal::VectorXd;

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("efg_hybrid: " + what);
}

void CheckParameters(const EfgHybridParameters& p) {
  if (!checks::FinitePositive(p.region_radius)) {
    Refuse("region_radius [m] must be a finite value > 0");
  }
  if (!(p.follow_fraction > 0.0 && p.follow_fraction <= 1.0)) {
    Refuse("follow_fraction must lie in (0, 1]");
  }
  if (!(p.max_region_nodes >= 1 && p.max_region_nodes <= 4096)) {
    Refuse("max_region_nodes must lie in 1..4096");
  }
  if (!(p.adapt_interval >= 1)) Refuse("adapt_interval must be >= 1");
  if (!(p.refine_threshold > 0.0 && p.refine_threshold <= 1.0)) {
    Refuse("refine_threshold must lie in (0, 1]");
  }
  if (!(p.coarsen_threshold >= 0.0 && p.coarsen_threshold <= p.refine_threshold)) {
    Refuse("coarsen_threshold must lie in [0, refine_threshold]");
  }
  if (p.region_centre.hasNaN() == false && !p.region_centre.allFinite()) {
    Refuse("region_centre [m] must be finite (or NaN: the tool decides)");
  }
}

}  // namespace

EfgHybridModel::EfgHybridModel() = default;
EfgHybridModel::~EfgHybridModel() = default;

std::unique_ptr<EfgHybridModel> EfgHybridModel::FromTetMesh(const mesh::TetMesh& mesh,
                                                            const EfgHybridParameters& parameters) {
  CheckParameters(parameters);
  std::unique_ptr<EfgHybridModel> model(new EfgHybridModel());
  model->efg_ = EfgModel::FromTetMesh(mesh, parameters.efg);
  model->parameters_ = parameters;
  model->centroid_ = model->efg_->system_->rest.rowwise().mean();
  model->tets_ = mesh.tetrahedra;
  if (parameters.adaptive) {
    model->intensity_ =
        std::make_unique<CellIntensityEvaluator>(model->efg_->shape_functions(), model->tets_);
  }
  model->set_speed_limit(parameters.efg.speed_limit);
  return model;
}

int32_t EfgHybridModel::num_nodes() const { return efg_->num_nodes(); }

std::unique_ptr<TissueState> EfgHybridModel::MakeState() const {
  auto st = std::make_unique<HybridState>();
  const int32_t n = num_nodes();
  const auto nn = size_t(n);
  const int32_t c = parameters_.efg.max_low_rank_nodes;
  const EfgSystem& system = *efg_->system_;
  InitialiseState(system.rest, st.get());
  st->kept_of.assign(nn, -1);
  st->touches_far.assign(nn, 0);
  st->slots.Size(c, n, c);  // more distinct attached nodes than slots: the step is refused
  st->support.assign(nn, 0.0);
  st->cached_support.assign(nn, -1.0);  // never a stiffness: the first step factorises
  st->support_target = mesh::Points::Zero(3, n);
  st->anchor = system.rest;
  st->fixed_now.assign(nn, 0);
  st->fixed_prev.assign(nn, 0);
  st->support_nodes.reserve(nn);
  st->support_listed.assign(nn, 0);
  st->system.size = 3 * n;
  st->system.col_start = system.csc_col_start;
  st->system.rows = system.csc_rows;
  st->system.values.assign(system.csc_rows.size(), 0.0);
  st->blocks.assign(system.k_blocks.size(), 0.0);
  st->static_factor = std::make_unique<fem::SparseCholesky>();
  st->static_factor->Analyse(st->system);
  for (mesh::Points* p : {&st->far_loads, &st->cached_far_loads, &st->offset_l, &st->param_offset_l,
                          &st->full_rhs, &st->full_solution, &st->full_phi, &st->offsets}) {
    *p = mesh::Points::Zero(3, n);
  }
  st->local_stiffness.assign(9 * nn, 0.0);
  st->local_valid.assign(nn, 0);
  st->refined.assign(nn, 0);
  return st;
}

Eigen::Matrix3d EfgHybridModel::LocalStiffness(const TissueState& base, int32_t node) const {
  const auto& st = static_cast<const HybridState&>(base);
  if (!st.partitioned || !st.has_supports || node < 0 || node >= num_nodes()) {
    return Matrix3d::Zero();
  }
  auto* cached = const_cast<double*>(st.local_stiffness.data()) + 9 * size_t(node);
  if (st.local_valid[size_t(node)] != 0) return Eigen::Map<const Matrix3d>(cached);
  const auto di = st.d.middleRows<3>(3 * Index(node));
  auto& work = const_cast<MatrixXd&>(st.local_work);  // sized by the partition
  work.noalias() = st.s_inv * di.transpose();
  const Matrix3d compliance = di * work;
  const Matrix3d stiffness = compliance.inverse();
  Eigen::Map<Matrix3d> out(cached);
  out = 0.5 * (stiffness + stiffness.transpose());
  const_cast<uint8_t&>(st.local_valid[size_t(node)]) = 1;
  return Eigen::Map<const Matrix3d>(cached);
}

mesh::Points EfgHybridModel::NodalParameters(const TissueState& base) const {
  const auto& st = static_cast<const HybridState&>(base);
  const int32_t n = num_nodes();
  if (!st.partitioned) return mesh::Points::Zero(3, n);
  VectorXd params = st.t * st.q;
  params += Eigen::Map<const VectorXd>(st.param_offset_l.data(), 3 * Index(n));
  params += st.param_offset_g * st.gravity;
  return Eigen::Map<const mesh::Points>(params.data(), 3, n);
}

void EfgHybridModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  efg_->ForcesOfParameters(NodalParameters(state), forces,
                           static_cast<const HybridState&>(state).cut.get());
}

const EfgCutValues* EfgHybridModel::CutOf(const TissueState& state) const {
  return static_cast<const HybridState&>(state).cut.get();
}

int32_t EfgHybridModel::Cut(const SweptQuad& sweep, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  if (!sweep.AllFinite()) return 0;
  if (st->cut == nullptr) st->cut = std::make_unique<EfgCutValues>();
  const int64_t hidden = efg_->ApplyCut(efg_->PullBack(sweep, st->positions), st->cut.get());
  if (hidden == 0) return 0;
  // The next step factorises the cut K̃ and partitions again; the physical field carries over.
  if (st->partitioned) {
    const mesh::Points displacements = st->positions - efg_->system_->rest;
    st->carry =
        efg_->ParametersOfDisplacements(displacements, &st->carried_params, st->cut.get()) &&
        efg_->ParametersOfDisplacements(st->velocities, &st->carried_vparams, st->cut.get());
  }
  st->cut_pending = true;
  return static_cast<int32_t>(std::min<int64_t>(hidden, std::numeric_limits<int32_t>::max()));
}

EnergyReport EfgHybridModel::Energy(const TissueState& state, const Vector3d& gravity) const {
  EnergyReport report;
  report.elastic = efg_->ElasticEnergyOfParameters(
      NodalParameters(state), static_cast<const HybridState&>(state).cut.get());
  AddKineticAndGravity(efg_->system_->mass, state, gravity, &report);
  return report;
}

void EfgHybridModel::SolveStatic(const EfgStaticLoads& loads, TissueState* base) const {
  auto* st = static_cast<HybridState*>(base);
  const int32_t n = num_nodes();
  const mesh::Points& rest = efg_->system_->rest;
  if (loads.parameter_forces != nullptr) {
    Refuse("SolveStatic: parameter_forces (distributed loads) are not supported by the hybrid");
  }
  CheckStaticLoads(loads, n, "efg_hybrid");
  // Supports: fixed at rest, prescribed at their positions.
  std::fill(st->support.begin(), st->support.end(), 0.0);
  mesh::Points h = mesh::Points::Zero(3, n);
  AddStaticSupports(loads, rest, efg_->system_->penalty, &st->support, &h);
  if (loads.external_forces != nullptr) h += *loads.external_forces;
  if (!FactoriseStatic(st)) {
    throw std::runtime_error(
        "efg_hybrid: SolveStatic: K + penalties is not positive definite "
        "(too few held nodes to remove the rigid motions)");
  }
  Vector3d centre = parameters_.region_centre;
  if (!centre.allFinite()) {
    Index largest = 0;
    if (loads.external_forces != nullptr && !loads.external_forces->isZero(0.0)) {
      loads.external_forces->colwise().squaredNorm().maxCoeff(&largest);
    } else {
      (rest.colwise() - centroid_).colwise().squaredNorm().minCoeff(&largest);
    }
    centre = rest.col(largest);
  }
  Partition(centre, st);
  const Index rows = 3 * Index(n);
  // q = S⁻¹ Dᵀ (h + m g); the far-reaching part of h adds its particular response.
  VectorXd rhs = st->g_r * loads.gravity;
  for (int32_t i = 0; i < n; ++i) {
    if (NonZero(h.col(i).data())) rhs += st->d.middleRows<3>(3 * Index(i)).transpose() * h.col(i);
  }
  st->q = st->s_inv * rhs;
  st->vq.setZero();
  st->far_loads.setZero();
  bool any_far = false;
  for (int32_t i = 0; i < n; ++i) {
    if (st->touches_far[size_t(i)] != 0 && NonZero(h.col(i).data())) {
      st->far_loads.col(i) = h.col(i);
      any_far = true;
    }
  }
  if (any_far && st->shift == 0.0) {
    ParticularResponse(st->far_loads.data(), st->offset_l.data(), st);
    std::copy(st->full_solution.data(), st->full_solution.data() + rows, st->param_offset_l.data());
    ++st->far_solves;
  }
  st->gravity = loads.gravity;
  st->offsets = st->offset_l;
  Eigen::Map<VectorXd>(st->offsets.data(), rows).noalias() += st->offset_g * loads.gravity;
  // The supports as a step would have gathered them, so the next step starts from them.
  st->support_nodes.clear();
  for (int32_t i = 0; i < n; ++i) {
    st->support_listed[size_t(i)] = uint8_t(st->support[size_t(i)] > 0.0);
    if (st->support[size_t(i)] > 0.0) st->support_nodes.push_back(i);
  }
  for (Index r = 0; r < rows; ++r) {
    st->positions.data()[r] = rest.data()[r] + st->offsets.data()[r] + st->d.row(r).dot(st->q);
  }
  st->velocities.setZero();
  st->good_q = st->q;
  st->good_vq = st->vq;
}

int64_t EfgHybridModel::Adaptations(const TissueState& state) const {
  return static_cast<const HybridState&>(state).adaptations;
}

int32_t EfgHybridModel::RegionNodes(const TissueState& state) const {
  return int32_t(static_cast<const HybridState&>(state).kept.size());
}

bool EfgHybridModel::InRegion(const TissueState& state, int32_t node) const {
  const auto& st = static_cast<const HybridState&>(state);
  return node >= 0 && node < num_nodes() && st.kept_of[size_t(node)] >= 0;
}

Vector3d EfgHybridModel::RegionCentre(const TissueState& state) const {
  return static_cast<const HybridState&>(state).centre;
}

int64_t EfgHybridModel::Partitions(const TissueState& state) const {
  return static_cast<const HybridState&>(state).partitions;
}

int64_t EfgHybridModel::Factorisations(const TissueState& state) const {
  return static_cast<const HybridState&>(state).factorisations;
}

int64_t EfgHybridModel::FarSolves(const TissueState& state) const {
  return static_cast<const HybridState&>(state).far_solves;
}

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
