#include "server/models/tissue_model.h"

#include <algorithm>
#include <cmath>
#include <cstring>

#include "common/checks/finite.h"
#include "server/models/cpu_features.h"
#include "server/models/huge_pages.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_CHECK_AVX512 1
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace somasim::models {
namespace {

// x − x is 0 for every finite x and NaN for NaN and ±∞. SSE2 (the x86-64 baseline) checks two
// doubles per instruction; other targets take the scalar loop; CPUs with AVX-512 take
// CheckFlatAvx512 (same answers).
StateCheck CheckFlat(const double* __restrict x, const double* __restrict v, size_t count,
                     double component_limit) {
  size_t k = 0;
  int non_finite = 0;
  int fast = 0;
#if defined(__SSE2__)
  __m128d bad = _mm_setzero_pd();
  __m128d above = _mm_setzero_pd();
  const __m128d limit = _mm_set1_pd(component_limit);
  const __m128d magnitude_mask = _mm_castsi128_pd(_mm_set1_epi64x(0x7fffffffffffffffLL));
  for (; k + 2 <= count; k += 2) {
    const __m128d xv = _mm_loadu_pd(x + k);
    const __m128d vv = _mm_loadu_pd(v + k);
    const __m128d dx = _mm_sub_pd(xv, xv);
    const __m128d dv = _mm_sub_pd(vv, vv);
    bad = _mm_or_pd(bad, _mm_or_pd(_mm_cmpunord_pd(dx, dx), _mm_cmpunord_pd(dv, dv)));
    above = _mm_or_pd(above, _mm_cmpgt_pd(_mm_and_pd(vv, magnitude_mask), limit));
  }
  non_finite = _mm_movemask_pd(bad);
  fast = _mm_movemask_pd(above);
#endif
  for (; k < count; ++k) {
    non_finite |= static_cast<int>(!(x[k] - x[k] == 0.0)) | static_cast<int>(!(v[k] - v[k] == 0.0));
    fast |= static_cast<int>(std::abs(v[k]) > component_limit);
  }
  return {non_finite != 0, fast != 0};
}

#ifdef SOMASIM_CHECK_AVX512
// CheckFlat, eight doubles per instruction: the check runs after every step over every node,
// which at 10 kHz on a 5400-node organ is a tenth of a mass-spring step with SSE2.
__attribute__((target("avx512f"))) StateCheck CheckFlatAvx512(const double* __restrict x,
                                                              const double* __restrict v,
                                                              size_t count,
                                                              double component_limit) {
  size_t k = 0;
  __mmask8 bad = 0, above = 0;
  const __m512d limit = _mm512_set1_pd(component_limit);
  for (; k + 8 <= count; k += 8) {
    const __m512d xv = _mm512_loadu_pd(x + k);
    const __m512d vv = _mm512_loadu_pd(v + k);
    bad |= _mm512_cmp_pd_mask(_mm512_sub_pd(xv, xv), _mm512_sub_pd(vv, vv), _CMP_UNORD_Q);
    above |= _mm512_cmp_pd_mask(_mm512_abs_pd(vv), limit, _CMP_GT_OQ);
  }
  StateCheck result{bad != 0, above != 0};
  for (; k < count; ++k) {
    result.non_finite = result.non_finite || !(x[k] - x[k] == 0.0) || !(v[k] - v[k] == 0.0);
    result.maybe_too_fast = result.maybe_too_fast || std::abs(v[k]) > component_limit;
  }
  return result;
}
#endif

// Whether every value is finite: no exponent of all ones (NaN, ±∞), on the bits, so that the
// loop has no early exit and vectorises (a step's external forces: 3 × num_nodes values).
bool AllFinite(const double* values, size_t count) {
  constexpr uint64_t kExponent = 0x7FF0000000000000ULL;
  uint64_t bad = 0;
  for (size_t k = 0; k < count; ++k) {
    uint64_t bits = 0;
    std::memcpy(&bits, values + k, sizeof bits);
    bad |= static_cast<uint64_t>((bits & kExponent) == kExponent);
  }
  return bad == 0;
}

#ifdef SOMASIM_CHECK_AVX512
// AllFinite, eight doubles per compare (x − x is NaN exactly for NaN and ±∞).
__attribute__((target("avx512f"))) bool AllFiniteAvx512(const double* values, size_t count) {
  size_t k = 0;
  __mmask8 bad = 0;
  for (; k + 8 <= count; k += 8) {
    const __m512d v = _mm512_loadu_pd(values + k);
    const __m512d d = _mm512_sub_pd(v, v);
    bad |= _mm512_cmp_pd_mask(d, d, _CMP_UNORD_Q);
  }
  return bad == 0 && AllFinite(values + k, count - k);
}
#endif

bool ValuesFinite(const double* values, size_t count) {
#ifdef SOMASIM_CHECK_AVX512
  if (CpuHasAvx512()) return AllFiniteAvx512(values, count);
#endif
  return AllFinite(values, count);
}

StateCheck CheckState(const double* x, const double* v, size_t count, double component_limit) {
#ifdef SOMASIM_CHECK_AVX512
  if (CpuHasAvx512()) return CheckFlatAvx512(x, v, count, component_limit);
#endif
  return CheckFlat(x, v, count, component_limit);
}

}  // namespace

const char* StepStatusName(StepStatus status) {
  switch (status) {
    case StepStatus::kOk:
      return "ok";
    case StepStatus::kRejectedNonFinite:
      return "rejected: non-finite state";
    case StepStatus::kRejectedTooFast:
      return "rejected: speed above the limit";
    case StepStatus::kBadInput:
      return "bad step input";
  }
  return "?";
}

void TissueModel::InitialiseState(const mesh::Points& rest, TissueState* state) {
  state->positions = rest;
  state->velocities = mesh::Points::Zero(3, rest.cols());
  state->last_good_positions_ = rest;
  state->last_good_velocities_ = state->velocities;
  // Large organs' x and v on huge pages where the kernel can (huge_pages.h): a best effort.
  for (mesh::Points* points : {&state->positions, &state->velocities, &state->last_good_positions_,
                               &state->last_good_velocities_}) {
    AdviseHugePages(points->data(), static_cast<size_t>(points->size()) * sizeof(double));
  }
  state->time = 0.0;
  state->counters = {};
}

void TissueModel::CheckWholeState(TissueState* state) const {
  const StateCheck flat =
      CheckState(state->positions.data(), state->velocities.data(),
                 static_cast<size_t>(state->positions.size()), component_speed_limit());
  SetStateChecked(state, flat.non_finite, flat.maybe_too_fast);
}

StepStatus TissueModel::Step(const StepInputs& inputs, TissueState* state) const {
  const int32_t n = num_nodes();
  const auto in_range = [n](int32_t node) { return node >= 0 && node < n; };
  bool ok = checks::FinitePositive(inputs.dt) && inputs.gravity.allFinite();
  if (inputs.external_forces != nullptr) {
    ok = ok && inputs.external_forces->cols() == n &&
         ValuesFinite(inputs.external_forces->data(),
                      static_cast<size_t>(inputs.external_forces->size()));
  }
  for (const int32_t node : inputs.fixed_nodes) ok = ok && in_range(node);
  for (const int32_t node : inputs.prescribed_nodes) ok = ok && in_range(node);
  if (!inputs.prescribed_nodes.empty()) {
    ok = ok && inputs.prescribed_positions != nullptr &&
         inputs.prescribed_positions->cols() ==
             static_cast<Eigen::Index>(inputs.prescribed_nodes.size()) &&
         inputs.prescribed_positions->allFinite();
  }
  for (const Attachment& a : inputs.attachments) {
    ok = ok && in_range(a.node) && a.target.allFinite() && checks::FiniteNonNegative(a.stiffness);
  }
  if (!ok) {
    ++state->counters.bad_inputs;
    return StepStatus::kBadInput;
  }

  Advance(inputs, state);

  // A NaN or infinity anywhere, or a node faster than the limit. The flat pass (vectorisable:
  // integer OR reductions over contiguous doubles) finds non-finite values and any velocity
  // component above limit/√3, which every node faster than the limit has; only then are the
  // nodes' speeds checked exactly.
  const auto count = static_cast<size_t>(3 * static_cast<Eigen::Index>(n));
  const double* x = state->positions.data();
  const double* v = state->velocities.data();
  const StateCheck flat =
      ChecksStateItself() ? StateCheck{state->checked_non_finite_, state->checked_maybe_too_fast_}
                          : CheckState(x, v, count, component_speed_limit());
  const bool non_finite = flat.non_finite;
  bool too_fast = false;
  if (flat.maybe_too_fast && !non_finite) {
    const double limit2 = speed_limit_ * speed_limit_;
    for (size_t i = 0; i < count; i += 3) {
      too_fast |= v[i] * v[i] + v[i + 1] * v[i + 1] + v[i + 2] * v[i + 2] > limit2;
    }
  }
  StepStatus status = StepStatus::kOk;
  if (non_finite) {
    status = StepStatus::kRejectedNonFinite;
  } else if (too_fast) {
    status = StepStatus::kRejectedTooFast;
  }
  if (status != StepStatus::kOk) {
    state->positions = state->last_good_positions_;  // same size: no allocation
    state->velocities = state->last_good_velocities_;
    state->RestoreGood();
    ++state->counters.rejected_steps;
    return status;
  }
  if (!SavesGoodStateItself()) {
    state->last_good_positions_ = state->positions;
    state->last_good_velocities_ = state->velocities;
  }
  state->SaveGood();
  state->time += inputs.dt;
  ++state->counters.steps;
  return StepStatus::kOk;
}

}  // namespace somasim::models
