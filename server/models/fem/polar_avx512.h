// PolarRotationFrom's iteration (tet_elements.h) on eight 3×3 matrices in the eight lanes of
// AVX-512 registers, structure of arrays: lane l of every vector is matrix l. Internal to the
// FEM target: PolarRotations (tet_elements.cc) runs it on matrices in memory, the corotational
// element pass (fem_corotational_pass.cc) on the deformation gradients it has just computed in
// registers.
// Callers compile with SOMASIM_FEM_AVX512 and check CpuHasAvx512() first.
#ifndef SOMASIM_SERVER_MODELS_FEM_POLAR_AVX512_H_
#define SOMASIM_SERVER_MODELS_FEM_POLAR_AVX512_H_

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>

#define SOMASIM_FEM_AVX512 __attribute__((target("avx2,fma,avx512f,avx512vl")))
#define SOMASIM_FEM_HAS_AVX512_PATH 1

namespace somasim::models::fem {

// The rotation (column-major rm[9]) of the unit quaternions (qw, qx, qy, qz).
SOMASIM_FEM_AVX512 __attribute__((always_inline)) inline void QuaternionRotations8(
    const __m512d q[4], __m512d rm[9]) {
  const __m512d one = _mm512_set1_pd(1.0), two = _mm512_set1_pd(2.0);
  const __m512d qw = q[0], qx = q[1], qy = q[2], qz = q[3];
  const __m512d xx = _mm512_mul_pd(qx, qx), yy = _mm512_mul_pd(qy, qy), zz = _mm512_mul_pd(qz, qz);
  const __m512d xy = _mm512_mul_pd(qx, qy), xz = _mm512_mul_pd(qx, qz), yz = _mm512_mul_pd(qy, qz);
  const __m512d wx = _mm512_mul_pd(qw, qx), wy = _mm512_mul_pd(qw, qy), wz = _mm512_mul_pd(qw, qz);
  rm[0] = _mm512_sub_pd(one, _mm512_mul_pd(two, _mm512_add_pd(yy, zz)));
  rm[1] = _mm512_mul_pd(two, _mm512_add_pd(xy, wz));
  rm[2] = _mm512_mul_pd(two, _mm512_sub_pd(xz, wy));
  rm[3] = _mm512_mul_pd(two, _mm512_sub_pd(xy, wz));
  rm[4] = _mm512_sub_pd(one, _mm512_mul_pd(two, _mm512_add_pd(xx, zz)));
  rm[5] = _mm512_mul_pd(two, _mm512_add_pd(yz, wx));
  rm[6] = _mm512_mul_pd(two, _mm512_add_pd(xz, wy));
  rm[7] = _mm512_mul_pd(two, _mm512_sub_pd(yz, wx));
  rm[8] = _mm512_sub_pd(one, _mm512_mul_pd(two, _mm512_add_pd(xx, yy)));
}

// From the warm start q, the rotations rm (column-major) of fm (column-major F), and q updated.
// Returns the lanes that did not converge: their q and rm are not to be kept (the caller hands
// those matrices to PolarRotationFrom with the q they came with).
SOMASIM_FEM_AVX512 __attribute__((always_inline)) inline __mmask8 PolarIterate8(const __m512d fm[9],
                                                                                __m512d q[4],
                                                                                __m512d rm[9]) {
  const __m512d one = _mm512_set1_pd(1.0), half = _mm512_set1_pd(0.5);
  const __m512d zero = _mm512_setzero_pd();
  const __m512d converged2 = _mm512_set1_pd(1e-20);
  __mmask8 active = 0xFF, failed = 0;
  for (int step = 0; step < 8 && active != 0; ++step) {
    QuaternionRotations8(q, rm);
    // A = Rᵀ F: a(i, j) = Σ_k R(k, i) F(k, j) (column-major: R(k, i) = rm[3 i + k]).
    __m512d a[3][3];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        __m512d sum = _mm512_mul_pd(rm[3 * i], fm[3 * j]);
        sum = _mm512_fmadd_pd(rm[3 * i + 1], fm[3 * j + 1], sum);
        a[i][j] = _mm512_fmadd_pd(rm[3 * i + 2], fm[3 * j + 2], sum);
      }
    }
    const __m512d g0 = _mm512_sub_pd(a[2][1], a[1][2]);
    const __m512d g1 = _mm512_sub_pd(a[0][2], a[2][0]);
    const __m512d g2 = _mm512_sub_pd(a[1][0], a[0][1]);
    const __m512d h00 = _mm512_add_pd(a[1][1], a[2][2]);
    const __m512d h11 = _mm512_add_pd(a[0][0], a[2][2]);
    const __m512d h22 = _mm512_add_pd(a[0][0], a[1][1]);
    const __m512d mhalf = _mm512_set1_pd(-0.5);
    const __m512d h01 = _mm512_mul_pd(mhalf, _mm512_add_pd(a[0][1], a[1][0]));
    const __m512d h02 = _mm512_mul_pd(mhalf, _mm512_add_pd(a[0][2], a[2][0]));
    const __m512d h12 = _mm512_mul_pd(mhalf, _mm512_add_pd(a[1][2], a[2][1]));
    // ω = adj(H) g / det(H), as PolarRotationFrom: one division (a Cholesky form takes six,
    // each a long-latency instruction on the one divider). Cofactors a0 b0 - a1 b1.
    const __m512d c00 = _mm512_fmsub_pd(h11, h22, _mm512_mul_pd(h12, h12));
    const __m512d c01 = _mm512_fmsub_pd(h02, h12, _mm512_mul_pd(h01, h22));
    const __m512d c02 = _mm512_fmsub_pd(h01, h12, _mm512_mul_pd(h02, h11));
    const __m512d c11 = _mm512_fmsub_pd(h00, h22, _mm512_mul_pd(h02, h02));
    const __m512d c12 = _mm512_fmsub_pd(h01, h02, _mm512_mul_pd(h00, h12));
    const __m512d c22 = _mm512_fmsub_pd(h00, h11, _mm512_mul_pd(h01, h01));
    const __m512d det =
        _mm512_fmadd_pd(h02, c02, _mm512_fmadd_pd(h01, c01, _mm512_mul_pd(h00, c00)));
    // Positive definite (Sylvester: every leading minor > 0); a NaN fails the tests too.
    __mmask8 ok = _mm512_cmp_pd_mask(h00, zero, _CMP_GT_OQ);
    ok &= _mm512_cmp_pd_mask(c22, zero, _CMP_GT_OQ);
    ok &= _mm512_cmp_pd_mask(det, zero, _CMP_GT_OQ);
    const __m512d s = _mm512_div_pd(one, det);
    const __m512d w0 = _mm512_mul_pd(
        s, _mm512_fmadd_pd(c02, g2, _mm512_fmadd_pd(c01, g1, _mm512_mul_pd(c00, g0))));
    const __m512d w1 = _mm512_mul_pd(
        s, _mm512_fmadd_pd(c12, g2, _mm512_fmadd_pd(c11, g1, _mm512_mul_pd(c01, g0))));
    const __m512d w2 = _mm512_mul_pd(
        s, _mm512_fmadd_pd(c22, g2, _mm512_fmadd_pd(c12, g1, _mm512_mul_pd(c02, g0))));
    const __m512d v0 = _mm512_mul_pd(half, w0), v1 = _mm512_mul_pd(half, w1);
    const __m512d v2 = _mm512_mul_pd(half, w2);
    // q ⊗ (1, v).
    const __m512d qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    const __m512d nw =
        _mm512_fnmadd_pd(qz, v2, _mm512_fnmadd_pd(qy, v1, _mm512_fnmadd_pd(qx, v0, qw)));
    const __m512d nx =
        _mm512_fnmadd_pd(qz, v1, _mm512_fmadd_pd(qy, v2, _mm512_fmadd_pd(qw, v0, qx)));
    const __m512d ny =
        _mm512_fnmadd_pd(qx, v2, _mm512_fmadd_pd(qz, v0, _mm512_fmadd_pd(qw, v1, qy)));
    const __m512d nz =
        _mm512_fnmadd_pd(qy, v0, _mm512_fmadd_pd(qx, v1, _mm512_fmadd_pd(qw, v2, qz)));
    __m512d norm2 = _mm512_mul_pd(nw, nw);
    norm2 = _mm512_fmadd_pd(nx, nx, norm2);
    norm2 = _mm512_fmadd_pd(ny, ny, norm2);
    norm2 = _mm512_fmadd_pd(nz, nz, norm2);
    // 1/|n| from rsqrt14 and two Newton steps y ← y (3/2 - |n|²/2 y²) (14 → 28 → 56 bits)
    // instead of a square root and a division. |n|² = 0, ∞ or NaN gives NaN: caught below.
    const __m512d half_norm2 = _mm512_mul_pd(half, norm2);
    const __m512d three_halves = _mm512_set1_pd(1.5);
    __m512d inverse = _mm512_maskz_rsqrt14_pd(0xFF, norm2);
    inverse = _mm512_mul_pd(
        inverse, _mm512_fnmadd_pd(half_norm2, _mm512_mul_pd(inverse, inverse), three_halves));
    inverse = _mm512_mul_pd(
        inverse, _mm512_fnmadd_pd(half_norm2, _mm512_mul_pd(inverse, inverse), three_halves));
    // Finite: |inverse| < inf (a NaN compares false).
    ok &= _mm512_cmp_pd_mask(_mm512_abs_pd(inverse), _mm512_set1_pd(1e300), _CMP_LT_OQ);
    failed |= static_cast<__mmask8>(active & ~ok);
    const __mmask8 update = static_cast<__mmask8>(active & ok);
    q[0] = _mm512_mask_mul_pd(qw, update, nw, inverse);
    q[1] = _mm512_mask_mul_pd(qx, update, nx, inverse);
    q[2] = _mm512_mask_mul_pd(qy, update, ny, inverse);
    q[3] = _mm512_mask_mul_pd(qz, update, nz, inverse);
    __m512d omega2 = _mm512_mul_pd(w0, w0);
    omega2 = _mm512_fmadd_pd(w1, w1, omega2);
    omega2 = _mm512_fmadd_pd(w2, w2, omega2);
    const __mmask8 done = _mm512_mask_cmp_pd_mask(update, omega2, converged2, _CMP_LE_OQ);
    active = static_cast<__mmask8>(update & ~done);
  }
  QuaternionRotations8(q, rm);
  return static_cast<__mmask8>(failed | active);
}

}  // namespace somasim::models::fem

#endif  // x86-64 with GCC or Clang
#endif  // SOMASIM_SERVER_MODELS_FEM_POLAR_AVX512_H_
