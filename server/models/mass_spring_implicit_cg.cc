#include "server/models/mass_spring_implicit_cg.h"

#include <cstddef>
#include <cstdint>

#include "server/models/mass_spring_implicit_simd.h"

namespace somasim::models {
namespace {

// Σ over rows [begin, end) of lane `lane`: B_s x_j = a_s x_j + (w_s · x_j) w_s.
void AccumulateScalar(const ImplicitLayout& l, size_t begin, size_t end, size_t lane,
                      const double* x, double out[3]) {
  const size_t p = l.padded;
  for (size_t row = begin; row < end; ++row) {
    const auto j = static_cast<size_t>(l.neighbour[kImplicitLanes * row + lane]);
    const double* r = l.rows + 4 * kImplicitLanes * row + lane;
    const double wx = r[0], wy = r[kImplicitLanes], wz = r[2 * kImplicitLanes],
                 a = r[3 * kImplicitLanes];
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

}  // namespace

// --- Scalar operators (the reference; every lane of a group done in turn). ---

double PreconditionScalar(const ImplicitLayout& l, const double* r, double* dy, double* z,
                          double* az) {
  const size_t p = l.padded;
  for (size_t c = 0; c < l.colours; ++c) {
    for (auto g = static_cast<size_t>(l.colour_start[c]);
         g < static_cast<size_t>(l.colour_start[c + 1]); ++g) {
      const auto begin = static_cast<size_t>(l.row_start[g]);
      for (size_t lane = 0; lane < kImplicitLanes; ++lane) {
        const size_t i = kImplicitLanes * g + lane;
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
      for (size_t lane = 0; lane < kImplicitLanes; ++lane) {
        const size_t i = kImplicitLanes * g + lane;
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
    for (size_t lane = 0; lane < kImplicitLanes; ++lane) {
      const size_t i = kImplicitLanes * g + lane;
      double s[3] = {0.0, 0.0, 0.0};
      AccumulateScalar(l, begin, begin + static_cast<size_t>(l.lower_rows[g]), lane, z, s);
      for (size_t k = 0; k < 3; ++k) az[k * p + i] = l.keep[i] * (az[k * p + i] - s[k]);
    }
  }
  return rz;
}

void ProductScalar(const ImplicitLayout& l, const double* x, double* q) {
  const size_t p = l.padded;
  for (size_t g = 0; g < l.groups; ++g) {
    for (size_t lane = 0; lane < kImplicitLanes; ++lane) {
      const size_t i = kImplicitLanes * g + lane;
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

double DotScalar(size_t size, const double* a, const double* b) {
  double sum = 0.0;
  for (size_t c = 0; c < size; ++c) sum += a[c] * b[c];
  return sum;
}

// --- AVX-512 operators: the same arithmetic, the 8 lanes of a group in one register. ---

namespace {

// The sum of the 8 lanes, in a fixed order.
SOMASIM_MSI_TARGET inline double Sum8(__m512d v) {
  alignas(64) double t[kImplicitLanes];
  _mm512_store_pd(t, v);
  return ((t[0] + t[1]) + (t[2] + t[3])) + ((t[4] + t[5]) + (t[6] + t[7]));
}

// out += Σ over rows [begin, end) of B_s x_j, x in records (AoS4) at xg.
SOMASIM_MSI_TARGET inline void Accumulate(const ImplicitLayout& l, size_t begin, size_t end,
                                          const double* xg, Vec3* out) {
  for (size_t row = begin; row < end; ++row) {
    __m512d xj[4];
    LoadRecords<false>(xg, l.neighbour + kImplicitLanes * row, 4, xj);
    const double* r = l.rows + 4 * kImplicitLanes * row;
    const __m512d wx = _mm512_loadu_pd(r), wy = _mm512_loadu_pd(r + kImplicitLanes),
                  wz = _mm512_loadu_pd(r + 2 * kImplicitLanes),
                  a = _mm512_loadu_pd(r + 3 * kImplicitLanes);
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

}  // namespace

SOMASIM_MSI_TARGET double PreconditionAvx512(const ImplicitLayout& l, const CgUpdate& update,
                                             double* r, double* dy, double* az, double* zg,
                                             bool first, double rz_before, double* search,
                                             double* q, double* curvature, double* residual_norm2) {
  const size_t p = l.padded;
  const __m512d alpha = _mm512_set1_pd(update.alpha);
  __m512d rz = _mm512_setzero_pd(), rr = _mm512_setzero_pd();
  for (size_t c = 0; c < l.colours; ++c) {
    for (auto g = static_cast<size_t>(l.colour_start[c]);
         g < static_cast<size_t>(l.colour_start[c + 1]); ++g) {
      const size_t i = kImplicitLanes * g;
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
      for (size_t c = 0; c < 3 * p; c += kImplicitLanes) {
        _mm512_storeu_pd(update.dv + c, _mm512_fmadd_pd(alpha, _mm512_loadu_pd(search + c),
                                                        _mm512_loadu_pd(update.dv + c)));
      }
      return 0.0;
    }
  }
  for (size_t c = l.colours; c-- > 0;) {
    for (auto g = static_cast<size_t>(l.colour_start[c]);
         g < static_cast<size_t>(l.colour_start[c + 1]); ++g) {
      const size_t i = kImplicitLanes * g;
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
    const size_t i = kImplicitLanes * g;
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

SOMASIM_MSI_TARGET void ProductAvx512(const ImplicitLayout& l, const double* x, double* q,
                                      double* xg) {
  const size_t p = l.padded;
  for (size_t i = 0; i < p; i += kImplicitLanes) StoreRecords3(xg + 4 * i, Load3(x, p, i));
  for (size_t g = 0; g < l.groups; ++g) {
    const size_t i = kImplicitLanes * g;
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
SOMASIM_MSI_TARGET double DotAvx512(size_t size, const double* a, const double* b) {
  __m512d sum = _mm512_setzero_pd();
  for (size_t c = 0; c < size; c += kImplicitLanes) {
    sum = _mm512_fmadd_pd(_mm512_loadu_pd(a + c), _mm512_loadu_pd(b + c), sum);
  }
  return Sum8(sum);
}

}  // namespace somasim::models
