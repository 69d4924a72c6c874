// Position-based particles, seed 004 (Bezdelnikov, eye tissues / capsulorhexis; SPEC §4.3):
// nodes are particles, mesh edges are distance constraints. A step predicts every particle by
// Verlet integration, x' = 2x - x* + a Δt² (seed 004 eq. 1), then projects the constraints by
// Gauss–Seidel sweeps in a fixed order, either with the seed's stiffness k ∈ (0,1] (eq. 2–3) or
// with XPBD compliance (Macklin, Müller & Chentanez 2016, "XPBD: position-based simulation of
// compliant constrained dynamics"). Pure kernel; how the sweeps run: docs/models.md.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/solid_angle_volume.h"
#include "server/models/tissue_model.h"

namespace somasim::models {

class PositionBasedState;

enum class PositionBasedMode {
  // Seed 004 eq. 2–3: x1 += k w1/(w1+w2) (|d|-a)/|d| d, x2 -= k w2/(w1+w2) (|d|-a)/|d| d with
  // d = x2 - x1. The apparent stiffness grows with the iteration count and 1/Δt².
  kSeedStiffness,
  // XPBD: one multiplier λ per constraint, α̃ = compliance/Δt²,
  // Δλ = (-C - α̃ λ)/(w1 + w2 + α̃). Converged, it is a spring of stiffness 1/compliance
  // integrated by (approximately) backward Euler.
  kXpbd,
};

// The material, given physically as for the mass-spring model (docs/models.md): the compliance
// of edge e is 1/k_e with the Van Gelder rule k_e = E · Σ_{elements ∋ e} size / |e|² (size =
// volume for tetrahedra, area × thickness for triangles), and lumped masses ρ · size / corners.
struct PositionBasedParameters {
  PositionBasedMode mode = PositionBasedMode::kXpbd;
  int iterations = 20;        // Gauss–Seidel sweeps per step, >= 1
  double stiffness = 1.0;     // k [-], seed mode, in (0, 1]; 1 is a rigid link
  double youngs_modulus = 0;  // E [Pa], XPBD, > 0 (unless compliance is given)
  double compliance = 0.0;    // [m/N], XPBD, >= 0: when > 0 replaces the Van Gelder rule
  double density = 1000.0;    // ρ [kg/m³], > 0 (unless node_mass is given)
  double thickness = 0.005;   // [m], > 0: shell thickness of a surface mesh
  double node_mass = 0.0;     // [kg], >= 0: when > 0 every node gets this mass
  // XPBD: after each sweep, re-anchor x = x̃ + M⁻¹ Σ ∇C(x) λ, removing the lagged-gradient
  // error of Gauss–Seidel XPBD (its g ≈ 0 assumption), so a converged step is an exact
  // backward-Euler step and the rest state is the static solution of springs 1/compliance for
  // any Δt. A fixed-point iteration: it converges while w λ / a = (ω Δt)² |C|/a < 1 for the
  // stiffest constraint, i.e. for soft tissue at small steps; otherwise leave it off.
  bool primal_correction = false;
  // Relative constraint residual (see LastConstraintResidual) at which the sweeps stop early;
  // 0 runs every iteration. Steps that end above it count as solver_unconverged.
  double tolerance = 0.0;
  double speed_limit = 100.0;  // [m/s], > 0: a faster node marks a diverged step
  // Project each colour 8 constraints at a time with AVX-512 (F and VL) when the CPU has it
  // (the same sweep order; results differ from the scalar sweep by rounding only), and predict
  // with it. False: always scalar.
  bool vectorised = true;
  // Seed 004's volume reaction (solid_angle_volume.h): a restoring force at every surface node
  // against the change of its solid angle, added to the prediction's forces each step. All zero
  // (the default) is off. Needs a closed surface (FromSurface) or a tetrahedral mesh (its
  // boundary); refused for FromEdges.
  SolidAngleVolumeParameters volume;
};

class PositionBasedModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the bad parameter or mesh fault (no elements, NaN
  // coordinates, zero-length edge, index out of range). A tetrahedral mesh contributes its
  // edges; a surface (closed or open) its triangle edges.
  static std::unique_ptr<PositionBasedModel> FromTetMesh(const mesh::TetMesh& mesh,
                                                         const PositionBasedParameters& parameters);
  static std::unique_ptr<PositionBasedModel> FromSurface(const mesh::SurfaceMesh& surface,
                                                         const PositionBasedParameters& parameters);
  // Constraints given explicitly (pairs of node indices into rest, 3 × num_nodes); needs
  // node_mass > 0 and, in XPBD mode, compliance > 0.
  static std::unique_ptr<PositionBasedModel> FromEdges(
      const mesh::Points& rest, const std::vector<std::array<int32_t, 2>>& edges,
      const PositionBasedParameters& parameters);

  int32_t num_nodes() const override { return static_cast<int32_t>(mass_.size()); }
  int32_t num_constraints() const { return static_cast<int32_t>(edge_i_.size()); }
  std::unique_ptr<TissueState> MakeState() const override;
  // Σ over incident constraints of k_eff [u uᵀ + (1 - a/l)(I - u uᵀ)] (the Hessian of
  // ½ k_eff C², geometric term included). k_eff = 1/compliance in XPBD mode. In seed mode it is
  // the stiffness one step of projections emulates: (1 - (1-k)^iterations) m_e / Δt², with the
  // pair's reduced mass m_e and the last step's Δt (1 ms before the first step).
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  // -∇ of the elastic energy: Σ k_eff C along each constraint [N], plus the volume reaction,
  // 3 × num_nodes.
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  // elastic = Σ ½ k_eff C², C = |x_j - x_i| - a, plus the volume term's energy.
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;
  bool SupportsCutting() const override { return true; }
  // Removes the distance constraints crossing the sweep (kept in the state; the volume reaction's
  // rings are not changed).
  int32_t Cut(const SweptQuad& sweep, TissueState* state) const override;

  // The largest relative violation after the last step: max_e |C_e + α̃ λ_e| / a_e in XPBD mode
  // (the compliant constraint equation; α̃ λ = 0 for rigid links), max_e |C_e| / a_e in seed mode.
  double LastConstraintResidual(const TissueState& state) const;

  const std::vector<double>& masses() const { return mass_; }  // [kg], num_nodes
  // 1/compliance [N/m] per constraint (XPBD); empty in seed mode.
  const std::vector<double>& constraint_stiffness() const { return edge_stiffness_; }
  const std::vector<double>& rest_lengths() const { return rest_length_; }  // [m]
  const mesh::Points& rest_positions() const { return rest_; }
  // The sweep order: the constraints of colour c are sweep slots
  // colour_starts()[c] .. colour_starts()[c + 1] - 1 (num_colours + 1 entries), and slot s
  // projects constraint sweep_constraints()[s] (an index into rest_lengths() etc.). No two
  // constraints of a colour share a node.
  const std::vector<int32_t>& colour_starts() const { return colour_start_; }
  const std::vector<int32_t>& sweep_constraints() const { return sweep_edge_; }
  std::array<int32_t, 2> constraint_nodes(int32_t e) const {
    return {edge_i_[static_cast<size_t>(e)], edge_j_[static_cast<size_t>(e)]};
  }
  // Whether the sweeps run the AVX-512 kernel (parameters().vectorised and the CPU has it).
  bool uses_simd() const { return simd_; }
  // The volume reaction, or null when parameters().volume is all zero.
  const SolidAngleVolumeTerm* volume_term() const { return volume_.get(); }
  const PositionBasedParameters& parameters() const { return parameters_; }

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;
  // The step keeps the state it starts from as the last-good one (SwapWithLastGood), writes
  // every node's new x and v in its copy back from the records, and checks them there.
  bool SavesGoodStateItself() const override { return true; }
  bool ChecksStateItself() const override { return true; }

 private:
  PositionBasedModel() = default;
  void Build(const mesh::Points& rest, const std::vector<std::array<int32_t, 2>>& edges,
             const std::vector<double>& edge_size_sum, const std::vector<double>& node_size,
             const PositionBasedParameters& parameters);
  // k_eff of constraint e [N/m] for a step of dt (see LocalStiffness).
  double EffectiveStiffness(size_t e, double dt) const;
  // The internal node order of the sweeps (node_order_, node_slot_): reverse Cuthill–McKee.
  void OrderNodes();
  // Greedy colouring of the constraints into sweep order (colour_start_, sweep_*).
  void ColourConstraints();
  // The step's stages (position_based_step.cc), in the order Advance runs them: the Verlet
  // prediction into the node records (with the volume reaction; fixed and prescribed nodes get
  // inverse mass 0), the attachments merged per node, the per-constraint factors (recomputed
  // only when Δt or the inverse masses change), the sweeps (each: the distance constraints colour
  // by colour, the attachments, the primal correction if on), and the copy back to public order
  // with the state's check.
  void PredictRecords(const StepInputs& inputs, PositionBasedState* state) const;
  void MergeAttachments(const StepInputs& inputs, PositionBasedState* state) const;
  void PrepareSweepFactors(double dt, PositionBasedState* state) const;
  void RunSweeps(double dt, PositionBasedState* state) const;
  void ProjectAttachments(double inverse_dt2, PositionBasedState* state) const;
  void CorrectPrimal(PositionBasedState* state) const;
  void CopyBack(double dt, PositionBasedState* state) const;

  PositionBasedParameters parameters_;
  mesh::Points rest_;         // [m], 3 × num_nodes
  std::vector<double> mass_;  // [kg], num_nodes
  std::vector<double> inverse_mass_;
  std::vector<int32_t> edge_i_;  // num_constraints, i < j, sorted
  std::vector<int32_t> edge_j_;
  std::vector<double> rest_length_;       // a [m], num_constraints
  std::vector<double> edge_stiffness_;    // 1/compliance [N/m], num_constraints (XPBD)
  std::vector<double> edge_compliance_;   // [m/N], num_constraints (XPBD)
  std::vector<int32_t> node_edge_start_;  // num_nodes + 1, CSR of constraints per node
  std::vector<int32_t> node_edges_;
  // The sweeps run on internal records (x, y, z, w) per node in a locality-friendly order (the
  // public numbering is unchanged): node_order_[p] is the node of record p, node_slot_ its inverse.
  std::vector<int32_t> node_order_;  // num_nodes
  std::vector<int32_t> node_slot_;   // num_nodes
  // The sweep: constraints in colour order, num_constraints each (see colour_starts()).
  std::vector<int32_t> colour_start_;     // num_colours + 1
  std::vector<int32_t> sweep_edge_;       // constraint index of each slot
  std::vector<int32_t> sweep_i4_;         // 4 node_slot_[i]: offset of i's record
  std::vector<int32_t> sweep_j4_;         // 4 node_slot_[j]
  std::vector<double> sweep_rest_;        // a [m]
  std::vector<double> sweep_inv_rest_;    // 1/a [1/m]
  std::vector<double> sweep_compliance_;  // [m/N] (XPBD), 0 in seed mode
  bool simd_ = false;
  std::unique_ptr<SolidAngleVolumeTerm> volume_;  // null when off
};

}  // namespace somasim::models
