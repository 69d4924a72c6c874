// FemModel's step pass for the linear and corotational kinds: forces, rotations and the warped
// step matrix in one pass over the elements, portable or, where the CPU has AVX-512, eight
// elements at a time in vector registers.
#include <Eigen/Core>
#include <algorithm>
#include <cassert>
#include <cstddef>
#include <cstdint>

#include "server/models/cpu_features.h"
#include "server/models/fem/fem_model.h"
#include "server/models/fem/fem_model_internal.h"
#include "server/models/fem/polar_avx512.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;

// ForcesAndWarpedMatrix's pass over the elements, on raw arrays: the portable ElementPass, and
// with AVX-512 ElementPassAvx512 (the linear kind) or CorotationalPassAvx512.
struct WarpedPass {
  const double* x;                // 3 × num_nodes
  const double* rest;             // 3 × num_nodes
  const int32_t* tets;            // 4 × num_tets
  const double* gradients;        // 12 × num_tets
  const double* volumes;          // num_tets
  const double* rotations;        // 9 × num_tets
  const double* offset;           // 9 × num_tets, or null
  const int32_t* element_blocks;  // 16 × num_tets
  double* forces;                 // 3 × num_nodes, accumulated
  double* values;                 // the matrix's blocks, accumulated
  size_t num_tets;
  double g, lambda, mu, k_scale;
  bool linear;
};

// H = F - I = Σ_a (x_a - X_a) ∇N_aᵀ of element e (TetElements::DisplacementGradient), h[i][j] =
// H(i, j).
__attribute__((always_inline)) inline void DisplacementGradient(const WarpedPass& a, size_t e,
                                                                double h[3][3]) {
  const double* grad = a.gradients + 12 * e;
  const int32_t* node = a.tets + 4 * e;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) h[i][j] = 0.0;
  }
  for (int c0 = 0; c0 < 4; ++c0) {
    const auto k = 3 * static_cast<size_t>(node[c0]);
    for (int i = 0; i < 3; ++i) {
      const double u = a.x[k + static_cast<size_t>(i)] - a.rest[k + static_cast<size_t>(i)];
      for (int j = 0; j < 3; ++j) h[i][j] += u * grad[3 * c0 + j];
    }
  }
}

// F = I + H of every element into f (9 × num_tets, column-major), for PolarRotations (the
// portable path; CorotationalPassAvx512 keeps F in registers).
void DeformationGradients(const WarpedPass& a, double* f) {
  for (size_t e = 0; e < a.num_tets; ++e) {
    double h[3][3];
    DisplacementGradient(a, e, h);
    double* out = f + 9 * e;
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 3; ++i) out[3 * j + i] = h[i][j] + (i == j ? 1.0 : 0.0);
    }
  }
}

// Element e's part before its blocks: its nodal forces into a.forces, its rotated gradients
// r_a = R ∇N_a (r[4][3]) and the blocks' factors V k λ, V k μ (k = k_scale g).
// Always inlined, so that the AVX-512 pass compiles it for its target too (FMA).
__attribute__((always_inline)) inline void ElementForcesAndGradients(const WarpedPass& a, size_t e,
                                                                     double r[4][3], double* cl_out,
                                                                     double* cm_out) {
  const double g = a.g, lambda = a.lambda, mu = a.mu;
  const double* grad = a.gradients + 12 * e;  // ∇N_a at grad + 3a
  const double* rot = a.rotations + 9 * e;    // column-major R
  const int32_t* node = a.tets + 4 * e;
  double h[3][3];
  DisplacementGradient(a, e, h);
  // ε: linear sym(H); corotational sym((Rᵀ - I) + Rᵀ H) (ElementStress).
  double eps[3][3];
  if (a.linear) {
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) eps[i][j] = 0.5 * (h[i][j] + h[j][i]);
    }
  } else {
    double s[3][3];  // S - I = Rᵀ - I + Rᵀ H
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        double v = rot[3 * i + j] - (i == j ? 1.0 : 0.0);  // Rᵀ(i, j) = R(j, i)
        for (int k = 0; k < 3; ++k) v += rot[3 * i + k] * h[k][j];
        s[i][j] = v;
      }
    }
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) eps[i][j] = 0.5 * (s[i][j] + s[j][i]);
    }
  }
  // σ = g (λ tr ε I + 2 μ ε) + offset, P = R σ.
  const double tr = eps[0][0] + eps[1][1] + eps[2][2];
  double sigma[3][3];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      sigma[i][j] = g * (2.0 * mu * eps[i][j] + (i == j ? lambda * tr : 0.0));
    }
  }
  if (a.offset != nullptr) {
    const double* c = a.offset + 9 * e;  // column-major
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) sigma[i][j] += c[3 * j + i];
    }
  }
  double p[3][3];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      p[i][j] = rot[i] * sigma[0][j] + rot[3 + i] * sigma[1][j] + rot[6 + i] * sigma[2][j];
    }
  }
  const double volume = a.volumes[e];
  // f_a = -V P ∇N_a; r_a = R ∇N_a for the blocks.
  for (int c0 = 0; c0 < 4; ++c0) {
    const double* ga = grad + 3 * c0;
    double* out = a.forces + 3 * static_cast<size_t>(node[c0]);
    for (int i = 0; i < 3; ++i) {
      out[i] -= volume * (p[i][0] * ga[0] + p[i][1] * ga[1] + p[i][2] * ga[2]);
      r[c0][i] = rot[i] * ga[0] + rot[3 + i] * ga[1] + rot[6 + i] * ga[2];
    }
  }
  const double v = a.k_scale * g * volume;  // a viscous step's stiffness is g times the elastic
  *cl_out = v * lambda;
  *cm_out = v * mu;
}

void ElementPass(const WarpedPass& a) {
  for (size_t e = 0; e < a.num_tets; ++e) {
    double r[4][3], cl, cm;
    ElementForcesAndGradients(a, e, r, &cl, &cm);
    internal::AddWarpedElementBlocks(a.element_blocks + 16 * e, a.gradients + 12 * e, r, cl, cm,
                                     a.values);
  }
}

#ifdef SOMASIM_FEM_HAS_AVX512_PATH
// ElementPass's blocks of element e, each block's first eight values (column-major) in one
// AVX-512 register: value 3c + i is cl r_a[i] r_b[c] + cm r_b[i] r_a[c] (+ the diagonal term
// where c = i), so with each corner's r in the lane patterns I_a = (r0 r1 r2 r0 r1 r2 r0 r1)
// (lane k: r[k mod 3]) and C_a = (r0 r0 r0 r1 r1 r1 r2 r2) (lane k: r[k / 3]) the eight are
// cl I_a C_b + cm I_b C_a, two FMAs; value 8 (c = i = 2) is (cl + cm) r_a[2] r_b[2] + diagonal.
// Equal to ElementPass up to rounding (the order of the additions).
SOMASIM_FEM_AVX512 __attribute__((always_inline)) inline void AddWarpedBlocks(
    const WarpedPass& a, size_t e, const double r[4][3], double cl, double cm) {
  const __m512i i_pattern = _mm512_set_epi64(1, 0, 2, 1, 0, 2, 1, 0);
  const __m512i c_pattern = _mm512_set_epi64(2, 2, 1, 1, 1, 0, 0, 0);
  __m512d lanes_i[4], lanes_c[4];
  for (int c0 = 0; c0 < 4; ++c0) {
    // From registers (a vector load of the three just-stored scalars would stall on store
    // forwarding).
    const __m512d ra = _mm512_castpd256_pd512(_mm256_set_pd(0.0, r[c0][2], r[c0][1], r[c0][0]));
    lanes_i[c0] = _mm512_maskz_permutexvar_pd(0xFF, i_pattern, ra);
    lanes_c[c0] = _mm512_maskz_permutexvar_pd(0xFF, c_pattern, ra);
  }
  const __m512d cl8 = _mm512_set1_pd(cl), cm8 = _mm512_set1_pd(cm);
  const double* grad = a.gradients + 12 * e;
  const int32_t* blocks = a.element_blocks + 16 * e;
  for (int c0 = 0; c0 < 4; ++c0) {
    const __m512d cl_ia = _mm512_mul_pd(cl8, lanes_i[c0]);
    for (int b = 0; b < 4; ++b) {
      const int32_t block = blocks[4 * c0 + b];
      if (block < 0) continue;  // upper storage: the transpose of (b, a)
      const double* ga = grad + 3 * c0;
      const double* gb = grad + 3 * b;
      const double diagonal = cm * (ga[0] * gb[0] + ga[1] * gb[1] + ga[2] * gb[2]);
      double* out = a.values + 9 * static_cast<size_t>(block);
      __m512d v = _mm512_maskz_mov_pd(0x11, _mm512_set1_pd(diagonal));
      v = _mm512_fmadd_pd(_mm512_mul_pd(cm8, lanes_i[b]), lanes_c[c0], v);
      v = _mm512_fmadd_pd(cl_ia, lanes_c[b], v);
      _mm512_storeu_pd(out, _mm512_add_pd(_mm512_loadu_pd(out), v));
      out[8] += (cl + cm) * r[c0][2] * r[b][2] + diagonal;
    }
  }
}

// ElementPass with the blocks written by AddWarpedBlocks (the linear kind: R = I).
SOMASIM_FEM_AVX512 void ElementPassAvx512(const WarpedPass& a) {
  for (size_t e = 0; e < a.num_tets; ++e) {
    double r[4][3], cl, cm;
    ElementForcesAndGradients(a, e, r, &cl, &cm);
    AddWarpedBlocks(a, e, r, cl, cm);
  }
}

// The corotational kind's DeformationGradients, PolarRotations and ElementPass in one pass,
// eight elements in the eight lanes of AVX-512 registers (lane l: element e0 + l): H and F from
// gathered x - X and ∇N, R by PolarIterate8 warm-started from `quaternions` (4 × num_tets,
// updated; a lane it leaves goes to PolarRotationFrom, as in PolarRotations), the stress and
// forces as ElementForcesAndGradients, then per element its forces into a.forces and its blocks
// by AddWarpedBlocks. Writes R into `rotations` (9 × num_tets, column-major), which is
// a.rotations. The last num_tets mod 8 elements go one at a time. Equal to the three passes up
// to rounding; F is not stored (a pass over memory less) and the rotations never wait for a
// separate pass to write them.
SOMASIM_FEM_AVX512 void CorotationalPassAvx512(const WarpedPass& a, double* rotations,
                                               double* quaternions) {
  const __m512i twelve = _mm512_set_epi64(84, 72, 60, 48, 36, 24, 12, 0);
  const __m512i nine = _mm512_set_epi64(63, 54, 45, 36, 27, 18, 9, 0);
  const __m512i four = _mm512_set_epi64(28, 24, 20, 16, 12, 8, 4, 0);
  // Corner c of element l of 8 is tets value 4 l + c of the 32 in two registers.
  const __m512i corner_index =
      _mm512_set_epi32(0, 0, 0, 0, 0, 0, 0, 0, 28, 24, 20, 16, 12, 8, 4, 0);
  const __m512d zero = _mm512_setzero_pd();
  const __m512d g = _mm512_set1_pd(a.g), two_mu = _mm512_set1_pd(2.0 * a.mu);
  const __m512d lambda = _mm512_set1_pd(a.lambda), mu = _mm512_set1_pd(a.mu);
  const __m512d k_scale = _mm512_set1_pd(a.k_scale), half = _mm512_set1_pd(0.5);
  alignas(64) double rbuf[12][8];  // r_c[i] of lane l at [3 c + i][l]
  alignas(64) double fbuf[12][8];  // the forces on corner c, f_c[i], likewise [N]
  alignas(64) double cbuf[2][8];   // cl, cm
  alignas(64) double mbuf[9][8];   // F, then R, of lanes left to PolarRotationFrom
  const size_t groups = a.num_tets / 8;
  for (size_t group = 0; group < groups; ++group) {
    const size_t e0 = 8 * group;
    const __m512i t0 = _mm512_loadu_si512(a.tets + 4 * e0);
    const __m512i t1 = _mm512_loadu_si512(a.tets + 4 * e0 + 16);
    const double* gradients = a.gradients + 12 * e0;
    __m512d grad[4][3];  // ∇N_c[j]
    __m512d h[3][3];     // H(i, j) = Σ_c (x_c - X_c)[i] ∇N_c[j]
    for (int c = 0; c < 4; ++c) {
      const __m256i node = _mm512_maskz_extracti64x4_epi64(
          0xF,
          _mm512_permutex2var_epi32(t0, _mm512_add_epi32(corner_index, _mm512_set1_epi32(c)), t1),
          0);
      const __m256i node3 = _mm256_add_epi32(node, _mm256_add_epi32(node, node));
      for (int j = 0; j < 3; ++j) {
        grad[c][j] = _mm512_mask_i64gather_pd(zero, 0xFF, twelve, gradients + 3 * c + j, 8);
      }
      for (int i = 0; i < 3; ++i) {
        const __m512d u = _mm512_sub_pd(_mm512_mask_i32gather_pd(zero, 0xFF, node3, a.x + i, 8),
                                        _mm512_mask_i32gather_pd(zero, 0xFF, node3, a.rest + i, 8));
        for (int j = 0; j < 3; ++j) {
          h[i][j] = c == 0 ? _mm512_mul_pd(u, grad[c][j]) : _mm512_fmadd_pd(u, grad[c][j], h[i][j]);
        }
      }
    }
    __m512d fm[9];  // F column-major
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 3; ++i) {
        fm[3 * j + i] = i == j ? _mm512_add_pd(h[i][j], _mm512_set1_pd(1.0)) : h[i][j];
      }
    }
    double* const qb = quaternions + 4 * e0;
    __m512d q[4];
    for (int k = 0; k < 4; ++k) q[k] = _mm512_mask_i64gather_pd(zero, 0xFF, four, qb + k, 8);
    __m512d rm[9];  // R column-major: R(i, k) = rm[3 k + i]
    const __mmask8 left = PolarIterate8(fm, q, rm);
    for (int k = 0; k < 4; ++k) {
      _mm512_mask_i64scatter_pd(qb + k, static_cast<__mmask8>(~left), four, q[k], 8);
    }
    if (left != 0) {
      for (int k = 0; k < 9; ++k) _mm512_store_pd(mbuf[k], fm[k]);
      Matrix3d f[8];
      for (int l = 0; l < 8; ++l) {
        for (int k = 0; k < 9; ++k) f[l](k) = mbuf[k][l];
      }
      for (int k = 0; k < 9; ++k) _mm512_store_pd(mbuf[k], rm[k]);
      for (int l = 0; l < 8; ++l) {
        if (((left >> l) & 1U) == 0) continue;
        const Matrix3d r = PolarRotationFrom(f[l], qb + 4 * l);
        for (int k = 0; k < 9; ++k) mbuf[k][l] = r(k);
      }
      for (int k = 0; k < 9; ++k) rm[k] = _mm512_load_pd(mbuf[k]);
    }
    for (int k = 0; k < 9; ++k) {
      _mm512_mask_i64scatter_pd(rotations + 9 * e0 + k, 0xFF, nine, rm[k], 8);
    }
    // ε = sym((Rᵀ - I) + Rᵀ H) (ElementStress), σ = g (λ tr ε I + 2 μ ε) + offset, P = R σ.
    __m512d st[3][3];  // (Rᵀ - I) + Rᵀ H
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        __m512d v = i == j ? _mm512_sub_pd(rm[3 * i + j], _mm512_set1_pd(1.0)) : rm[3 * i + j];
        for (int k = 0; k < 3; ++k) v = _mm512_fmadd_pd(rm[3 * i + k], h[k][j], v);
        st[i][j] = v;
      }
    }
    const __m512d tr = _mm512_add_pd(st[0][0], _mm512_add_pd(st[1][1], st[2][2]));
    const __m512d lambda_tr = _mm512_mul_pd(lambda, tr);
    __m512d sigma[3][3];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        const __m512d eps = _mm512_mul_pd(half, _mm512_add_pd(st[i][j], st[j][i]));
        __m512d v = i == j ? _mm512_fmadd_pd(two_mu, eps, lambda_tr) : _mm512_mul_pd(two_mu, eps);
        v = _mm512_mul_pd(g, v);
        if (a.offset != nullptr) {  // column-major 9 per element
          v = _mm512_add_pd(
              v, _mm512_mask_i64gather_pd(zero, 0xFF, nine, a.offset + 9 * e0 + 3 * j + i, 8));
        }
        sigma[i][j] = v;
      }
    }
    __m512d p[3][3];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        p[i][j] = _mm512_fmadd_pd(
            rm[6 + i], sigma[2][j],
            _mm512_fmadd_pd(rm[3 + i], sigma[1][j], _mm512_mul_pd(rm[i], sigma[0][j])));
      }
    }
    const __m512d volume = _mm512_loadu_pd(a.volumes + e0);
    const __m512d minus_volume = _mm512_sub_pd(zero, volume);
    // f_c = -V P ∇N_c; r_c = R ∇N_c.
    for (int c = 0; c < 4; ++c) {
      for (int i = 0; i < 3; ++i) {
        const __m512d pg = _mm512_fmadd_pd(
            p[i][2], grad[c][2],
            _mm512_fmadd_pd(p[i][1], grad[c][1], _mm512_mul_pd(p[i][0], grad[c][0])));
        _mm512_store_pd(fbuf[3 * c + i], _mm512_mul_pd(minus_volume, pg));
        const __m512d rg = _mm512_fmadd_pd(
            rm[6 + i], grad[c][2],
            _mm512_fmadd_pd(rm[3 + i], grad[c][1], _mm512_mul_pd(rm[i], grad[c][0])));
        _mm512_store_pd(rbuf[3 * c + i], rg);
      }
    }
    const __m512d v = _mm512_mul_pd(_mm512_mul_pd(k_scale, g), volume);
    _mm512_store_pd(cbuf[0], _mm512_mul_pd(v, lambda));
    _mm512_store_pd(cbuf[1], _mm512_mul_pd(v, mu));
    for (size_t l = 0; l < 8; ++l) {
      const size_t e = e0 + l;
      const int32_t* node = a.tets + 4 * e;
      double r[4][3];
      for (int c = 0; c < 4; ++c) {
        double* out = a.forces + 3 * static_cast<size_t>(node[c]);
        for (int i = 0; i < 3; ++i) {
          out[i] += fbuf[3 * c + i][l];
          r[c][i] = rbuf[3 * c + i][l];
        }
      }
      AddWarpedBlocks(a, e, r, cbuf[0][l], cbuf[1][l]);
    }
  }
  for (size_t e = 8 * groups; e < a.num_tets; ++e) {
    double h[3][3];
    DisplacementGradient(a, e, h);
    Matrix3d f;
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) f(i, j) = h[i][j] + (i == j ? 1.0 : 0.0);
    }
    Eigen::Map<Matrix3d>(rotations + 9 * e) = PolarRotationFrom(f, quaternions + 4 * e);
    double r[4][3], cl, cm;
    ElementForcesAndGradients(a, e, r, &cl, &cm);
    AddWarpedBlocks(a, e, r, cl, cm);
  }
}
#endif

}  // namespace

void FemModel::ForcesAndWarpedMatrix(const Shape& sh, const mesh::Points& x, double* forces,
                                     double* rotations, double* quaternions,
                                     const ViscousStep* viscous, double k_scale, double m_scale,
                                     BlockSparseMatrix* matrix) const {
  assert(kind_ != FemKind::kHyperelastic);
  const auto m = static_cast<size_t>(num_tets());
  std::fill(forces, forces + 3 * static_cast<size_t>(num_nodes()), 0.0);
  matrix->SetZero();
  WarpedPass pass{};
  pass.x = x.data();
  pass.rest = sh.rest.data();
  pass.tets = elements_.tets.data();
  pass.gradients = sh.gradients.data();
  pass.volumes = sh.volumes.data();
  pass.rotations = rotations;
  pass.offset = viscous != nullptr ? viscous->offset : nullptr;
  pass.element_blocks = matrix->element_blocks();
  pass.forces = forces;
  pass.values = matrix->values();
  pass.num_tets = m;
  pass.g = viscous != nullptr ? viscous->g : 1.0;
  pass.lambda = lambda_;
  pass.mu = mu_;
  pass.k_scale = k_scale;
  pass.linear = kind_ == FemKind::kLinear;
  const bool vector = CpuHasAvx512() && !force_scalar_element_pass_;
#ifdef SOMASIM_FEM_HAS_AVX512_PATH
  if (vector && kind_ != FemKind::kLinear) {
    CorotationalPassAvx512(pass, rotations, quaternions);
  } else
#endif
  {
    // The rotations first, in batches (PolarRotations): F of each element into `rotations`,
    // turned into R in place.
    if (kind_ == FemKind::kLinear) {
      for (size_t e = 0; e < m; ++e) Eigen::Map<Matrix3d>(rotations + 9 * e).setIdentity();
    } else {
      DeformationGradients(pass, rotations);
      PolarRotations(rotations, quaternions, rotations, m);
    }
#ifdef SOMASIM_FEM_HAS_AVX512_PATH
    if (vector) {
      ElementPassAvx512(pass);
    } else {
      ElementPass(pass);
    }
#else
    ElementPass(pass);
#endif
  }
  for (int32_t i = 0; i < num_nodes(); ++i) {
    matrix->block(matrix->diagonal_block(i)).diagonal().array() +=
        m_scale * mass_[static_cast<size_t>(i)];
  }
}

}  // namespace somasim::models::fem
