// Implicit Euler for the mass-spring model (MassSpringIntegrator::kImplicitEuler): linearised
// backward Euler (Baraff & Witkin 1998) solved by conjugate gradients, matrix-free over the
// springs, preconditioned by a multicolour symmetric block Gauss-Seidel sweep.
//
// Speed (issue 4, BM_MassSpringImplicit): a Gauss-Seidel sweep in the mesh's own node order is a
// chain of dependent nodes (on gallbladder5400 the longest has 2206 of its 5400 nodes), so the
// sweep ran at the latency of its floating-point chain, ~60 cycles a node. Build therefore
// colours the nodes greedily (no spring joins two nodes of one colour; the built-in surfaces
// need 5-6 colours) and lays them out colour by colour in groups of 8 lanes: every node of a
// colour depends only on other colours, so one AVX-512 register holds 8 independent nodes, each
// lane walking its own springs in rows of 8 slots (one spring per lane and row; the sort by
// spring counts leaves <1 % of the slots empty). Hardware gathers cost ~16 cycles each here, so
// the values read at other nodes are kept as records (x, y, z, 0) and fetched with 8 plain loads
// and a transpose (Transpose8x4). Each step:
//   1. Linearise: per spring, 8 at a time, its block B_s = a_s I + w_s w_sᵀ of A and K_s (v_i -
//      v_j) for the right-hand side;
//   2. Assemble: per group, copies the blocks into the slot rows (so the sweeps read them
//      contiguously) and sums each node's diagonal block and K v, then inverts the blocks;
//   3. CG, each iteration one preconditioner application (forward sweep over the lower-colour
//      slots, backward sweep over the higher-colour ones, which also yields A z but for the
//      lower-colour part, added by a third pass over the lower slots), so that CG updates
//      A p = A z + β A p without a separate product; that third pass also updates p and A p
//      (the CG direction), and r · z comes from the forward sweep (r · z = yᵀ D y). CG's own
//      step along the last direction rides along too (CgUpdate): the forward sweep, which loads
//      r anyway, does r -= α q and sums |r|² (stopping right there once converged), the third
//      pass, which loads p anyway, does Δv += α p; no separate pass over p, q, Δv, r, and z is
//      read back from the sweeps' records instead of a 3 × P array of its own. CG starts from
//      Δv extrapolated from the last two steps (kept only when it beats zero).
// The colour ordering needs ~25 % more iterations than the natural one (its sweeps couple fewer
// neighbours per pass), for sweeps that run several times faster.
#include <immintrin.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <numeric>
#include <span>
#include <vector>

#include "server/models/cpu_features.h"
#include "server/models/mass_spring_model.h"
#include "server/models/mass_spring_state.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {

// Test switch: false forces the scalar kernels (declared where the tests use it).
void SetMassSpringImplicitAvx512ForTesting(bool enabled);

namespace {

constexpr size_t kLanes = 8;
constexpr size_t kRecord = 8;   // doubles per spring in implicit_springs
bool g_implicit_avx512 = true;  // NOLINT: a test switch, written only by tests

bool UseAvx512() { return g_implicit_avx512 && CpuHasAvx512(); }

// Raw views of the solver's layout (see MassSpringModel's implicit-step data).
struct Layout {
  size_t padded = 0;  // P
  size_t groups = 0;
  size_t colours = 0;
  const int32_t* colour_start = nullptr;
  const int32_t* row_start = nullptr;
  const int32_t* lower_rows = nullptr;
  const int32_t* neighbour = nullptr;
  const double* rows = nullptr;             // rows × 32
  const double* inverse = nullptr;          // 6 × P
  const double* diagonal = nullptr;         // 6 × P
  const double* keep = nullptr;             // P
  const uint8_t* massless_group = nullptr;  // groups: 1 if a lane has no mass
};

// --- Scalar kernels (the reference; every lane of a group done in turn). ---

// Σ over rows [begin, end) of lane `lane`: B_s x_j = a_s x_j + (w_s · x_j) w_s.
void AccumulateScalar(const Layout& l, size_t begin, size_t end, size_t lane, const double* x,
                      double out[3]) {
  const size_t p = l.padded;
  for (size_t row = begin; row < end; ++row) {
    const auto j = static_cast<size_t>(l.neighbour[kLanes * row + lane]);
    const double* r = l.rows + 4 * kLanes * row + lane;
    const double wx = r[0], wy = r[kLanes], wz = r[2 * kLanes], a = r[3 * kLanes];
    const double xx = x[j], xy = x[p + j], xz = x[2 * p + j];
    const double t = wx * xx + wy * xy + wz * xz;
    out[0] += a * xx + t * wx;
    out[1] += a * xy + t * wy;
    out[2] += a * xz + t * wz;
  }
}

// out = S s for the symmetric block S stored at `m` (6 × P) on lane i.
void SymmetricScalar(const double* m, size_t p, size_t i, const double s[3], double out[3]) {
  const double xx = m[i], xy = m[p + i], xz = m[2 * p + i], yy = m[3 * p + i], yz = m[4 * p + i],
               zz = m[5 * p + i];
  out[0] = xx * s[0] + xy * s[1] + xz * s[2];
  out[1] = xy * s[0] + yy * s[1] + yz * s[2];
  out[2] = xz * s[0] + yz * s[1] + zz * s[2];
}

// The preconditioner (see the Precondition comment in MassSpringImplicitStep).
double PreconditionScalar(const Layout& l, const double* r, double* dy, double* z, double* az) {
  const size_t p = l.padded;
  for (size_t c = 0; c < l.colours; ++c) {
    for (auto g = static_cast<size_t>(l.colour_start[c]);
         g < static_cast<size_t>(l.colour_start[c + 1]); ++g) {
      const auto begin = static_cast<size_t>(l.row_start[g]);
      for (size_t lane = 0; lane < kLanes; ++lane) {
        const size_t i = kLanes * g + lane;
        double s[3] = {r[i], r[p + i], r[2 * p + i]};
        AccumulateScalar(l, begin, begin + static_cast<size_t>(l.lower_rows[g]), lane, z, s);
        double y[3];
        SymmetricScalar(l.inverse, p, i, s, y);
        for (size_t k = 0; k < 3; ++k) {
          dy[k * p + i] = s[k];
          z[k * p + i] = y[k];
        }
      }
    }
  }
  double rz = 0.0;
  for (size_t c = l.colours; c-- > 0;) {
    for (auto g = static_cast<size_t>(l.colour_start[c]);
         g < static_cast<size_t>(l.colour_start[c + 1]); ++g) {
      const size_t begin =
          static_cast<size_t>(l.row_start[g]) + static_cast<size_t>(l.lower_rows[g]);
      const auto end = static_cast<size_t>(l.row_start[g + 1]);
      for (size_t lane = 0; lane < kLanes; ++lane) {
        const size_t i = kLanes * g + lane;
        double s[3] = {dy[i], dy[p + i], dy[2 * p + i]};
        AccumulateScalar(l, begin, end, lane, z, s);
        double zi[3], dz[3];
        SymmetricScalar(l.inverse, p, i, s, zi);
        SymmetricScalar(l.diagonal, p, i, zi, dz);
        for (size_t k = 0; k < 3; ++k) {
          z[k * p + i] = zi[k];
          az[k * p + i] = dy[k * p + i] + (dz[k] - s[k]);
          rz += r[k * p + i] * zi[k];
        }
      }
    }
  }
  for (size_t g = 0; g < l.groups; ++g) {
    const auto begin = static_cast<size_t>(l.row_start[g]);
    for (size_t lane = 0; lane < kLanes; ++lane) {
      const size_t i = kLanes * g + lane;
      double s[3] = {0.0, 0.0, 0.0};
      AccumulateScalar(l, begin, begin + static_cast<size_t>(l.lower_rows[g]), lane, z, s);
      for (size_t k = 0; k < 3; ++k) az[k * p + i] = l.keep[i] * (az[k * p + i] - s[k]);
    }
  }
  return rz;
}

// q = A x (held lanes 0).
void ProductScalar(const Layout& l, const double* x, double* q) {
  const size_t p = l.padded;
  for (size_t g = 0; g < l.groups; ++g) {
    for (size_t lane = 0; lane < kLanes; ++lane) {
      const size_t i = kLanes * g + lane;
      double s[3] = {0.0, 0.0, 0.0};
      AccumulateScalar(l, static_cast<size_t>(l.row_start[g]),
                       static_cast<size_t>(l.row_start[g + 1]), lane, x, s);
      const double xi[3] = {x[i], x[p + i], x[2 * p + i]};
      double d[3];
      SymmetricScalar(l.diagonal, p, i, xi, d);
      for (size_t k = 0; k < 3; ++k) q[k * p + i] = l.keep[i] * (d[k] - s[k]);
    }
  }
}

// --- AVX-512 kernels: the same arithmetic, the 8 lanes of a group in one register. ---

#define SOMASIM_MSI_TARGET __attribute__((target("avx512f,avx512vl,avx2,fma")))

struct Vec3 {
  __m512d x, y, z;
};

// All lanes (GCC 12 warns about the unmasked forms of some intrinsics, so the masked ones are used
// with every lane set).
constexpr __mmask8 kAll = 0xff;

// The sum of the 8 lanes, in a fixed order.
SOMASIM_MSI_TARGET inline double Sum8(__m512d v) {
  alignas(64) double t[kLanes];
  _mm512_store_pd(t, v);
  return ((t[0] + t[1]) + (t[2] + t[3])) + ((t[4] + t[5]) + (t[6] + t[7]));
}

SOMASIM_MSI_TARGET inline Vec3 Load3(const double* v, size_t p, size_t i) {
  return {_mm512_loadu_pd(v + i), _mm512_loadu_pd(v + p + i), _mm512_loadu_pd(v + 2 * p + i)};
}

SOMASIM_MSI_TARGET inline void Store3(double* v, size_t p, size_t i, const Vec3& a) {
  _mm512_storeu_pd(v + i, a.x);
  _mm512_storeu_pd(v + p + i, a.y);
  _mm512_storeu_pd(v + 2 * p + i, a.z);
}

// Gathers are slow on this hardware (~16 cycles each, three per row of slots), so the values a
// sweep reads at other nodes are kept as records of 4 doubles (x, y, z, 0 per lane, "AoS4"):
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
  const double* at[kLanes];
  for (size_t k = 0; k < kLanes; ++k) at[k] = base + stride * static_cast<size_t>(offset[k]);
  Transpose8x4<kFourth>(_mm256_loadu_pd(at[0]), _mm256_loadu_pd(at[1]), _mm256_loadu_pd(at[2]),
                        _mm256_loadu_pd(at[3]), _mm256_loadu_pd(at[4]), _mm256_loadu_pd(at[5]),
                        _mm256_loadu_pd(at[6]), _mm256_loadu_pd(at[7]), out);
}

// x, y, z of nodes offset[0..7] of a 3 × n array (masked loads read nothing past a node).
SOMASIM_MSI_TARGET inline void LoadPoints(const double* base, const int32_t* offset,
                                          __m512d out[4]) {
  const double* at[kLanes];
  for (size_t k = 0; k < kLanes; ++k) at[k] = base + 3 * static_cast<size_t>(offset[k]);
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

// out += Σ over rows [begin, end) of B_s x_j, x in records (AoS4) at xg.
SOMASIM_MSI_TARGET inline void Accumulate(const Layout& l, size_t begin, size_t end,
                                          const double* xg, Vec3* out) {
  for (size_t row = begin; row < end; ++row) {
    __m512d xj[4];
    LoadRecords<false>(xg, l.neighbour + kLanes * row, 4, xj);
    const double* r = l.rows + 4 * kLanes * row;
    const __m512d wx = _mm512_loadu_pd(r), wy = _mm512_loadu_pd(r + kLanes),
                  wz = _mm512_loadu_pd(r + 2 * kLanes), a = _mm512_loadu_pd(r + 3 * kLanes);
    const __m512d t =
        _mm512_fmadd_pd(wx, xj[0], _mm512_fmadd_pd(wy, xj[1], _mm512_mul_pd(wz, xj[2])));
    out->x = _mm512_add_pd(out->x, _mm512_fmadd_pd(a, xj[0], _mm512_mul_pd(t, wx)));
    out->y = _mm512_add_pd(out->y, _mm512_fmadd_pd(a, xj[1], _mm512_mul_pd(t, wy)));
    out->z = _mm512_add_pd(out->z, _mm512_fmadd_pd(a, xj[2], _mm512_mul_pd(t, wz)));
  }
}

SOMASIM_MSI_TARGET inline Vec3 Symmetric(const double* m, size_t p, size_t i, const Vec3& s) {
  const __m512d xx = _mm512_loadu_pd(m + i), xy = _mm512_loadu_pd(m + p + i),
                xz = _mm512_loadu_pd(m + 2 * p + i), yy = _mm512_loadu_pd(m + 3 * p + i),
                yz = _mm512_loadu_pd(m + 4 * p + i), zz = _mm512_loadu_pd(m + 5 * p + i);
  return {_mm512_fmadd_pd(xx, s.x, _mm512_fmadd_pd(xy, s.y, _mm512_mul_pd(xz, s.z))),
          _mm512_fmadd_pd(xy, s.x, _mm512_fmadd_pd(yy, s.y, _mm512_mul_pd(yz, s.z))),
          _mm512_fmadd_pd(xz, s.x, _mm512_fmadd_pd(yz, s.y, _mm512_mul_pd(zz, s.z)))};
}

SOMASIM_MSI_TARGET inline void StoreRecords3(double* base, const Vec3& v) {
  StoreRecords(base, 4, v.x, v.y, v.z, _mm512_setzero_pd());
}

// CG's step along the last direction, done inside the next preconditioner application (its
// forward sweep reads r anyway, its last pass p): r -= α q, Δv += α p, and the stop when |r|² <=
// threshold2 (then only Δv is updated).
struct CgUpdate {
  double alpha = 0.0;
  double threshold2 = 0.0;
  double* dv = nullptr;
};

// Unless `first`, first CG's step along the last direction (see CgUpdate; the forward sweep
// updates r and sums |r|² into *residual_norm2, returning 0 at once if that converged). Then z =
// P⁻¹ r as PreconditionScalar, fused with CG's direction update: p = z + β p and q = A z + β q
// with β = (r · z) / rz_before (p = z, q = A z when `first`); returns r · z and sets *curvature =
// p · q. A z is formed as in PreconditionScalar, its lower-colour part in the last pass, which
// updates Δv, p and q right away. zg (4 × P): the records of y, then z, that the sweeps read at
// other nodes (z itself is read back from them); az holds D z - s on groups with a massless lane.
SOMASIM_MSI_TARGET double PreconditionAvx512(const Layout& l, const CgUpdate& update, double* r,
                                             double* dy, double* az, double* zg, bool first,
                                             double rz_before, double* search, double* q,
                                             double* curvature, double* residual_norm2) {
  const size_t p = l.padded;
  const __m512d alpha = _mm512_set1_pd(update.alpha);
  __m512d rz = _mm512_setzero_pd(), rr = _mm512_setzero_pd();
  for (size_t c = 0; c < l.colours; ++c) {
    for (auto g = static_cast<size_t>(l.colour_start[c]);
         g < static_cast<size_t>(l.colour_start[c + 1]); ++g) {
      const size_t i = kLanes * g;
      const auto begin = static_cast<size_t>(l.row_start[g]);
      Vec3 s = Load3(r, p, i);
      if (!first) {  // CG's residual update r -= α q (q = A p of the last direction)
        const Vec3 qo = Load3(q, p, i);
        s = {_mm512_fnmadd_pd(alpha, qo.x, s.x), _mm512_fnmadd_pd(alpha, qo.y, s.y),
             _mm512_fnmadd_pd(alpha, qo.z, s.z)};
        Store3(r, p, i, s);
        rr = _mm512_fmadd_pd(s.x, s.x, rr);
        rr = _mm512_fmadd_pd(s.y, s.y, rr);
        rr = _mm512_fmadd_pd(s.z, s.z, rr);
      }
      Accumulate(l, begin, begin + static_cast<size_t>(l.lower_rows[g]), zg, &s);
      Store3(dy, p, i, s);
      const Vec3 y = Symmetric(l.inverse, p, i, s);
      StoreRecords3(zg + 4 * i, y);
      // r · z = yᵀ P y with P the blocks the sweeps invert, (P + L) y = r, (P + U) z = P y.
      rz = _mm512_fmadd_pd(y.x, s.x, rz);
      rz = _mm512_fmadd_pd(y.y, s.y, rz);
      rz = _mm512_fmadd_pd(y.z, s.z, rz);
    }
  }
  if (!first) {
    *residual_norm2 = Sum8(rr);
    if (*residual_norm2 <= update.threshold2) {  // converged: only Δv += α p is left to do
      for (size_t c = 0; c < 3 * p; c += kLanes) {
        _mm512_storeu_pd(update.dv + c, _mm512_fmadd_pd(alpha, _mm512_loadu_pd(search + c),
                                                        _mm512_loadu_pd(update.dv + c)));
      }
      return 0.0;
    }
  }
  for (size_t c = l.colours; c-- > 0;) {
    for (auto g = static_cast<size_t>(l.colour_start[c]);
         g < static_cast<size_t>(l.colour_start[c + 1]); ++g) {
      const size_t i = kLanes * g;
      Vec3 s = Load3(dy, p, i);
      Accumulate(l, static_cast<size_t>(l.row_start[g]) + static_cast<size_t>(l.lower_rows[g]),
                 static_cast<size_t>(l.row_start[g + 1]), zg, &s);
      const Vec3 zi = Symmetric(l.inverse, p, i, s);
      StoreRecords3(zg + 4 * i, zi);
      if (l.massless_group[g] != 0) {  // the inverse is a stand-in on some lanes: D z != s
        const Vec3 dz = Symmetric(l.diagonal, p, i, zi);
        Store3(az, p, i,
               {_mm512_sub_pd(dz.x, s.x), _mm512_sub_pd(dz.y, s.y), _mm512_sub_pd(dz.z, s.z)});
      }
    }
  }
  const double rz_sum = Sum8(rz);
  const __m512d beta = _mm512_set1_pd(first ? 0.0 : rz_sum / rz_before);
  __m512d pq = _mm512_setzero_pd();
  for (size_t g = 0; g < l.groups; ++g) {
    const size_t i = kLanes * g;
    const auto begin = static_cast<size_t>(l.row_start[g]);
    Vec3 s = {_mm512_setzero_pd(), _mm512_setzero_pd(), _mm512_setzero_pd()};
    Accumulate(l, begin, begin + static_cast<size_t>(l.lower_rows[g]), zg, &s);
    // (A z)_i = (D y)_i + (U z)_i + D_i z_i - s_i... = (D y)_i + (L z)_i (+ D z - s off mass).
    Vec3 a = Load3(dy, p, i);
    if (l.massless_group[g] != 0) {
      const Vec3 e = Load3(az, p, i);
      a = {_mm512_add_pd(a.x, e.x), _mm512_add_pd(a.y, e.y), _mm512_add_pd(a.z, e.z)};
    }
    const __m512d keep = _mm512_loadu_pd(l.keep + i);
    a = {_mm512_mul_pd(keep, _mm512_sub_pd(a.x, s.x)), _mm512_mul_pd(keep, _mm512_sub_pd(a.y, s.y)),
         _mm512_mul_pd(keep, _mm512_sub_pd(a.z, s.z))};
    Vec3 zi;
    {
      __m512d t[4];
      const double* at = zg + 4 * i;  // this group's 8 records, contiguous
      Transpose8x4<false>(_mm256_loadu_pd(at), _mm256_loadu_pd(at + 4), _mm256_loadu_pd(at + 8),
                          _mm256_loadu_pd(at + 12), _mm256_loadu_pd(at + 16),
                          _mm256_loadu_pd(at + 20), _mm256_loadu_pd(at + 24),
                          _mm256_loadu_pd(at + 28), t);
      zi = {t[0], t[1], t[2]};
    }
    Vec3 pn = zi, qn = a;
    if (!first) {
      const Vec3 po = Load3(search, p, i), qo = Load3(q, p, i);
      const Vec3 x = Load3(update.dv, p, i);  // CG's Δv += α p with the last direction
      Store3(update.dv, p, i,
             {_mm512_fmadd_pd(alpha, po.x, x.x), _mm512_fmadd_pd(alpha, po.y, x.y),
              _mm512_fmadd_pd(alpha, po.z, x.z)});
      pn = {_mm512_fmadd_pd(beta, po.x, zi.x), _mm512_fmadd_pd(beta, po.y, zi.y),
            _mm512_fmadd_pd(beta, po.z, zi.z)};
      qn = {_mm512_fmadd_pd(beta, qo.x, a.x), _mm512_fmadd_pd(beta, qo.y, a.y),
            _mm512_fmadd_pd(beta, qo.z, a.z)};
    }
    Store3(search, p, i, pn);
    Store3(q, p, i, qn);
    pq = _mm512_fmadd_pd(pn.x, qn.x, pq);
    pq = _mm512_fmadd_pd(pn.y, qn.y, pq);
    pq = _mm512_fmadd_pd(pn.z, qn.z, pq);
  }
  *curvature = Sum8(pq);
  return rz_sum;
}

// q = A x; xg (4 × P) receives the records of x.
SOMASIM_MSI_TARGET void ProductAvx512(const Layout& l, const double* x, double* q, double* xg) {
  const size_t p = l.padded;
  for (size_t i = 0; i < p; i += kLanes) StoreRecords3(xg + 4 * i, Load3(x, p, i));
  for (size_t g = 0; g < l.groups; ++g) {
    const size_t i = kLanes * g;
    Vec3 s = {_mm512_setzero_pd(), _mm512_setzero_pd(), _mm512_setzero_pd()};
    Accumulate(l, static_cast<size_t>(l.row_start[g]), static_cast<size_t>(l.row_start[g + 1]), xg,
               &s);
    const Vec3 d = Symmetric(l.diagonal, p, i, Load3(x, p, i));
    const __m512d keep = _mm512_loadu_pd(l.keep + i);
    Store3(
        q, p, i,
        {_mm512_mul_pd(keep, _mm512_sub_pd(d.x, s.x)), _mm512_mul_pd(keep, _mm512_sub_pd(d.y, s.y)),
         _mm512_mul_pd(keep, _mm512_sub_pd(d.z, s.z))});
  }
}

// CG's fused vector updates over `size` doubles (a multiple of 8).
// dv += α p, r -= α q; returns |r|².
double StepScalar(double alpha, size_t size, const double* p, const double* q, double* dv,
                  double* r) {
  double sum = 0.0;
  for (size_t c = 0; c < size; ++c) {
    dv[c] += alpha * p[c];
    r[c] -= alpha * q[c];
    sum += r[c] * r[c];
  }
  return sum;
}

// p = z + β p, q = az + β q; returns p · q.
double DirectionScalar(double beta, size_t size, const double* z, const double* az, double* p,
                       double* q) {
  double sum = 0.0;
  for (size_t c = 0; c < size; ++c) {
    p[c] = z[c] + beta * p[c];
    q[c] = az[c] + beta * q[c];
    sum += p[c] * q[c];
  }
  return sum;
}

// a · b over `size` doubles (a multiple of 8).
double DotScalar(size_t size, const double* a, const double* b) {
  double sum = 0.0;
  for (size_t c = 0; c < size; ++c) sum += a[c] * b[c];
  return sum;
}

SOMASIM_MSI_TARGET double DotAvx512(size_t size, const double* a, const double* b) {
  __m512d sum = _mm512_setzero_pd();
  for (size_t c = 0; c < size; c += kLanes) {
    sum = _mm512_fmadd_pd(_mm512_loadu_pd(a + c), _mm512_loadu_pd(b + c), sum);
  }
  return Sum8(sum);
}

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

// The pieces of one implicit step; a friend of MassSpringModel to read its spring arrays.
//
// Each spring s (nodes i, j, unit direction u from i to j, length l) contributes the block
//   B_s = (dt D_s + dt² k_s) u uᵀ + dt² k_s c_s (I - u uᵀ),   c_s = (1 - l0/l)₊ ∈ [0, 1),
// to A = M + dt C + dt² K (Baraff & Witkin 1998 eq. 18, with the spring Jacobian of seed 002
// eq. 1–3 keeping only the non-negative transverse stiffness), added on the diagonal blocks ii
// and jj and subtracted on ij and ji. Written as B_s = a_s I + w_s w_sᵀ with
//   a_s = dt² k_s c_s,   w_s = √(dt D_s + dt² k_s (1 - c_s)) u
// (the root's argument is >= 0 because c_s < 1), B_s d costs 3 products, one dot and 3 FMAs.
class MassSpringImplicitStep {
 public:
  // Per spring s (state->implicit_springs, records of kRecord = 8 doubles): w_s, a_s, h_s =
  // K_s (v_i - v_j), K_s = k (c I + (1 - c) u uᵀ) (the spring's part of K v: +h_s on i, -h_s on
  // j) and 0.
  static void LineariseScalar(const MassSpringModel& model, double dt, MassSpringState* state,
                              size_t begin) {
    const double* __restrict x = state->positions.data();
    const double* __restrict v = state->velocities.data();
    double* __restrict out = state->implicit_springs.data();
    const double dt2 = dt * dt;
    for (size_t s = begin; s < model.spring_i_.size(); ++s) {
      const size_t i = 3 * static_cast<size_t>(model.spring_i_[s]);
      const size_t j = 3 * static_cast<size_t>(model.spring_j_[s]);
      const double dx = x[j] - x[i], dy = x[j + 1] - x[i + 1], dz = x[j + 2] - x[i + 2];
      const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
      const double inv = length > 0.0 ? 1.0 / length : 0.0;
      const double ux = dx * inv, uy = dy * inv, uz = dz * inv;
      const double c = length > 0.0 ? std::max(0.0, 1.0 - model.rest_length_[s] * inv) : 0.0;
      const double k = state->stiffness[s];
      const double ex = v[i] - v[j], ey = v[i + 1] - v[j + 1], ez = v[i + 2] - v[j + 2];
      const double kc = k * c;
      const double kt = k * (1.0 - c) * (ux * ex + uy * ey + uz * ez);
      const double scale = std::sqrt(dt * state->damping[s] + dt2 * (k - kc));
      double* o = out + kRecord * s;
      o[0] = scale * ux;
      o[1] = scale * uy;
      o[2] = scale * uz;
      o[3] = dt2 * kc;
      o[4] = kc * ex + kt * ux;
      o[5] = kc * ey + kt * uy;
      o[6] = kc * ez + kt * uz;
    }
  }

  SOMASIM_MSI_TARGET static void LineariseAvx512(const MassSpringModel& model, double dt,
                                                 MassSpringState* state) {
    const double* x = state->positions.data();
    const double* v = state->velocities.data();
    double* out = state->implicit_springs.data();
    const __m512d vdt = _mm512_set1_pd(dt), vdt2 = _mm512_set1_pd(dt * dt);
    const __m512d zero = _mm512_setzero_pd(), one = _mm512_set1_pd(1.0);
    const size_t m = model.spring_i_.size();
    const size_t full = m / kLanes * kLanes;
    for (size_t s = 0; s < full; s += kLanes) {
      const int32_t* si = model.spring_i_.data() + s;
      const int32_t* sj = model.spring_j_.data() + s;
      __m512d xi[4], xj[4], vi[4], vj[4];
      LoadPoints(x, si, xi);
      LoadPoints(x, sj, xj);
      LoadPoints(v, si, vi);
      LoadPoints(v, sj, vj);
      const __m512d dx = _mm512_sub_pd(xj[0], xi[0]), dy = _mm512_sub_pd(xj[1], xi[1]),
                    dz = _mm512_sub_pd(xj[2], xi[2]);
      const __m512d length = _mm512_maskz_sqrt_pd(
          kAll, _mm512_fmadd_pd(dx, dx, _mm512_fmadd_pd(dy, dy, _mm512_mul_pd(dz, dz))));
      const __mmask8 positive = _mm512_cmp_pd_mask(length, zero, _CMP_GT_OQ);
      const __m512d inv = _mm512_maskz_div_pd(positive, one, length);
      const __m512d ux = _mm512_mul_pd(dx, inv), uy = _mm512_mul_pd(dy, inv),
                    uz = _mm512_mul_pd(dz, inv);
      const __m512d c = _mm512_maskz_max_pd(
          positive, zero,
          _mm512_fnmadd_pd(_mm512_loadu_pd(model.rest_length_.data() + s), inv, one));
      const __m512d k = _mm512_loadu_pd(state->stiffness.data() + s);
      const __m512d ex = _mm512_sub_pd(vi[0], vj[0]), ey = _mm512_sub_pd(vi[1], vj[1]),
                    ez = _mm512_sub_pd(vi[2], vj[2]);
      const __m512d kc = _mm512_mul_pd(k, c);
      const __m512d kt =
          _mm512_mul_pd(_mm512_mul_pd(k, _mm512_sub_pd(one, c)),
                        _mm512_fmadd_pd(ux, ex, _mm512_fmadd_pd(uy, ey, _mm512_mul_pd(uz, ez))));
      const __m512d scale = _mm512_maskz_sqrt_pd(
          kAll, _mm512_fmadd_pd(vdt, _mm512_loadu_pd(state->damping.data() + s),
                                _mm512_mul_pd(vdt2, _mm512_sub_pd(k, kc))));
      // Records of 8 per spring: w, a, then h = K_s (v_i - v_j) and 0.
      double* o = out + kRecord * s;
      StoreRecords(o, kRecord, _mm512_mul_pd(scale, ux), _mm512_mul_pd(scale, uy),
                   _mm512_mul_pd(scale, uz), _mm512_mul_pd(vdt2, kc));
      StoreRecords(o + 4, kRecord, _mm512_fmadd_pd(kc, ex, _mm512_mul_pd(kt, ux)),
                   _mm512_fmadd_pd(kc, ey, _mm512_mul_pd(kt, uy)),
                   _mm512_fmadd_pd(kc, ez, _mm512_mul_pd(kt, uz)), zero);
    }
    LineariseScalar(model, dt, state, full);
  }

  // Per group: the slot rows (w, a of each lane's springs), each lane's diagonal block
  // Σ B_s + m I (6 × P) and K v over its springs (3 × P, into implicit_dy).
  static void AssembleScalar(const MassSpringModel& model, MassSpringState* state) {
    const size_t p = model.implicit_padded_;
    const double* sp = state->implicit_springs.data();
    double* rows = state->implicit_rows.data();
    double* diag = state->implicit_diagonal.data();
    double* kv = state->implicit_dy.data();
    const size_t groups = p / kLanes;
    for (size_t g = 0; g < groups; ++g) {
      for (size_t lane = 0; lane < kLanes; ++lane) {
        double d[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        double h[3] = {0.0, 0.0, 0.0};
        for (auto row = static_cast<size_t>(model.implicit_row_start_[g]);
             row < static_cast<size_t>(model.implicit_row_start_[g + 1]); ++row) {
          const size_t slot = kLanes * row + lane;
          const auto s = static_cast<size_t>(model.implicit_spring_[slot]);
          const double* o = sp + kRecord * s;
          const double wx = o[0], wy = o[1], wz = o[2], a = o[3];
          double* r = rows + 4 * kLanes * row + lane;
          r[0] = wx;
          r[kLanes] = wy;
          r[2 * kLanes] = wz;
          r[3 * kLanes] = a;
          d[0] += a + wx * wx;
          d[1] += wx * wy;
          d[2] += wx * wz;
          d[3] += a + wy * wy;
          d[4] += wy * wz;
          d[5] += a + wz * wz;
          const double sign = model.implicit_sign_[slot];
          for (size_t k = 0; k < 3; ++k) h[k] += sign * o[4 + k];
        }
        const size_t i = kLanes * g + lane;
        const double mass = model.implicit_mass_[i];
        d[0] += mass;
        d[3] += mass;
        d[5] += mass;
        for (size_t e = 0; e < 6; ++e) diag[e * p + i] = d[e];
        for (size_t k = 0; k < 3; ++k) kv[k * p + i] = h[k];
      }
    }
  }

  SOMASIM_MSI_TARGET static void AssembleAvx512(const MassSpringModel& model,
                                                MassSpringState* state) {
    const size_t p = model.implicit_padded_;
    const double* sp = state->implicit_springs.data();
    double* rows = state->implicit_rows.data();
    double* diag = state->implicit_diagonal.data();
    double* kv = state->implicit_dy.data();
    const size_t groups = p / kLanes;
    for (size_t g = 0; g < groups; ++g) {
      __m512d d0 = _mm512_setzero_pd(), d1 = d0, d2 = d0, d3 = d0, d4 = d0, d5 = d0;
      __m512d hx = d0, hy = d0, hz = d0;
      for (auto row = static_cast<size_t>(model.implicit_row_start_[g]);
           row < static_cast<size_t>(model.implicit_row_start_[g + 1]); ++row) {
        const int32_t* s = model.implicit_spring_.data() + kLanes * row;
        __m512d w[4], h[4];
        LoadRecords<true>(sp, s, kRecord, w);
        LoadRecords<false>(sp + 4, s, kRecord, h);
        double* r = rows + 4 * kLanes * row;
        _mm512_storeu_pd(r, w[0]);
        _mm512_storeu_pd(r + kLanes, w[1]);
        _mm512_storeu_pd(r + 2 * kLanes, w[2]);
        _mm512_storeu_pd(r + 3 * kLanes, w[3]);
        d0 = _mm512_add_pd(d0, _mm512_fmadd_pd(w[0], w[0], w[3]));
        d1 = _mm512_fmadd_pd(w[0], w[1], d1);
        d2 = _mm512_fmadd_pd(w[0], w[2], d2);
        d3 = _mm512_add_pd(d3, _mm512_fmadd_pd(w[1], w[1], w[3]));
        d4 = _mm512_fmadd_pd(w[1], w[2], d4);
        d5 = _mm512_add_pd(d5, _mm512_fmadd_pd(w[2], w[2], w[3]));
        const __m512d sign = _mm512_loadu_pd(model.implicit_sign_.data() + kLanes * row);
        hx = _mm512_fmadd_pd(sign, h[0], hx);
        hy = _mm512_fmadd_pd(sign, h[1], hy);
        hz = _mm512_fmadd_pd(sign, h[2], hz);
      }
      const size_t i = kLanes * g;
      const __m512d mass = _mm512_loadu_pd(model.implicit_mass_.data() + i);
      _mm512_storeu_pd(diag + i, _mm512_add_pd(d0, mass));
      _mm512_storeu_pd(diag + p + i, d1);
      _mm512_storeu_pd(diag + 2 * p + i, d2);
      _mm512_storeu_pd(diag + 3 * p + i, _mm512_add_pd(d3, mass));
      _mm512_storeu_pd(diag + 4 * p + i, d4);
      _mm512_storeu_pd(diag + 5 * p + i, _mm512_add_pd(d5, mass));
      Store3(kv, p, i, {hx, hy, hz});
    }
  }

  // rhs = keep (dt f - dt² K v) per lane (f from state->forces, K v in implicit_dy), and the
  // inverse diagonal blocks: D_i⁻¹ on lanes with mass, the identity as a stand-in on massless
  // ones, zero on held lanes and padding (so that z, every search direction and Δv stay zero
  // there).
  static void Finalise(const MassSpringModel& model, double dt, MassSpringState* state) {
    const size_t p = model.implicit_padded_;
    const double* f = state->forces.data();
    const double* kv = state->implicit_dy.data();
    const double* d = state->implicit_diagonal.data();
    const double* keep = state->implicit_keep.data();
    double* rhs = state->implicit_rhs.data();
    double* inv = state->implicit_inverse.data();
    const double dt2 = dt * dt;
    for (size_t i = 0; i < p; ++i) {
      const int32_t node = model.implicit_node_[i];
      if (node < 0 || keep[i] == 0.0) {
        for (size_t k = 0; k < 3; ++k) rhs[k * p + i] = 0.0;
        for (size_t e = 0; e < 6; ++e) inv[e * p + i] = 0.0;
        continue;
      }
      const auto n3 = 3 * static_cast<size_t>(node);
      for (size_t k = 0; k < 3; ++k) rhs[k * p + i] = dt * f[n3 + k] - dt2 * kv[k * p + i];
      if (!(model.implicit_mass_[i] > 0.0)) {
        const double identity[6] = {1.0, 0.0, 0.0, 1.0, 0.0, 0.0};
        for (size_t e = 0; e < 6; ++e) inv[e * p + i] = identity[e];
        continue;
      }
      const double xx = d[i], xy = d[p + i], xz = d[2 * p + i], yy = d[3 * p + i],
                   yz = d[4 * p + i], zz = d[5 * p + i];
      const double cxx = yy * zz - yz * yz, cxy = xz * yz - xy * zz, cxz = xy * yz - xz * yy;
      const double cyy = xx * zz - xz * xz, cyz = xy * xz - xx * yz, czz = xx * yy - xy * xy;
      const double r = 1.0 / (xx * cxx + xy * cxy + xz * cxz);
      const double cof[6] = {cxx, cxy, cxz, cyy, cyz, czz};
      for (size_t e = 0; e < 6; ++e) inv[e * p + i] = r * cof[e];
    }
  }

  static Layout MakeLayout(const MassSpringModel& model, const MassSpringState& state) {
    Layout l;
    l.padded = model.implicit_padded_;
    l.groups = l.padded / kLanes;
    l.colours = model.implicit_colour_start_.size() - 1;
    l.colour_start = model.implicit_colour_start_.data();
    l.row_start = model.implicit_row_start_.data();
    l.lower_rows = model.implicit_lower_rows_.data();
    l.neighbour = model.implicit_neighbour_.data();
    l.rows = state.implicit_rows.data();
    l.inverse = state.implicit_inverse.data();
    l.diagonal = state.implicit_diagonal.data();
    l.keep = state.implicit_keep.data();
    l.massless_group = model.implicit_massless_group_.data();
    return l;
  }
};

namespace {}  // namespace

void MassSpringModel::BuildImplicitData() {
  const auto n = static_cast<size_t>(rest_.cols());
  const size_t m = spring_i_.size();
  // Greedy colouring in node order: the smallest colour no neighbour has.
  std::vector<int32_t> colour(n, -1);
  int32_t colours = 0;
  std::vector<uint8_t> taken;
  for (size_t i = 0; i < n; ++i) {
    taken.assign(static_cast<size_t>(colours) + 1, 0);
    for (auto e = static_cast<size_t>(node_spring_start_[i]);
         e < static_cast<size_t>(node_spring_start_[i + 1]); ++e) {
      const auto s = static_cast<size_t>(node_springs_[e]);
      const auto other = static_cast<size_t>(
          spring_i_[s] == static_cast<int32_t>(i) ? spring_j_[s] : spring_i_[s]);
      if (colour[other] >= 0) taken[static_cast<size_t>(colour[other])] = 1;
    }
    int32_t c = 0;
    while (taken[static_cast<size_t>(c)] != 0) ++c;
    colour[i] = c;
    colours = std::max(colours, c + 1);
  }
  // Per node: its springs to lower and to higher colours.
  std::vector<int32_t> lower_count(n, 0), upper_count(n, 0);
  for (size_t s = 0; s < m; ++s) {
    const auto i = static_cast<size_t>(spring_i_[s]), j = static_cast<size_t>(spring_j_[s]);
    ++(colour[j] < colour[i] ? lower_count[i] : upper_count[i]);
    ++(colour[i] < colour[j] ? lower_count[j] : upper_count[j]);
  }
  // Lanes: colour by colour; within a colour by (lower, upper) counts so that a group's lanes
  // need about the same number of rows, then by node.
  std::vector<int32_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(), [&](int32_t a, int32_t b) {
    const auto ua = static_cast<size_t>(a), ub = static_cast<size_t>(b);
    if (colour[ua] != colour[ub]) return colour[ua] < colour[ub];
    if (lower_count[ua] != lower_count[ub]) return lower_count[ua] < lower_count[ub];
    if (upper_count[ua] != upper_count[ub]) return upper_count[ua] < upper_count[ub];
    return a < b;
  });
  implicit_node_.clear();
  implicit_colour_start_.assign(1, 0);
  for (size_t k = 0; k < n;) {
    const int32_t c = colour[static_cast<size_t>(order[k])];
    while (k < n && colour[static_cast<size_t>(order[k])] == c)
      implicit_node_.push_back(order[k++]);
    while (implicit_node_.size() % kLanes != 0) implicit_node_.push_back(-1);
    implicit_colour_start_.push_back(static_cast<int32_t>(implicit_node_.size() / kLanes));
  }
  implicit_padded_ = implicit_node_.size();
  const size_t p = implicit_padded_;
  const size_t groups = p / kLanes;
  implicit_lane_.assign(n, 0);
  implicit_massless_group_.assign(groups, 0);
  implicit_mass_.assign(p, 0.0);
  implicit_real_.assign(p, 0.0);
  for (size_t i = 0; i < p; ++i) {
    if (implicit_node_[i] < 0) continue;
    const auto node = static_cast<size_t>(implicit_node_[i]);
    implicit_lane_[node] = static_cast<int32_t>(i);
    implicit_mass_[i] = mass_[node];
    implicit_real_[i] = 1.0;
    if (!(mass_[node] > 0.0)) implicit_massless_group_[i / kLanes] = 1;
  }
  // Rows: per group, max lower count, then max upper count, rows of 8 slots.
  implicit_row_start_.assign(groups + 1, 0);
  implicit_lower_rows_.assign(groups, 0);
  std::vector<int32_t> upper_rows(groups, 0);
  for (size_t g = 0; g < groups; ++g) {
    for (size_t lane = 0; lane < kLanes; ++lane) {
      const int32_t node = implicit_node_[kLanes * g + lane];
      if (node < 0) continue;
      const auto u = static_cast<size_t>(node);
      implicit_lower_rows_[g] = std::max(implicit_lower_rows_[g], lower_count[u]);
      upper_rows[g] = std::max(upper_rows[g], upper_count[u]);
    }
    implicit_row_start_[g + 1] = implicit_row_start_[g] + implicit_lower_rows_[g] + upper_rows[g];
  }
  const size_t slots = kLanes * static_cast<size_t>(implicit_row_start_[groups]);
  implicit_neighbour_.assign(slots, 0);
  implicit_spring_.assign(slots, static_cast<int32_t>(m));
  implicit_sign_.assign(slots, 0.0);
  for (size_t g = 0; g < groups; ++g) {
    for (size_t lane = 0; lane < kLanes; ++lane) {
      const size_t i = kLanes * g + lane;
      size_t lower = static_cast<size_t>(implicit_row_start_[g]);
      size_t upper = lower + static_cast<size_t>(implicit_lower_rows_[g]);
      for (size_t row = lower; row < static_cast<size_t>(implicit_row_start_[g + 1]); ++row) {
        implicit_neighbour_[kLanes * row + lane] = static_cast<int32_t>(i);
      }
      const int32_t node = implicit_node_[i];
      if (node < 0) continue;
      const auto u = static_cast<size_t>(node);
      for (auto e = static_cast<size_t>(node_spring_start_[u]);
           e < static_cast<size_t>(node_spring_start_[u + 1]); ++e) {
        const auto s = static_cast<size_t>(node_springs_[e]);
        const bool first = spring_i_[s] == node;
        const auto other = static_cast<size_t>(first ? spring_j_[s] : spring_i_[s]);
        size_t& row = colour[other] < colour[u] ? lower : upper;
        implicit_neighbour_[kLanes * row + lane] = implicit_lane_[other];
        implicit_spring_[kLanes * row + lane] = static_cast<int32_t>(s);
        implicit_sign_[kLanes * row + lane] = first ? 1.0 : -1.0;
        ++row;
      }
    }
  }
}

void MassSpringModel::SizeImplicitScratch(MassSpringState* state) const {
  const size_t p = implicit_padded_;
  state->implicit_springs.assign(kRecord * (spring_i_.size() + 1), 0.0);
  state->implicit_gather.assign(4 * p, 0.0);
  state->implicit_rows.assign(4 * implicit_neighbour_.size(), 0.0);
  state->implicit_diagonal.assign(6 * p, 0.0);
  state->implicit_inverse.assign(6 * p, 0.0);
  state->implicit_keep.assign(p, 0.0);
  for (std::vector<double>* v :
       {&state->implicit_rhs, &state->implicit_dv, &state->implicit_residual, &state->implicit_z,
        &state->implicit_search, &state->implicit_product, &state->implicit_az, &state->implicit_dy,
        &state->implicit_dv_previous}) {
    v->assign(3 * p, 0.0);
  }
}

void MassSpringModel::AdvanceImplicit(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<MassSpringState*>(base);
  const double dt = inputs.dt;
  const double dt2 = dt * dt;
  const auto n = static_cast<size_t>(rest_.cols());
  const size_t p = implicit_padded_;
  const size_t size = 3 * p;
  const bool avx512 = UseAvx512();
  InternalForces(*state, &state->forces);
  AddExternalForces(inputs, state);

  // Linearise every spring at the current state, then gather each node's blocks.
  if (avx512) {
    MassSpringImplicitStep::LineariseAvx512(*this, dt, state);
    MassSpringImplicitStep::AssembleAvx512(*this, state);
  } else {
    MassSpringImplicitStep::LineariseScalar(*this, dt, state, 0);
    MassSpringImplicitStep::AssembleScalar(*this, state);
  }
  // Anchors (seed 001's generalised springs) and attachments: k I in K and dt² k + dt d on the
  // diagonal of A.
  double* diag = state->implicit_diagonal.data();
  double* kv = state->implicit_dy.data();
  const double* v = state->velocities.data();
  const auto add_diagonal = [&](int32_t node, double stiffness, double block) {
    const auto i = static_cast<size_t>(implicit_lane_[static_cast<size_t>(node)]);
    const auto n3 = 3 * static_cast<size_t>(node);
    for (size_t k = 0; k < 3; ++k) kv[k * p + i] += stiffness * v[n3 + k];
    diag[i] += block;
    diag[3 * p + i] += block;
    diag[5 * p + i] += block;
  };
  for (size_t a = 0; a < anchor_nodes_.size(); ++a) {
    add_diagonal(anchor_nodes_[a], anchor_stiffness_,
                 dt2 * anchor_stiffness_ + dt * anchor_damping_[a]);
  }
  for (const Attachment& a : inputs.attachments)
    add_diagonal(a.node, a.stiffness, dt2 * a.stiffness);
  std::copy(implicit_real_.begin(), implicit_real_.end(), state->implicit_keep.begin());
  for (const std::span<const int32_t> nodes : {inputs.fixed_nodes, inputs.prescribed_nodes}) {
    for (const int32_t node : nodes) {
      state->implicit_keep[static_cast<size_t>(implicit_lane_[static_cast<size_t>(node)])] = 0.0;
    }
  }
  MassSpringImplicitStep::Finalise(*this, dt, state);

  // Preconditioned conjugate gradients on (M + dt C + dt² K) Δv = rhs, held rows at 0, from
  // 2 Δv_last - Δv_before_last when that is closer than 0 (it differs from this step's Δv by
  // O(dt²) in smooth motion, against O(dt) for Δv_last alone: ~11 % fewer iterations on
  // gallbladder5400; a guess left by a rejected step, or non-finite, fails the test and is
  // dropped).
  const Layout layout = MassSpringImplicitStep::MakeLayout(*this, *state);
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
  state->counters.solver_iterations += iterations;
  if (!converged) ++state->counters.solver_unconverged;

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
