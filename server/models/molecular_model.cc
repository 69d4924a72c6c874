#include "server/models/molecular_model.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <cstddef>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/checks/finite.h"
#include "server/models/cpu_features.h"
#include "server/models/particle_mesh.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_MOLECULAR_AVX512 1
#endif

namespace somasim::models {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

// The state of a molecular model: the base state plus a step's force buffer, sized by MakeState
// so that stepping allocates nothing.
class MolecularState final : public TissueState {
 public:
  mesh::Points forces;  // [N], 3 × num_nodes
};

void Require(bool ok, const char* what) {
  if (!ok) throw std::invalid_argument(std::string("molecular: ") + what);
}

void CheckParameters(const MolecularParameters& p) {
  if (!(p.bond_stiffness > 0.0)) {
    Require(checks::FinitePositive(p.youngs_modulus),
            "youngs_modulus [Pa] must be a finite value > 0");
  }
  if (!(p.node_mass > 0.0)) {
    Require(checks::FinitePositive(p.density), "density [kg/m^3] must be a finite value > 0");
  }
  checks::RequireFiniteNonNegative("molecular", "damping_ratio", p.damping_ratio);
  Require(checks::FinitePositive(p.thickness), "thickness [m] must be a finite value > 0");
  checks::RequireFiniteNonNegative("molecular", "bend_factor", p.bend_factor);
  Require(std::isfinite(p.stretch_bend_factor), "stretch_bend_factor must be finite");
  checks::RequireFiniteNonNegative("molecular", "bond_stiffness [N/m]", p.bond_stiffness);
  checks::RequireFiniteNonNegative("molecular", "angle_stiffness [J]", p.angle_stiffness);
  checks::RequireFiniteNonNegative("molecular", "stretch_bend_stiffness [N]",
                                   p.stretch_bend_stiffness);
  checks::RequireFiniteNonNegative("molecular", "node_mass [kg]", p.node_mass);
  Require(checks::FinitePositive(p.speed_limit), "speed_limit [m/s] must be a finite value > 0");
}

// The geometry of one bond angle: bonds a = x_p - x_c and b = x_q - x_c, their lengths and unit
// vectors, cos θ = a·b / (|a| |b|) and its gradients ∂cos θ/∂a = (b̂ - cos θ â) / |a|, ∂/∂b alike.
struct AngleGeometry {
  Vector3d ua, ub;  // â, b̂
  Vector3d ca, cb;  // ∂cos θ/∂a, ∂cos θ/∂b [1/m]
  double ra = 0.0, rb = 0.0, cos = 0.0;
};

AngleGeometry MakeAngleGeometry(const Vector3d& a, const Vector3d& b) {
  AngleGeometry g;
  g.ra = a.norm();
  g.rb = b.norm();
  const double ia = g.ra > 0.0 ? 1.0 / g.ra : 0.0;
  const double ib = g.rb > 0.0 ? 1.0 / g.rb : 0.0;
  g.ua = ia * a;
  g.ub = ib * b;
  g.cos = g.ua.dot(g.ub);
  g.ca = ia * (g.ub - g.cos * g.ua);
  g.cb = ib * (g.ua - g.cos * g.ub);
  return g;
}

// The coefficients of one angle's energy gradient, seed 002 eq. 9 and 11:
//   Φ = ½ K_θ Δc² + K_bθ Δc S,  Δc = cos θ - cos θ0,  S = (r_a - r_a0) + (r_b - r_b0),
//   ∂Φ/∂a = A ∂cos θ/∂a + B â,  ∂Φ/∂b = A ∂cos θ/∂b + B b̂,
//   A = K_θ Δc + K_bθ S,  B = K_bθ Δc.
struct AngleCoefficients {
  double energy = 0.0, a = 0.0, b = 0.0;
};

AngleCoefficients MakeCoefficients(const AngleGeometry& g, double rest_cos, double rest_a,
                                   double rest_b, double k_angle, double k_stretch_bend) {
  const double dc = g.cos - rest_cos;
  const double s = (g.ra - rest_a) + (g.rb - rest_b);
  return {0.5 * k_angle * dc * dc + k_stretch_bend * dc * s, k_angle * dc + k_stretch_bend * s,
          k_stretch_bend * dc};
}

// One angle's energy, and when `ga`, `gb` are given its gradients ∂Φ/∂a, ∂Φ/∂b [N] (3 each), on
// raw coordinates (3 each) of the corner c and the neighbours p, q: the per-step kernel, in
// plain scalars so that it is fast in unoptimised (sanitizer) builds too. Same formulas as
// MakeAngleGeometry and MakeCoefficients.
double AngleKernel(const double* xc, const double* xp, const double* xq, double rest_cos,
                   double rest_a, double rest_b, double k_angle, double k_stretch_bend, double* ga,
                   double* gb) {
  const double a[3] = {xp[0] - xc[0], xp[1] - xc[1], xp[2] - xc[2]};
  const double b[3] = {xq[0] - xc[0], xq[1] - xc[1], xq[2] - xc[2]};
  const double ra = std::sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
  const double rb = std::sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]);
  const double ia = ra > 0.0 ? 1.0 / ra : 0.0;
  const double ib = rb > 0.0 ? 1.0 / rb : 0.0;
  const double ua[3] = {a[0] * ia, a[1] * ia, a[2] * ia};
  const double ub[3] = {b[0] * ib, b[1] * ib, b[2] * ib};
  const double cos = ua[0] * ub[0] + ua[1] * ub[1] + ua[2] * ub[2];
  const double dc = cos - rest_cos;
  const double stretch = (ra - rest_a) + (rb - rest_b);
  if (ga != nullptr && gb != nullptr) {
    const double coeff_a = k_angle * dc + k_stretch_bend * stretch;  // A
    const double coeff_b = k_stretch_bend * dc;                      // B
    for (int k = 0; k < 3; ++k) {
      ga[k] = coeff_a * ia * (ub[k] - cos * ua[k]) + coeff_b * ua[k];
      gb[k] = coeff_a * ib * (ua[k] - cos * ub[k]) + coeff_b * ub[k];
    }
  }
  return 0.5 * k_angle * dc * dc + k_stretch_bend * dc * stretch;
}

// Hessian blocks of one angle's energy with respect to the bond vectors a and b, by
// differentiating ∂Φ/∂a above once more (P_a = I - â âᵀ):
//   ∂²cos θ/∂a² = -(â c_aᵀ + c_a âᵀ)/r_a - cos θ P_a/r_a²,  ∂²cos θ/∂a∂b = (P_b/r_b - â c_bᵀ)/r_a,
//   H_aa = K_θ c_a c_aᵀ + K_bθ (c_a âᵀ + â c_aᵀ) + A ∂²cos θ/∂a² + B P_a/r_a,
//   H_ab = K_θ c_a c_bᵀ + K_bθ (c_a b̂ᵀ + â c_bᵀ) + A ∂²cos θ/∂a∂b,  H_ba = H_abᵀ.
void AngleHessian(const AngleGeometry& g, const AngleCoefficients& c, double k_angle,
                  double k_stretch_bend, Matrix3d* h_aa, Matrix3d* h_bb, Matrix3d* h_ab) {
  const Matrix3d identity = Matrix3d::Identity();
  const Matrix3d pa = identity - g.ua * g.ua.transpose();
  const Matrix3d pb = identity - g.ub * g.ub.transpose();
  const double ia = 1.0 / g.ra, ib = 1.0 / g.rb;
  const Matrix3d caa =
      -ia * (g.ua * g.ca.transpose() + g.ca * g.ua.transpose()) - (g.cos * ia * ia) * pa;
  const Matrix3d cbb =
      -ib * (g.ub * g.cb.transpose() + g.cb * g.ub.transpose()) - (g.cos * ib * ib) * pb;
  const Matrix3d cab = ia * (ib * pb - g.ua * g.cb.transpose());
  *h_aa = k_angle * g.ca * g.ca.transpose() +
          k_stretch_bend * (g.ca * g.ua.transpose() + g.ua * g.ca.transpose()) + c.a * caa +
          (c.b * ia) * pa;
  *h_bb = k_angle * g.cb * g.cb.transpose() +
          k_stretch_bend * (g.cb * g.ub.transpose() + g.ub * g.cb.transpose()) + c.a * cbb +
          (c.b * ib) * pb;
  *h_ab = k_angle * g.ca * g.cb.transpose() +
          k_stretch_bend * (g.ca * g.ub.transpose() + g.ua * g.cb.transpose()) + c.a * cab;
}

// The per-step triangle kernel (see the header). A triangle (n0, n1, n2) has edges
// E_k = x_{n(k+1)} - x_{nk} (k = 0, 1, 2, indices mod 3), each with length r_k, unit vector u_k,
// stretch δ_k = r_k - r0_k; its energy is, seed 002 eq. 6, 9, 11,
//   Φ_t = Σ_k ½ K'_k δ_k²  +  Σ_corners k [½ K_θ Δc_k² + K_bθ Δc_k (δ_k + δ_{k+2})],
// with K'_k the bond's K_b shared evenly among its triangles, and the corner angle at n_k between
// a = E_k and b = -E_{k+2}: cos θ_k = -u_k·u_{k+2}, Δc_k = cos θ_k - cos θ0_k. Its gradient with
// respect to each edge vector is a combination of the three unit vectors,
//   ∂Φ_t/∂E_k = G_k = Σ_m α_km u_m,
// built from the corner formulas of AngleKernel (A = K_θ Δc + K_bθ S, B = K_bθ Δc):
//   ∂Φ/∂a = (B - A cos θ / r_a) u_a + (A / r_a) u_b, ∂Φ/∂b = (A / r_b) u_a + (B - A cos θ / r_b)
//   u_b,
// plus the bond's K'_k δ_k and its damping D'_k (v_{k+1} - v_k)·u_k on α_kk (seed 002 eq. 8). As
// Φ depends on x only through the edges, the forces are f_{nk} = G_k - G_{k+2}.
constexpr size_t kBlock = 8;  // triangles per block (the AVX-512 width in doubles)
enum TriangleField : size_t {
  kBondK = 0,          // 3 fields, one per edge k: K'_k [N/m]
  kBondDamping = 3,    // D'_k [N s/m]
  kRestLength = 6,     // r0_k [m]
  kRestCos = 9,        // 3 fields, one per corner k: cos θ0_k [-]
  kAngleK = 12,        // K_θ [J]
  kStretchBendK = 15,  // K_bθ [N]
  kTriangleFields = 18,
};

// Multipliers (1 or 0) of the terms a force evaluation includes.
struct TermScale {
  double bond = 1.0, angle = 1.0, stretch_bend = 1.0;
};

TermScale ScaleOf(uint32_t terms) {
  return {(terms & MolecularModel::kBond) != 0 ? 1.0 : 0.0,
          (terms & MolecularModel::kAngle) != 0 ? 1.0 : 0.0,
          (terms & MolecularModel::kStretchBend) != 0 ? 1.0 : 0.0};
}

// Triangle `lane` of a block: `nodes` its 3 · kBlock coordinate offsets, `c` its kTriangleFields ·
// kBlock constants. Adds the triangle's forces [N] to f.
void ScalarTriangle(const double* x, const double* v, double* f, const int32_t* nodes,
                    const double* c, size_t lane, const TermScale& scale) {
  size_t at[3];
  for (size_t k = 0; k < 3; ++k) at[k] = static_cast<size_t>(nodes[k * kBlock + lane]);
  double u[3][3], inverse[3], stretch[3], alpha[3][3] = {};
  for (size_t k = 0; k < 3; ++k) {
    const size_t i = at[k], j = at[(k + 1) % 3];
    const double d[3] = {x[j] - x[i], x[j + 1] - x[i + 1], x[j + 2] - x[i + 2]};
    const double r = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    inverse[k] = r > 0.0 ? 1.0 / r : 0.0;
    double closing = 0.0;
    for (size_t e = 0; e < 3; ++e) {
      u[k][e] = d[e] * inverse[k];
      closing += (v[j + e] - v[i + e]) * u[k][e];
    }
    stretch[k] = r - c[(kRestLength + k) * kBlock + lane];
    alpha[k][k] = scale.bond * (c[(kBondK + k) * kBlock + lane] * stretch[k] +
                                c[(kBondDamping + k) * kBlock + lane] * closing);
  }
  for (size_t k = 0; k < 3; ++k) {
    const size_t m = (k + 2) % 3;  // a = E_k, b = -E_m
    const double cos = -(u[k][0] * u[m][0] + u[k][1] * u[m][1] + u[k][2] * u[m][2]);
    const double dc = cos - c[(kRestCos + k) * kBlock + lane];
    const double k_angle = scale.angle * c[(kAngleK + k) * kBlock + lane];
    const double k_stretch_bend = scale.stretch_bend * c[(kStretchBendK + k) * kBlock + lane];
    const double coeff_a = k_angle * dc + k_stretch_bend * (stretch[k] + stretch[m]);  // A
    const double coeff_b = k_stretch_bend * dc;                                        // B
    const double aa = coeff_a * inverse[k], ab = coeff_a * inverse[m];
    alpha[k][k] += coeff_b - aa * cos;
    alpha[k][m] -= aa;
    alpha[m][k] -= ab;
    alpha[m][m] += coeff_b - ab * cos;
  }
  double g[3][3];  // G_k [N]
  for (size_t k = 0; k < 3; ++k) {
    for (size_t e = 0; e < 3; ++e) {
      g[k][e] = alpha[k][0] * u[0][e] + alpha[k][1] * u[1][e] + alpha[k][2] * u[2][e];
    }
  }
  for (size_t k = 0; k < 3; ++k) {
    for (size_t e = 0; e < 3; ++e) f[at[k] + e] += g[k][e] - g[(k + 2) % 3][e];
  }
}

#ifdef SOMASIM_MOLECULAR_AVX512
// The same for whole blocks, 8 triangles per vector (AVX-512); the forces of a block are then
// added to the nodes in the scalar kernel's order.
__attribute__((target("avx512f"))) void VectorTriangles(const double* x, const double* v, double* f,
                                                        const int32_t* nodes,
                                                        const double* constants, size_t num_blocks,
                                                        const TermScale& scale) {
  const __m512d zero = _mm512_setzero_pd();
  const __m512d half = _mm512_set1_pd(0.5);
  const __m512d three_halves = _mm512_set1_pd(1.5);
  const __mmask8 all = 0xFF;  // masked gathers with a defined source (no GCC 12 false warning)
  const __m512d scale_bond = _mm512_set1_pd(scale.bond);
  const __m512d scale_angle = _mm512_set1_pd(scale.angle);
  const __m512d scale_stretch_bend = _mm512_set1_pd(scale.stretch_bend);
  alignas(64) double out[9][kBlock];
  for (size_t block = 0; block < num_blocks; ++block) {
    const int32_t* nb = nodes + 3 * kBlock * block;
    const double* c = constants + kTriangleFields * kBlock * block;
    __m256i index[3];
    __m512d px[3][3], pv[3][3];
    for (size_t k = 0; k < 3; ++k) {
      index[k] = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(nb + k * kBlock));
      for (size_t e = 0; e < 3; ++e) {
        px[k][e] = _mm512_mask_i32gather_pd(zero, all, index[k], x + e, 8);
        pv[k][e] = _mm512_mask_i32gather_pd(zero, all, index[k], v + e, 8);
      }
    }
    __m512d u[3][3], inverse[3], stretch[3], alpha[3][3];
    for (size_t k = 0; k < 3; ++k) {
      const size_t j = (k + 1) % 3;
      const __m512d d0 = px[j][0] - px[k][0], d1 = px[j][1] - px[k][1], d2 = px[j][2] - px[k][2];
      // 1/r by the 14-bit estimate and two Newton steps y ← y (3/2 - ½ r² y²) (14 → 28 → 56
      // bits: within a few ulp, far cheaper than a vector square root and division); 0 at r = 0.
      const __m512d r2 = d0 * d0 + d1 * d1 + d2 * d2;
      const __m512d half_r2 = half * r2;
      __m512d y = _mm512_maskz_rsqrt14_pd(_mm512_cmp_pd_mask(r2, zero, _CMP_GT_OQ), r2);
      y = y * (three_halves - half_r2 * y * y);
      y = y * (three_halves - half_r2 * y * y);
      inverse[k] = y;
      const __m512d r = r2 * y;
      u[k][0] = d0 * inverse[k];
      u[k][1] = d1 * inverse[k];
      u[k][2] = d2 * inverse[k];
      const __m512d closing = (pv[j][0] - pv[k][0]) * u[k][0] + (pv[j][1] - pv[k][1]) * u[k][1] +
                              (pv[j][2] - pv[k][2]) * u[k][2];
      stretch[k] = r - _mm512_loadu_pd(c + (kRestLength + k) * kBlock);
      alpha[k][k] = scale_bond * (_mm512_loadu_pd(c + (kBondK + k) * kBlock) * stretch[k] +
                                  _mm512_loadu_pd(c + (kBondDamping + k) * kBlock) * closing);
      alpha[k][(k + 1) % 3] = zero;
      alpha[k][(k + 2) % 3] = zero;
    }
    for (size_t k = 0; k < 3; ++k) {
      const size_t m = (k + 2) % 3;
      const __m512d cos = zero - (u[k][0] * u[m][0] + u[k][1] * u[m][1] + u[k][2] * u[m][2]);
      const __m512d dc = cos - _mm512_loadu_pd(c + (kRestCos + k) * kBlock);
      const __m512d k_angle = scale_angle * _mm512_loadu_pd(c + (kAngleK + k) * kBlock);
      const __m512d k_stretch_bend =
          scale_stretch_bend * _mm512_loadu_pd(c + (kStretchBendK + k) * kBlock);
      const __m512d coeff_a = k_angle * dc + k_stretch_bend * (stretch[k] + stretch[m]);
      const __m512d coeff_b = k_stretch_bend * dc;
      const __m512d aa = coeff_a * inverse[k], ab = coeff_a * inverse[m];
      alpha[k][k] += coeff_b - aa * cos;
      alpha[k][m] -= aa;
      alpha[m][k] -= ab;
      alpha[m][m] += coeff_b - ab * cos;
    }
    __m512d g[3][3];
    for (size_t k = 0; k < 3; ++k) {
      for (size_t e = 0; e < 3; ++e) {
        g[k][e] = alpha[k][0] * u[0][e] + alpha[k][1] * u[1][e] + alpha[k][2] * u[2][e];
      }
    }
    for (size_t k = 0; k < 3; ++k) {
      for (size_t e = 0; e < 3; ++e) _mm512_store_pd(out[3 * k + e], g[k][e] - g[(k + 2) % 3][e]);
    }
    for (size_t lane = 0; lane < kBlock; ++lane) {
      for (size_t k = 0; k < 3; ++k) {
        double* fk = f + nb[k * kBlock + lane];
        for (size_t e = 0; e < 3; ++e) fk[e] += out[3 * k + e][lane];
      }
    }
  }
}

#endif

// Fills a CSR (num_nodes + 1 starts, then items) of the items touching each node; `nodes_of`
// lists, for item k, the nodes it touches.
template <int kNodes, typename NodesOf>
void BuildIncidence(size_t num_nodes, size_t num_items, NodesOf nodes_of,
                    std::vector<int32_t>* start, std::vector<int32_t>* items) {
  start->assign(num_nodes + 1, 0);
  for (size_t k = 0; k < num_items; ++k) {
    for (const int32_t node : nodes_of(k)) ++(*start)[static_cast<size_t>(node) + 1];
  }
  for (size_t i = 0; i < num_nodes; ++i) (*start)[i + 1] += (*start)[i];
  items->resize(kNodes * num_items);
  std::vector<int32_t> fill(start->begin(), start->end() - 1);
  for (size_t k = 0; k < num_items; ++k) {
    for (const int32_t node : nodes_of(k)) {
      (*items)[static_cast<size_t>(fill[static_cast<size_t>(node)]++)] = static_cast<int32_t>(k);
    }
  }
}

}  // namespace

std::unique_ptr<MolecularModel> MolecularModel::FromSurface(const mesh::SurfaceMesh& surface,
                                                            const MolecularParameters& p) {
  CheckParameters(p);
  const mesh::Points& x = surface.vertices;
  const Eigen::Index n = x.cols();
  // Unique edges (bonds), each with the shell volume Σ area · thickness of its triangles, and the
  // shell volume lumped on the nodes, a third per corner.
  const MeshEdges mesh_edges = SurfaceEdges(surface, p.thickness, "molecular");
  const std::vector<std::array<int32_t, 2>>& edges = mesh_edges.edges;
  const std::vector<double>& edge_size = mesh_edges.edge_size;
  const std::vector<double>& node_size = mesh_edges.node_size;

  std::unique_ptr<MolecularModel> model(new MolecularModel());
  MolecularModel& m = *model;
  m.rest_ = x;
  const auto nn = static_cast<size_t>(n);
  m.mass_.resize(nn);
  m.inverse_mass_.resize(nn);
  for (size_t i = 0; i < nn; ++i) {
    m.mass_[i] = p.node_mass > 0.0 ? p.node_mass : p.density * node_size[i];
    // A node no triangle with area touches has no mass: it cannot move (inverse mass 0).
    m.inverse_mass_[i] = m.mass_[i] > 0.0 ? 1.0 / m.mass_[i] : 0.0;
  }

  // Bonds: seed 002 eq. 6 with K_b by Van Gelder's rule, damping along the bond.
  const size_t num_bonds = edges.size();
  m.bond_i_.resize(num_bonds);
  m.bond_j_.resize(num_bonds);
  m.bond_rest_.resize(num_bonds);
  m.bond_k_.resize(num_bonds);
  m.bond_damping_.resize(num_bonds);
  for (size_t s = 0; s < num_bonds; ++s) {
    const auto [i, j] = edges[s];
    const double length = (x.col(j) - x.col(i)).norm();
    if (!(length > 0.0)) {
      throw std::invalid_argument("molecular: nodes " + std::to_string(i) + " and " +
                                  std::to_string(j) + " coincide (a zero-length bond)");
    }
    m.bond_i_[s] = i;
    m.bond_j_[s] = j;
    m.bond_rest_[s] = length;
    m.bond_k_[s] = p.bond_stiffness > 0.0 ? p.bond_stiffness
                                          : p.youngs_modulus * edge_size[s] / (length * length);
    const double mi = m.mass_[static_cast<size_t>(i)];
    const double mj = m.mass_[static_cast<size_t>(j)];
    const double reduced = mi + mj > 0.0 ? mi * mj / (mi + mj) : 0.0;
    m.bond_damping_[s] = 2.0 * p.damping_ratio * std::sqrt(m.bond_k_[s] * reduced);
  }
  const auto bond_of = [&edges](int32_t i, int32_t j) {
    const std::array<int32_t, 2> key = {std::min(i, j), std::max(i, j)};
    return static_cast<size_t>(std::lower_bound(edges.begin(), edges.end(), key) - edges.begin());
  };

  // Angles: one per triangle corner (seed 002 Fig. 3), seed 002 eq. 9 and 11.
  const size_t num_angles = 3 * static_cast<size_t>(surface.triangles.cols());
  for (std::vector<int32_t>* v : {&m.angle_corner_, &m.angle_p_, &m.angle_q_}) {
    v->resize(num_angles);
  }
  for (std::vector<double>* v :
       {&m.angle_rest_cos_, &m.angle_rest_a_, &m.angle_rest_b_, &m.angle_k_, &m.stretch_bend_k_}) {
    v->resize(num_angles);
  }
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    for (int k = 0; k < 3; ++k) {
      const auto angle = 3 * static_cast<size_t>(t) + static_cast<size_t>(k);
      const int32_t c = surface.triangles(k, t);
      const int32_t pa = surface.triangles((k + 1) % 3, t);
      const int32_t pb = surface.triangles((k + 2) % 3, t);
      const AngleGeometry g = MakeAngleGeometry(x.col(pa) - x.col(c), x.col(pb) - x.col(c));
      m.angle_corner_[angle] = c;
      m.angle_p_[angle] = pa;
      m.angle_q_[angle] = pb;
      m.angle_rest_cos_[angle] = g.cos;
      m.angle_rest_a_[angle] = g.ra;
      m.angle_rest_b_[angle] = g.rb;
      const double ka = m.bond_k_[bond_of(c, pa)];
      const double kb = m.bond_k_[bond_of(c, pb)];
      m.angle_k_[angle] = p.angle_stiffness > 0.0
                              ? p.angle_stiffness
                              : p.bend_factor * 0.5 * (ka * g.ra * g.ra + kb * g.rb * g.rb);
      m.stretch_bend_k_[angle] = p.stretch_bend_stiffness > 0.0
                                     ? p.stretch_bend_stiffness
                                     : p.stretch_bend_factor * 0.5 * (ka * g.ra + kb * g.rb);
    }
  }

  // The per-step kernel's triangle blocks (see the header and ScalarTriangle): each edge gets
  // its bond's K_b and D divided by the number of triangles sharing the bond.
  const auto num_triangles = static_cast<size_t>(surface.triangles.cols());
  if (n > std::numeric_limits<int32_t>::max() / 3) {
    throw std::invalid_argument("molecular: too many nodes");
  }
  std::vector<int32_t> triangles_of_bond(num_bonds, 0);
  for (size_t t = 0; t < num_triangles; ++t) {
    for (Eigen::Index k = 0; k < 3; ++k) {
      const auto column = static_cast<Eigen::Index>(t);
      ++triangles_of_bond[bond_of(surface.triangles(k, column),
                                  surface.triangles((k + 1) % 3, column))];
    }
  }
  const size_t num_blocks = (num_triangles + kBlock - 1) / kBlock;
  m.num_triangles_ = static_cast<int32_t>(num_triangles);
  m.tri_nodes_.assign(num_blocks * 3 * kBlock, 0);
  m.tri_constants_.assign(num_blocks * kTriangleFields * kBlock, 0.0);
  for (size_t t = 0; t < num_triangles; ++t) {
    const size_t lane = t % kBlock;
    int32_t* nodes = m.tri_nodes_.data() + 3 * kBlock * (t / kBlock);
    double* c = m.tri_constants_.data() + kTriangleFields * kBlock * (t / kBlock);
    for (size_t k = 0; k < 3; ++k) {
      const auto column = static_cast<Eigen::Index>(t);
      const int32_t node = surface.triangles(static_cast<Eigen::Index>(k), column);
      const int32_t next = surface.triangles(static_cast<Eigen::Index>((k + 1) % 3), column);
      nodes[k * kBlock + lane] = 3 * node;
      const size_t s = bond_of(node, next);
      const double share = 1.0 / static_cast<double>(triangles_of_bond[s]);
      c[(kBondK + k) * kBlock + lane] = m.bond_k_[s] * share;
      c[(kBondDamping + k) * kBlock + lane] = m.bond_damping_[s] * share;
      c[(kRestLength + k) * kBlock + lane] = m.bond_rest_[s];
      const size_t angle = 3 * t + k;  // the corner angle at `node`
      c[(kRestCos + k) * kBlock + lane] = m.angle_rest_cos_[angle];
      c[(kAngleK + k) * kBlock + lane] = m.angle_k_[angle];
      c[(kStretchBendK + k) * kBlock + lane] = m.stretch_bend_k_[angle];
    }
  }

  BuildIncidence<2>(
      nn, num_bonds,
      [&m](size_t s) {
        return std::array<int32_t, 2>{m.bond_i_[s], m.bond_j_[s]};
      },
      &m.node_bond_start_, &m.node_bonds_);
  BuildIncidence<3>(
      nn, num_angles,
      [&m](size_t a) {
        return std::array<int32_t, 3>{m.angle_corner_[a], m.angle_p_[a], m.angle_q_[a]};
      },
      &m.node_angle_start_, &m.node_angles_);
  m.set_speed_limit(p.speed_limit);
  return model;
}

std::unique_ptr<TissueState> MolecularModel::MakeState() const {
  auto state = std::make_unique<MolecularState>();
  InitialiseState(rest_, state.get());
  state->forces = mesh::Points::Zero(3, rest_.cols());
  return state;
}

void MolecularModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  TermForces(state, kAllTerms, forces);
}

void MolecularModel::TermForces(const TissueState& state, uint32_t terms,
                                mesh::Points* forces) const {
  KernelTermForces(state, terms, true, forces);
}

bool MolecularModel::HasVectorKernel() {
#ifdef SOMASIM_MOLECULAR_AVX512
  return CpuHasAvx512();
#else
  return false;
#endif
}

void MolecularModel::KernelTermForces(const TissueState& state, uint32_t terms,
                                      [[maybe_unused]] bool simd, mesh::Points* forces) const {
  forces->resize(3, rest_.cols());  // a no-op (no allocation) when already sized
  forces->setZero();
  const double* x = state.positions.data();
  const double* v = state.velocities.data();
  double* f = forces->data();
  const TermScale scale = ScaleOf(terms);
  const auto num_triangles = static_cast<size_t>(num_triangles_);
  size_t done = 0;
#ifdef SOMASIM_MOLECULAR_AVX512
  if (simd && CpuHasAvx512()) {
    const size_t full_blocks = num_triangles / kBlock;
    VectorTriangles(x, v, f, tri_nodes_.data(), tri_constants_.data(), full_blocks, scale);
    done = full_blocks * kBlock;
  }
#endif
  for (size_t t = done; t < num_triangles; ++t) {
    const size_t block = t / kBlock;
    ScalarTriangle(x, v, f, tri_nodes_.data() + 3 * kBlock * block,
                   tri_constants_.data() + kTriangleFields * kBlock * block, t % kBlock, scale);
  }
}

void MolecularModel::ReferenceTermForces(const TissueState& state, uint32_t terms,
                                         mesh::Points* forces) const {
  forces->resize(3, rest_.cols());  // a no-op (no allocation) when already sized
  forces->setZero();
  const double* x = state.positions.data();
  const double* v = state.velocities.data();
  double* f = forces->data();
  if ((terms & kBond) != 0) {
    // Seed 002 eq. 8 and the bond damping: f_i += [K_b (r - r0) + D (v_j - v_i)·u] u, f_j -= …,
    // u = (x_j - x_i) / r.
    for (size_t s = 0; s < bond_i_.size(); ++s) {
      const size_t i = 3 * static_cast<size_t>(bond_i_[s]);
      const size_t j = 3 * static_cast<size_t>(bond_j_[s]);
      const double d[3] = {x[j] - x[i], x[j + 1] - x[i + 1], x[j + 2] - x[i + 2]};
      const double r = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
      const double inverse = r > 0.0 ? 1.0 / r : 0.0;
      double closing = 0.0;
      for (size_t k = 0; k < 3; ++k) closing += (v[j + k] - v[i + k]) * d[k] * inverse;
      const double magnitude =
          (bond_k_[s] * (r - bond_rest_[s]) + bond_damping_[s] * closing) * inverse;
      for (size_t k = 0; k < 3; ++k) {
        f[i + k] += magnitude * d[k];
        f[j + k] -= magnitude * d[k];
      }
    }
  }
  if ((terms & (kAngle | kStretchBend)) != 0) {
    // Seed 002 eq. 7, 9–11: f = -∇Φ exactly; f_p = -∂Φ/∂a, f_q = -∂Φ/∂b, f_c = -(f_p + f_q).
    const bool angle = (terms & kAngle) != 0;
    const bool stretch_bend = (terms & kStretchBend) != 0;
    for (size_t k = 0; k < angle_corner_.size(); ++k) {
      const size_t c = 3 * static_cast<size_t>(angle_corner_[k]);
      const size_t pa = 3 * static_cast<size_t>(angle_p_[k]);
      const size_t pb = 3 * static_cast<size_t>(angle_q_[k]);
      double ga[3], gb[3];
      AngleKernel(x + c, x + pa, x + pb, angle_rest_cos_[k], angle_rest_a_[k], angle_rest_b_[k],
                  angle ? angle_k_[k] : 0.0, stretch_bend ? stretch_bend_k_[k] : 0.0, ga, gb);
      for (size_t e = 0; e < 3; ++e) {
        f[pa + e] -= ga[e];
        f[pb + e] -= gb[e];
        f[c + e] += ga[e] + gb[e];
      }
    }
  }
}

double MolecularModel::TermEnergy(const TissueState& state, uint32_t terms) const {
  const double* x = state.positions.data();
  double energy = 0.0;
  if ((terms & kBond) != 0) {
    for (size_t s = 0; s < bond_i_.size(); ++s) {  // seed 002 eq. 6
      const size_t i = 3 * static_cast<size_t>(bond_i_[s]);
      const size_t j = 3 * static_cast<size_t>(bond_j_[s]);
      const double d[3] = {x[j] - x[i], x[j + 1] - x[i + 1], x[j + 2] - x[i + 2]};
      const double stretch = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) - bond_rest_[s];
      energy += 0.5 * bond_k_[s] * stretch * stretch;
    }
  }
  if ((terms & (kAngle | kStretchBend)) != 0) {
    const bool angle = (terms & kAngle) != 0;
    const bool stretch_bend = (terms & kStretchBend) != 0;
    for (size_t k = 0; k < angle_corner_.size(); ++k) {  // seed 002 eq. 9 and 11
      energy += AngleKernel(x + 3 * static_cast<size_t>(angle_corner_[k]),
                            x + 3 * static_cast<size_t>(angle_p_[k]),
                            x + 3 * static_cast<size_t>(angle_q_[k]), angle_rest_cos_[k],
                            angle_rest_a_[k], angle_rest_b_[k], angle ? angle_k_[k] : 0.0,
                            stretch_bend ? stretch_bend_k_[k] : 0.0, nullptr, nullptr);
    }
  }
  return energy;
}

Eigen::Matrix3d MolecularModel::LocalStiffness(const TissueState& state, int32_t node) const {
  return TermLocalStiffness(state, node, kAllTerms);
}

Eigen::Matrix3d MolecularModel::TermLocalStiffness(const TissueState& state, int32_t node,
                                                   uint32_t terms) const {
  assert(node >= 0 && node < num_nodes());
  const mesh::Points& x = state.positions;
  const auto n = static_cast<size_t>(node);
  Matrix3d k_local = Matrix3d::Zero();
  if ((terms & kBond) != 0) {
    // Each bond: K_b [u uᵀ + (1 - r0/r)(I - u uᵀ)].
    for (int32_t e = node_bond_start_[n]; e < node_bond_start_[n + 1]; ++e) {
      const auto s = static_cast<size_t>(node_bonds_[static_cast<size_t>(e)]);
      const Vector3d d = x.col(bond_j_[s]) - x.col(bond_i_[s]);
      const double r = d.norm();
      if (!(r > 0.0)) continue;
      const Vector3d u = d / r;
      const Matrix3d uu = u * u.transpose();
      k_local += bond_k_[s] * (uu + (1.0 - bond_rest_[s] / r) * (Matrix3d::Identity() - uu));
    }
  }
  if ((terms & (kAngle | kStretchBend)) != 0) {
    // Each angle: the node's diagonal block of ∂²Φ/∂x², from the blocks in a and b. As
    // a = x_p - x_c and b = x_q - x_c: p gets H_aa, q gets H_bb, c gets H_aa + H_bb + H_ab + H_ba.
    const bool angle = (terms & kAngle) != 0;
    const bool stretch_bend = (terms & kStretchBend) != 0;
    for (int32_t e = node_angle_start_[n]; e < node_angle_start_[n + 1]; ++e) {
      const auto k = static_cast<size_t>(node_angles_[static_cast<size_t>(e)]);
      const int32_t c = angle_corner_[k], pa = angle_p_[k], pb = angle_q_[k];
      const AngleGeometry g = MakeAngleGeometry(x.col(pa) - x.col(c), x.col(pb) - x.col(c));
      if (!(g.ra > 0.0) || !(g.rb > 0.0)) continue;
      const double ka = angle ? angle_k_[k] : 0.0;
      const double ksb = stretch_bend ? stretch_bend_k_[k] : 0.0;
      const AngleCoefficients co =
          MakeCoefficients(g, angle_rest_cos_[k], angle_rest_a_[k], angle_rest_b_[k], ka, ksb);
      Matrix3d h_aa, h_bb, h_ab;
      AngleHessian(g, co, ka, ksb, &h_aa, &h_bb, &h_ab);
      if (node == c) {
        k_local += h_aa + h_bb + h_ab + h_ab.transpose();
      } else if (node == pa) {
        k_local += h_aa;
      } else {
        k_local += h_bb;
      }
    }
  }
  return k_local;
}

EnergyReport MolecularModel::Energy(const TissueState& state,
                                    const Eigen::Vector3d& gravity) const {
  EnergyReport report;
  report.elastic = TermEnergy(state, kAllTerms);
  const double* x = state.positions.data();
  const double* v = state.velocities.data();
  double momentum[3] = {0.0, 0.0, 0.0};
  for (size_t i = 0; i < mass_.size(); ++i) {
    const double m = mass_[i];
    for (int k = 0; k < 3; ++k) {
      const size_t at = 3 * i + static_cast<size_t>(k);
      report.kinetic += 0.5 * m * v[at] * v[at];
      report.gravity -= m * gravity[k] * x[at];
      momentum[k] += m * v[at];
    }
  }
  report.momentum = Vector3d(momentum[0], momentum[1], momentum[2]);
  return report;
}

void MolecularModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<MolecularState*>(base);
  InternalForces(*state, &state->forces);
  if (inputs.external_forces != nullptr) state->forces += *inputs.external_forces;
  for (const Attachment& a : inputs.attachments) {
    state->forces.col(a.node) += a.stiffness * (a.target - state->positions.col(a.node));
  }
  // Symplectic Euler (seed 002 §2.2, "açık-kapalı Euler", as eq. 4–5) with gravity:
  // v += dt (f/m + g), then x += dt v. Massless nodes (inverse mass 0) do not move.
  const double dt = inputs.dt;
  const double g[3] = {inputs.gravity.x(), inputs.gravity.y(), inputs.gravity.z()};
  const double* f = state->forces.data();
  double* x = state->positions.data();
  double* v = state->velocities.data();
  for (size_t i = 0; i < inverse_mass_.size(); ++i) {
    const double w = inverse_mass_[i];
    if (!(w > 0.0)) continue;
    for (size_t k = 0; k < 3; ++k) {
      v[3 * i + k] += dt * (w * f[3 * i + k] + g[k]);
      x[3 * i + k] += dt * v[3 * i + k];
    }
  }
  ApplyFixedAndPrescribed(inputs, state);
}

}  // namespace somasim::models
