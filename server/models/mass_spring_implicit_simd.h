// The AVX-512 loads and stores of the mass-spring implicit solver (mass_spring_implicit_*.cc):
// 8 lanes of x, y, z vectors, and records of 4 doubles transposed into and out of the lanes.
// Internal to server/models; x86-64 only, each function compiled for AVX-512 F and VL.
#pragma once

#include <immintrin.h>

#include <cstddef>
#include <cstdint>

#include "server/models/mass_spring_implicit_cg.h"

#define SOMASIM_MSI_TARGET __attribute__((target("avx512f,avx512vl,avx2,fma")))

namespace somasim::models {

struct Vec3 {
  __m512d x, y, z;
};

// All lanes (GCC 12 warns about the unmasked forms of some intrinsics, so the masked ones are used
// with every lane set).
constexpr __mmask8 kAll = 0xff;

SOMASIM_MSI_TARGET inline Vec3 Load3(const double* v, size_t p, size_t i) {
  return {_mm512_loadu_pd(v + i), _mm512_loadu_pd(v + p + i), _mm512_loadu_pd(v + 2 * p + i)};
}

SOMASIM_MSI_TARGET inline void Store3(double* v, size_t p, size_t i, const Vec3& a) {
  _mm512_storeu_pd(v + i, a.x);
  _mm512_storeu_pd(v + p + i, a.y);
  _mm512_storeu_pd(v + 2 * p + i, a.z);
}

// Hardware gathers are slow next to plain loads (a sweep would need three per row of slots), so
// the values a sweep reads at other nodes are kept as records of 4 doubles (x, y, z, 0, "AoS4"):
// 8 records are 8 plain 256-bit loads, transposed here into one vector per component (record k
// in lane k). With kFourth, out[3] gets the fourth components.
template <bool kFourth>
SOMASIM_MSI_TARGET inline void Transpose8x4(__m256d r0, __m256d r1, __m256d r2, __m256d r3,
                                            __m256d r4, __m256d r5, __m256d r6, __m256d r7,
                                            __m512d out[4]) {
  const __m512d a = _mm512_maskz_insertf64x4(
      kAll, _mm512_maskz_insertf64x4(kAll, _mm512_setzero_pd(), r0, 0), r1, 1);
  const __m512d b = _mm512_maskz_insertf64x4(
      kAll, _mm512_maskz_insertf64x4(kAll, _mm512_setzero_pd(), r2, 0), r3, 1);
  const __m512d c = _mm512_maskz_insertf64x4(
      kAll, _mm512_maskz_insertf64x4(kAll, _mm512_setzero_pd(), r4, 0), r5, 1);
  const __m512d d = _mm512_maskz_insertf64x4(
      kAll, _mm512_maskz_insertf64x4(kAll, _mm512_setzero_pd(), r6, 0), r7, 1);
  // lo_ab = x0 x2 z0 z2 x1 x3 z1 z3, hi_ab = y0 y2 w0 w2 y1 y3 w1 w3 (and 4..7 in cd).
  const __m512d lo_ab = _mm512_maskz_unpacklo_pd(kAll, a, b),
                hi_ab = _mm512_maskz_unpackhi_pd(kAll, a, b);
  const __m512d lo_cd = _mm512_maskz_unpacklo_pd(kAll, c, d),
                hi_cd = _mm512_maskz_unpackhi_pd(kAll, c, d);
  const __m512i first = _mm512_set_epi64(13, 9, 12, 8, 5, 1, 4, 0);
  const __m512i second = _mm512_set_epi64(15, 11, 14, 10, 7, 3, 6, 2);
  out[0] = _mm512_permutex2var_pd(lo_ab, first, lo_cd);
  out[1] = _mm512_permutex2var_pd(hi_ab, first, hi_cd);
  out[2] = _mm512_permutex2var_pd(lo_ab, second, lo_cd);
  if constexpr (kFourth) out[3] = _mm512_permutex2var_pd(hi_ab, second, hi_cd);
}

// The records (`stride` doubles apart) numbered offset[0..7] of `base`.
template <bool kFourth>
SOMASIM_MSI_TARGET inline void LoadRecords(const double* base, const int32_t* offset, size_t stride,
                                           __m512d out[4]) {
  const double* at[kImplicitLanes];
  for (size_t k = 0; k < kImplicitLanes; ++k)
    at[k] = base + stride * static_cast<size_t>(offset[k]);
  Transpose8x4<kFourth>(_mm256_loadu_pd(at[0]), _mm256_loadu_pd(at[1]), _mm256_loadu_pd(at[2]),
                        _mm256_loadu_pd(at[3]), _mm256_loadu_pd(at[4]), _mm256_loadu_pd(at[5]),
                        _mm256_loadu_pd(at[6]), _mm256_loadu_pd(at[7]), out);
}

// x, y, z of nodes offset[0..7] of a 3 × n array (masked loads read nothing past a node).
SOMASIM_MSI_TARGET inline void LoadPoints(const double* base, const int32_t* offset,
                                          __m512d out[4]) {
  const double* at[kImplicitLanes];
  for (size_t k = 0; k < kImplicitLanes; ++k) at[k] = base + 3 * static_cast<size_t>(offset[k]);
  Transpose8x4<false>(_mm256_maskz_loadu_pd(0x7, at[0]), _mm256_maskz_loadu_pd(0x7, at[1]),
                      _mm256_maskz_loadu_pd(0x7, at[2]), _mm256_maskz_loadu_pd(0x7, at[3]),
                      _mm256_maskz_loadu_pd(0x7, at[4]), _mm256_maskz_loadu_pd(0x7, at[5]),
                      _mm256_maskz_loadu_pd(0x7, at[6]), _mm256_maskz_loadu_pd(0x7, at[7]), out);
}

// The inverse of Transpose8x4: stores (x, y, z, w) of lane k as the record at base + stride k.
SOMASIM_MSI_TARGET inline void StoreRecords(double* base, size_t stride, __m512d x, __m512d y,
                                            __m512d z, __m512d w) {
  const __m512d lo_xy = _mm512_maskz_unpacklo_pd(kAll, x, y),
                hi_xy = _mm512_maskz_unpackhi_pd(kAll, x, y);
  const __m512d lo_zw = _mm512_maskz_unpacklo_pd(kAll, z, w),
                hi_zw = _mm512_maskz_unpackhi_pd(kAll, z, w);
  // lo_xy = x0 y0 | x2 y2 | x4 y4 | x6 y6; lo_zw = z0 w0 | z2 w2 | ...; hi_*: lanes 1, 3, 5, 7.
  const __m512i first = _mm512_set_epi64(11, 10, 3, 2, 9, 8, 1, 0);
  const __m512i second = _mm512_set_epi64(15, 14, 7, 6, 13, 12, 5, 4);
  const __m512d r02 = _mm512_permutex2var_pd(lo_xy, first, lo_zw);
  const __m512d r13 = _mm512_permutex2var_pd(hi_xy, first, hi_zw);
  const __m512d r46 = _mm512_permutex2var_pd(lo_xy, second, lo_zw);
  const __m512d r57 = _mm512_permutex2var_pd(hi_xy, second, hi_zw);
  if (stride == 4) {  // contiguous: two records per store
    _mm512_storeu_pd(base, _mm512_maskz_shuffle_f64x2(kAll, r02, r13, 0x44));       // records 0, 1
    _mm512_storeu_pd(base + 8, _mm512_maskz_shuffle_f64x2(kAll, r02, r13, 0xee));   // 2, 3
    _mm512_storeu_pd(base + 16, _mm512_maskz_shuffle_f64x2(kAll, r46, r57, 0x44));  // 4, 5
    _mm512_storeu_pd(base + 24, _mm512_maskz_shuffle_f64x2(kAll, r46, r57, 0xee));  // 6, 7
    return;
  }
  _mm256_storeu_pd(base, _mm512_maskz_extractf64x4_pd(kAll, r02, 0));
  _mm256_storeu_pd(base + stride, _mm512_maskz_extractf64x4_pd(kAll, r13, 0));
  _mm256_storeu_pd(base + 2 * stride, _mm512_maskz_extractf64x4_pd(kAll, r02, 1));
  _mm256_storeu_pd(base + 3 * stride, _mm512_maskz_extractf64x4_pd(kAll, r13, 1));
  _mm256_storeu_pd(base + 4 * stride, _mm512_maskz_extractf64x4_pd(kAll, r46, 0));
  _mm256_storeu_pd(base + 5 * stride, _mm512_maskz_extractf64x4_pd(kAll, r57, 0));
  _mm256_storeu_pd(base + 6 * stride, _mm512_maskz_extractf64x4_pd(kAll, r46, 1));
  _mm256_storeu_pd(base + 7 * stride, _mm512_maskz_extractf64x4_pd(kAll, r57, 1));
}

}  // namespace somasim::models
