// Seed 000's reduced model (SPEC §4.5; seed 000 §3–4, Karhunen–Loève with viscoelastic
// scaling): U = B ξ on Karhunen–Loève modes (pod.h), ξ from the Galerkin-projected linear statics
// (Bᵀ K B) ξ = Bᵀ f with one stiffness chosen offline (reduce_fem.h), the tool's load scaled by
// the loaded node's creep curve. Quasi-static; cannot be cut. Per-step equations:
// docs/reduced.md, "Seed 000's model per step". Pure: no I/O.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/reduced/modal_field.h"
#include "server/models/tissue_model.h"

namespace somasim::models::reduced {

// One node's creep curve (seed 000 §4): its displacement under a constant force applied at
// t = 0, divided by the displacement at t = 0⁺ (the instantaneous response): c(0) = 1, rising as
// the tissue relaxes (for Fung's QLV towards about 1 / γ∞).
struct CreepCurve {
  int32_t node = 0;                // [0, num_nodes)
  double interval = 0.1;           // [s] between samples, > 0
  std::vector<double> multiplier;  // c(k · interval), k = 0..; c(0) = 1; each finite, > 0
};

struct KlModelData {
  mesh::Points rest;                  // X [m], 3 × N (N >= 1), finite
  std::vector<double> masses;         // [kg], N, each > 0 (gravity, energy, momentum)
  Eigen::MatrixXd modes;              // B [-], 3N × n (1 <= n <= 3N), row 3i + axis
  Eigen::MatrixXd stiffness_modes;    // K B [N/m], 3N × n: internal forces −K B ξ
  Eigen::MatrixXd reduced_stiffness;  // Bᵀ K B [N/m], n × n, symmetric positive definite
  std::vector<CreepCurve> creep;      // one per node at most; empty: elastic
  // A loaded node without a curve takes the curve of the nearest node with one within this
  // distance [m] of it at rest (the seed's radius of influence), else no creep (c = 1). >= 0.
  double creep_radius = 0.01;
  // Springs for prescribed nodes and for fixed nodes the modes can move [N/m], > 0.
  double penalty_stiffness = 1e5;
  // LocalStiffness's cap [N/m], > 0, in directions the modes cannot move a node.
  double max_local_stiffness = 1e4;
};

class KlReducedModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the field that is wrong (sizes, a non-finite value, a
  // reduced stiffness that is not symmetric positive definite, a curve's node out of range or
  // repeated, c(0) != 1, ...).
  static std::unique_ptr<KlReducedModel> Create(KlModelData data);

  int32_t num_nodes() const override { return static_cast<int32_t>(data_.masses.size()); }
  int32_t num_modes() const { return static_cast<int32_t>(data_.modes.cols()); }
  std::unique_ptr<TissueState> MakeState() const override;
  // The condensed stiffness at `node`: the inverse of the reduced model's compliance there,
  // c · B_i (Bᵀ K B)⁻¹ B_iᵀ (c the state's creep multiplier), its eigenvalues capped at
  // max_local_stiffness (directions the modes do not move the node in). O(1): the compliances
  // are computed at Create.
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  // −K B ξ [N] (the chosen stiffness on the reduced displacement).
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  // Elastic: ½ ξᵀ (Bᵀ K B) ξ.
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;

  // The state's reduced coordinates ξ (n) and its creep multiplier c.
  const Eigen::VectorXd& Coordinates(const TissueState& state) const;
  double CreepMultiplier(const TissueState& state) const;
  const KlModelData& data() const { return data_; }

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;
  // The state is ξ (with the last step's ξ and dt for the velocities): a rejected step rebuilds
  // x and v from the last accepted ones, so the base class's last-good copies of the field are
  // not needed (two fewer passes over it per step).
  bool SavesGoodStateItself() const override { return true; }
  // The reconstruction checks x and v as it writes them (modal_field.h).
  bool ChecksStateItself() const override { return true; }

 private:
  explicit KlReducedModel(KlModelData data);
  double CurveValue(int32_t curve, double t) const;  // c(t) of data_.creep[curve], t >= 0

  KlModelData data_;
  Eigen::LLT<Eigen::MatrixXd> factor_;       // of Bᵀ K B
  Eigen::MatrixXd gravity_modes_;            // n × 3: column a = Bᵀ (m e_a)
  std::vector<Eigen::Matrix3d> compliance_;  // N: B_i (Bᵀ K B)⁻¹ B_iᵀ [m/N]
  std::vector<int32_t> curve_of_node_;       // N: index into data_.creep, or -1
  std::vector<uint8_t> moves_;               // N: 1 when the modes move the node
  ModalField field_;  // B in single precision for the reconstruction (the solves use modes)
};

}  // namespace somasim::models::reduced
