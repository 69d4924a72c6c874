// FemModel: construction and parameter checks, the state, the tissue-model queries (forces,
// energy, local stiffness) and the implicit Euler step. The element kernels, assembly, the step's
// vector pass, QLV, cutting and statics have files of their own (fem_*.cc).
#include "server/models/fem/fem_model.h"

#include <Eigen/Core>
#include <algorithm>
#include <cassert>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/checks/finite.h"
#include "server/models/fem/fem_model_internal.h"
#include "server/models/particle_mesh.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using internal::FemState;
using internal::Refuse;

// Refuses parameters out of the ranges fem_model.h gives them, naming the first bad one.
void CheckParameters(const FemParameters& p) {
  const auto finite_positive = [](double value, const char* what) {
    if (!checks::FinitePositive(value)) Refuse(std::string(what) + " must be a finite value > 0");
  };
  if (p.kind == FemKind::kHyperelastic) {
    CheckMaterial(p.hyperelastic);
  } else {
    finite_positive(p.youngs_modulus, "youngs_modulus [Pa]");
  }
  finite_positive(p.density, "density [kg/m^3]");
  finite_positive(p.speed_limit, "speed_limit [m/s]");
  finite_positive(p.cg_tolerance, "cg_tolerance");
  if (p.kind != FemKind::kHyperelastic && !(p.poisson_ratio > -1.0 && p.poisson_ratio < 0.5)) {
    Refuse("poisson_ratio must lie in (-1, 0.5)");
  }
  if (!checks::FiniteNonNegative(p.rayleigh_mass) ||
      !checks::FiniteNonNegative(p.rayleigh_stiffness)) {
    Refuse("rayleigh_mass [1/s] and rayleigh_stiffness [s] must be finite and >= 0");
  }
  if (!(p.cg_max_iterations > 0)) Refuse("cg_max_iterations must be > 0");
  if (p.prony.size() > kMaxPronyTerms) {
    Refuse("at most " + std::to_string(kMaxPronyTerms) + " Prony terms");
  }
  double gamma_sum = 0.0;
  for (size_t k = 0; k < p.prony.size(); ++k) {
    const PronyTerm& t = p.prony[k];
    if (!checks::FiniteNonNegative(t.gamma) || !checks::FinitePositive(t.tau)) {
      Refuse("Prony term " + std::to_string(k + 1) + " needs gamma >= 0 and tau [s] > 0");
    }
    gamma_sum += t.gamma;
  }
  if (!(gamma_sum <= 1.0)) {
    Refuse("the Prony gammas sum to more than 1 (G(0) = 1 needs gamma_inf = 1 - sum >= 0)");
  }
}

}  // namespace

std::unique_ptr<FemModel> FemModel::FromTetMesh(const mesh::TetMesh& mesh,
                                                const FemParameters& parameters) {
  CheckParameters(parameters);
  std::unique_ptr<FemModel> model(new FemModel());
  model->elements_ = BuildTetElements(mesh, "fem");
  model->rest_ = mesh.vertices;
  model->pattern_ = BlockSparseMatrix::FromTets(mesh.tetrahedra, model->num_nodes());
  if (parameters.kind != FemKind::kHyperelastic) {
    model->upper_pattern_ = BlockSparseMatrix::FromTets(mesh.tetrahedra, model->num_nodes(), true);
  }
  model->mass_.resize(model->elements_.node_volume.size());
  for (size_t i = 0; i < model->mass_.size(); ++i) {
    model->mass_[i] = parameters.density * model->elements_.node_volume[i];
  }
  const double e = parameters.youngs_modulus, nu = parameters.poisson_ratio;
  model->lambda_ = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
  model->mu_ = e / (2.0 * (1.0 + nu));
  model->kind_ = parameters.kind;
  model->material_ = parameters.hyperelastic;
  model->prony_ = parameters.prony;
  if (parameters.kind == FemKind::kHyperelastic) {  // λ, μ at rest (the rest stiffness)
    const double k0 = parameters.hyperelastic.InitialBulkModulus();
    model->mu_ = parameters.hyperelastic.InitialShearModulus();
    model->lambda_ = k0 - 2.0 * model->mu_ / 3.0;
  }
  model->rayleigh_mass_ = parameters.rayleigh_mass;
  model->rayleigh_stiffness_ = parameters.rayleigh_stiffness;
  model->cg_tolerance_ = parameters.cg_tolerance;
  model->cg_max_iterations_ = parameters.cg_max_iterations;
  model->cg_fixed_iterations_ = parameters.cg_fixed_iterations;
  model->set_speed_limit(parameters.speed_limit);
  return model;
}

std::unique_ptr<TissueState> FemModel::MakeState() const {
  auto state = std::make_unique<FemState>();
  InitialiseState(rest_, state.get());
  state->matrix = kind_ == FemKind::kHyperelastic ? pattern_ : upper_pattern_;
  state->rest = rest_;
  state->gradients = elements_.gradients;
  state->volumes = elements_.volumes;
  state->rest_move = mesh::Points::Zero(3, num_nodes());
  state->cg = CgScratch(num_nodes());
  state->rotations.assign(9 * static_cast<size_t>(num_tets()), 0.0);
  for (size_t e = 0; e < static_cast<size_t>(num_tets()); ++e) {
    Eigen::Map<Matrix3d>(state->rotations.data() + 9 * e).setIdentity();
  }
  // Warm starts for the corotational model's rotations (the others have none).
  const size_t rotated = kind_ == FemKind::kCorotational ? static_cast<size_t>(num_tets()) : 0;
  state->quaternions.assign(4 * rotated, 0.0);
  for (size_t e = 0; e < rotated; ++e) state->quaternions[4 * e] = 1.0;
  state->good_quaternions = state->quaternions;
  for (mesh::Points* p : {&state->forces, &state->rhs, &state->dv, &state->temp, &state->good_dv}) {
    *p = mesh::Points::Zero(3, num_nodes());
  }
  state->constrained.assign(static_cast<size_t>(num_nodes()), 0);
  const size_t m = static_cast<size_t>(num_tets());
  for (std::vector<double>* v : {&state->history, &state->good_history}) {
    v->assign(9 * prony_.size() * m, 0.0);
  }
  for (std::vector<double>* v : {&state->elastic_last, &state->offset, &state->good_elastic_last}) {
    v->assign(prony_.empty() ? 0 : 9 * m, 0.0);
  }
  return state;
}

FemModel::Shape FemModel::ShapeOf(const TissueState& base) const {
  const auto& state = static_cast<const FemState&>(base);
  return {state.rest, state.gradients, state.volumes, elements_.tets};
}

bool FemModel::ElementAlive(const TissueState& state, int32_t e) const {
  assert(e >= 0 && e < num_tets());
  return static_cast<const FemState&>(state).volumes[static_cast<size_t>(e)] > 0.0;
}

const mesh::Points& FemModel::RestPositions(const TissueState& state) const {
  return static_cast<const FemState&>(state).rest;
}

double FemModel::LastSolverResidual(const TissueState& state) const {
  return static_cast<const FemState&>(state).last_cg_residual;
}

void FemModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  forces->resize(3, num_nodes());
  const Shape sh = ShapeOf(state);
  ElasticForces(sh, state.positions, forces->data(), nullptr);
  if (rayleigh_mass_ > 0.0 || rayleigh_stiffness_ > 0.0) {
    // -C v = -α M v - β K v, K the warped stiffness at the state.
    for (int32_t i = 0; i < num_nodes(); ++i) {
      forces->col(i) -= rayleigh_mass_ * mass_[static_cast<size_t>(i)] * state.velocities.col(i);
    }
    if (rayleigh_stiffness_ > 0.0) {
      for (int32_t e = 0; e < num_tets(); ++e) {
        if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
        const Eigen::Matrix<double, 12, 12> k = ElementTangentOf(sh, state.positions, e, false);
        for (int a = 0; a < 4; ++a) {
          Vector3d kv = Vector3d::Zero();
          for (int b = 0; b < 4; ++b) {
            kv += k.block<3, 3>(3 * a, 3 * b) * state.velocities.col(elements_.tets(b, e));
          }
          forces->col(elements_.tets(a, e)) -= rayleigh_stiffness_ * kv;
        }
      }
    }
  }
}

EnergyReport FemModel::Energy(const TissueState& state, const Eigen::Vector3d& gravity) const {
  EnergyReport report;
  report.elastic = ElasticEnergy(ShapeOf(state), state.positions, nullptr);
  AddKineticAndGravity(mass_, state, gravity, &report);
  return report;
}

Eigen::Matrix3d FemModel::LocalStiffness(const TissueState& state, int32_t node) const {
  assert(node >= 0 && node < num_nodes());
  const Shape sh = ShapeOf(state);
  Matrix3d k = Matrix3d::Zero();
  for (int32_t k_index = elements_.node_start[static_cast<size_t>(node)];
       k_index < elements_.node_start[static_cast<size_t>(node) + 1]; ++k_index) {
    const int32_t packed = elements_.element_of_node[static_cast<size_t>(k_index)];
    const int32_t e = packed / 4;
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const int a = packed % 4;
    if (kind_ == FemKind::kHyperelastic) {
      k += ElementTangentOf(sh, state.positions, e, true).block<3, 3>(3 * a, 3 * a);
      continue;
    }
    Matrix3d r = Matrix3d::Identity();
    if (kind_ == FemKind::kCorotational) {  // from the element's rotation in the last step
      const double* last = static_cast<const FemState&>(state).quaternions.data() + 4 * e;
      double q[4] = {last[0], last[1], last[2], last[3]};
      r = PolarRotationFrom(Matrix3d::Identity() + DisplacementGradientOf(sh, state.positions, e),
                            q);
    }
    k += r * RestBlock(sh, e, a, a) * r.transpose();
  }
  return k;
}

void FemModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<FemState*>(base);
  const Shape sh = ShapeOf(*state);
  const double dt = inputs.dt;
  const auto n = static_cast<size_t>(num_nodes());
  const double alpha = rayleigh_mass_, beta = rayleigh_stiffness_;
  // QLV: this step's stress is g S^e + offset (ViscousStep); elastic models skip it.
  ViscousStep viscous;
  const ViscousStep* const visc = prony_.empty() ? nullptr : &viscous;
  if (visc != nullptr) viscous = BeginViscousStep(*state, dt, state->offset.data());
  // f(x) and the rotations, then A = (1 + dt α) M + (dt² + dt β) K.
  const double k_scale = dt * dt + dt * beta;
  const double m_scale = 1.0 + dt * alpha;
  if (kind_ == FemKind::kHyperelastic) {
    ElasticForces(sh, state->positions, state->forces.data(), state->rotations.data(), visc);
    AssembleWarped(sh, state->positions, state->rotations.data(), k_scale, m_scale, &state->matrix,
                   visc);
  } else {  // one pass over the elements for both
    ForcesAndWarpedMatrix(sh, state->positions, state->forces.data(), state->rotations.data(),
                          state->quaternions.data(), visc, k_scale, m_scale, &state->matrix);
  }
  // K v = (A v - m_scale M v) / k_scale (before the grasps join A: they have no damping).
  double* const kv = state->temp.data();
  const double* const v = state->velocities.data();
  state->matrix.Multiply(v, kv, nullptr);
  for (size_t i = 0; i < n; ++i) {
    for (size_t c = 0; c < 3; ++c) {
      kv[3 * i + c] = (kv[3 * i + c] - m_scale * mass_[i] * v[3 * i + c]) / k_scale;
    }
  }
  // b = dt (f(x) + f_ext + M g - α M v - (β + dt) K v).
  double* const b = state->rhs.data();
  const double* const f = state->forces.data();
  const double* const external =
      inputs.external_forces != nullptr ? inputs.external_forces->data() : nullptr;
  for (size_t i = 0; i < n; ++i) {
    for (size_t c = 0; c < 3; ++c) {
      const size_t k = 3 * i + c;
      const double ext = external != nullptr ? external[k] : 0.0;
      b[k] = dt * (f[k] + ext +
                   mass_[i] * (inputs.gravity[static_cast<Eigen::Index>(c)] - alpha * v[k]) -
                   (beta + dt) * kv[k]);
    }
  }
  // Grasps: f = k (target - x), stiffness k I (implicit in x: dt² k on A, -dt² k v in b).
  for (const Attachment& grasp : inputs.attachments) {
    const auto i = static_cast<size_t>(grasp.node);
    state->matrix.block(state->matrix.diagonal_block(grasp.node)).diagonal().array() +=
        dt * dt * grasp.stiffness;
    for (size_t c = 0; c < 3; ++c) {
      const auto ci = static_cast<Eigen::Index>(c);
      b[3 * i + c] += dt * grasp.stiffness *
                      (grasp.target[ci] - state->positions(ci, grasp.node) - dt * v[3 * i + c]);
    }
  }
  // Dirichlet nodes: Δv known (fixed: -v; prescribed: reach the target in dt); their columns
  // move to the right-hand side.
  std::fill(state->constrained.begin(), state->constrained.end(), uint8_t{0});
  double* const known = state->temp.data();  // K v is no longer needed
  std::fill(known, known + 3 * n, 0.0);
  for (const int32_t node : inputs.fixed_nodes) {
    const auto i = static_cast<size_t>(node);
    state->constrained[i] = 1;
    for (size_t c = 0; c < 3; ++c) known[3 * i + c] = -v[3 * i + c];
  }
  for (size_t k = 0; k < inputs.prescribed_nodes.size(); ++k) {
    const auto i = static_cast<size_t>(inputs.prescribed_nodes[k]);
    state->constrained[i] = 1;
    for (size_t c = 0; c < 3; ++c) {
      const auto ci = static_cast<Eigen::Index>(c);
      known[3 * i + c] = (inputs.prescribed_positions->coeff(ci, static_cast<Eigen::Index>(k)) -
                          state->positions(ci, static_cast<Eigen::Index>(i))) /
                             dt -
                         v[3 * i + c];
    }
  }
  // Held nodes at rest (a fixed node after its first step, a prescribed one whose target stays)
  // know Δv = 0 and move nothing: no product then.
  const bool any_known = std::any_of(known, known + 3 * n, [](double k) { return k != 0.0; });
  if (any_known) {
    double* const moved = state->cg.product.data();  // free before the solve
    state->matrix.Multiply(known, moved, nullptr);
    for (size_t i = 0; i < n; ++i) {
      for (size_t c = 0; c < 3; ++c) {
        b[3 * i + c] =
            state->constrained[i] != 0 ? known[3 * i + c] : b[3 * i + c] - moved[3 * i + c];
      }
    }
  } else {
    for (size_t i = 0; i < n; ++i) {
      if (state->constrained[i] != 0) std::fill(b + 3 * i, b + 3 * i + 3, 0.0);
    }
  }
  const CgResult cg =
      ConjugateGradients(state->matrix, state->constrained.data(), b, state->dv.data(),
                         cg_tolerance_, cg_max_iterations_, &state->cg, cg_fixed_iterations_);
  state->counters.solver_iterations += cg.iterations;
  if (!cg.converged) ++state->counters.solver_unconverged;
  state->last_cg_residual = cg.relative_residual;
  state->velocities += state->dv;
  state->positions += dt * state->velocities;
  ApplyFixedAndPrescribed(inputs, state);
  if (visc != nullptr) EndViscousStep(dt, state);  // a rejected step restores h (RestoreGood)
}

}  // namespace somasim::models::fem
