#include "server/models/tissue_model.h"

#include <algorithm>
#include <cmath>

namespace somasim::models {

const char* StepStatusName(StepStatus status) {
  switch (status) {
    case StepStatus::kOk:
      return "ok";
    case StepStatus::kRejectedNonFinite:
      return "rejected: non-finite state";
    case StepStatus::kRejectedTooFast:
      return "rejected: speed above the limit";
    case StepStatus::kBadInput:
      return "bad step input";
  }
  return "?";
}

void TissueModel::InitialiseState(const mesh::Points& rest, TissueState* state) {
  state->positions = rest;
  state->velocities = mesh::Points::Zero(3, rest.cols());
  state->last_good_positions_ = rest;
  state->last_good_velocities_ = state->velocities;
  state->time = 0.0;
  state->counters = {};
}

StepStatus TissueModel::Step(const StepInputs& inputs, TissueState* state) const {
  const int32_t n = num_nodes();
  const auto in_range = [n](int32_t node) { return node >= 0 && node < n; };
  bool ok = inputs.dt > 0.0 && std::isfinite(inputs.dt) && inputs.gravity.allFinite();
  if (inputs.external_forces != nullptr) {
    ok = ok && inputs.external_forces->cols() == n && inputs.external_forces->allFinite();
  }
  for (const int32_t node : inputs.fixed_nodes) ok = ok && in_range(node);
  for (const int32_t node : inputs.prescribed_nodes) ok = ok && in_range(node);
  if (!inputs.prescribed_nodes.empty()) {
    ok = ok && inputs.prescribed_positions != nullptr &&
         inputs.prescribed_positions->cols() ==
             static_cast<Eigen::Index>(inputs.prescribed_nodes.size()) &&
         inputs.prescribed_positions->allFinite();
  }
  for (const Attachment& a : inputs.attachments) {
    ok = ok && in_range(a.node) && a.target.allFinite() && a.stiffness >= 0.0 &&
         std::isfinite(a.stiffness);
  }
  if (!ok) {
    ++state->counters.bad_inputs;
    return StepStatus::kBadInput;
  }

  Advance(inputs, state);

  // One pass over the raw arrays: a NaN or infinity anywhere, or a node faster than the limit.
  // Flags are OR-ed, not reduced in floating point, so the compiler vectorises the loop. A
  // non-finite x, v or |v|² makes (x + y + z + |v|² + vx + vy + vz)·0 NaN.
  const double limit2 = speed_limit_ * speed_limit_;
  const double* x = state->positions.data();
  const double* v = state->velocities.data();
  bool non_finite = false;
  bool too_fast = false;
  for (Eigen::Index i = 0; i < 3 * static_cast<Eigen::Index>(n); i += 3) {
    const double speed2 = v[i] * v[i] + v[i + 1] * v[i + 1] + v[i + 2] * v[i + 2];
    const double probe = (x[i] + x[i + 1] + x[i + 2] + speed2 + v[i] + v[i + 1] + v[i + 2]) * 0.0;
    non_finite |= !(probe == 0.0);
    too_fast |= speed2 > limit2;
  }
  StepStatus status = StepStatus::kOk;
  if (non_finite) {
    status = StepStatus::kRejectedNonFinite;
  } else if (too_fast) {
    status = StepStatus::kRejectedTooFast;
  }
  if (status != StepStatus::kOk) {
    state->positions = state->last_good_positions_;  // same size: no allocation
    state->velocities = state->last_good_velocities_;
    state->RestoreGood();
    ++state->counters.rejected_steps;
    return status;
  }
  state->last_good_positions_ = state->positions;
  state->last_good_velocities_ = state->velocities;
  state->SaveGood();
  state->time += inputs.dt;
  ++state->counters.steps;
  return StepStatus::kOk;
}

}  // namespace somasim::models
