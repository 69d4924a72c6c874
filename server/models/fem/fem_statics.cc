// FemModel's static and quasi-static solves: Newton's method on the total potential with load
// stepping, a backtracking line search and CHOLMOD factorisations; the workspace that solves keep
// between calls.
#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "server/models/fem/fem_model.h"
#include "server/models/fem/fem_model_internal.h"
#include "server/models/fem/sparse_cholesky.h"

namespace somasim::models::fem {

using internal::Refuse;

struct StaticWorkspace::Impl {
  const FemModel* owner = nullptr;  // the model the pattern below belongs to
  std::vector<int32_t> dof;         // 3 × num_nodes: free DOF number, or -1 where held
  std::vector<int32_t> lower_dof;   // the numbering k_free (and the analysis) is for
  BlockSparseMatrix tangent;        // the model's pattern
  LowerCsc k_free;                  // the tangent on the free DOFs, scalar lower triangle
  std::vector<int32_t> k_source;    // k_free.values[k] = tangent value k_source[k]
  SparseCholesky cholesky;
  bool analysed = false;       // cholesky holds the analysis of k_free's pattern
  bool factorised = false;     // and a factor of a tangent on these free DOFs
  std::vector<double> offset;  // a QLV step's offset stress, 9 × num_tets
  // The last converged call's result and its change from where it started (time-history mode,
  // StaticLoads::reuse_factorisation), 3 × num_nodes.
  bool has_history = false;
  mesh::Points last_solution, last_change;
};

StaticWorkspace::StaticWorkspace() : impl_(std::make_unique<Impl>()) {}
StaticWorkspace::~StaticWorkspace() = default;

StaticResult FemModel::SolveStatic(const StaticLoads& loads, TissueState* state,
                                   StaticWorkspace* workspace) const {
  return SolveStaticImpl(loads, state, nullptr, workspace, false);
}

StaticResult FemModel::NewtonIteration(const StaticLoads& loads, TissueState* state,
                                       StaticWorkspace* workspace) const {
  return SolveStaticImpl(loads, state, nullptr, workspace, true);
}

StaticResult FemModel::SolveQuasiStatic(const StaticLoads& loads, double dt, TissueState* state,
                                        StaticWorkspace* workspace) const {
  if (!(dt > 0.0) || !std::isfinite(dt)) Refuse("quasi-static dt [s] must be > 0");
  if (prony_.empty()) return SolveStaticImpl(loads, state, nullptr, workspace, false);
  StaticWorkspace local;
  if (workspace == nullptr) workspace = &local;
  std::vector<double>& offset = workspace->impl_->offset;
  offset.resize(9 * static_cast<size_t>(num_tets()));
  const ViscousStep viscous = BeginViscousStep(*state, dt, offset.data());
  StaticResult result = SolveStaticImpl(loads, state, &viscous, workspace, false);
  if (result.converged) {
    EndViscousStep(dt, state);
    state->time += dt;
  }
  return result;
}

StaticResult FemModel::SolveStaticImpl(const StaticLoads& loads, TissueState* state,
                                       const ViscousStep* viscous, StaticWorkspace* workspace,
                                       bool single_iteration) const {
  const Shape sh = ShapeOf(*state);
  const auto n = static_cast<size_t>(num_nodes());
  StaticWorkspace local;
  if (workspace == nullptr) workspace = &local;
  StaticWorkspace::Impl& ws = *workspace->impl_;
  if (ws.owner != this) {  // a fresh workspace, or one another model used: start over
    ws.owner = this;
    ws.tangent = pattern_;
    ws.lower_dof.clear();
    ws.analysed = false;
    ws.factorised = false;
    ws.has_history = false;
  }
  if (loads.external_forces != nullptr &&
      (loads.external_forces->cols() != num_nodes() || !loads.external_forces->allFinite())) {
    Refuse("static external forces must be 3 x num_nodes and finite");
  }
  if (!loads.gravity.allFinite()) Refuse("static gravity must be finite");
  if (!(loads.load_steps > 0) || !(loads.tolerance > 0.0) || !(loads.step_tolerance >= 0.0) ||
      !(loads.max_newton_iterations > 0)) {
    Refuse("load_steps, tolerance, step_tolerance and max_newton_iterations must be > 0");
  }
  if (loads.reuse_factorisation && !(loads.reuse_ratio > 0.0 && loads.reuse_ratio < 1.0)) {
    Refuse("reuse_ratio must lie in (0, 1)");
  }
  std::vector<int32_t>& dof = ws.dof;
  dof.assign(3 * n, 0);
  for (const int32_t node : loads.fixed_nodes) {
    if (node < 0 || node >= num_nodes())
      Refuse("fixed node " + std::to_string(node) + " out of range");
    for (size_t c = 0; c < 3; ++c) dof[3 * static_cast<size_t>(node) + c] = -1;
  }
  if (!loads.prescribed_nodes.empty() &&
      (loads.prescribed_positions == nullptr ||
       loads.prescribed_positions->cols() !=
           static_cast<Eigen::Index>(loads.prescribed_nodes.size()) ||
       !loads.prescribed_positions->allFinite())) {
    Refuse("prescribed positions must be 3 x prescribed_nodes and finite");
  }
  for (const int32_t node : loads.prescribed_nodes) {
    if (node < 0 || node >= num_nodes()) {
      Refuse("prescribed node " + std::to_string(node) + " out of range");
    }
    for (size_t c = 0; c < 3; ++c) dof[3 * static_cast<size_t>(node) + c] = -1;
  }
  for (const ComponentConstraint& c : loads.components) {
    if (c.node < 0 || c.node >= num_nodes() || c.axis < 0 || c.axis > 2 ||
        !std::isfinite(c.value)) {
      Refuse("component constraint on node " + std::to_string(c.node) + " axis " +
             std::to_string(c.axis) + " is out of range or not finite");
    }
    dof[3 * static_cast<size_t>(c.node) + static_cast<size_t>(c.axis)] = -1;
  }
  int32_t num_dofs = 0;
  for (int32_t& d : dof) {
    if (d == 0) d = num_dofs++;
  }
  if (dof != ws.lower_dof) {  // new held DOFs: a new reduced pattern and a new analysis
    ws.k_free = ws.tangent.ScalarLowerPattern(dof, num_dofs, &ws.k_source);
    ws.lower_dof = dof;
    ws.analysed = false;
    ws.factorised = false;
  }
  BlockSparseMatrix& tangent = ws.tangent;
  SparseCholesky& cholesky = ws.cholesky;
  // Total load at full scale: external forces and gravity.
  mesh::Points load = mesh::Points::Zero(3, num_nodes());
  if (loads.external_forces != nullptr) load = *loads.external_forces;
  for (size_t i = 0; i < n; ++i) {
    load.col(static_cast<Eigen::Index>(i)) += mass_[i] * loads.gravity;
  }
  const mesh::Points start = state->positions;
  StaticResult result;
  mesh::Points forces(3, num_nodes());
  // Free-DOF norm of r = f(x) + scale · load.
  const auto residual = [&](double scale, Eigen::VectorXd* r) {
    ElasticForces(sh, state->positions, forces.data(), nullptr, viscous);
    r->setZero(num_dofs);
    double load_norm2 = 0.0;
    for (size_t k = 0; k < 3 * n; ++k) {
      if (dof[k] < 0) continue;
      const double l = scale * load.data()[k];
      (*r)[dof[k]] = forces.data()[k] + l;
      load_norm2 += l * l;
    }
    return std::sqrt(load_norm2);
  };
  const auto potential = [&](double scale) {
    double value = ElasticEnergy(sh, state->positions, viscous);
    for (Eigen::Index k = 0; k < load.size(); ++k) {
      value -= scale * load.data()[k] * (state->positions.data()[k] - sh.rest.data()[k]);
    }
    return value;
  };
  // Factorises the tangent at the state's positions: the exact one when it is positive definite
  // on the free DOFs, else the rotated one (corotational), else the rest stiffness (always
  // positive definite: a quasi-Newton step). The linear model's K is constant: factorised once.
  bool linear_factorised = false;
  const auto factorise_tangent = [&]() {
    if (kind_ == FemKind::kLinear && linear_factorised) return true;
    for (int attempt = 0; attempt < 3; ++attempt) {
      if (attempt == 1 && kind_ != FemKind::kCorotational) continue;
      // 0: the exact tangent at x; 1: the rotated (warped) one, positive semi-definite; 2: the
      // exact tangent at rest.
      AssembleElementTangents(sh, attempt == 2 ? sh.rest : state->positions, attempt != 1, viscous,
                              &tangent);
      tangent.FillScalarLower(ws.k_source, &ws.k_free);
      if (!ws.analysed) {
        cholesky.Analyse(ws.k_free);
        ws.analysed = true;
      }
      ++result.factorisations;
      if (cholesky.Factorise(ws.k_free)) {
        linear_factorised = true;
        ws.factorised = true;
        return true;
      }
    }
    ws.factorised = false;
    return false;
  };
  // A single iteration (NewtonIteration) is at full load, with the held DOFs put in place.
  const int load_steps = single_iteration ? 1 : loads.load_steps;
  for (int step = 1; step <= load_steps; ++step) {
    const double scale = static_cast<double>(step) / load_steps;
    // This step's Dirichlet values (they move in increments too), as an increment d.
    mesh::Points target = state->positions;
    for (const int32_t node : loads.fixed_nodes) target.col(node) = sh.rest.col(node);
    for (size_t k = 0; k < loads.prescribed_nodes.size(); ++k) {
      const int32_t node = loads.prescribed_nodes[k];
      const Eigen::Index kk = static_cast<Eigen::Index>(k);
      target.col(node) =
          start.col(node) + scale * (loads.prescribed_positions->col(kk) - start.col(node));
    }
    for (const ComponentConstraint& c : loads.components) {
      const double from = start(c.axis, c.node);
      target(c.axis, c.node) = from + scale * (c.value - from);
    }
    const mesh::Points increment = target - state->positions;  // zero on free DOFs
    // Predictor: the free DOFs follow the held ones through the tangent at the last equilibrium,
    // K_ff Δu_f = r_f - K_fc d_c (moving only the held nodes would crush the elements next to
    // them, and a hyperelastic tangent there may not be positive definite).
    Eigen::VectorXd r;
    if (!single_iteration && num_dofs > 0 && increment.cwiseAbs().maxCoeff() > 0.0 &&
        factorise_tangent()) {
      residual(scale, &r);
      mesh::Points moved(3, num_nodes());
      tangent.Multiply(increment.data(), moved.data(), nullptr);
      for (size_t k = 0; k < 3 * n; ++k) {
        if (dof[k] >= 0) r[dof[k]] -= moved.data()[k];
      }
      Eigen::VectorXd du(num_dofs);
      cholesky.Solve(r.data(), du.data());
      const mesh::Points before = state->positions;
      state->positions = target;
      for (size_t k = 0; k < 3 * n; ++k) {
        if (dof[k] >= 0) state->positions.data()[k] += du[dof[k]];
      }
      if (!std::isfinite(residual(scale, &r)) || !r.allFinite()) {  // overshot: no predictor
        state->positions = before + increment;
      }
    } else {
      state->positions = target;
    }
    // Time-history mode: a state that is the one the last call left starts from its positions
    // extrapolated along that call's change (the next step of a creep or relaxation is close to
    // it), cutting the first residual and so the iterations; not where that is not finite.
    if (loads.reuse_factorisation && loads.load_steps == 1 && !single_iteration && ws.has_history &&
        ws.last_solution.cols() == num_nodes() && state->positions == ws.last_solution) {
      const mesh::Points here = state->positions;
      for (size_t k = 0; k < 3 * n; ++k) {
        if (dof[k] >= 0) state->positions.data()[k] += ws.last_change.data()[k];
      }
      if (!std::isfinite(residual(scale, &r)) || !r.allFinite() ||
          !std::isfinite(potential(scale))) {
        state->positions = here;
      }
    }
    result.residual_history.clear();
    const double load_norm = residual(scale, &r);
    // A scale for "zero" when nothing is loaded (pure Dirichlet): the forces at the start.
    double reference = load_norm;
    if (!(reference > 0.0)) {
      reference = 0.0;
      for (Eigen::Index k = 0; k < forces.size(); ++k) {
        reference += forces.data()[k] * forces.data()[k];
      }
      reference = std::max(std::sqrt(reference), 1e-300);
    }
    double r_norm = r.norm();
    bool small_step = false;
    const int max_iterations = single_iteration ? 1 : loads.max_newton_iterations;
    bool refactorise = false;
    for (int it = 0; num_dofs > 0 && it < max_iterations &&
                     (single_iteration || r_norm > loads.tolerance * reference) && !small_step;
         ++it) {
      const bool reuse = loads.reuse_factorisation && ws.factorised && !refactorise;
      if (!reuse && !factorise_tangent()) break;
      Eigen::VectorXd du(num_dofs);
      cholesky.Solve(r.data(), du.data());
      // Backtracking on the potential (Armijo), accepting a full step that lowers the residual
      // (tested first: the potential is evaluated only when needed).
      double pi0 = 0.0;
      bool have_pi0 = false;
      const double slope = -r.dot(du);  // dΠ/dt along du at t = 0 (r = -∇Π)
      const mesh::Points before = state->positions;
      double t = 1.0;
      Eigen::VectorXd r_new;
      double r_new_norm = 0.0;
      for (int ls = 0; ls < 20; ++ls) {
        state->positions = before;
        for (size_t k = 0; k < 3 * n; ++k) {
          if (dof[k] >= 0) state->positions.data()[k] += t * du[dof[k]];
        }
        residual(scale, &r_new);
        r_new_norm = r_new.norm();
        if (r_new_norm < r_norm) break;
        if (!have_pi0) {
          const mesh::Points trial = state->positions;
          state->positions = before;
          pi0 = potential(scale);
          have_pi0 = true;
          state->positions = trial;
        }
        if (potential(scale) <= pi0 + 1e-4 * t * slope) break;
        t *= 0.5;
      }
      // A step of the old factor that no longer shrinks the residual enough: refactorise.
      refactorise = r_new_norm > loads.reuse_ratio * r_norm;
      r = r_new;
      r_norm = r_new_norm;
      double u_norm2 = 0.0;
      for (size_t k = 0; k < 3 * n; ++k) {
        const double u = state->positions.data()[k] - sh.rest.data()[k];
        u_norm2 += u * u;
      }
      small_step = t * du.norm() <= loads.step_tolerance * std::sqrt(u_norm2);
      ++result.newton_iterations;
      result.residual_history.push_back(r_norm / reference);
    }
    result.final_residual = r_norm / reference;
    result.converged = r_norm <= loads.tolerance * reference || small_step || num_dofs == 0;
    if (!result.converged) break;
  }
  if (single_iteration) {
    result.converged = result.final_residual <= loads.tolerance;
    state->velocities.setZero();
    return result;
  }
  ws.has_history = result.converged;
  if (result.converged) {
    ws.last_change = state->positions - start;
    ws.last_solution = state->positions;
  }
  // Reactions: what the supports must supply, -(f(x) + load) on the held DOFs. `forces` is f at
  // the final positions already: every path above ends on a residual evaluation there.
  result.reactions = mesh::Points::Zero(3, num_nodes());
  for (size_t k = 0; k < 3 * n; ++k) {
    if (dof[k] < 0) result.reactions.data()[k] = -(forces.data()[k] + load.data()[k]);
  }
  state->velocities.setZero();
  return result;
}

}  // namespace somasim::models::fem
