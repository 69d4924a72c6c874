// Element-free Galerkin coupled to a mass-spring system (SPEC §4.6; seed 001's table 1 middle
// variant, its reference [14]): EFG on the tetrahedra near the surgical site, linear springs on
// the other tetrahedra's edges, one energy and one sparse system over both. With the region
// covering every node it is EfgModel; covering none, a linear mass-spring system. Derivations:
// docs/models.md, "The coupled model in detail". Pure kernel: no I/O.
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
