// Implicit Euler for the mass-spring model (MassSpringIntegrator::kImplicitEuler): linearised
// backward Euler (Baraff & Witkin 1998) solved by preconditioned conjugate gradients.
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdint>

#include "server/models/mass_spring_model.h"
#include "server/models/mass_spring_state.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {

using Eigen::Vector3d;

// The linear operator of a spring network: out = mass_coeff M in + Σ_s B_s (in_i - in_j) on i,
// minus on j, with B_s = (damping_coeff D_s + stiffness_coeff k_s) u uᵀ
//                        + stiffness_coeff k_s c_s (I - u uᵀ),
// plus stiffness_coeff k_a in_i for every attachment. (M + dt C + dt² K) and K v are both
// instances.
class MassSpringImplicitStep {
 public:
  static void Multiply(const MassSpringModel& model, const MassSpringState& state,
                       const StepInputs& inputs, const mesh::Points& in, double mass_coeff,
                       double stiffness_coeff, double damping_coeff, mesh::Points* out) {
    const Eigen::Index n = in.cols();
    for (Eigen::Index i = 0; i < n; ++i) {
      out->col(i) = (mass_coeff * model.mass_[static_cast<size_t>(i)]) * in.col(i);
    }
    const size_t m = model.spring_i_.size();
    for (size_t s = 0; s < m; ++s) {
      const Eigen::Index i = model.spring_i_[s];
      const Eigen::Index j = model.spring_j_[s];
      const Vector3d u = state.spring_direction.col(static_cast<Eigen::Index>(s));
      const double along =
          damping_coeff * model.damping_[s] + stiffness_coeff * model.stiffness_[s];
      const double across = stiffness_coeff * model.stiffness_[s] * state.spring_transverse[s];
      const Vector3d d = in.col(i) - in.col(j);
      const Vector3d b = across * d + (along - across) * u.dot(d) * u;
      out->col(i) += b;
      out->col(j) -= b;
    }
    for (const Attachment& a : inputs.attachments) {
      out->col(a.node) += stiffness_coeff * a.stiffness * in.col(a.node);
    }
  }
};

void MassSpringModel::AdvanceImplicit(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<MassSpringState*>(base);
  const double dt = inputs.dt;
  const Eigen::Index n = rest_.cols();
  InternalForces(*state, &state->forces);
  AddExternalForces(inputs, state);

  // Spring directions and clamped transverse factors at the current positions.
  for (size_t s = 0; s < spring_i_.size(); ++s) {
    const Vector3d d = state->positions.col(spring_j_[s]) - state->positions.col(spring_i_[s]);
    const double length = d.norm();
    const auto col = static_cast<Eigen::Index>(s);
    state->spring_direction.col(col) = length > 0.0 ? Vector3d(d / length) : Vector3d::Zero();
    state->spring_transverse[s] =
        length > 0.0 ? std::max(0.0, 1.0 - rest_length_[s] / length) : 0.0;
  }
  std::fill(state->constrained.begin(), state->constrained.end(), uint8_t{0});
  for (const int32_t node : inputs.fixed_nodes) state->constrained[static_cast<size_t>(node)] = 1;
  for (const int32_t node : inputs.prescribed_nodes) {
    state->constrained[static_cast<size_t>(node)] = 1;
  }
  const auto mask = [&](mesh::Points* v) {
    for (Eigen::Index i = 0; i < n; ++i) {
      if (state->constrained[static_cast<size_t>(i)] != 0) v->col(i).setZero();
    }
  };

  // rhs = dt f - dt² K v.
  MassSpringImplicitStep::Multiply(*this, *state, inputs, state->velocities, 0.0, 1.0, 0.0,
                                   &state->product);
  state->rhs = dt * state->forces - (dt * dt) * state->product;
  mask(&state->rhs);

  // Block-Jacobi preconditioner: the inverse of each node's 3×3 diagonal block of A.
  for (Eigen::Index i = 0; i < n; ++i) {
    Eigen::Matrix3d block = mass_[static_cast<size_t>(i)] * Eigen::Matrix3d::Identity();
    for (int32_t e = node_spring_start_[static_cast<size_t>(i)];
         e < node_spring_start_[static_cast<size_t>(i) + 1]; ++e) {
      const auto s = static_cast<size_t>(node_springs_[static_cast<size_t>(e)]);
      const Vector3d u = state->spring_direction.col(static_cast<Eigen::Index>(s));
      const double along = dt * damping_[s] + dt * dt * stiffness_[s];
      const double across = dt * dt * stiffness_[s] * state->spring_transverse[s];
      block += across * Eigen::Matrix3d::Identity() + (along - across) * (u * u.transpose());
    }
    Eigen::Map<Eigen::Matrix3d> inverse(state->inverse_diagonal.col(i).data());
    if (mass_[static_cast<size_t>(i)] > 0.0) {
      inverse = block.inverse();
    } else {
      inverse.setIdentity();
    }
  }
  for (const Attachment& a : inputs.attachments) {
    Eigen::Map<Eigen::Matrix3d> inverse(state->inverse_diagonal.col(a.node).data());
    inverse = (inverse.inverse() + dt * dt * a.stiffness * Eigen::Matrix3d::Identity()).inverse();
  }
  const auto precondition = [&](const mesh::Points& r, mesh::Points* z) {
    for (Eigen::Index i = 0; i < n; ++i) {
      z->col(i) =
          Eigen::Map<const Eigen::Matrix3d>(state->inverse_diagonal.col(i).data()) * r.col(i);
    }
    mask(z);
  };

  // Preconditioned conjugate gradients on (M + dt C + dt² K) Δv = rhs, constrained rows held at 0.
  state->dv.setZero();
  state->residual = state->rhs;
  const double rhs_norm = state->rhs.norm();
  int iterations = 0;
  bool converged = !(rhs_norm > 0.0);
  if (!converged) {
    precondition(state->residual, &state->preconditioned);
    state->search = state->preconditioned;
    double rz = state->residual.cwiseProduct(state->preconditioned).sum();
    while (iterations < cg_max_iterations_) {
      MassSpringImplicitStep::Multiply(*this, *state, inputs, state->search, 1.0, dt * dt, dt,
                                       &state->product);
      mask(&state->product);
      const double curvature = state->search.cwiseProduct(state->product).sum();
      if (!(curvature > 0.0)) break;
      const double alpha = rz / curvature;
      state->dv += alpha * state->search;
      state->residual -= alpha * state->product;
      ++iterations;
      if (state->residual.norm() <= cg_tolerance_ * rhs_norm) {
        converged = true;
        break;
      }
      precondition(state->residual, &state->preconditioned);
      const double rz_next = state->residual.cwiseProduct(state->preconditioned).sum();
      state->search = state->preconditioned + (rz_next / rz) * state->search;
      rz = rz_next;
    }
  }
  state->counters.solver_iterations += iterations;
  if (!converged) ++state->counters.solver_unconverged;

  state->velocities += state->dv;
  state->positions += dt * state->velocities;
  ApplyFixedAndPrescribed(inputs, state);
}

}  // namespace somasim::models
