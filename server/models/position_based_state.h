// The mutable state of a position-based model (internal to server/models: the model's
// construction, its step and its sweep share it).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/tissue_model.h"

namespace somasim::models {

class PositionBasedModel;

// The state of a position-based model: the base state, the multipliers of the last step and the
// scratch of a step, all sized by MakeState so that stepping allocates nothing. The sweeps run on
// an internal copy of the positions: one 32-byte record (x, y, z, w) per node, w the inverse mass
// of this step, in the model's internal node order (see PositionBasedModel::OrderNodes).
class PositionBasedState final : public TissueState {
 public:
  // The 4 × num_nodes internal records, 64-byte aligned inside node_buffer.
  double* nodes() { return node_buffer.data() + node_offset; }
  std::vector<double> node_buffer;   // 4 num_nodes + 8
  size_t node_offset = 0;            // of the first record in node_buffer
  std::vector<double> predicted;     // x̃ (primal correction), 4 × num_nodes, internal order
  std::vector<double> impulse;       // Σ ∇C λ per node [N s²], 4 × num_nodes, internal order
  std::vector<double> inverse_mass;  // w this step (0 for fixed, prescribed), internal order
  std::vector<double> lambda;  // multipliers [N s²] of this step, num_constraints, sweep order
  // Per-constraint factors of the step, in sweep order (num_constraints), functions of Δt and w
  // only: recomputed when either changes.
  std::vector<double> sweep_alpha;  // α̃ = compliance/Δt² [1/kg] (0 in seed mode)
  std::vector<double> sweep_gain;  // 1/(w_i + w_j + α̃) (seed: k/(w_i + w_j)); 0 if w_i + w_j = 0
  // w_i gain and w_j gain [–], the vector sweep's factors: it then needs no w from the records,
  // and stores only their x, y and z.
  std::vector<double> sweep_wi_gain;
  std::vector<double> sweep_wj_gain;
  std::vector<double> prepared_w;  // the w the factors were computed with, internal order
  double prepared_dt = 0.0;        // and the Δt [s] (0: not yet)
  double last_dt = 0.0;            // [s] of the last accepted step, 0 before any
  std::vector<uint8_t> cut;        // 1 = removed by Cut, num_constraints, constraint order
  // Attachments, merged per node: Σ_a k_a (t_a - x) = K (t̄ - x) with K = Σ k_a,
  // t̄ = Σ k_a t_a / K, projected as one compliant vector constraint (compliance 1/K).
  std::vector<double> attach_stiffness;  // K [N/m], num_nodes, 0 between steps
  mesh::Points attach_weighted_target;   // Σ k_a t_a [N], 3 × num_nodes
  mesh::Points attach_lambda;            // [N s²], 3 × num_nodes
  std::vector<int32_t> attached_nodes;   // the first num_attached are this step's, num_nodes
  size_t num_attached = 0;

 protected:
  // λ is zeroed at the start of every step, so an accepted step's multipliers are kept by a swap
  // (no copy): good_lambda_ then holds them (LastConstraintResidual reads it).
  void SaveGood() override {
    lambda.swap(good_lambda_);
    good_last_dt_ = last_dt;
  }
  void RestoreGood() override { last_dt = good_last_dt_; }

 private:
  friend class PositionBasedModel;
  std::vector<double> good_lambda_;  // the last accepted step's λ, sweep order
  mesh::Points volume_forces;        // [N], 3 × num_nodes when the volume reaction is on
  double good_last_dt_ = 0.0;
};

}  // namespace somasim::models
