// The mass-spring model's implicit step (MassSpringIntegrator::kImplicitEuler): linearised
// backward Euler (Baraff & Witkin 1998), A Δv = b built at the state the step starts from
// (mass_spring_implicit_system.cc) and solved by conjugate gradients preconditioned with a
// multicolour symmetric block Gauss-Seidel sweep (mass_spring_implicit_cg.cc). The derivation,
// the layout and the fused CG passes: docs/models.md, "The implicit mass-spring step".
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <span>

#include "server/models/cpu_features.h"
#include "server/models/mass_spring_implicit_cg.h"
#include "server/models/mass_spring_model.h"
#include "server/models/mass_spring_state.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {

// Test switch: false forces the scalar kernels (declared where the tests use it).
void SetMassSpringImplicitAvx512ForTesting(bool enabled);

namespace {

bool g_implicit_avx512 = true;  // NOLINT: a test switch, written only by tests

bool UseAvx512() { return g_implicit_avx512 && CpuHasAvx512(); }

// Zeroes the fixed and prescribed nodes' entries of the AoS vector `v` (3 × num_nodes).
void ZeroConstrainedLanes(const StepInputs& inputs, const int32_t* lane_of, size_t p, double* v) {
  for (const std::span<const int32_t> nodes : {inputs.fixed_nodes, inputs.prescribed_nodes}) {
    for (const int32_t node : nodes) {
      const auto i = static_cast<size_t>(lane_of[node]);
      v[i] = v[p + i] = v[2 * p + i] = 0.0;
    }
  }
}

}  // namespace

void SetMassSpringImplicitAvx512ForTesting(bool enabled) { g_implicit_avx512 = enabled; }

bool MassSpringModel::SolveImplicitSystem(const StepInputs& inputs, bool avx512,
                                          MassSpringState* state, int* iterations_out) const {
  const size_t p = implicit_padded_;
  const size_t size = 3 * p;
  // Preconditioned conjugate gradients on (M + dt C + dt² K) Δv = rhs, held rows at 0, from
  // 2 Δv_last - Δv_before_last when that is closer than 0 (it differs from this step's Δv by
  // O(dt²) in smooth motion, against O(dt) for Δv_last alone, and so saves iterations; a guess
  // left by a rejected step, or non-finite, fails the test and is dropped).
  ImplicitLayout layout;
  layout.padded = p;
  layout.groups = p / kImplicitLanes;
  layout.colours = implicit_colour_start_.size() - 1;
  layout.colour_start = implicit_colour_start_.data();
  layout.row_start = implicit_row_start_.data();
  layout.lower_rows = implicit_lower_rows_.data();
  layout.neighbour = implicit_neighbour_.data();
  layout.rows = state->implicit_rows.data();
  layout.inverse = state->implicit_inverse.data();
  layout.diagonal = state->implicit_diagonal.data();
  layout.keep = state->implicit_keep.data();
  layout.massless_group = implicit_massless_group_.data();
  double* dv = state->implicit_dv.data();
  double* r = state->implicit_residual.data();
  double* z = state->implicit_z.data();
  double* search = state->implicit_search.data();
  double* q = state->implicit_product.data();
  double* az = state->implicit_az.data();
  double* dy = state->implicit_dy.data();
  const double* rhs = state->implicit_rhs.data();
  const auto dot = [&](const double* a, const double* b) {
    return avx512 ? DotAvx512(size, a, b) : DotScalar(size, a, b);
  };
  const double rhs_norm2 = dot(rhs, rhs);
  int iterations = 0;
  bool converged = !(rhs_norm2 > 0.0);
  if (converged) {
    std::fill(dv, dv + size, 0.0);
  } else {
    {  // the guess: Δv extrapolated linearly from the last two steps (O(dt²) off in smooth motion)
      double* previous = state->implicit_dv_previous.data();
      for (size_t c = 0; c < size; ++c) {
        const double last = dv[c];
        dv[c] = 2.0 * last - previous[c];
        previous[c] = last;
      }
    }
    ZeroConstrainedLanes(inputs, implicit_lane_.data(), p, dv);
    if (avx512) {
      ProductAvx512(layout, dv, q, state->implicit_gather.data());
    } else {
      ProductScalar(layout, dv, q);
    }
    for (size_t c = 0; c < size; ++c) r[c] = rhs[c] - q[c];
    double warm_norm2 = dot(r, r);
    if (!(warm_norm2 < rhs_norm2)) {  // also false for a non-finite guess
      std::fill(dv, dv + size, 0.0);
      std::copy(rhs, rhs + size, r);
      warm_norm2 = rhs_norm2;
    }
    const double threshold2 = cg_tolerance_ * cg_tolerance_ * rhs_norm2;
    // z = P⁻¹ r, then p = z + β p and q = A p (= A z + β A p, exact up to rounding) with β =
    // (r · z) / rz_before (p = z, q = A z when first); returns r · z, sets curvature = p · q.
    double curvature = 0.0;
    double residual_norm2 = warm_norm2;
    const auto precondition = [&](bool first, double rz_before) {
      if (avx512) {  // fused with the step r -= α q, Δv += α p unless `first` (see CgUpdate)
        const CgUpdate update{first ? 0.0 : rz_before / curvature, threshold2, dv};
        return PreconditionAvx512(layout, update, r, dy, az, state->implicit_gather.data(), first,
                                  rz_before, search, q, &curvature, &residual_norm2);
      }
      const double rz_next = PreconditionScalar(layout, r, dy, z, az);
      if (first) {
        std::copy(z, z + size, search);
        std::copy(az, az + size, q);
        curvature = dot(search, q);
      } else {
        curvature = DirectionScalar(rz_next / rz_before, size, z, az, search, q);
      }
      return rz_next;
    };
    double rz = precondition(true, 0.0);
    converged = residual_norm2 <= threshold2;
    while (!converged && iterations < cg_max_iterations_) {
      if (!(curvature > 0.0)) break;
      ++iterations;
      if (avx512) {  // step, test and (unless converged) the next direction in one call
        rz = precondition(false, rz);
        converged = residual_norm2 <= threshold2;
        continue;
      }
      residual_norm2 = StepScalar(rz / curvature, size, search, q, dv, r);
      if (residual_norm2 <= threshold2) {
        converged = true;
        break;
      }
      rz = precondition(false, rz);
    }
  }
  *iterations_out = iterations;
  return converged;
}

void MassSpringModel::AdvanceImplicit(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<MassSpringState*>(base);
  const double dt = inputs.dt;
  const auto n = static_cast<size_t>(rest_.cols());
  const size_t p = implicit_padded_;
  const bool avx512 = UseAvx512();
  InternalForces(*state, &state->forces);
  AddExternalForces(inputs, state);
  // Linearise every spring at the current state, gather each node's blocks, then solve.
  BuildImplicitSystem(inputs, avx512, state);
  int iterations = 0;
  const bool converged = SolveImplicitSystem(inputs, avx512, state, &iterations);
  state->counters.solver_iterations += iterations;
  if (!converged) ++state->counters.solver_unconverged;
  const double* dv = state->implicit_dv.data();
  double* vel = state->velocities.data();
  double* x = state->positions.data();
  for (size_t node = 0; node < n; ++node) {
    const auto i = static_cast<size_t>(implicit_lane_[node]);
    for (size_t k = 0; k < 3; ++k) {
      vel[3 * node + k] += dv[k * p + i];
      x[3 * node + k] += dt * vel[3 * node + k];
    }
  }
  ApplyFixedAndPrescribed(inputs, state);
}

}  // namespace somasim::models
