// The one interface every tissue model implements (mass-spring, molecular, position-based, FEM,
// reduced, meshless): a read-only model plus a mutable state (../shared/STYLE.md), stepped by
// the server's physics thread. Pure physics: no I/O, no DDS, no logging.
//
// A step reads StepInputs (views into caller-owned arrays, so stepping allocates nothing), moves
// the state, and checks the result: a step that produces a non-finite value or a speed above the
// model's limit is rejected — the state is restored to the last good step and the rejection is
// counted — so no NaN ever leaves a model.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <memory>
#include <span>

#include "common/mesh/mesh_types.h"
#include "server/models/cut_geometry.h"

namespace somasim::models {

// A spring from a node to a target point: a grasping jaw holding tissue.
struct Attachment {
  int32_t node = 0;                                  // 0..num_nodes-1
  Eigen::Vector3d target = Eigen::Vector3d::Zero();  // [m]
  double stiffness = 0.0;                            // [N/m], >= 0
};

// What drives one step. Spans and pointers view the caller's arrays; nothing is copied.
struct StepInputs {
  double dt = 1e-3;                                    // [s], > 0
  Eigen::Vector3d gravity = Eigen::Vector3d::Zero();   // [m/s²]
  const mesh::Points* external_forces = nullptr;       // [N], 3 × num_nodes, or none
  std::span<const int32_t> fixed_nodes;                // held still where they are
  std::span<const int32_t> prescribed_nodes;           // moved to prescribed_positions
  const mesh::Points* prescribed_positions = nullptr;  // [m], 3 × prescribed_nodes.size()
  std::span<const Attachment> attachments;             // grasps
};

enum class StepStatus {
  kOk,
  kRejectedNonFinite,  // a position or velocity became NaN or infinite
  kRejectedTooFast,    // a node moved faster than the model's speed limit (energy blow-up)
  kBadInput,           // StepInputs out of range (dt, indices, sizes); nothing changed
};
const char* StepStatusName(StepStatus status);

struct StepCounters {
  int64_t steps = 0;               // accepted steps
  int64_t rejected_steps = 0;      // steps rolled back because they diverged
  int64_t bad_inputs = 0;          // steps refused because of their inputs
  int64_t solver_iterations = 0;   // iterations of the model's linear or constraint solver
  int64_t solver_unconverged = 0;  // steps whose solver stopped at its iteration limit
};

// The mutable part of a model: what a snapshot, a replay or a rollback needs. Models derive from
// it to add their internal variables and scratch, all sized by MakeState.
class TissueState {
 public:
  virtual ~TissueState() = default;
  mesh::Points positions;   // [m], 3 × num_nodes
  mesh::Points velocities;  // [m/s], 3 × num_nodes
  double time = 0.0;        // [s] of accepted steps
  StepCounters counters;

 protected:
  friend class TissueModel;
  // Models with internal variables beyond positions and velocities save and restore them here,
  // so a rejected step rolls back completely. Must not allocate.
  virtual void SaveGood() {}
  virtual void RestoreGood() {}
  mesh::Points last_good_positions_;  // restored when a step diverges
  mesh::Points last_good_velocities_;
  // Written by the Advance of a model that checks the state it produces itself
  // (TissueModel::ChecksStateItself): a position or velocity is not finite; a velocity component
  // is above speed_limit() / √3 (the node's speed is then checked exactly).
  bool checked_non_finite_ = false;
  bool checked_maybe_too_fast_ = false;
};

// What a model that checks the state it writes itself (TissueModel::ChecksStateItself) finds:
// a position or velocity that is not finite; a velocity component above the limit (the node's
// speed is then checked exactly).
struct StateCheck {
  bool non_finite = false;
  bool maybe_too_fast = false;
  // One position component x [m] and velocity component v [m/s] as written; component_limit
  // [m/s] is TissueModel::component_speed_limit().
  void Add(double x, double v, double component_limit) {
    // x − x is 0 for every finite x and NaN for NaN and ±∞.
    non_finite = non_finite || !(x - x == 0.0) || !(v - v == 0.0);
    maybe_too_fast = maybe_too_fast || std::abs(v) > component_limit;
  }
};

struct EnergyReport {
  double kinetic = 0.0;                                // [J] ½ Σ m |v|²
  double elastic = 0.0;                                // [J] the model's internal energy
  double gravity = 0.0;                                // [J] -Σ m g·x
  Eigen::Vector3d momentum = Eigen::Vector3d::Zero();  // [kg m/s] Σ m v
  double total() const { return kinetic + elastic + gravity; }
};

class TissueModel {
 public:
  virtual ~TissueModel() = default;
  TissueModel() = default;
  TissueModel(const TissueModel&) = delete;
  TissueModel& operator=(const TissueModel&) = delete;

  virtual int32_t num_nodes() const = 0;
  // A state at rest in the reference configuration, with every buffer a step needs.
  virtual std::unique_ptr<TissueState> MakeState() const = 0;
  // Advances `state` by inputs.dt. Allocates nothing; never leaves a NaN in `state`.
  StepStatus Step(const StepInputs& inputs, TissueState* state) const;
  // The 3×3 stiffness -∂f_node/∂x_node [N/m] at the current state (what the haptic node renders).
  virtual Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const = 0;
  // Internal forces [N] at the state's positions and velocities, 3 × num_nodes.
  virtual void InternalForces(const TissueState& state, mesh::Points* forces) const = 0;
  virtual EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const = 0;
  // Whether Cut() can remove elements crossing a swept surface (the cutting issue).
  virtual bool SupportsCutting() const { return false; }
  // The cut hook (SPEC §5.3, the cutting issue calls it between steps): removes the springs or
  // constraints whose segment, at the state's current positions, crosses the blade's swept quad,
  // and returns how many it removed. The removal is part of the state (a snapshot or replay
  // carries it; a rejected step does not undo it); the model stays read-only. Models that do not
  // support cutting remove nothing and return 0. Not for the 1 kHz path: O(springs).
  virtual int32_t Cut(const SweptQuad& /*sweep*/, TissueState* /*state*/) const { return 0; }
  // Nodes faster than this [m/s] mark a step as diverged (tissue never moves like that).
  double speed_limit() const { return speed_limit_; }

 protected:
  // The model's own integration of one step; inputs are already checked.
  virtual void Advance(const StepInputs& inputs, TissueState* state) const = 0;
  void set_speed_limit(double limit) { speed_limit_ = limit; }
  // True when Advance itself writes the positions and velocities it starts from into the
  // state's last-good buffers (LastGoodPositions/Velocities below) before changing them, in its
  // own pass over the nodes: Step then skips its copy of the accepted state, and a rejected step
  // restores the state the step started from. (That is the last accepted state unless the
  // caller edited the state in between, in which case it is the edited one.) The last-good
  // buffers then lag one step behind between steps, which nothing outside Step reads.
  virtual bool SavesGoodStateItself() const { return false; }
  // True when Advance checks every position and velocity as it writes them and sets the state's
  // checked_non_finite_ and checked_maybe_too_fast_ (the same tests as Step's own pass over the
  // nodes, which Step then skips: a reduced model writes the whole field in one pass anyway).
  virtual bool ChecksStateItself() const { return false; }
  // The last-good buffers of `state` (3 × num_nodes each), for a model that saves them itself.
  static double* LastGoodPositions(TissueState* state) {
    return state->last_good_positions_.data();
  }
  static double* LastGoodVelocities(TissueState* state) {
    return state->last_good_velocities_.data();
  }
  // For a model whose Advance writes every position and velocity anew from the ones the step
  // starts from (SavesGoodStateItself without a copy): exchanges the state's positions and
  // velocities with its last-good buffers, which swaps pointers (no copy, no allocation). The
  // start of the step is then the last-good state, to be read, and `positions`/`velocities`
  // hold stale values until the model writes them all.
  static void SwapWithLastGood(TissueState* state) {
    state->positions.swap(state->last_good_positions_);
    state->velocities.swap(state->last_good_velocities_);
  }
  // For a model that checks the state itself (ChecksStateItself): sets the flags Step reads.
  static void SetStateChecked(TissueState* state, bool non_finite, bool maybe_too_fast) {
    state->checked_non_finite_ = non_finite;
    state->checked_maybe_too_fast_ = maybe_too_fast;
  }
  // The velocity component above which Step measures a node's speed [m/s]: every node faster
  // than speed_limit() has a component above speed_limit() / √3.
  double component_speed_limit() const { return speed_limit_ / std::sqrt(3.0); }
  // Step's own check of every position and velocity, setting the same flags: the fallback of a
  // model that checks itself when its own check cannot answer for the final state.
  void CheckWholeState(TissueState* state) const;
  // Sizes the base-class buffers of a freshly made state and fills them with `rest`.
  static void InitialiseState(const mesh::Points& rest, TissueState* state);

 private:
  double speed_limit_ = 100.0;  // [m/s]
};

}  // namespace somasim::models
