// Seed 001's hybrid liver (SPEC §4.6, issue 13; Chen, Zhao & Zhu 2015, §1.3): element-free
// Galerkin where the surgeon works, the rest of the organ condensed exactly onto it (Guyan), so
// that force and displacement balance across the transition; the region follows the tool and
// adapts to the field. Derivations: docs/models.md, "The hybrid in detail". Pure kernel: no I/O.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <limits>
#include <memory>

#include "common/mesh/mesh_types.h"
#include "server/models/meshless/adaptivity.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/tissue_model.h"

namespace somasim::models::meshless {

struct EfgHybridParameters {
  EfgParameters efg;            // the EFG discretisation and material (efg_model.h)
  double region_radius = 0.05;  // [m], finite, > 0: the surgical region around its centre
  // [m]: the region's first centre; non-finite (the default): the first tool's node (an
  // attachment, else the largest external force), or without one the node nearest the
  // organ's centroid.
  Eigen::Vector3d region_centre =
      Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  bool follow_tool = true;         // rebuild the region around the tool when it leaves
  double follow_fraction = 0.5;    // in (0, 1]: how far (× radius) the tool may go first
  int32_t max_region_nodes = 400;  // 1..4096: kept nodes at most (dense 3k × 3k matrices)
  // Seed 001's adaptivity (adaptivity.h, eq. 1–9): every adapt_interval steps the cells' mesh
  // intensity is computed from the field; the nodes of cells whose normalised intensity is at
  // least refine_threshold join the region, and nodes that joined that way leave it when their
  // cells fall below coarsen_threshold (the ball around the centre always stays). A change of
  // the region rebuilds it (a partition). Off by default: an adaptation costs a pass over the
  // cells' shape-function gradients (evaluated once, at construction) and a partition when the
  // region changes (docs/models.md gives the costs).
  bool adaptive = false;
  int32_t adapt_interval = 250;      // steps between adaptations, >= 1
  double refine_threshold = 0.01;    // in (0, 1]
  double coarsen_threshold = 0.003;  // in [0, refine_threshold]
};

class EfgHybridModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the bad parameter (those of EfgModel::FromTetMesh too).
  static std::unique_ptr<EfgHybridModel> FromTetMesh(const mesh::TetMesh& mesh,
                                                     const EfgHybridParameters& parameters);
  ~EfgHybridModel() override;

  int32_t num_nodes() const override;
  std::unique_ptr<TissueState> MakeState() const override;
  // (D_I S⁻¹ D_Iᵀ)⁻¹ [N/m]: the condensed static stiffness at node I's point with the state's
  // supports — pure EFG's (EfgModel::LocalStiffness) for a node whose support lies in the
  // surgical region. Zero before the first step and without supports. Cached per node until the
  // next partition; allocates nothing.
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  // From the state's full parameter field û = T q (allocates), as EfgModel's.
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;
  bool SupportsCutting() const override { return true; }
  // The cut hook: EfgModel's visibility criterion on the whole organ's EFG (the surgical and
  // the condensed region are one MLS field, so a cut anywhere separates both); the next step
  // factorises the cut K̃ and partitions again (≈ the cost of a region rebuild), carrying the
  // physical field over. Returns the (node, point) pairs hidden. Allocates.
  int32_t Cut(const SweptQuad& sweep, TissueState* state) const override;
  // The state's cut, or nullptr before its first.
  const EfgCutValues* CutOf(const TissueState& state) const;

  // Static equilibrium through the hybrid's own reduced system (partitions for these supports
  // around the region centre, or the largest load's node; allocates): q = S⁻¹ Dᵀ f plus the
  // particular far response of loads reaching far parameters. Writes positions, zero
  // velocities. Throws as EfgModel::SolveStatic (parameter_forces is not supported: refused).
  void SolveStatic(const EfgStaticLoads& loads, TissueState* state) const;

  // Diagnostics for tests and benchmarks.
  const EfgModel& efg() const { return *efg_; }
  int32_t RegionNodes(const TissueState& state) const;          // k of the current partition
  bool InRegion(const TissueState& state, int32_t node) const;  // node is a kept node
  Eigen::Vector3d RegionCentre(const TissueState& state) const;
  int64_t Partitions(const TissueState& state) const;      // regions built so far
  int64_t Factorisations(const TissueState& state) const;  // static and step factors
  int64_t FarSolves(const TissueState& state) const;       // particular responses of loads
  int64_t Adaptations(const TissueState& state) const;     // intensity evaluations made
  // The state's full EFG parameter field û = T q [m], 3 × num_nodes (allocates).
  mesh::Points NodalParameters(const TissueState& state) const;

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;

 private:
  EfgHybridModel();
  // The region (efg_hybrid_region.cc). Partition: the kept nodes around `centre`, the extension
  // T, S⁻¹, D, the reduced M_r, K_r, P_r and gravity's far response, from the static factor.
  void Partition(const Eigen::Vector3d& centre, TissueState* state) const;
  // Marks the nodes the intensity adds to the region; true when the region must change.
  bool Adapt(TissueState* state) const;
  // Factorises K̃ for the state's supports (and cut); false when it cannot.
  bool FactoriseStatic(TissueState* state) const;
  // The far response of node-point loads (3N): physical offsets into `offsets`, the parameters'
  // in the state's full_solution.
  void ParticularResponse(const double* node_loads, double* offsets, TissueState* state) const;
  // Advance's stages (efg_hybrid_step.cc). 1: the supports and the distinct attached nodes
  // (false: more than the slots). 2: the static factor and the region, partitioned again when
  // the supports, a cut, the tool or the adaptivity move it (false: K̃ cannot be factorised).
  // 3: A's factor and the attached nodes' slots (false: A is not positive definite). 4: the
  // far response of the loads that reach far parameters. 5: the right-hand side b.
  bool GatherSupportsAndTools(const StepInputs& inputs, TissueState* state) const;
  bool UpdateRegion(const StepInputs& inputs, TissueState* state) const;
  bool PrepareStepFactor(double dt, TissueState* state) const;
  void UpdateFarLoads(const StepInputs& inputs, TissueState* state) const;
  void AssembleRightHandSide(const StepInputs& inputs, TissueState* state) const;
  // The tools' low-rank update: slot `slot`'s Z columns A⁻¹ D_Iᵀ and G's row; the correction
  // of the solution in the state's b (false: not positive definite, the step is rejected).
  void FillSlot(int32_t slot, int32_t node, TissueState* state) const;
  bool CorrectForAttachments(double dt, TissueState* state) const;

  std::unique_ptr<EfgModel> efg_;
  EfgHybridParameters parameters_;
  Eigen::Vector3d centroid_ = Eigen::Vector3d::Zero();  // [m] of the rest nodes
  mesh::Tetrahedra tets_;                               // the background cells, for the adaptivity
  std::unique_ptr<CellIntensityEvaluator> intensity_;   // when adaptive
};

}  // namespace somasim::models::meshless
