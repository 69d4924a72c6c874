#include "server/models/fem/tet_elements.h"

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "server/models/cpu_features.h"
#include "server/models/fem/polar_avx512.h"
#include "server/models/particle_mesh.h"

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
    // ω = H⁻¹ g with H = tr(S) I - S, by its adjugate (one division; PolarRotations8 does the
    // same on eight lanes). H not positive definite (a leading minor <= 0, Sylvester): not at
    // the maximum's basin.
    const double h00 = a(1, 1) + a(2, 2), h11 = a(0, 0) + a(2, 2), h22 = a(0, 0) + a(1, 1);
    const double h01 = -0.5 * (a(0, 1) + a(1, 0)), h02 = -0.5 * (a(0, 2) + a(2, 0));
    const double h12 = -0.5 * (a(1, 2) + a(2, 1));
    const double c00 = h11 * h22 - h12 * h12, c01 = h02 * h12 - h01 * h22;
    const double c02 = h01 * h12 - h02 * h11, c11 = h00 * h22 - h02 * h02;
    const double c12 = h01 * h02 - h00 * h12, c22 = h00 * h11 - h01 * h01;
    const double det = h00 * c00 + h01 * c01 + h02 * c02;
    if (!(h00 > 0.0) || !(c22 > 0.0) || !(det > 0.0)) break;
    const double s = 1.0 / det;
    const double w0 = s * (c00 * g0 + c01 * g1 + c02 * g2);
    const double w1 = s * (c01 * g0 + c11 * g1 + c12 * g2);
    const double w2 = s * (c02 * g0 + c12 * g1 + c22 * g2);
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

#ifdef SOMASIM_FEM_HAS_AVX512_PATH
// PolarIterate8 on the matrices e0 .. e0 + 7 in memory. Returns the lanes that did not converge
// (left to the scalar path with their starting q).
SOMASIM_FEM_AVX512 __mmask8 PolarRotations8(const double* f, double* q, double* r, size_t e0) {
  const __m512i nine = _mm512_set_epi64(63, 54, 45, 36, 27, 18, 9, 0);
  const __m512i four = _mm512_set_epi64(28, 24, 20, 16, 12, 8, 4, 0);
  const double* fb = f + 9 * e0;
  double* qb = q + 4 * e0;
  __m512d fm[9];
  for (int k = 0; k < 9; ++k)
    fm[k] = _mm512_mask_i64gather_pd(_mm512_setzero_pd(), 0xFF, nine, fb + k, 8);
  __m512d qv[4];
  for (int k = 0; k < 4; ++k)
    qv[k] = _mm512_mask_i64gather_pd(_mm512_setzero_pd(), 0xFF, four, qb + k, 8);
  __m512d rm[9];  // R column-major
  const __mmask8 left = PolarIterate8(fm, qv, rm);
  const auto good = static_cast<__mmask8>(~left);
  double* rb = r + 9 * e0;
  for (int k = 0; k < 9; ++k) _mm512_mask_i64scatter_pd(rb + k, good, nine, rm[k], 8);
  for (int k = 0; k < 4; ++k) _mm512_mask_i64scatter_pd(qb + k, good, four, qv[k], 8);
  return left;
}
#endif

}  // namespace

void PolarRotations(const double* f, double* q, double* r, size_t count, bool force_scalar) {
  size_t e = 0;
#ifdef SOMASIM_FEM_HAS_AVX512_PATH
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
