#include "server/models/meshless/efg_hybrid_model.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
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
using hybrid_internal::Matrix3d;
using hybrid_internal::MatrixXd;
using hybrid_internal::NonZero;
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

}  // namespace somasim::models::meshless
