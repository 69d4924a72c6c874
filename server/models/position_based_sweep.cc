#include "server/models/position_based_sweep.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_PBD_AVX512 1
#endif

namespace somasim::models {
namespace {

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
// transpose them; storing pairs 0 4, 1 5, 2 6, 3 7 and uses two-source permutes. A lane selection
// takes less of the shuffle units than a two-source permute (docs/benchmarks.md).
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

// LoadRecords and StoreRecords are always inlined into the sweep: out of line they slow it
// markedly (docs/benchmarks.md), and left to gcc the choice follows the size of the translation
// unit.
__attribute__((target("avx512f,avx512vl"), always_inline)) inline Lanes LoadRecords(
    const double* x, const int32_t* offset) {
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
// where the sweep is bound by its shuffles, which issue on one port, this saves one in four of
// the stores' permutes).
__attribute__((target("avx512f,avx512vl"))) inline void StorePair(__m512d record, double* x,
                                                                  const int32_t* offset, int a) {
  const __m256d unused = _mm256_setzero_pd();
  // The lower half is the register's own ymm (AVX512VL's encoding reaches ymm16–31; without it
  // gcc extracts the half with a shuffle, which the sweep would pay for).
  _mm256_mask_store_pd(x + offset[a], 0x7, __builtin_shufflevector(record, record, 0, 1, 2, 3));
  _mm256_mask_store_pd(x + offset[a + 4], 0x7, _mm512_mask_extractf64x4_pd(unused, 0xF, record, 1));
}

// The inverse of LoadRecords (the w of a record never changes in a sweep, so lane 3 is left as
// it is): the y row needs no permute for records 0 1 4 5, whose
// y sit in lanes 0 1 4 5 already, and one in-lane permute for 2 3 6 7.
__attribute__((target("avx512f,avx512vl"), always_inline)) inline void StoreRecords(
    const Lanes& r, double* x, const int32_t* offset, __m512i low, __m512i high) {
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
  // chain after r is three steps: the sweep is bound by this chain (hence two independent groups
  // of 8 per iteration, docs/benchmarks.md), not by the operation count.
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

#endif

}  // namespace

double ProjectColour(const SweepArrays& arrays, size_t begin, size_t end, double* x, bool simd,
                     bool residual, bool first) {
#ifdef SOMASIM_PBD_AVX512
  if (simd) {
    if (first) {
      return residual ? ProjectAvx512<true, true>(arrays, begin, end, x)
                      : ProjectAvx512<false, true>(arrays, begin, end, x);
    }
    return residual ? ProjectAvx512<true, false>(arrays, begin, end, x)
                    : ProjectAvx512<false, false>(arrays, begin, end, x);
  }
#else
  (void)simd;
#endif
  if (first) {
    return residual ? ProjectScalar<true, true>(arrays, begin, end, x)
                    : ProjectScalar<false, true>(arrays, begin, end, x);
  }
  return residual ? ProjectScalar<true, false>(arrays, begin, end, x)
                  : ProjectScalar<false, false>(arrays, begin, end, x);
}

}  // namespace somasim::models
