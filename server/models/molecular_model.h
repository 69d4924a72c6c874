// Molecular modelling system (MMS), seed 002 §2.2 eq. 6–11 (SPEC §4.2): the nodes of a triangle
// surface are atoms, its unique edges are bonds, and each triangle corner is a bond angle between
// the two edges that meet there. Three energies (seed 002, after Sekercioglu & Duysak 2009):
//   bond          ½ K_b (r - r0)²                                    (eq. 6)
//   angle         ½ K_θ (cos θ - cos θ0)²                            (eq. 9)
//   stretch–bend  K_bθ (cos θ - cos θ0) [(r_a - r_a0) + (r_b - r_b0)] (eq. 11, with SPEC's K_bθ)
// Forces are the exact negative gradients f = -∇Φ (eq. 7), derived analytically; the seed's
// approximations of their directions (eq. 8, 10: along the bond, along the opposite edge) are not
// used. Damping acts along the bonds only, as in the mass-spring model, so rigid motion is
// undamped. Symplectic Euler as in the seed ("açık-kapalı Euler"). Pure kernel.
//
// Speed: the per-step forces come from one pass over the triangles, each evaluating its three
// edges once (length, unit vector, stretch, damping) and reusing them for its three angles; a
// bond's stretch term is shared among its triangles (K_b and D split evenly), so the sum is the
// same energy. Per-triangle constants sit in blocks of 8 triangles (structure of arrays), and on
// CPUs with AVX-512 a vector kernel evaluates 8 triangles at once; forces are then added to the
// nodes in triangle order, so results are deterministic for a given machine.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/tissue_model.h"

namespace somasim::models {

// The material, given physically and mapped to the force field by documented rules
// (docs/models.md):
//  - bond stiffness K_b = E · Σ_{triangles ∋ bond} area · thickness / r0² (Van Gelder 1998, as
//    the mass-spring model), lumped masses ρ · area · thickness / 3 per corner;
//  - angle stiffness of the angle between bonds a and b: K_θ = bend_factor · ½ (K_a r_a0² +
//    K_b r_b0²) [J], i.e. a fraction of the bond energy scale of its two bonds;
//  - stretch–bend coupling K_bθ = stretch_bend_factor · ½ (K_a r_a0 + K_b r_b0) [N];
//  - bond damping D = 2 ζ √(K_b m_reduced), m_reduced = m_i m_j / (m_i + m_j).
// The rest shape is an energy minimum when K_bθ² is small against K_θ K_b; with the factors
// below that holds with a wide margin (stretch_bend_factor² = 4e-4 ≪ bend_factor = 0.1).
struct MolecularParameters {
  double youngs_modulus = 0.0;  // E [Pa], > 0 (unless bond_stiffness is given)
  double density = 1000.0;      // ρ [kg/m³], > 0 (unless node_mass is given)
  double damping_ratio = 0.05;  // ζ [-], >= 0: fraction of each bond's critical damping
  double thickness = 0.005;     // [m], > 0: shell thickness of the surface
  double bend_factor = 0.1;     // [-], >= 0: K_θ relative to K_b r0² (unless angle_stiffness)
  double stretch_bend_factor = 0.02;  // [-], finite: K_bθ relative to K_b r0 (any sign)
  // Raw constants, when > 0, replace the physical rules: every bond gets bond_stiffness [N/m],
  // every angle angle_stiffness [J] and stretch_bend_stiffness [N], every node node_mass [kg].
  double bond_stiffness = 0.0;
  double angle_stiffness = 0.0;
  double stretch_bend_stiffness = 0.0;
  double node_mass = 0.0;
  double speed_limit = 100.0;  // [m/s], > 0: a faster node marks a diverged step
};

class MolecularModel final : public TissueModel {
 public:
  // Which terms of the energy InternalForces, LocalStiffness and Energy include (all by default);
  // tests switch single terms on to check each one's gradient.
  enum Term : uint32_t { kBond = 1, kAngle = 2, kStretchBend = 4, kAllTerms = 7 };

  // Throws std::invalid_argument naming the bad parameter or mesh fault (no triangles, NaN
  // coordinates, index out of range, a zero-length bond).
  static std::unique_ptr<MolecularModel> FromSurface(const mesh::SurfaceMesh& surface,
                                                     const MolecularParameters& parameters);

  int32_t num_nodes() const override { return static_cast<int32_t>(mass_.size()); }
  int32_t num_bonds() const { return static_cast<int32_t>(bond_i_.size()); }
  int32_t num_angles() const { return static_cast<int32_t>(angle_corner_.size()); }
  std::unique_ptr<TissueState> MakeState() const override;
  // -∂f_node/∂x_node of the elastic terms (analytic), at the state's positions [N/m].
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  // Elastic forces of every term plus bond damping [N], 3 × num_nodes.
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;

  // The same restricted to `terms` (a mask of Term); damping is included with kBond.
  void TermForces(const TissueState& state, uint32_t terms, mesh::Points* forces) const;
  double TermEnergy(const TissueState& state, uint32_t terms) const;  // [J]
  Eigen::Matrix3d TermLocalStiffness(const TissueState& state, int32_t node, uint32_t terms) const;
  // TermForces with the triangle kernel chosen: the portable scalar code (simd = false), or the
  // vector kernel when the CPU has one (simd = true, what TermForces does).
  void KernelTermForces(const TissueState& state, uint32_t terms, bool simd,
                        mesh::Points* forces) const;
  // The definition, for tests: straightforward loops over the bonds and the angles, each
  // evaluated on its own (slow; the same forces as TermForces up to rounding).
  void ReferenceTermForces(const TissueState& state, uint32_t terms, mesh::Points* forces) const;
  // Whether this CPU runs the vector kernel (AVX-512).
  static bool HasVectorKernel();

  const std::vector<double>& masses() const { return mass_; }                  // [kg], num_nodes
  const std::vector<double>& bond_stiffness() const { return bond_k_; }        // [N/m], num_bonds
  const std::vector<double>& angle_stiffness() const { return angle_k_; }      // [J], num_angles
  const std::vector<double>& stretch_bend() const { return stretch_bend_k_; }  // [N], num_angles
  const mesh::Points& rest_positions() const { return rest_; }

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;

 private:
  MolecularModel() = default;

  mesh::Points rest_;         // [m], 3 × num_nodes
  std::vector<double> mass_;  // [kg], num_nodes
  std::vector<double> inverse_mass_;
  // Bonds, sorted by (i, j), i < j; num_bonds each.
  std::vector<int32_t> bond_i_;
  std::vector<int32_t> bond_j_;
  std::vector<double> bond_rest_;     // r0 [m]
  std::vector<double> bond_k_;        // K_b [N/m]
  std::vector<double> bond_damping_;  // D [N s/m]
  // Angles, one per triangle corner: the corner atom c and its neighbours p, q, so bond a runs
  // c→p and bond b c→q; num_angles = 3 · num_triangles each.
  std::vector<int32_t> angle_corner_;
  std::vector<int32_t> angle_p_;
  std::vector<int32_t> angle_q_;
  std::vector<double> angle_rest_cos_;  // cos θ0 [-]
  std::vector<double> angle_rest_a_;    // r_a0 [m]
  std::vector<double> angle_rest_b_;    // r_b0 [m]
  std::vector<double> angle_k_;         // K_θ [J]
  std::vector<double> stretch_bend_k_;  // K_bθ [N]
  // CSR of the bonds and angles touching each node: num_nodes + 1 starts, then indices.
  std::vector<int32_t> node_bond_start_;
  std::vector<int32_t> node_bonds_;
  std::vector<int32_t> node_angle_start_;
  std::vector<int32_t> node_angles_;
  // The per-step kernel's triangles, in blocks of kBlock = 8 (the last padded with zeros):
  // triangle t = (n0, n1, n2) has edges E_k = x_{n(k+1)} - x_{nk} and corner angles at n_k
  // between E_k and -E_{k+2} (the angles 3t + k above). tri_nodes_: 3 · 8 per block, 3 · node
  // (offsets into the coordinates). tri_constants_: kTriangleFields · 8 per block, see the .cc.
  int32_t num_triangles_ = 0;
  std::vector<int32_t> tri_nodes_;
  std::vector<double> tri_constants_;
};

}  // namespace somasim::models
