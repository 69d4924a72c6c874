#include "server/models/position_based_model.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "common/checks/finite.h"
#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "server/models/cpu_features.h"
#include "server/models/particle_edges.h"
#include "server/models/particle_mesh.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_PBD_AVX512 1
#endif

namespace somasim::models {
namespace {

using Eigen::Vector3d;

constexpr double kDefaultDt = 1e-3;  // [s] seed-mode k_eff before the first step

// The state of a position-based model: the base state, the multipliers of the last step and the
// scratch of a step, all sized by MakeState so that stepping allocates nothing. The sweeps run on
// an internal copy of the positions: one 32-byte record (x, y, z, w) per node, w the inverse mass
// of this step, in the model's internal node order (see PositionBasedModel::OrderNodes).
class PositionBasedState final : public TissueState {
 public:
  // The 4 × num_nodes internal records, 64-byte aligned inside node_buffer.
  double* nodes() { return node_buffer.data() + node_offset; }
  std::vector<double> node_buffer;   // 4 num_nodes + 8
  size_t node_offset = 0;            // of the first record in node_buffer
  std::vector<double> predicted;     // x̃ (primal correction), 4 × num_nodes, internal order
  std::vector<double> impulse;       // Σ ∇C λ per node [N s²], 4 × num_nodes, internal order
  std::vector<double> inverse_mass;  // w this step (0 for fixed, prescribed), internal order
  std::vector<double> lambda;  // multipliers [N s²] of this step, num_constraints, sweep order
  // Per-constraint factors of the step, in sweep order (num_constraints), functions of Δt and w
  // only: recomputed when either changes.
  std::vector<double> sweep_alpha;  // α̃ = compliance/Δt² [1/kg] (0 in seed mode)
  std::vector<double> sweep_gain;  // 1/(w_i + w_j + α̃) (seed: k/(w_i + w_j)); 0 if w_i + w_j = 0
  // w_i gain and w_j gain [–], the vector sweep's factors: it then needs no w from the records,
  // and stores only their x, y and z.
  std::vector<double> sweep_wi_gain;
  std::vector<double> sweep_wj_gain;
  std::vector<double> prepared_w;  // the w the factors were computed with, internal order
  double prepared_dt = 0.0;        // and the Δt [s] (0: not yet)
  double last_dt = 0.0;            // [s] of the last accepted step, 0 before any
  std::vector<uint8_t> cut;        // 1 = removed by Cut, num_constraints, constraint order
  // Attachments, merged per node: Σ_a k_a (t_a - x) = K (t̄ - x) with K = Σ k_a,
  // t̄ = Σ k_a t_a / K, projected as one compliant vector constraint (compliance 1/K).
  std::vector<double> attach_stiffness;  // K [N/m], num_nodes, 0 between steps
  mesh::Points attach_weighted_target;   // Σ k_a t_a [N], 3 × num_nodes
  mesh::Points attach_lambda;            // [N s²], 3 × num_nodes
  std::vector<int32_t> attached_nodes;   // the first num_attached are this step's, num_nodes
  size_t num_attached = 0;

 protected:
  // λ is zeroed at the start of every step, so an accepted step's multipliers are kept by a swap
  // (no copy): good_lambda_ then holds them (LastConstraintResidual reads it).
  void SaveGood() override {
    lambda.swap(good_lambda_);
    good_last_dt_ = last_dt;
  }
  void RestoreGood() override { last_dt = good_last_dt_; }

 private:
  friend class somasim::models::PositionBasedModel;
  std::vector<double> good_lambda_;  // the last accepted step's λ, sweep order
  mesh::Points volume_forces;        // [N], 3 × num_nodes when the volume reaction is on
  double good_last_dt_ = 0.0;
};

// The arrays one sweep reads, in sweep order. Projecting slot e: d = x_j - x_i, l = |d|,
// t = l - a + α̃ λ, Δλ = -t · gain, λ += Δλ, x_i -= w_i Δλ d/l, x_j += w_j Δλ d/l. In XPBD mode
// (gain = 1/(w_i + w_j + α̃)) that is Macklin et al. 2016 eq. 18; in seed mode (α̃ = 0,
// gain = k/(w_i + w_j)) seed 004 eq. 2–3, λ then being unused. Positions and inverse masses come
// from the internal node records (x, y, z, w).
struct SweepArrays {
  const int32_t* i4;  // offset 4 p of node i's record
  const int32_t* j4;
  const double* rest;
  const double* inverse_rest;
  const double* alpha;
  const double* gain;
  const double* wi_gain;  // w_i gain: the vector sweep's
  const double* wj_gain;  // w_j gain
  double* lambda;
};

// Projects slots [begin, end) in order onto the node records x (4 × n); returns the largest
// relative residual |C + α̃ λ|/a seen before each projection (0 unless kResidual). kFirst: the
// first sweep of a step, where every λ is 0 (so neither α̃ nor λ is read, and λ is written
// rather than updated: the step needs no zeroing pass over λ).
template <bool kResidual, bool kFirst>
double ProjectScalar(const SweepArrays& s, size_t begin, size_t end, double* __restrict x) {
  double residual = 0.0;
  for (size_t e = begin; e < end; ++e) {
    double* __restrict xi = x + s.i4[e];
    double* __restrict xj = x + s.j4[e];
    const double dx = xj[0] - xi[0];
    const double dy = xj[1] - xi[1];
    const double dz = xj[2] - xi[2];
    const double l2 = dx * dx + dy * dy + dz * dz;
    const double length = std::sqrt(l2);
    const double t = kFirst ? length - s.rest[e] : (length - s.rest[e]) + s.alpha[e] * s.lambda[e];
    if constexpr (kResidual) residual = std::max(residual, std::abs(t) * s.inverse_rest[e]);
    if (!(l2 > 0.0)) {
      if constexpr (kFirst) s.lambda[e] = 0.0;
      continue;
    }
    const double dlambda = -t * s.gain[e];
    if constexpr (kFirst) {
      s.lambda[e] = dlambda;
    } else {
      s.lambda[e] += dlambda;
    }
    const double f = dlambda / length;
    const double fi = xi[3] * f;
    const double fj = xj[3] * f;
    xi[0] -= fi * dx;
    xi[1] -= fi * dy;
    xi[2] -= fi * dz;
    xj[0] += fj * dx;
    xj[1] += fj * dy;
    xj[2] += fj * dz;
  }
  return residual;
}

#ifdef SOMASIM_PBD_AVX512
// 8 node records (x, y, z, w) at x + offset[0..7] (32-byte aligned) as the rows X, Y, Z of 8
// lanes: two 256-bit loads per 512-bit register, then an 8 × 4 transpose of which the W row is
// not formed (the sweep's factors w gain come from the state). Loading pairs the
// records 0 2, 1 3, 4 6, 5 7, so that unpacks and 128-bit lane selections (vshuff64x2)
// transpose them; storing pairs 0 4, 1 5, 2 6, 3 7 and uses two-source permutes. On Zen 4 a
// two-source permute takes a whole multiply slot and a lane selection about 0.6 of one (3–4 %
// of the sweep).
// (The masked forms of unpack, shuffle and extract, all lanes set, are the plain instructions
// without gcc-12's uninitialised-value warnings.)
struct Lanes {
  __m512d x, y, z;
};

// Records offset[a] and offset[b] in one register.
__attribute__((target("avx512f,avx512vl"))) inline __m512d LoadPair(const double* x,
                                                                    const int32_t* offset, int a,
                                                                    int b) {
  return _mm512_mask_broadcast_f64x4(_mm512_castpd256_pd512(_mm256_load_pd(x + offset[a])), 0xF0,
                                     _mm256_load_pd(x + offset[b]));
}

__attribute__((target("avx512f,avx512vl"))) inline Lanes LoadRecords(const double* x,
                                                                     const int32_t* offset) {
  const __m512d r02 = LoadPair(x, offset, 0, 2);  // x0 y0 z0 w0 x2 y2 z2 w2
  const __m512d r13 = LoadPair(x, offset, 1, 3);
  const __m512d r46 = LoadPair(x, offset, 4, 6);
  const __m512d r57 = LoadPair(x, offset, 5, 7);
  const __m512d t0 = _mm512_mask_unpacklo_pd(r02, 0xFF, r02, r13);  // x0 x1 z0 z1 x2 x3 z2 z3
  const __m512d t1 = _mm512_mask_unpackhi_pd(r02, 0xFF, r02, r13);  // y0 y1 w0 w1 y2 y3 w2 w3
  const __m512d t2 = _mm512_mask_unpacklo_pd(r46, 0xFF, r46, r57);  // x4 x5 z4 z5 x6 x7 z6 z7
  const __m512d t3 = _mm512_mask_unpackhi_pd(r46, 0xFF, r46, r57);  // y4 y5 w4 w5 y6 y7 w6 w7
  // 128-bit lanes 0 2 of t0 then 0 2 of t2 (0x88), or 1 3 of each (0xDD).
  return {_mm512_maskz_shuffle_f64x2(0xFF, t0, t2, 0x88),
          _mm512_maskz_shuffle_f64x2(0xFF, t1, t3, 0x88),
          _mm512_maskz_shuffle_f64x2(0xFF, t0, t2, 0xDD)};
}

// The inverse of LoadPair for x, y, z: lane 3 (w) of the records is not written (masked stores:
// on Sapphire/Emerald Rapids the sweep is bound by its shuffles, one port's, and this saves one
// in four of the stores' permutes; −7 to −8 % on gallbladder5400/10).
__attribute__((target("avx512f,avx512vl"))) inline void StorePair(__m512d record, double* x,
                                                                  const int32_t* offset, int a) {
  const __m256d unused = _mm256_setzero_pd();
  // The lower half is the register's own ymm (AVX512VL's encoding reaches ymm16–31; without it
  // gcc extracts the half with a shuffle, 3–4 % of the sweep on Zen 4).
  _mm256_mask_store_pd(x + offset[a], 0x7, __builtin_shufflevector(record, record, 0, 1, 2, 3));
  _mm256_mask_store_pd(x + offset[a + 4], 0x7, _mm512_mask_extractf64x4_pd(unused, 0xF, record, 1));
}

// The inverse of LoadRecords (the w of a record never changes in a sweep, so lane 3 is left as
// it is): the y row needs no permute for records 0 1 4 5, whose
// y sit in lanes 0 1 4 5 already, and one in-lane permute for 2 3 6 7.
__attribute__((target("avx512f,avx512vl"))) inline void StoreRecords(const Lanes& r, double* x,
                                                                     const int32_t* offset,
                                                                     __m512i low, __m512i high) {
  const __m512d t0 = _mm512_permutex2var_pd(r.x, low, r.z);          // x0 x1 z0 z1 x4 x5 z4 z5
  const __m512d t1 = r.y;                                            // y0 y1 .. .. y4 y5 .. ..
  const __m512d t2 = _mm512_permutex2var_pd(r.x, high, r.z);         // x2 x3 z2 z3 x6 x7 z6 z7
  const __m512d t3 = _mm512_mask_permutex_pd(r.y, 0xFF, r.y, 0xEE);  // y2 y3 .. .. y6 y7 .. ..
  StorePair(_mm512_mask_unpacklo_pd(t0, 0xFF, t0, t1), x, offset, 0);
  StorePair(_mm512_mask_unpackhi_pd(t0, 0xFF, t0, t1), x, offset, 1);
  StorePair(_mm512_mask_unpacklo_pd(t2, 0xFF, t2, t3), x, offset, 2);
  StorePair(_mm512_mask_unpackhi_pd(t2, 0xFF, t2, t3), x, offset, 3);
}

// The projection of 8 slots from their loaded records (see SweepArrays): updates i and j in
// place, stores λ + Δλ (Δλ alone when kFirst: λ = 0), and folds |t|/a into worst when
// kResidual.
template <bool kResidual, bool kFirst>
__attribute__((target("avx512f,avx512vl"), always_inline)) inline void ProjectLanes(
    const SweepArrays& s, size_t e, Lanes* i, Lanes* j, __m512d* worst) {
  const __m512d zero = _mm512_setzero_pd();
  const __m512d one = _mm512_set1_pd(1.0);
  const __m512d half = _mm512_set1_pd(0.5);
  const __m512d dx = _mm512_sub_pd(j->x, i->x);
  const __m512d dy = _mm512_sub_pd(j->y, i->y);
  const __m512d dz = _mm512_sub_pd(j->z, i->z);
  const __m512d l2 = _mm512_fmadd_pd(dz, dz, _mm512_fmadd_pd(dy, dy, _mm512_mul_pd(dx, dx)));
  const __mmask8 ok = _mm512_cmp_pd_mask(l2, zero, _CMP_GT_OQ);
  // 1/l from y0 = rsqrt14(l²) (relative error < 2^-14) by one third-order correction: with
  // r = 1 - l² y0², 1/l = y0 (1 - r)^(-1/2) = y0 (1 + r/2 + 3r²/8 + 5r³/16 + O(r⁴)), O(r⁴) <
  // 2^-56: as exact as two Newton steps. Summed as y0 + y0 r/2 + (y0 r) r (3/8 + 5r/16), the
  // chain after r is three steps: the sweep is bound by this chain (one group of 8 per
  // iteration instead of two is 20 % slower on Zen 4), not by the operation count.
  __m512d y = _mm512_maskz_rsqrt14_pd(ok, l2);
  const __m512d r = _mm512_fnmadd_pd(l2, _mm512_mul_pd(y, y), one);
  const __m512d yr = _mm512_mul_pd(y, r);
  y = _mm512_fmadd_pd(_mm512_mul_pd(yr, r),
                      _mm512_fmadd_pd(r, _mm512_set1_pd(0.3125), _mm512_set1_pd(0.375)),
                      _mm512_fmadd_pd(yr, half, y));
  // t = l - (a - α̃ λ), one fused step after 1/l: a - α̃ λ is ready before it.
  const __m512d lambda = kFirst ? zero : _mm512_loadu_pd(s.lambda + e);
  const __m512d rest = _mm512_loadu_pd(s.rest + e);
  const __m512d t = _mm512_fmsub_pd(
      l2, y, kFirst ? rest : _mm512_fnmadd_pd(_mm512_loadu_pd(s.alpha + e), lambda, rest));
  if constexpr (kResidual) {
    const __m512i sign_mask = _mm512_set1_epi64(INT64_MAX);
    const __m512d relative =
        _mm512_mul_pd(_mm512_castsi512_pd(_mm512_and_si512(_mm512_castpd_si512(t), sign_mask)),
                      _mm512_loadu_pd(s.inverse_rest + e));
    *worst = _mm512_mask_max_pd(*worst, 0xFF, *worst, relative);
  }
  // -(t gain) + 0, exactly the scalar -t · gain.
  const __m512d gain = _mm512_loadu_pd(s.gain + e);
  const __m512d dlambda = _mm512_maskz_fnmadd_pd(ok, t, gain, zero);
  _mm512_storeu_pd(s.lambda + e, kFirst ? dlambda : _mm512_add_pd(lambda, dlambda));
  // x_i -= w_i Δλ d/l = x_i + t (w_i gain / l) d, with w_i gain precomputed (the state's
  // sweep_wi_gain) and (w_i gain) / l formed while t is: two steps after t instead of four. (0
  // where l = 0: y is 0 there, and those lanes do not move.)
  const __m512d fi = _mm512_mul_pd(t, _mm512_mul_pd(_mm512_loadu_pd(s.wi_gain + e), y));
  const __m512d fj = _mm512_mul_pd(t, _mm512_mul_pd(_mm512_loadu_pd(s.wj_gain + e), y));
  i->x = _mm512_fmadd_pd(fi, dx, i->x);
  i->y = _mm512_fmadd_pd(fi, dy, i->y);
  i->z = _mm512_fmadd_pd(fi, dz, i->z);
  j->x = _mm512_fnmadd_pd(fj, dx, j->x);
  j->y = _mm512_fnmadd_pd(fj, dy, j->y);
  j->z = _mm512_fnmadd_pd(fj, dz, j->z);
}

// ProjectScalar, 16 then 8 slots at a time: valid only when no two slots of [begin, end) share a
// node (one colour), so that the order within a vector does not matter; two independent groups
// of 8 per iteration let their latency chains overlap. The last (end - begin) % 8 slots go
// through ProjectScalar. 1/l comes from rsqrt14 and a third-order correction (relative error
// ~1e-16), so results differ from the scalar sweep by rounding.
template <bool kResidual, bool kFirst>
__attribute__((target("avx512f,avx512vl"))) double ProjectAvx512(const SweepArrays& arrays,
                                                                 size_t begin, size_t end,
                                                                 double* x) {
  const SweepArrays s = arrays;  // local: the record stores may alias anything
  // Lanes 0 1 8 9 4 5 12 13 and 2 3 10 11 6 7 14 15 of two registers (the transpose).
  const __m512i low = _mm512_set_epi64(13, 12, 5, 4, 9, 8, 1, 0);
  const __m512i high = _mm512_set_epi64(15, 14, 7, 6, 11, 10, 3, 2);
  __m512d worst = _mm512_setzero_pd();
  size_t e = begin;
  for (; e + 16 <= end; e += 16) {
    Lanes i0 = LoadRecords(x, s.i4 + e);
    Lanes j0 = LoadRecords(x, s.j4 + e);
    Lanes i1 = LoadRecords(x, s.i4 + e + 8);
    Lanes j1 = LoadRecords(x, s.j4 + e + 8);
    ProjectLanes<kResidual, kFirst>(s, e, &i0, &j0, &worst);
    ProjectLanes<kResidual, kFirst>(s, e + 8, &i1, &j1, &worst);
    StoreRecords(i0, x, s.i4 + e, low, high);
    StoreRecords(j0, x, s.j4 + e, low, high);
    StoreRecords(i1, x, s.i4 + e + 8, low, high);
    StoreRecords(j1, x, s.j4 + e + 8, low, high);
  }
  if (e + 8 <= end) {
    Lanes i0 = LoadRecords(x, s.i4 + e);
    Lanes j0 = LoadRecords(x, s.j4 + e);
    ProjectLanes<kResidual, kFirst>(s, e, &i0, &j0, &worst);
    StoreRecords(i0, x, s.i4 + e, low, high);
    StoreRecords(j0, x, s.j4 + e, low, high);
    e += 8;
  }
  alignas(64) double lane_worst[8];
  _mm512_store_pd(lane_worst, worst);
  const double tail = ProjectScalar<kResidual, kFirst>(s, e, end, x);
  return std::max(tail, *std::max_element(lane_worst, lane_worst + 8));
}

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

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("position-based: " + what);
}

bool VolumeOn(const SolidAngleVolumeParameters& v) {
  return v.gamma_plus != 0.0 || v.sigma_plus != 0.0 || v.gamma_minus != 0.0 || v.sigma_minus != 0.0;
}

void CheckParameters(const PositionBasedParameters& p) {
  if (p.mode != PositionBasedMode::kSeedStiffness && p.mode != PositionBasedMode::kXpbd) {
    Refuse("mode must be kSeedStiffness or kXpbd");
  }
  if (!(p.iterations >= 1)) Refuse("iterations must be >= 1");
  if (!(p.stiffness > 0.0 && p.stiffness <= 1.0)) Refuse("stiffness k must lie in (0, 1]");
  checks::RequireFiniteNonNegative("position-based", "compliance [m/N]", p.compliance);
  if (p.mode == PositionBasedMode::kXpbd && !(p.compliance > 0.0) &&
      !checks::FinitePositive(p.youngs_modulus)) {
    Refuse("youngs_modulus [Pa] must be a finite value > 0 (or give compliance > 0)");
  }
  checks::RequireFiniteNonNegative("position-based", "node_mass [kg]", p.node_mass);
  if (!(p.node_mass > 0.0) && !checks::FinitePositive(p.density)) {
    Refuse("density [kg/m^3] must be a finite value > 0 (or give node_mass > 0)");
  }
  if (!checks::FinitePositive(p.thickness)) Refuse("thickness [m] must be a finite value > 0");
  checks::RequireFiniteNonNegative("position-based", "tolerance", p.tolerance);
  if (!(p.speed_limit > 0.0)) Refuse("speed_limit [m/s] must be > 0");
}

}  // namespace

std::unique_ptr<PositionBasedModel> PositionBasedModel::FromTetMesh(
    const mesh::TetMesh& mesh, const PositionBasedParameters& parameters) {
  CheckParameters(parameters);
  const MeshEdges edges = TetMeshEdges(mesh, "position-based");
  std::unique_ptr<PositionBasedModel> model(new PositionBasedModel());
  model->Build(mesh.vertices, edges.edges, edges.edge_size, edges.node_size, parameters);
  if (VolumeOn(parameters.volume)) {
    model->volume_ = std::make_unique<SolidAngleVolumeTerm>(SolidAngleVolumeTerm::Build(
        mesh.vertices, mesh::ExtractBoundarySurface(mesh).triangles, parameters.volume));
  }
  return model;
}

std::unique_ptr<PositionBasedModel> PositionBasedModel::FromSurface(
    const mesh::SurfaceMesh& surface, const PositionBasedParameters& parameters) {
  CheckParameters(parameters);
  const MeshEdges edges = SurfaceEdges(surface, parameters.thickness, "position-based");
  std::unique_ptr<PositionBasedModel> model(new PositionBasedModel());
  model->Build(surface.vertices, edges.edges, edges.edge_size, edges.node_size, parameters);
  if (VolumeOn(parameters.volume)) {
    model->volume_ = std::make_unique<SolidAngleVolumeTerm>(
        SolidAngleVolumeTerm::Build(surface, parameters.volume));
  }
  return model;
}

std::unique_ptr<PositionBasedModel> PositionBasedModel::FromEdges(
    const mesh::Points& rest, const std::vector<std::array<int32_t, 2>>& edges,
    const PositionBasedParameters& parameters) {
  CheckParameters(parameters);
  CheckFinitePoints(rest, "position-based");
  if (!(parameters.node_mass > 0.0)) Refuse("constraints given as edges need node_mass > 0");
  if (parameters.mode == PositionBasedMode::kXpbd && !(parameters.compliance > 0.0)) {
    Refuse("XPBD constraints given as edges need compliance > 0");
  }
  if (edges.empty()) Refuse("no constraints");
  if (VolumeOn(parameters.volume)) {
    Refuse("the volume reaction needs a closed surface; constraints given as edges have none");
  }
  std::vector<std::array<int32_t, 2>> ordered =
      SortedEdges(edges, rest.cols(), "position-based", "constraint");
  ordered.erase(std::unique(ordered.begin(), ordered.end()), ordered.end());
  std::unique_ptr<PositionBasedModel> model(new PositionBasedModel());
  model->Build(rest, ordered, std::vector<double>(ordered.size(), 0.0),
               std::vector<double>(static_cast<size_t>(rest.cols()), 0.0), parameters);
  return model;
}

void PositionBasedModel::Build(const mesh::Points& rest,
                               const std::vector<std::array<int32_t, 2>>& edges,
                               const std::vector<double>& edge_size_sum,
                               const std::vector<double>& node_size,
                               const PositionBasedParameters& p) {
  parameters_ = p;
  rest_ = rest;
  const auto n = static_cast<size_t>(rest.cols());
  LumpMasses(node_size, p.density, p.node_mass, &mass_, &inverse_mass_);
  const size_t m = edges.size();
  edge_i_.resize(m);
  edge_j_.resize(m);
  rest_length_.resize(m);
  const bool xpbd = p.mode == PositionBasedMode::kXpbd;
  edge_stiffness_.assign(xpbd ? m : 0, 0.0);
  edge_compliance_.assign(xpbd ? m : 0, 0.0);
  for (size_t e = 0; e < m; ++e) {
    const auto [i, j] = edges[e];
    edge_i_[e] = i;
    edge_j_[e] = j;
    const double length = EdgeRestLength(rest, i, j, "position-based", "constraint");
    rest_length_[e] = length;
    if (xpbd) {
      // Van Gelder 1998: k_e = E Σ size / |e|²; compliance = 1/k_e.
      const double k = p.compliance > 0.0 ? 1.0 / p.compliance
                                          : p.youngs_modulus * edge_size_sum[e] / (length * length);
      if (!checks::FinitePositive(k)) {
        Refuse("constraint " + std::to_string(e) + " (nodes " + std::to_string(i) + ", " +
               std::to_string(j) + ") gets no stiffness from the material");
      }
      edge_stiffness_[e] = k;
      edge_compliance_[e] = 1.0 / k;
    }
  }
  NodeEdgeLists(n, edge_i_, edge_j_, &node_edge_start_, &node_edges_);
  OrderNodes();
  ColourConstraints();
  simd_ = p.vectorised && CpuHasAvx512();
  set_speed_limit(p.speed_limit);
}

void PositionBasedModel::OrderNodes() {
  // Reverse Cuthill–McKee on the constraint graph (breadth first from a node of least degree,
  // neighbours by increasing degree, then reversed; component by component), so that the
  // records a sweep touches in turn lie close together in memory.
  const size_t n = mass_.size();
  const auto degree = [this](size_t i) { return node_edge_start_[i + 1] - node_edge_start_[i]; };
  const auto by_degree = [&degree](int32_t a, int32_t b) {
    const int32_t da = degree(static_cast<size_t>(a));
    const int32_t db = degree(static_cast<size_t>(b));
    return da != db ? da < db : a < b;
  };
  std::vector<int32_t> starts(n);
  for (size_t i = 0; i < n; ++i) starts[i] = static_cast<int32_t>(i);
  std::sort(starts.begin(), starts.end(), by_degree);
  std::vector<char> seen(n, 0);
  std::vector<int32_t> order;
  order.reserve(n);
  for (const int32_t start : starts) {
    if (seen[static_cast<size_t>(start)] != 0) continue;
    seen[static_cast<size_t>(start)] = 1;
    size_t head = order.size();
    order.push_back(start);
    while (head < order.size()) {
      const auto node = static_cast<size_t>(order[head++]);
      const size_t first = order.size();
      for (int32_t slot = node_edge_start_[node]; slot < node_edge_start_[node + 1]; ++slot) {
        const auto e = static_cast<size_t>(node_edges_[static_cast<size_t>(slot)]);
        const int32_t other = static_cast<size_t>(edge_i_[e]) == node ? edge_j_[e] : edge_i_[e];
        if (seen[static_cast<size_t>(other)] != 0) continue;
        seen[static_cast<size_t>(other)] = 1;
        order.push_back(other);
      }
      std::sort(order.begin() + static_cast<std::ptrdiff_t>(first), order.end(), by_degree);
    }
  }
  std::reverse(order.begin(), order.end());
  node_order_ = std::move(order);
  node_slot_.resize(n);
  for (size_t p = 0; p < n; ++p)
    node_slot_[static_cast<size_t>(node_order_[p])] = static_cast<int32_t>(p);
}

void PositionBasedModel::ColourConstraints() {
  // Greedy colouring, constraints taken by their internal node slots (lower, then upper): each
  // takes the lowest colour that neither of its nodes has yet. At most 2 · (max degree) - 1
  // colours. Within a colour the same order, so consecutive slots touch nearby records.
  const size_t n = mass_.size();
  const size_t m = edge_i_.size();
  int32_t max_degree = 0;
  for (size_t i = 0; i < n; ++i) {
    max_degree = std::max(max_degree, node_edge_start_[i + 1] - node_edge_start_[i]);
  }
  std::vector<std::array<int32_t, 3>> by_slot(m);  // lower slot, upper slot, constraint
  for (size_t e = 0; e < m; ++e) {
    const int32_t a = node_slot_[static_cast<size_t>(edge_i_[e])];
    const int32_t b = node_slot_[static_cast<size_t>(edge_j_[e])];
    by_slot[e] = {std::min(a, b), std::max(a, b), static_cast<int32_t>(e)};
  }
  std::sort(by_slot.begin(), by_slot.end());
  const size_t words = (2 * static_cast<size_t>(max_degree) + 63) / 64;
  std::vector<uint64_t> used(n * words, 0);  // bit c of node i: colour c touches i
  std::vector<int32_t> colour(m);            // of by_slot[k]
  int32_t num_colours = 0;
  for (size_t k = 0; k < m; ++k) {
    const auto e = static_cast<size_t>(by_slot[k][2]);
    uint64_t* ui = &used[static_cast<size_t>(edge_i_[e]) * words];
    uint64_t* uj = &used[static_cast<size_t>(edge_j_[e]) * words];
    size_t c = 0;
    for (size_t w = 0; w < words; ++w) {
      const uint64_t taken = ui[w] | uj[w];
      if (taken != ~uint64_t{0}) {
        c = 64 * w + static_cast<size_t>(__builtin_ctzll(~taken));
        break;
      }
    }
    colour[k] = static_cast<int32_t>(c);
    num_colours = std::max(num_colours, static_cast<int32_t>(c) + 1);
    ui[c / 64] |= uint64_t{1} << (c % 64);
    uj[c / 64] |= uint64_t{1} << (c % 64);
  }
  // Slots by colour, in by_slot order within a colour (a counting sort).
  colour_start_.assign(static_cast<size_t>(num_colours) + 1, 0);
  for (size_t k = 0; k < m; ++k) ++colour_start_[static_cast<size_t>(colour[k]) + 1];
  for (size_t c = 0; c < static_cast<size_t>(num_colours); ++c) {
    colour_start_[c + 1] += colour_start_[c];
  }
  std::vector<int32_t> fill(colour_start_.begin(), colour_start_.end() - 1);
  sweep_edge_.resize(m);
  for (size_t k = 0; k < m; ++k) {
    sweep_edge_[static_cast<size_t>(fill[static_cast<size_t>(colour[k])]++)] = by_slot[k][2];
  }
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  sweep_i4_.resize(m);
  sweep_j4_.resize(m);
  sweep_rest_.resize(m);
  sweep_inv_rest_.resize(m);
  sweep_compliance_.resize(m);
  for (size_t s = 0; s < m; ++s) {
    const auto e = static_cast<size_t>(sweep_edge_[s]);
    sweep_i4_[s] = 4 * node_slot_[static_cast<size_t>(edge_i_[e])];
    sweep_j4_[s] = 4 * node_slot_[static_cast<size_t>(edge_j_[e])];
    sweep_rest_[s] = rest_length_[e];
    sweep_inv_rest_[s] = 1.0 / rest_length_[e];
    sweep_compliance_[s] = xpbd ? edge_compliance_[e] : 0.0;
  }
}

std::unique_ptr<TissueState> PositionBasedModel::MakeState() const {
  auto state = std::make_unique<PositionBasedState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = rest_.cols();
  const auto nn = static_cast<size_t>(n);
  const auto m = static_cast<size_t>(num_constraints());
  state->node_buffer.assign(4 * nn + 8, 0.0);
  void* first = state->node_buffer.data();
  size_t space = state->node_buffer.size() * sizeof(double);
  std::align(64, 4 * nn * sizeof(double), first, space);
  state->node_offset = static_cast<size_t>(static_cast<double*>(first) - state->node_buffer.data());
  state->predicted.assign(4 * nn, 0.0);
  state->impulse.assign(4 * nn, 0.0);
  state->inverse_mass.assign(nn, 0.0);
  state->lambda.assign(m, 0.0);
  state->good_lambda_.assign(m, 0.0);
  state->sweep_alpha.assign(m, 0.0);
  state->sweep_gain.assign(m, 0.0);
  state->sweep_wi_gain.assign(m, 0.0);
  state->sweep_wj_gain.assign(m, 0.0);
  state->cut.assign(m, 0);
  state->prepared_w.assign(nn, 0.0);
  state->prepared_dt = 0.0;
  state->attach_stiffness.assign(nn, 0.0);
  state->attach_weighted_target = mesh::Points::Zero(3, n);
  state->attach_lambda = mesh::Points::Zero(3, n);
  state->attached_nodes.assign(nn, 0);
  if (volume_ != nullptr) state->volume_forces = mesh::Points::Zero(3, n);
  return state;
}

double PositionBasedModel::EffectiveStiffness(size_t e, double dt) const {
  if (parameters_.mode == PositionBasedMode::kXpbd) return edge_stiffness_[e];
  // Seed mode: `iterations` projections of one isolated constraint with factor k close the gap
  // by s = 1 - (1-k)^iterations; as a backward-Euler spring that is k_eff = s m_e / Δt².
  const double mi = mass_[static_cast<size_t>(edge_i_[e])];
  const double mj = mass_[static_cast<size_t>(edge_j_[e])];
  const double reduced = mi + mj > 0.0 ? mi * mj / (mi + mj) : 0.0;
  const double s = 1.0 - std::pow(1.0 - parameters_.stiffness, parameters_.iterations);
  const double h = dt > 0.0 ? dt : kDefaultDt;
  return s * reduced / (h * h);
}

void PositionBasedModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<PositionBasedState*>(base);
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
#ifdef SOMASIM_PBD_AVX512
  if (simd_) {
    PredictAvx512(n, node_order_.data(), inverse_mass_.data(), px, pv, pf, g, dt, nodes, w);
  } else if (pf != nullptr) {
#else
  if (pf != nullptr) {
#endif
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
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  const bool primal_correction = xpbd && parameters_.primal_correction;
  if (primal_correction) std::copy(nodes, nodes + 4 * n, state->predicted.begin());
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

  // The per-constraint factors: they change only with Δt and the inverse masses (fixed and
  // prescribed nodes), so most steps reuse the last ones.
  const size_t m = sweep_edge_.size();
  const double inverse_dt2 = 1.0 / dt2;
  if (!(dt == state->prepared_dt) || !std::equal(w, w + n, state->prepared_w.begin())) {
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
  double residual = 0.0;  // computed only when a tolerance asks for it
  const double tolerance = parameters_.tolerance;
  // The sweep kernel for this sweep: vector or scalar, residual or not, first sweep (λ = 0, not
  // read: this is what sets every λ of the step) or later.
  const bool with_residual = tolerance > 0.0;
  const auto project = [&](size_t begin, size_t end) {
    const bool first = iteration == 1;
#ifdef SOMASIM_PBD_AVX512
    if (simd_) {
      if (first) {
        return with_residual ? ProjectAvx512<true, true>(arrays, begin, end, nodes)
                             : ProjectAvx512<false, true>(arrays, begin, end, nodes);
      }
      return with_residual ? ProjectAvx512<true, false>(arrays, begin, end, nodes)
                           : ProjectAvx512<false, false>(arrays, begin, end, nodes);
    }
#endif
    if (first) {
      return with_residual ? ProjectScalar<true, true>(arrays, begin, end, nodes)
                           : ProjectScalar<false, true>(arrays, begin, end, nodes);
    }
    return with_residual ? ProjectScalar<true, false>(arrays, begin, end, nodes)
                         : ProjectScalar<false, false>(arrays, begin, end, nodes);
  };
  while (iteration < parameters_.iterations) {
    ++iteration;
    residual = 0.0;
    // Distance constraints colour by colour (Gauss–Seidel; within a colour no two constraints
    // share a node, so their order there does not matter).
    for (size_t c = 0; c < num_colours; ++c) {
      const auto begin = static_cast<size_t>(colour_start_[c]);
      const auto end = static_cast<size_t>(colour_start_[c + 1]);
      residual = std::max(residual, project(begin, end));
    }
    // Attachments: the vector constraint C = x - t̄ with compliance 1/K, ∇C = I (XPBD).
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
    // Further constraints of the whole body (e.g. a volume term) are projected here, once per
    // sweep, after the distance constraints and attachments.
    if (primal_correction) {
      // Primal correction: Gauss–Seidel moved each node along gradients taken at intermediate
      // positions, so x - x̃ drifts from M⁻¹ Σ ∇C(x) λ by O(|Δx|/l) (the g ≈ 0 assumption of
      // Macklin et al. §4). Re-anchoring x = x̃ + M⁻¹ (Σ_e ∇C_e(x) λ_e + λ_attach) makes a
      // converged step an exact backward-Euler step, whose rest state is the static solution
      // of springs 1/compliance, whatever Δt or the sweep count.
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
    if (tolerance > 0.0 && residual < tolerance) break;
  }
  state->counters.solver_iterations += iteration;
  if (tolerance > 0.0 && !(residual < tolerance)) ++state->counters.solver_unconverged;
  for (size_t k = 0; k < state->num_attached; ++k) {
    state->attach_stiffness[static_cast<size_t>(state->attached_nodes[k])] = 0.0;
  }

  // Back to the public order, with velocities consistent with the Verlet step:
  // v = (x_new - x)/Δt (fixed nodes: 0). In public order, so that x and v are read and written
  // as streams and only the records are read at random (no random read-modify-write).
  // ChecksStateItself: every value written is checked here, as Step's own pass would.
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

double PositionBasedModel::LastConstraintResidual(const TissueState& base) const {
  const auto& state = static_cast<const PositionBasedState&>(base);
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  const double inverse_dt2 = state.last_dt > 0.0 ? 1.0 / (state.last_dt * state.last_dt) : 0.0;
  double worst = 0.0;
  for (size_t s = 0; s < sweep_edge_.size(); ++s) {
    const auto e = static_cast<size_t>(sweep_edge_[s]);
    if (state.cut[e] != 0) continue;
    const double c =
        (state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e])).norm() - sweep_rest_[s];
    // λ (of the last accepted step) is in sweep order, like the sweep arrays.
    const double h = xpbd ? c + sweep_compliance_[s] * inverse_dt2 * state.good_lambda_[s] : c;
    worst = std::max(worst, std::abs(h) * sweep_inv_rest_[s]);
  }
  return worst;
}

Eigen::Matrix3d PositionBasedModel::LocalStiffness(const TissueState& base, int32_t node) const {
  assert(node >= 0 && node < num_nodes());
  const auto& state = static_cast<const PositionBasedState&>(base);
  // Hessian of ½ k_eff C² at node i: k_eff [u uᵀ + (1 - a/l)(I - u uᵀ)].
  Eigen::Matrix3d k_local = Eigen::Matrix3d::Zero();
  for (int32_t slot = node_edge_start_[static_cast<size_t>(node)];
       slot < node_edge_start_[static_cast<size_t>(node) + 1]; ++slot) {
    const auto e = static_cast<size_t>(node_edges_[static_cast<size_t>(slot)]);
    if (state.cut[e] != 0) continue;
    AddEdgeStiffness(state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e]),
                     rest_length_[e], EffectiveStiffness(e, state.last_dt), &k_local);
  }
  if (volume_ != nullptr) k_local += volume_->LocalStiffness(state.positions, node);
  return k_local;
}

void PositionBasedModel::InternalForces(const TissueState& base, mesh::Points* forces) const {
  const auto& state = static_cast<const PositionBasedState&>(base);
  forces->resize(3, rest_.cols());  // a no-op (no allocation) when already sized
  forces->setZero();
  for (size_t e = 0; e < edge_i_.size(); ++e) {
    if (state.cut[e] != 0) continue;
    const Vector3d d = state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e]);
    const double length = d.norm();
    if (!(length > 0.0)) continue;
    // f_i = k_eff C u, f_j = -k_eff C u (a stretched constraint pulls its ends together).
    const Vector3d f =
        (EffectiveStiffness(e, state.last_dt) * (length - rest_length_[e]) / length) * d;
    forces->col(edge_i_[e]) += f;
    forces->col(edge_j_[e]) -= f;
  }
  if (volume_ != nullptr) volume_->AddForces(state.positions, forces);
}

EnergyReport PositionBasedModel::Energy(const TissueState& base,
                                        const Eigen::Vector3d& gravity) const {
  const auto& state = static_cast<const PositionBasedState&>(base);
  EnergyReport report;
  for (size_t e = 0; e < edge_i_.size(); ++e) {
    if (state.cut[e] != 0) continue;
    const double c = (state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e])).norm() -
                     rest_length_[e];
    report.elastic += 0.5 * EffectiveStiffness(e, state.last_dt) * c * c;
  }
  if (volume_ != nullptr) report.elastic += volume_->Energy(state.positions);
  AddKineticAndGravity(mass_, state, gravity, &report);
  return report;
}

int32_t PositionBasedModel::Cut(const SweptQuad& sweep, TissueState* base) const {
  auto* state = static_cast<PositionBasedState*>(base);
  if (!sweep.AllFinite()) return 0;
  int32_t removed = 0;
  for (size_t e = 0; e < edge_i_.size(); ++e) {
    if (state->cut[e] != 0) continue;
    if (SegmentCrossesSweep(state->positions.col(edge_i_[e]), state->positions.col(edge_j_[e]),
                            sweep)) {
      state->cut[e] = 1;
      ++removed;
    }
  }
  if (removed > 0) state->prepared_dt = 0.0;  // the sweep factors are recomputed next step
  return removed;
}

}  // namespace somasim::models
