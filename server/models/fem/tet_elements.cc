#include "server/models/fem/tet_elements.h"

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "server/models/cpu_features.h"
#include "server/models/particle_mesh.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#endif

namespace somasim::models::fem {
namespace {

[[noreturn]] void Refuse(const char* model, const std::string& what) {
  throw std::invalid_argument(std::string(model) + ": " + what);
}

}  // namespace

TetElements BuildTetElements(const mesh::TetMesh& mesh, const char* model) {
  CheckFinitePoints(mesh.vertices, model);
  const Eigen::Index n = mesh.vertices.cols();
  const Eigen::Index m = mesh.tetrahedra.cols();
  if (m == 0) Refuse(model, "the mesh has no tetrahedra");
  TetElements out;
  out.tets = mesh.tetrahedra;
  out.gradients.resize(3, 4 * m);
  out.volumes.resize(static_cast<size_t>(m));
  out.node_volume.assign(static_cast<size_t>(n), 0.0);
  for (Eigen::Index e = 0; e < m; ++e) {
    for (int a = 0; a < 4; ++a) {
      const int32_t node = mesh.tetrahedra(a, e);
      if (node < 0 || node >= n) {
        Refuse(model, "tetrahedron " + std::to_string(e) + " uses node " + std::to_string(node) +
                          ", outside 0.." + std::to_string(n - 1));
      }
      for (int b = 0; b < a; ++b) {
        if (mesh.tetrahedra(b, e) == node) {
          Refuse(model,
                 "tetrahedron " + std::to_string(e) + " repeats node " + std::to_string(node));
        }
      }
    }
    const Eigen::Vector3d x0 = mesh.vertices.col(mesh.tetrahedra(0, e));
    Eigen::Matrix3d dm;  // [X1 - X0, X2 - X0, X3 - X0]
    double longest = 0.0;
    for (int a = 1; a < 4; ++a) {
      dm.col(a - 1) = mesh.vertices.col(mesh.tetrahedra(a, e)) - x0;
      for (int b = 0; b < a; ++b) {
        longest = std::max(longest, (mesh.vertices.col(mesh.tetrahedra(a, e)) -
                                     mesh.vertices.col(mesh.tetrahedra(b, e)))
                                        .norm());
      }
    }
    const double volume = dm.determinant() / 6.0;
    if (!(volume > 1e-12 * longest * longest * longest)) {
      Refuse(model, "tetrahedron " + std::to_string(e) +
                        (volume < 0.0 ? " is inverted (negative volume)" : " is flat (no volume)"));
    }
    // F = Ds Dm⁻¹ = Σ_a x_a ∇N_aᵀ: ∇N_a (a = 1..3) is row a-1 of Dm⁻¹, ∇N_0 = -Σ.
    const Eigen::Matrix3d inverse = dm.inverse();
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (int a = 1; a < 4; ++a) {
      out.gradients.col(4 * e + a) = inverse.row(a - 1).transpose();
      sum += inverse.row(a - 1).transpose();
    }
    out.gradients.col(4 * e) = -sum;
    out.volumes[static_cast<size_t>(e)] = volume;
    for (int a = 0; a < 4; ++a) {
      out.node_volume[static_cast<size_t>(mesh.tetrahedra(a, e))] += volume / 4.0;
    }
  }
  out.node_start.assign(static_cast<size_t>(n) + 1, 0);
  for (Eigen::Index e = 0; e < m; ++e) {
    for (int a = 0; a < 4; ++a) ++out.node_start[static_cast<size_t>(mesh.tetrahedra(a, e)) + 1];
  }
  for (Eigen::Index i = 0; i < n; ++i) {
    out.node_start[static_cast<size_t>(i) + 1] += out.node_start[static_cast<size_t>(i)];
  }
  out.element_of_node.resize(static_cast<size_t>(4 * m));
  std::vector<int32_t> fill(out.node_start.begin(), out.node_start.end() - 1);
  for (Eigen::Index e = 0; e < m; ++e) {
    for (int a = 0; a < 4; ++a) {
      const auto node = static_cast<size_t>(mesh.tetrahedra(a, e));
      out.element_of_node[static_cast<size_t>(fill[node]++)] = static_cast<int32_t>(4 * e + a);
    }
  }
  return out;
}

Eigen::Matrix3d PolarRotation(const Eigen::Matrix3d& f) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(f, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d u = svd.matrixU();
  const Eigen::Matrix3d& v = svd.matrixV();
  // Singular values are sorted decreasing: flipping the last column of U (the smallest singular
  // value's) makes R proper when det(U Vᵀ) = -1 (an inverted or reflected element).
  if ((u * v.transpose()).determinant() < 0.0) u.col(2) = -u.col(2);
  return u * v.transpose();
}

namespace {

// The rotation of the unit quaternion q = (w, x, y, z).
Eigen::Matrix3d QuaternionRotation(const double* q) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  const double xx = x * x, yy = y * y, zz = z * z;
  const double xy = x * y, xz = x * z, yz = y * z, wx = w * x, wy = w * y, wz = w * z;
  Eigen::Matrix3d r;
  r << 1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy),  //
      2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx),   //
      2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy);
  return r;
}

}  // namespace

Eigen::Matrix3d PolarRotationFrom(const Eigen::Matrix3d& f, double* q) {
  constexpr int kMaxSteps = 8;
  // |ω| below this: the rotation is exact to rounding (the next step would be ~|ω|² × a
  // condition number).
  constexpr double kConverged2 = 1e-20;
  for (int step = 0; step < kMaxSteps; ++step) {
    const Eigen::Matrix3d r = QuaternionRotation(q);
    const Eigen::Matrix3d a = r.transpose() * f;
    const double g0 = a(2, 1) - a(1, 2), g1 = a(0, 2) - a(2, 0), g2 = a(1, 0) - a(0, 1);
    // H = tr(S) I - S by Cholesky (H = L D Lᵀ); a pivot <= 0: not at the maximum's basin.
    const double h00 = a(1, 1) + a(2, 2), h11 = a(0, 0) + a(2, 2), h22 = a(0, 0) + a(1, 1);
    const double h01 = -0.5 * (a(0, 1) + a(1, 0)), h02 = -0.5 * (a(0, 2) + a(2, 0));
    const double h12 = -0.5 * (a(1, 2) + a(2, 1));
    const double d0 = h00;
    if (!(d0 > 0.0)) break;
    const double l10 = h01 / d0, l20 = h02 / d0;
    const double d1 = h11 - l10 * h01;
    if (!(d1 > 0.0)) break;
    const double l21 = (h12 - l20 * h01) / d1;
    const double d2 = h22 - l20 * h02 - l21 * l21 * d1;
    if (!(d2 > 0.0)) break;
    // ω = H⁻¹ g: forward, diagonal, backward.
    const double y0 = g0, y1 = g1 - l10 * y0, y2 = g2 - l20 * y0 - l21 * y1;
    const double w2 = y2 / d2, w1 = y1 / d1 - l21 * w2, w0 = y0 / d0 - l10 * w1 - l20 * w2;
    // q ← q ⊗ (1, ω/2) normalised: R_k times the Cayley rotation of ω (a rotation by
    // 2 atan(|ω|/2) ≈ |ω| about ω), exact for any ω.
    const double v0 = 0.5 * w0, v1 = 0.5 * w1, v2 = 0.5 * w2;
    const double qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    const double nw = qw - qx * v0 - qy * v1 - qz * v2;
    const double nx = qx + qw * v0 + qy * v2 - qz * v1;
    const double ny = qy + qw * v1 + qz * v0 - qx * v2;
    const double nz = qz + qw * v2 + qx * v1 - qy * v0;
    const double inverse_norm = 1.0 / std::sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
    if (!std::isfinite(inverse_norm)) break;
    q[0] = nw * inverse_norm;
    q[1] = nx * inverse_norm;
    q[2] = ny * inverse_norm;
    q[3] = nz * inverse_norm;
    if (w0 * w0 + w1 * w1 + w2 * w2 <= kConverged2) return QuaternionRotation(q);
  }
  Eigen::Matrix3d r = PolarRotation(f);
  const Eigen::Quaterniond e(r);
  q[0] = e.w();
  q[1] = e.x();
  q[2] = e.y();
  q[3] = e.z();
  return r;
}

namespace {

void PolarRotationsScalar(const double* f, double* q, double* r, size_t begin, size_t end) {
  for (size_t e = begin; e < end; ++e) {
    Eigen::Map<Eigen::Matrix3d>(r + 9 * e) =
        PolarRotationFrom(Eigen::Map<const Eigen::Matrix3d>(f + 9 * e), q + 4 * e);
  }
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define SOMASIM_FEM_AVX512 __attribute__((target("avx2,fma,avx512f,avx512vl")))

// PolarRotationFrom's iteration on eight matrices e0 .. e0 + 7, structure of arrays: lane l of
// every vector is matrix e0 + l. Returns the lanes that did not converge (left to the scalar
// path with their starting q).
SOMASIM_FEM_AVX512 __mmask8 PolarRotations8(const double* f, double* q, double* r, size_t e0) {
  const __m512i nine = _mm512_set_epi64(63, 54, 45, 36, 27, 18, 9, 0);
  const __m512i four = _mm512_set_epi64(28, 24, 20, 16, 12, 8, 4, 0);
  const double* fb = f + 9 * e0;
  double* qb = q + 4 * e0;
  __m512d fm[9];
  for (int k = 0; k < 9; ++k)
    fm[k] = _mm512_mask_i64gather_pd(_mm512_setzero_pd(), 0xFF, nine, fb + k, 8);
  __m512d qw = _mm512_mask_i64gather_pd(_mm512_setzero_pd(), 0xFF, four, qb, 8);
  __m512d qx = _mm512_mask_i64gather_pd(_mm512_setzero_pd(), 0xFF, four, qb + 1, 8);
  __m512d qy = _mm512_mask_i64gather_pd(_mm512_setzero_pd(), 0xFF, four, qb + 2, 8);
  __m512d qz = _mm512_mask_i64gather_pd(_mm512_setzero_pd(), 0xFF, four, qb + 3, 8);
  const __m512d one = _mm512_set1_pd(1.0), two = _mm512_set1_pd(2.0), half = _mm512_set1_pd(0.5);
  const __m512d zero = _mm512_setzero_pd();
  const __m512d converged2 = _mm512_set1_pd(1e-20);
  __m512d rm[9];  // R column-major
  const auto rotation = [&]() SOMASIM_FEM_AVX512 {
    const __m512d xx = _mm512_mul_pd(qx, qx), yy = _mm512_mul_pd(qy, qy),
                  zz = _mm512_mul_pd(qz, qz);
    const __m512d xy = _mm512_mul_pd(qx, qy), xz = _mm512_mul_pd(qx, qz),
                  yz = _mm512_mul_pd(qy, qz);
    const __m512d wx = _mm512_mul_pd(qw, qx), wy = _mm512_mul_pd(qw, qy),
                  wz = _mm512_mul_pd(qw, qz);
    rm[0] = _mm512_sub_pd(one, _mm512_mul_pd(two, _mm512_add_pd(yy, zz)));
    rm[1] = _mm512_mul_pd(two, _mm512_add_pd(xy, wz));
    rm[2] = _mm512_mul_pd(two, _mm512_sub_pd(xz, wy));
    rm[3] = _mm512_mul_pd(two, _mm512_sub_pd(xy, wz));
    rm[4] = _mm512_sub_pd(one, _mm512_mul_pd(two, _mm512_add_pd(xx, zz)));
    rm[5] = _mm512_mul_pd(two, _mm512_add_pd(yz, wx));
    rm[6] = _mm512_mul_pd(two, _mm512_add_pd(xz, wy));
    rm[7] = _mm512_mul_pd(two, _mm512_sub_pd(yz, wx));
    rm[8] = _mm512_sub_pd(one, _mm512_mul_pd(two, _mm512_add_pd(xx, yy)));
  };
  __mmask8 active = 0xFF, failed = 0;
  for (int step = 0; step < 8 && active != 0; ++step) {
    rotation();
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
    const __m512d d0 = h00;
    __mmask8 ok = _mm512_cmp_pd_mask(d0, zero, _CMP_GT_OQ);
    const __m512d l10 = _mm512_div_pd(h01, d0), l20 = _mm512_div_pd(h02, d0);
    const __m512d d1 = _mm512_fnmadd_pd(l10, h01, h11);
    ok &= _mm512_cmp_pd_mask(d1, zero, _CMP_GT_OQ);
    const __m512d l21 = _mm512_div_pd(_mm512_fnmadd_pd(l20, h01, h12), d1);
    const __m512d d2 =
        _mm512_fnmadd_pd(_mm512_mul_pd(l21, l21), d1, _mm512_fnmadd_pd(l20, h02, h22));
    ok &= _mm512_cmp_pd_mask(d2, zero, _CMP_GT_OQ);
    const __m512d y0 = g0;
    const __m512d y1 = _mm512_fnmadd_pd(l10, y0, g1);
    const __m512d y2 = _mm512_fnmadd_pd(l21, y1, _mm512_fnmadd_pd(l20, y0, g2));
    const __m512d w2 = _mm512_div_pd(y2, d2);
    const __m512d w1 = _mm512_fnmadd_pd(l21, w2, _mm512_div_pd(y1, d1));
    const __m512d w0 = _mm512_fnmadd_pd(l20, w2, _mm512_fnmadd_pd(l10, w1, _mm512_div_pd(y0, d0)));
    const __m512d v0 = _mm512_mul_pd(half, w0), v1 = _mm512_mul_pd(half, w1);
    const __m512d v2 = _mm512_mul_pd(half, w2);
    // q ⊗ (1, v).
    __m512d nw = _mm512_fnmadd_pd(qz, v2, _mm512_fnmadd_pd(qy, v1, _mm512_fnmadd_pd(qx, v0, qw)));
    __m512d nx = _mm512_fnmadd_pd(qz, v1, _mm512_fmadd_pd(qy, v2, _mm512_fmadd_pd(qw, v0, qx)));
    __m512d ny = _mm512_fnmadd_pd(qx, v2, _mm512_fmadd_pd(qz, v0, _mm512_fmadd_pd(qw, v1, qy)));
    __m512d nz = _mm512_fnmadd_pd(qy, v0, _mm512_fmadd_pd(qx, v1, _mm512_fmadd_pd(qw, v2, qz)));
    __m512d norm2 = _mm512_mul_pd(nw, nw);
    norm2 = _mm512_fmadd_pd(nx, nx, norm2);
    norm2 = _mm512_fmadd_pd(ny, ny, norm2);
    norm2 = _mm512_fmadd_pd(nz, nz, norm2);
    const __m512d inverse = _mm512_div_pd(one, _mm512_maskz_sqrt_pd(0xFF, norm2));
    // Finite: |inverse| < inf (a NaN compares false).
    ok &= _mm512_cmp_pd_mask(_mm512_abs_pd(inverse), _mm512_set1_pd(1e300), _CMP_LT_OQ);
    failed |= static_cast<__mmask8>(active & ~ok);
    const __mmask8 update = static_cast<__mmask8>(active & ok);
    qw = _mm512_mask_mul_pd(qw, update, nw, inverse);
    qx = _mm512_mask_mul_pd(qx, update, nx, inverse);
    qy = _mm512_mask_mul_pd(qy, update, ny, inverse);
    qz = _mm512_mask_mul_pd(qz, update, nz, inverse);
    __m512d omega2 = _mm512_mul_pd(w0, w0);
    omega2 = _mm512_fmadd_pd(w1, w1, omega2);
    omega2 = _mm512_fmadd_pd(w2, w2, omega2);
    const __mmask8 done = _mm512_mask_cmp_pd_mask(update, omega2, converged2, _CMP_LE_OQ);
    active = static_cast<__mmask8>(update & ~done);
  }
  const __mmask8 good = static_cast<__mmask8>(~(failed | active));
  rotation();
  double* rb = r + 9 * e0;
  for (int k = 0; k < 9; ++k) _mm512_mask_i64scatter_pd(rb + k, good, nine, rm[k], 8);
  _mm512_mask_i64scatter_pd(qb, good, four, qw, 8);
  _mm512_mask_i64scatter_pd(qb + 1, good, four, qx, 8);
  _mm512_mask_i64scatter_pd(qb + 2, good, four, qy, 8);
  _mm512_mask_i64scatter_pd(qb + 3, good, four, qz, 8);
  return static_cast<__mmask8>(~good);
}
#endif

}  // namespace

void PolarRotations(const double* f, double* q, double* r, size_t count, bool force_scalar) {
  size_t e = 0;
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
  if (CpuHasAvx512() && !force_scalar) {
    for (; e + 8 <= count; e += 8) {
      const __mmask8 left = PolarRotations8(f, q, r, e);
      for (size_t l = 0; l < 8; ++l) {
        if ((left >> l) & 1U) PolarRotationsScalar(f, q, r, e + l, e + l + 1);
      }
    }
  }
#endif
  PolarRotationsScalar(f, q, r, e, count);
}

}  // namespace somasim::models::fem
