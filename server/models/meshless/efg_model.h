// Element-free Galerkin (EFG) tissue model (SPEC §4.6, issue 13; seed 001's model of the
// surgical region): MLS shape functions on the tet mesh's nodes, the tetrahedra as integration
// cells, small-strain linear elasticity, implicit Euler on the nodal parameters with the tools'
// springs by a low-rank update of the factor, and cutting by the visibility criterion.
// Formulation and derivations: docs/models.md, "The EFG model in detail". Pure kernel: no I/O.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/meshless/mls.h"
#include "server/models/tissue_model.h"

namespace somasim::models::meshless {

struct EfgSystem;  // efg_system.h
struct EfgValues;

struct EfgParameters {
  double youngs_modulus = 5000.0;    // E [Pa], finite, > 0 (seed 001's liver)
  double poisson_ratio = 0.35;       // ν [-], in (-1, 0.5) (seed 001's liver)
  double density = 1055.0;           // ρ [kg/m³], finite, > 0 (seed 001: 1.055 g/cm³)
  double rayleigh_mass = 2.0;        // α [1/s], finite, >= 0: C = α M̂ + β K
  double rayleigh_stiffness = 0.01;  // β [s], finite, >= 0
  MlsParameters mls;                 // shape functions (mls.h)
  // Every node's support covers at least this multiple of its longest incident tet edge
  // (finite, >= 1): A(x) is then invertible everywhere inside the mesh.
  double min_support_edge_factor = 1.2;
  int gauss_points = 4;         // per tetrahedron: 4 (degree 2) or 14 (degree 5)
  double penalty_factor = 1e5;  // κ / max diag K [-], finite, > 0
  double speed_limit = 100.0;   // [m/s], finite, > 0: a faster node marks a diverged step
  // Distinct attached nodes a step handles by the low-rank update of the supports' factor, in
  // 0..kMaxLowRankNodes; a step with more factorises A with its attachments inside. Each slot
  // costs MakeState 3 × 3·num_nodes doubles.
  int max_low_rank_nodes = 64;
  static constexpr int kMaxLowRankNodes = 1024;
};

// What cuts have changed in an EFG (EfgModel::ApplyCut): the cut surface and the matrices its
// visibility criterion changes, on the model's fixed patterns. Owned by a state (EfgModel's,
// or the hybrid's).
struct EfgCutValues {
  std::vector<Eigen::Vector3d> triangles;  // [m], reference configuration, 3 vertices each
  std::vector<double> phi_value;           // Φ's entries on Φ's pattern
  std::vector<double> k_blocks;            // K [N/m], 9 × blocks
  std::vector<double> m_blocks;            // M̂ [kg], blocks
  std::vector<uint8_t> dropped;            // per Gauss point: 1 once it cannot be evaluated
  std::vector<uint8_t> detached;           // per node point: 1 once its Φ row is e_I
  int64_t hidden_pairs = 0;                // (node, point) pairs hidden, Gauss and node points
  int64_t dropped_points = 0;              // Gauss points dropped
  int64_t detached_rows = 0;               // node points whose Φ row fell back to e_I
  int64_t version = 0;                     // +1 per change
};

// What SolveStatic holds and loads (one linear solve).
struct EfgStaticLoads {
  const mesh::Points* external_forces = nullptr;  // [N] at the node points, 3 × num_nodes
  // Forces on the nodal parameters directly (3 × num_nodes [N]): a distributed load
  // ∫ φ_J t dΓ, e.g. a traction; or none.
  const mesh::Points* parameter_forces = nullptr;
  Eigen::Vector3d gravity = Eigen::Vector3d::Zero();   // [m/s²]
  std::span<const int32_t> fixed_nodes;                // held at their rest positions
  std::span<const int32_t> prescribed_nodes;           // moved to prescribed_positions
  const mesh::Points* prescribed_positions = nullptr;  // [m], 3 × prescribed_nodes.size()
};

// Throws std::invalid_argument "<model>: SolveStatic: ..." naming the first bad load (a size, a
// non-finite value, an index out of range, no held node) for a model of num_nodes nodes.
void CheckStaticLoads(const EfgStaticLoads& loads, int32_t num_nodes, const std::string& model);

class EfgModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the bad parameter or mesh fault (empty mesh, NaN
  // coordinates, node index out of range, flat or inverted tetrahedron, node in no tetrahedron).
  static std::unique_ptr<EfgModel> FromTetMesh(const mesh::TetMesh& mesh,
                                               const EfgParameters& parameters);
  ~EfgModel() override;

  int32_t num_nodes() const override;
  std::unique_ptr<TissueState> MakeState() const override;
  // The tissue's condensed static stiffness at node I's point, (Φ_I K_s⁻¹ Φ_Iᵀ)⁻¹ [N/m] (3 × 3,
  // symmetric positive definite): the force a static point displacement of the node costs with
  // everything else free, K_s = K + P_s for the SUPPORTS (fixed and prescribed nodes) of the
  // state's last step — not its attachments: a tool's own spring is in series with this, as for
  // the FEM. Zero before the first step and for a body without supports (a free body has no
  // static stiffness). Cached per node in the state (9 doubles and a flag per node, sized by
  // MakeState) until the supports change: the first call for a node costs three solves with
  // the static factor, later ones a copy. Allocates nothing.
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  // Numeric factorisations the state's steps have made (the step's system and the static K_s
  // together): what a change of dt or of the supports, or a step past max_low_rank_nodes, costs.
  int64_t Factorisations(const TissueState& state) const;
  // The elastic forces at the node points [N], 3 × num_nodes: f = -Φ⁻ᵀ K û with û = Φ⁻¹ (x - X)
  // from the state's positions, so f = -∂E/∂x for the elastic energy of Energy(). Allocates.
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  // kinetic ½ Σ m_I |v_I|², elastic ½ ûᵀ K û (û from the state's positions), gravity -Σ m_I g·x_I.
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;
  bool SupportsCutting() const override { return true; }
  // The cut hook (docs/models.md, "Cutting"): returns the (node, point) pairs the sweep hid, 0
  // for a sweep that crosses none or has a non-finite corner. Allocates.
  int32_t Cut(const SweptQuad& sweep, TissueState* state) const override;
  // Cut's two parts, for the hybrid. PullBack: the sweep's corners in the reference
  // configuration of a body at `positions` (3 × num_nodes). ApplyCut: adds a reference sweep's
  // two triangles to `cut` (filled with the model's own values first when empty) and updates
  // the values they change; returns the pairs hidden (0: nothing changed, version kept).
  SweptQuad PullBack(const SweptQuad& sweep, const mesh::Points& positions) const;
  int64_t ApplyCut(const SweptQuad& reference_sweep, EfgCutValues* cut) const;
  // The state's cut, or nullptr before its first.
  const EfgCutValues* CutOf(const TissueState& state) const;

  // Static equilibrium (K + P) û = f̂ (one factorisation and solve; allocates): writes the
  // physical positions and û into the state and zeroes the velocities. Needs enough held nodes
  // to remove the rigid motions. Throws std::invalid_argument for bad loads (sizes, indices,
  // NaN) and std::runtime_error when the system is not positive definite (too few held nodes).
  void SolveStatic(const EfgStaticLoads& loads, TissueState* state) const;

  // For tests and later slices.
  const MlsShapeFunctions& shape_functions() const { return *shape_; }
  const std::vector<double>& masses() const;   // m_I [kg], num_nodes
  const mesh::Points& rest_positions() const;  // X [m], 3 × num_nodes
  double penalty() const;                      // κ [N/m]
  int64_t num_gauss_points() const { return num_gauss_; }
  int64_t stiffness_blocks() const;
  // The state's nodal parameters û [m], 3 × num_nodes.
  const mesh::Points& NodalParameters(const TissueState& state) const;
  // u(x) = Σ φ_J(x) û_J and its gradient ∇u (∂u_i/∂x_j) at a point x [m], for the state's û
  // (and its cut's visibility). Allocates (an MLS evaluation).
  void DisplacementAt(const TissueState& state, const Eigen::Vector3d& x, Eigen::Vector3d* u,
                      Eigen::Matrix3d* gradient) const;
  // For a parameter field û (3 × num_nodes): the elastic energy ½ ûᵀ K û [J], and the physical
  // node-point forces f = -Φ⁻ᵀ K û [N] (3 × num_nodes), of the model or of a cut one.
  // Allocate.
  double ElasticEnergyOfParameters(const mesh::Points& parameters,
                                   const EfgCutValues* cut = nullptr) const;
  void ForcesOfParameters(const mesh::Points& parameters, mesh::Points* forces,
                          const EfgCutValues* cut = nullptr) const;
  // Φ û for parameters û (3 × num_nodes): the physical displacements at the nodes.
  void NodeDisplacements(const mesh::Points& parameters, mesh::Points* displacements,
                         const EfgCutValues* cut = nullptr) const;
  // û = Φ⁻¹ u for node displacements u (3 × num_nodes), of the model or of a cut one. False
  // when a cut's Φ is singular. Allocates.
  bool ParametersOfDisplacements(const mesh::Points& displacements, mesh::Points* parameters,
                                 const EfgCutValues* cut = nullptr) const;

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;

 private:
  friend class EfgHybridModel;  // reduces this model: reads its system and shape functions
  EfgModel();
  // FromTetMesh's stages after the checks: the shape functions and Φ's rows (with each node's
  // longest incident tet edge); the Gauss points and the lower block pattern of the node pairs
  // that share a Gauss or a node point; K, then M̂ and the rest (EfgSystem::Finish).
  void BuildShapeFunctions(const mesh::TetMesh& mesh, const EfgParameters& parameters);
  void BuildGaussPointsAndPattern(const mesh::TetMesh& mesh, const std::vector<double>& volume,
                                  int gauss_points);
  void BuildStiffness();
  // The values the kernels read: the model's, or a cut's (EfgCutValues).
  EfgValues ValuesOf(const EfgCutValues* cut) const;
  // Adds sign × a Gauss point's contribution w Bᵀ D B (its MLS evaluation with gradients, its
  // weight w = rule weight × volume [m³]) to K's blocks.
  void AddGaussPoint(const MlsEvaluation& eval, double w, double sign, double* k_blocks) const;
  // Step 1 of Advance: the springs at the node points (supports and attachments) and the
  // distinct attached nodes.
  void GatherSprings(const StepInputs& inputs, TissueState* state) const;
  // Step 2 of Advance: makes the state's factors current (the step's system with the supports
  // only, on the low-rank path, or with the attachments too; the static K_s) and, on the
  // low-rank path, the cached Z and G of this step's attached nodes. False when the step's
  // system is not positive definite.
  bool PrepareFactors(double dt, bool low_rank, TissueState* state) const;
  // Fills low-rank slot `slot` with node I's columns Z = A0⁻¹ U_I and G's row and column.
  void FillLowRankSlot(int32_t slot, int32_t node, TissueState* state) const;
  // Applies the attachments' low-rank correction to dv = A0⁻¹ b in the state. False when the
  // 3m × 3m system is not positive definite (cannot happen but by rounding: the step is then
  // rejected).
  bool CorrectForAttachments(double dt, TissueState* state) const;

  // The nodes, Φ (the system's rows R), K and M̂ on their patterns (efg_system.h).
  std::unique_ptr<EfgSystem> system_;
  // The Gauss points [m] (3 × num_gauss, tet by tet) and their weights w |J| [m³] (num_gauss).
  mesh::Points gauss_x_;
  std::vector<double> gauss_w_;
  std::unique_ptr<MlsShapeFunctions> shape_;
  double lambda_ = 0.0, mu_ = 0.0;  // Lamé [Pa]
  int64_t num_gauss_ = 0;
  int32_t max_low_rank_nodes_ = 0;
};

}  // namespace somasim::models::meshless
