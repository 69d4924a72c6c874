// The step of the position-based model (seed 004; XPBD): the Verlet prediction into the node
// records, the Gauss-Seidel sweeps (colour by colour through the sweep kernel,
// position_based_sweep.h, then attachments and the primal correction), and the copy back to the
// public order, with the state's check.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <type_traits>

#include "server/models/position_based_model.h"
#include "server/models/position_based_state.h"
#include "server/models/position_based_sweep.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_PBD_AVX512 1
#endif

namespace somasim::models {
namespace {

using Eigen::Vector3d;

#ifdef SOMASIM_PBD_AVX512
// The prediction into the records, one node per 256-bit record (see Advance, whose scalar loop
// it mirrors operation for operation, so both give the same bits): record p =
// (x + (Δt v + Δt² a), w) with a = g + w f for node order[p], (x, 0) for a massless node.
// forces may be null. The 3-vectors of node i are read with a 3-lane mask (no overrun past the
// last node).
__attribute__((target("avx512f,avx512vl"))) void PredictAvx512(
    size_t n, const int32_t* order, const double* inverse_mass, const double* px, const double* pv,
    const double* forces, const std::array<double, 3>& g, double dt, double* nodes, double* w) {
  const __m256d vdt = _mm256_set1_pd(dt);
  const __m256d vdt2 = _mm256_set1_pd(dt * dt);
  const __m256d vg = _mm256_setr_pd(g[0], g[1], g[2], 0.0);
  for (size_t p = 0; p < n; ++p) {
    const auto i = static_cast<size_t>(order[p]);
    const double wi = inverse_mass[i];
    const __m256d x = _mm256_maskz_loadu_pd(0x7, px + 3 * i);
    __m256d record = x;
    if (wi > 0.0) {
      __m256d a = vg;
      if (forces != nullptr) {
        a = _mm256_add_pd(
            a, _mm256_mul_pd(_mm256_set1_pd(wi), _mm256_maskz_loadu_pd(0x7, forces + 3 * i)));
      }
      const __m256d v = _mm256_maskz_loadu_pd(0x7, pv + 3 * i);
      record = _mm256_add_pd(x, _mm256_add_pd(_mm256_mul_pd(vdt, v), _mm256_mul_pd(vdt2, a)));
    }
    // Lane 3 (0 so far) becomes w.
    _mm256_store_pd(nodes + 4 * p, _mm256_mask_broadcastsd_pd(record, 0x8, _mm_set_sd(wi)));
    w[p] = wi;
  }
}

// The records back to the public order (see the scalar loop in Advance, whose operations it
// repeats, so both give the same bits): for node i, x = record (x, y, z) of slot[i] and
// v = (x - x_start) inverse_dt, written as 3-lane masked vectors (no overrun past the last node),
// and checked as they are written: the answer is what StateCheck::Add gives for every value.
__attribute__((target("avx512f,avx512vl"))) StateCheck CopyBackAvx512(
    size_t n, const int32_t* slot, const double* nodes, const double* x_start, double inverse_dt,
    double component_limit, double* out_x, double* out_v) {
  const __m256d vinverse_dt = _mm256_set1_pd(inverse_dt);
  // x − x and v − v are 0 for finite values and NaN otherwise; their sums stay 0 until a NaN.
  __m256d finite_sum = _mm256_setzero_pd();
  __m256d largest_speed = _mm256_setzero_pd();  // max |v| per lane
  const __m256d sign = _mm256_set1_pd(-0.0);
  for (size_t i = 0; i < n; ++i) {
    const __m256d x = _mm256_maskz_load_pd(0x7, nodes + 4 * static_cast<size_t>(slot[i]));
    const __m256d v =
        _mm256_mul_pd(_mm256_sub_pd(x, _mm256_maskz_loadu_pd(0x7, x_start + 3 * i)), vinverse_dt);
    _mm256_mask_storeu_pd(out_x + 3 * i, 0x7, x);
    _mm256_mask_storeu_pd(out_v + 3 * i, 0x7, v);
    finite_sum = _mm256_add_pd(finite_sum, _mm256_add_pd(_mm256_sub_pd(x, x), _mm256_sub_pd(v, v)));
    largest_speed = _mm256_max_pd(largest_speed, _mm256_andnot_pd(sign, v));
  }
  StateCheck check;
  check.non_finite = _mm256_cmp_pd_mask(finite_sum, finite_sum, _CMP_UNORD_Q) != 0;
  check.maybe_too_fast =
      _mm256_cmp_pd_mask(largest_speed, _mm256_set1_pd(component_limit), _CMP_GT_OQ) != 0;
  return check;
}
#endif

}  // namespace

void PositionBasedModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<PositionBasedState*>(base);
  PredictRecords(inputs, state);
  MergeAttachments(inputs, state);
  PrepareSweepFactors(inputs.dt, state);
  RunSweeps(inputs.dt, state);
  CopyBack(inputs.dt, state);
}

void PositionBasedModel::PredictRecords(const StepInputs& inputs, PositionBasedState* state) const {
  const double dt = inputs.dt;
  const double dt2 = dt * dt;
  const auto n = static_cast<size_t>(rest_.cols());
  double* __restrict nodes = state->nodes();
  double* __restrict w = state->inverse_mass.data();
  // Prediction, seed 004 eq. 1: x' = 2x - x* + a Δt² = x + Δt v + Δt² (g + f_ext/m), with
  // v = (x - x*)/Δt kept as the state's velocity, written into the internal records. Massless
  // nodes do not move. The volume reaction (seed 004) joins f_ext, evaluated at the start of the
  // step.
  const double* __restrict pf =
      inputs.external_forces != nullptr ? inputs.external_forces->data() : nullptr;
  if (volume_ != nullptr) {
    state->volume_forces.setZero();
    volume_->AddForces(state->positions, &state->volume_forces);
    if (pf != nullptr) state->volume_forces += *inputs.external_forces;
    pf = state->volume_forces.data();
  }
  // SavesGoodStateItself: the state the step starts from becomes the last-good one by a swap of
  // buffers (no copy); the step reads it there and writes every node's new x and v at the end.
  SwapWithLastGood(state);
  const double* __restrict px = LastGoodPositions(state);
  const double* __restrict pv = LastGoodVelocities(state);
  const std::array<double, 3> g = {inputs.gravity.x(), inputs.gravity.y(), inputs.gravity.z()};
  // One loop per case, so that the test for external forces stays out of the loop.
  const auto predict = [&](auto forces) {
    for (size_t p = 0; p < n; ++p) {
      const auto i = static_cast<size_t>(node_order_[p]);
      const double wi = inverse_mass_[i];
      double* record = nodes + 4 * p;
      for (size_t k = 0; k < 3; ++k) {
        double a = g[k];
        if constexpr (decltype(forces)::value) a += wi * pf[3 * i + k];
        record[k] = wi > 0.0 ? px[3 * i + k] + (dt * pv[3 * i + k] + dt2 * a) : px[3 * i + k];
      }
      record[3] = wi;
      w[p] = wi;
    }
  };
  if (simd_) {  // never without SOMASIM_PBD_AVX512 (the CPU has no AVX-512 then)
#ifdef SOMASIM_PBD_AVX512
    PredictAvx512(n, node_order_.data(), inverse_mass_.data(), px, pv, pf, g, dt, nodes, w);
#endif
  } else if (pf != nullptr) {
    predict(std::true_type{});
  } else {
    predict(std::false_type{});
  }
  // Fixed nodes stay where they were; prescribed nodes go to their targets. Both get inverse
  // mass 0, so the projections never move them.
  for (const int32_t node : inputs.fixed_nodes) {
    const auto p = static_cast<size_t>(node_slot_[static_cast<size_t>(node)]);
    for (size_t k = 0; k < 3; ++k) nodes[4 * p + k] = px[3 * static_cast<size_t>(node) + k];
    nodes[4 * p + 3] = 0.0;
    w[p] = 0.0;
  }
  for (size_t q = 0; q < inputs.prescribed_nodes.size(); ++q) {
    const int32_t node = inputs.prescribed_nodes[q];
    const auto p = static_cast<size_t>(node_slot_[static_cast<size_t>(node)]);
    const double* target = inputs.prescribed_positions->col(static_cast<Eigen::Index>(q)).data();
    for (size_t k = 0; k < 3; ++k) nodes[4 * p + k] = target[k];
    nodes[4 * p + 3] = 0.0;
    w[p] = 0.0;
  }
  // The primal correction re-anchors the sweeps' result on the prediction x̃.
  if (parameters_.mode == PositionBasedMode::kXpbd && parameters_.primal_correction) {
    std::copy(nodes, nodes + 4 * n, state->predicted.begin());
  }
}

void PositionBasedModel::MergeAttachments(const StepInputs& inputs,
                                          PositionBasedState* state) const {
  // Attachments, merged per node into one compliant constraint x - t̄ = 0 with compliance 1/K.
  state->num_attached = 0;
  for (const Attachment& a : inputs.attachments) {
    if (!(a.stiffness > 0.0)) continue;
    const auto node = static_cast<size_t>(a.node);
    if (state->attach_stiffness[node] == 0.0) {
      state->attached_nodes[state->num_attached++] = a.node;
      state->attach_weighted_target.col(a.node).setZero();
      state->attach_lambda.col(a.node).setZero();
    }
    state->attach_stiffness[node] += a.stiffness;
    state->attach_weighted_target.col(a.node) += a.stiffness * a.target;
  }
}

void PositionBasedModel::PrepareSweepFactors(double dt, PositionBasedState* state) const {
  // The per-constraint factors: they change only with Δt and the inverse masses (fixed and
  // prescribed nodes), so most steps reuse the last ones.
  const auto n = static_cast<size_t>(rest_.cols());
  const double* __restrict w = state->inverse_mass.data();
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  const size_t m = sweep_edge_.size();
  const double inverse_dt2 = 1.0 / (dt * dt);
  if (dt == state->prepared_dt && std::equal(w, w + n, state->prepared_w.begin())) return;
  const double k_seed = parameters_.stiffness;
  for (size_t s = 0; s < m; ++s) {
    const double w1 = w[static_cast<size_t>(sweep_i4_[s] / 4)];
    const double w2 = w[static_cast<size_t>(sweep_j4_[s] / 4)];
    const double alpha = sweep_compliance_[s] * inverse_dt2;  // α̃, 0 in seed mode
    const double w_sum = w1 + w2;
    state->sweep_alpha[s] = alpha;
    // A constraint between two immovable nodes, or cut, is left alone (its λ stays 0).
    const bool inert = !(w_sum > 0.0) || state->cut[static_cast<size_t>(sweep_edge_[s])] != 0;
    const double gain = inert ? 0.0 : xpbd ? 1.0 / (w_sum + alpha) : k_seed / w_sum;
    state->sweep_gain[s] = gain;
    state->sweep_wi_gain[s] = w1 * gain;
    state->sweep_wj_gain[s] = w2 * gain;
  }
  std::copy(w, w + n, state->prepared_w.begin());
  state->prepared_dt = dt;
}

void PositionBasedModel::RunSweeps(double dt, PositionBasedState* state) const {
  double* __restrict nodes = state->nodes();
  const double inverse_dt2 = 1.0 / (dt * dt);
  const bool primal_correction =
      parameters_.mode == PositionBasedMode::kXpbd && parameters_.primal_correction;
  const SweepArrays arrays{sweep_i4_.data(),
                           sweep_j4_.data(),
                           sweep_rest_.data(),
                           sweep_inv_rest_.data(),
                           state->sweep_alpha.data(),
                           state->sweep_gain.data(),
                           state->sweep_wi_gain.data(),
                           state->sweep_wj_gain.data(),
                           state->lambda.data()};
  const size_t num_colours = colour_start_.size() - 1;
  int iteration = 0;
  double residual = 0.0;
  const double tolerance = parameters_.tolerance;
  // The residual is computed only when a tolerance asks for it; the first sweep (λ = 0, not
  // read) is what sets every λ of the step.
  const bool with_residual = tolerance > 0.0;
  while (iteration < parameters_.iterations) {
    ++iteration;
    residual = 0.0;
    // Distance constraints colour by colour (Gauss–Seidel; within a colour no two constraints
    // share a node, so their order there does not matter).
    for (size_t c = 0; c < num_colours; ++c) {
      const auto begin = static_cast<size_t>(colour_start_[c]);
      const auto end = static_cast<size_t>(colour_start_[c + 1]);
      residual = std::max(
          residual, ProjectColour(arrays, begin, end, nodes, simd_, with_residual, iteration == 1));
    }
    ProjectAttachments(inverse_dt2, state);
    // Further constraints of the whole body (e.g. a volume term) are projected here, once per
    // sweep, after the distance constraints and attachments.
    if (primal_correction) CorrectPrimal(state);
    if (tolerance > 0.0 && residual < tolerance) break;
  }
  state->counters.solver_iterations += iteration;
  if (tolerance > 0.0 && !(residual < tolerance)) ++state->counters.solver_unconverged;
  for (size_t k = 0; k < state->num_attached; ++k) {
    state->attach_stiffness[static_cast<size_t>(state->attached_nodes[k])] = 0.0;
  }
}

void PositionBasedModel::ProjectAttachments(double inverse_dt2, PositionBasedState* state) const {
  // Attachments: the vector constraint C = x - t̄ with compliance 1/K, ∇C = I (XPBD).
  double* nodes = state->nodes();
  for (size_t k = 0; k < state->num_attached; ++k) {
    const int32_t node = state->attached_nodes[k];
    double* record = nodes + 4 * node_slot_[static_cast<size_t>(node)];
    const double wi = record[3];
    if (!(wi > 0.0)) continue;
    const double stiffness = state->attach_stiffness[static_cast<size_t>(node)];
    const double alpha = inverse_dt2 / stiffness;
    Eigen::Map<Vector3d> xn(record);
    const Vector3d c = xn - state->attach_weighted_target.col(node) / stiffness;
    const Vector3d dlambda = (-c - alpha * state->attach_lambda.col(node)) / (wi + alpha);
    state->attach_lambda.col(node) += dlambda;
    xn += wi * dlambda;
  }
}

void PositionBasedModel::CorrectPrimal(PositionBasedState* state) const {
  // Primal correction: Gauss–Seidel moved each node along gradients taken at intermediate
  // positions, so x - x̃ drifts from M⁻¹ Σ ∇C(x) λ by O(|Δx|/l) (the g ≈ 0 assumption of
  // Macklin et al. §4). Re-anchoring x = x̃ + M⁻¹ (Σ_e ∇C_e(x) λ_e + λ_attach) makes a
  // converged step an exact backward-Euler step, whose rest state is the static solution
  // of springs 1/compliance, whatever Δt or the sweep count.
  const auto n = static_cast<size_t>(rest_.cols());
  const size_t m = sweep_edge_.size();
  double* __restrict nodes = state->nodes();
  const double* __restrict w = state->inverse_mass.data();
  std::fill(state->impulse.begin(), state->impulse.end(), 0.0);
  double* __restrict impulse = state->impulse.data();
  const double* __restrict lambda = state->lambda.data();
  for (size_t s = 0; s < m; ++s) {
    const auto i = static_cast<size_t>(sweep_i4_[s]);
    const auto j = static_cast<size_t>(sweep_j4_[s]);
    const double dx = nodes[j] - nodes[i];
    const double dy = nodes[j + 1] - nodes[i + 1];
    const double dz = nodes[j + 2] - nodes[i + 2];
    const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
    if (!(length > 0.0)) continue;
    const double f = lambda[s] / length;  // ∇_{x_j} C λ = f d
    impulse[j] += f * dx;
    impulse[j + 1] += f * dy;
    impulse[j + 2] += f * dz;
    impulse[i] -= f * dx;
    impulse[i + 1] -= f * dy;
    impulse[i + 2] -= f * dz;
  }
  for (size_t k = 0; k < state->num_attached; ++k) {
    const int32_t node = state->attached_nodes[k];
    const auto p = static_cast<size_t>(node_slot_[static_cast<size_t>(node)]);
    for (size_t d = 0; d < 3; ++d) {
      impulse[4 * p + d] += state->attach_lambda(static_cast<Eigen::Index>(d), node);
    }
  }
  const double* __restrict predicted = state->predicted.data();
  for (size_t p = 0; p < n; ++p) {
    for (size_t k = 0; k < 3; ++k) {
      nodes[4 * p + k] = predicted[4 * p + k] + w[p] * impulse[4 * p + k];
    }
  }
}

void PositionBasedModel::CopyBack(double dt, PositionBasedState* state) const {
  // Back to the public order, with velocities consistent with the Verlet step:
  // v = (x_new - x)/Δt (fixed nodes: 0). In public order, so that x and v are read and written
  // as streams and only the records are read at random (no random read-modify-write).
  // ChecksStateItself: every value written is checked here, as Step's own pass would.
  const auto n = static_cast<size_t>(rest_.cols());
  const double* __restrict nodes = state->nodes();
  const double* __restrict px = LastGoodPositions(state);
  const double inverse_dt = 1.0 / dt;
  const double component_limit = component_speed_limit();
  double* __restrict out_x = state->positions.data();
  double* __restrict out_v = state->velocities.data();
  StateCheck check;
#ifdef SOMASIM_PBD_AVX512
  if (simd_) {
    check =
        CopyBackAvx512(n, node_slot_.data(), nodes, px, inverse_dt, component_limit, out_x, out_v);
    SetStateChecked(state, check.non_finite, check.maybe_too_fast);
    state->last_dt = dt;
    return;
  }
#endif
  for (size_t i = 0; i < n; ++i) {
    const double* record = nodes + 4 * static_cast<size_t>(node_slot_[i]);
    for (size_t k = 0; k < 3; ++k) {
      const double updated = record[k];
      const double v = (updated - px[3 * i + k]) * inverse_dt;
      out_v[3 * i + k] = v;
      out_x[3 * i + k] = updated;
      check.Add(updated, v, component_limit);
    }
  }
  SetStateChecked(state, check.non_finite, check.maybe_too_fast);
  state->last_dt = dt;
}

}  // namespace somasim::models
