// Element-free Galerkin coupled to a mass-spring system (SPEC §4.6; seed 001's table 1 middle
// variant, "耦合模型": its reference [14], Liu Xuemei 2013, EFG in the surgical region and a
// mass-spring model (MSS) elsewhere; seed: 14.8 ms per step against 17.4 ms for pure EFG on a
// 295-node liver, displacements within ±0.018 cm of pure EFG). Pure kernel: no I/O.
//
// One linear, monolithic model (one energy, one sparse system), so it is stable at 1 ms steps and
// exact where it should be:
//  - Region. The tetrahedra with a corner within region_radius of region_centre are meshless:
//    integrated as the EFG (efg_model.h) does — MLS shape functions built on the nodes E of those
//    tetrahedra only (same basis, weight, support rule: ρ_J >= min_support_edge_factor × the
//    node's longest edge among them), the tetrahedra as background cells with the same Gauss rule,
//    small-strain Hooke, K_E = Σ_gauss Bᵀ D B w |J|. The other tetrahedra are MSS.
//  - MSS. Linear (small-displacement) axial springs on the MSS tetrahedra's unique edges: a
//    spring (a, b) of rest direction e stores ½ k (eᵀ (u_b - u_a))² (the exact linearisation of
//    a spring at its rest length: no transverse stiffness), k by the MassSpringModel's documented
//    rule (Van Gelder 1998), k = E Σ_{MSS tets ∋ edge} V / |edge|². A spring network fixes ν at
//    1/4 and is only approximately E: this, not the coupling, is what separates the coupled model
//    from pure EFG.
//  - Unknowns q: the EFG nodal parameters û_J of the region's nodes E (first, in increasing node
//    order), then the physical displacements u_I of the MSS-only nodes. Node I's physical
//    displacement is u_I = G_I q: G_I = Φ_I (MLS values φ_J(X_I), J in E) for I in E, the unit row
//    of its own unknown otherwise. G is square (num_nodes × num_nodes) and invertible.
//  - Interface nodes (corners of both kinds of tetrahedra) are in E: the springs touching them
//    act through Φ_I, so force balance between the regions holds by construction (one energy,
//    ½ qᵀ K q with K = K_E + Σ_springs k (G_b - G_a)ᵀ e eᵀ (G_b - G_a)) and displacement is
//    continuous (one field at each node).
//  - Masses: lumped, each tetrahedron's ρV/4 to its corners (both kinds; the MSS's rule too), so
//    M̂ = Gᵀ diag(m) G. Damping: Rayleigh C = α M̂ + β K (EfgParameters). Loads at node points
//    enter through Gᵀ; supports (fixed and prescribed nodes) are penalty springs ½ κ |u_I - ū_I|²
//    at the node points, κ = penalty_factor × max diagonal of K, a fixed node held where it was
//    when it became fixed — all as the EFG.
//  - Dynamics: implicit Euler as the EFG's, A Δq̇ = dt (Gᵀ h - K (q + (β + dt) q̇)) with the
//    node-point loads h_I = f_ext + m_I (g - α v_I) + Σ k (t - X_I) - s_I (u_I + dt v_I) (s_I the
//    node's summed support and tool-spring stiffness, t their targets) and
//    A = (1 + dt α) M̂ + (dt² + dt β) K + dt² Σ_I s_I G_Iᵀ G_I, one CHOLMOD factorisation (pattern
//    analysed once, by MakeState), re-done only when dt or a node's summed spring stiffness
//    changes. Attachments (tool springs) are inside A: a grasp whose target moves costs nothing,
//    a change of its stiffness or node re-factorises (correct, allocates; a few ms on liver288
//    with the default region, where the first step, both factors, takes 7–13 ms — no low-rank
//    update as in EfgModel). A step that factorises nothing allocates nothing.
// With the region covering every node this is EfgModel exactly; covering none, a linear MSS.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <limits>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/tissue_model.h"

namespace somasim::models::meshless {

struct EfgSystem;  // efg_system.h

struct EfgMssCoupledParameters {
  // The material (E, ν for the EFG; E and ρ for the springs and masses), the EFG discretisation
  // (MLS, support factor, Gauss points), Rayleigh damping, penalty_factor and speed_limit.
  // max_low_rank_nodes is not used (attachments are factorised in).
  EfgParameters efg;
  double region_radius = 0.05;  // [m], finite, >= 0: the meshless region around the centre
  // [m], finite (required): where the surgeon works, e.g. the tool's first contact.
  Eigen::Vector3d region_centre =
      Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
};

class EfgMssCoupledModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the bad parameter or mesh fault (empty mesh, NaN
  // coordinates, index out of range, flat or inverted tetrahedron, node in no tetrahedron,
  // region_radius negative or NaN, region_centre not finite, a non-empty region with no more
  // nodes than efg.mls.support_neighbours).
  static std::unique_ptr<EfgMssCoupledModel> FromTetMesh(const mesh::TetMesh& mesh,
                                                         const EfgMssCoupledParameters& parameters);
  ~EfgMssCoupledModel() override;

  int32_t num_nodes() const override;
  std::unique_ptr<TissueState> MakeState() const override;
  // (G_I K_s⁻¹ G_Iᵀ)⁻¹ [N/m], K_s = K + the supports' penalties of the state's last step (as
  // EfgModel's). Zero before the first step and without supports. Cached per node until the
  // supports change; allocates nothing.
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  // f = -G⁻ᵀ K q with q = G⁻¹ (x - X): -∂E/∂x of Energy's elastic energy. Allocates.
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  // kinetic ½ Σ m_I |v_I|², elastic ½ qᵀ K q (q from the positions), gravity -Σ m_I g·x_I.
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;
  bool SupportsCutting() const override { return false; }

  // Static equilibrium (K + P) q = Gᵀ h (one factorisation; allocates): writes the positions and
  // zero velocities. Throws as EfgModel::SolveStatic; parameter_forces is refused.
  void SolveStatic(const EfgStaticLoads& loads, TissueState* state) const;

  // Diagnostics for tests and benchmarks.
  int32_t num_efg_nodes() const { return num_efg_; }  // |E|
  int32_t num_interface_nodes() const { return num_interface_; }
  int32_t num_springs() const { return static_cast<int32_t>(spring_k_.size()); }
  int32_t num_meshless_tets() const { return num_meshless_tets_; }
  bool IsEfgNode(int32_t node) const { return efg_of_node_[size_t(node)] >= 0; }
  const std::vector<double>& spring_stiffness() const { return spring_k_; }  // [N/m], springs
  const std::vector<double>& masses() const;                                 // m_I [kg], nodes
  const mesh::Points& rest_positions() const;                                // X [m], 3 × nodes
  double penalty() const;                                                    // κ [N/m]
  int64_t num_gauss_points() const { return num_gauss_; }
  int64_t stiffness_blocks() const;
  int64_t Factorisations(const TissueState& state) const;  // the step's and the static factor
  // The state's unknowns q [m], 3 × num_nodes (E's parameters, then the MSS-only displacements).
  const mesh::Points& Unknowns(const TissueState& state) const;
  // For unknowns q (3 × num_nodes): ½ qᵀ K q [J].
  double ElasticEnergyOfUnknowns(const mesh::Points& unknowns) const;

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;

 private:
  EfgMssCoupledModel();
  // FromTetMesh's stages after the checks (efg_mss_coupled_model.cc).
  struct Build;
  // Makes the step's factor (dt, the springs' stiffness) and the static factor (the supports)
  // current. False when the step's system is not positive definite.
  bool PrepareFactors(double dt, TissueState* state) const;

  // The nodes, G (the system's rows R), K and M̂ on their patterns (efg_system.h).
  std::unique_ptr<EfgSystem> system_;
  int32_t num_efg_ = 0, num_interface_ = 0, num_meshless_tets_ = 0;
  std::vector<int32_t> efg_of_node_;  // index in E or -1, num_nodes
  // The springs: nodes, stiffness k [N/m], rest direction e (3 × springs).
  std::vector<int32_t> spring_a_, spring_b_;
  std::vector<double> spring_k_;
  mesh::Points spring_dir_;
  int64_t num_gauss_ = 0;
};

}  // namespace somasim::models::meshless
