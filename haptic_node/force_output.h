// The haptic node's one output stage (issue 9, SPEC §7): every force the arm renders passes
// here, once per 1 kHz tick, whatever computed it. Pure (no I/O, no clock: the caller passes the
// model's age), allocation-free, lock-free.
//
// In order, each tick:
//  1. A fault latches on a non-finite desired force or velocity, or when the device is not
//     usable (the caller's verdict: a silent arm heartbeat, a bad ABI header, torn or bad state
//     reads). While latched the output is zero; ClearFault() is an operator's act.
//  2. The emergency stop zeroes the output at once (no rate limit) and disengages.
//  3. Staleness: a model older than `fresh` (10 ms on the node's clock) scales the desired force
//     down linearly to zero over `ramp` (50 ms), so it is zero 60 ms after the last good model,
//     and its magnitude never rises above the last tick's while the model is stale; no model at
//     all gives zero.
//  4. Engagement: on start, after the emergency stop and after a fault clears, force engages
//     only once the (staleness-scaled) desired force has stayed below `engage_below` for
//     `engage_ticks` ticks; the authority then rises linearly from 0 to 1 over `engage_ramp`.
//     Without a usable model (none yet, or one stale to zero) the authority rests at 0 and rises
//     again over `engage_ramp` when models resume: a paused server's return never jolts.
//     Nothing at all is rendered while disengaged or once the stale ramp has reached zero, not
//     even the passivity controller's damping (step 7).
//  5. The magnitude is clamped to `max_force` (the arm's limit), keeping the direction.
//  6. The change per tick is limited to `max_step` (a jump in the model never jolts the hand).
//  7. Passivity observer (Hannaford & Ryu 2002): the energy the environment has absorbed,
//     W = Σ -F·v dt (F on the hand, v the hand's velocity). When this tick would take W below
//     -epsilon, damping b = (-epsilon - W) / (|v|² dt), at most `max_damping`, is added as -b v
//     in the same tick, then the magnitude clamp (and, while stale, last tick's magnitude) is
//     applied again. W starts again from 0 on every (re-)engagement and whenever nothing is
//     rendered: a deficit left by one coupling never damps the hand in the next.
#pragma once

#include <Eigen/Core>
#include <cstdint>

namespace somasim::haptic {

struct ForceOutputSettings {
  double dt = 1e-3;                   // [s] the tick
  double max_force = 8.0;             // [N] the arm's configured limit, > 0
  double max_step = 0.25;             // [N] per tick, > 0 (250 N/s)
  double fresh = 0.010;               // [s] a model this old is still used in full
  double ramp = 0.050;                // [s] then down to zero over this
  double engage_below = 0.2;          // [N]
  int32_t engage_ticks = 20;          // ticks the desired force stays below engage_below
  double engage_ramp = 0.5;           // [s] authority 0 -> 1
  double passivity_epsilon = 0.0005;  // [J] the energy the environment may lend
  double max_damping = 60.0;          // [N s/m] the passivity controller's at most
};

struct ForceInput {
  Eigen::Vector3d desired = Eigen::Vector3d::Zero();   // [N] the local force model's force
  double model_age = -1.0;                             // [s] on the node's clock; < 0: no model
  Eigen::Vector3d velocity = Eigen::Vector3d::Zero();  // [m/s] the hand's
  bool emergency_stop = false;
  bool device_ok = true;  // false: the caller found the arm unusable this tick
};

struct ForceOutputCounters {
  uint64_t ticks = 0;
  uint64_t faults = 0;         // latchings
  uint64_t stale_ticks = 0;    // model older than `fresh`, or none while engaged
  uint64_t clamped_ticks = 0;  // magnitude limited
  uint64_t rate_limited_ticks = 0;
  uint64_t damped_ticks = 0;  // the passivity controller acted
};

class ForceOutput {
 public:
  // Throws std::invalid_argument naming a setting that is not finite and positive (or an
  // engage_ticks below 1).
  explicit ForceOutput(const ForceOutputSettings& settings);

  // The force for this tick [N]: finite, |F| <= max_force, zero while faulted or stopped.
  Eigen::Vector3d Tick(const ForceInput& in);

  bool fault() const { return fault_; }
  // Why the fault latched (a static string; "" when none).
  const char* fault_reason() const { return fault_reason_; }
  // An operator clears the fault; force then engages again as on start.
  void ClearFault();
  bool engaged() const { return engaged_; }
  double authority() const { return authority_; }        // 0..1
  double observed_energy() const { return energy_; }     // W [J]
  double last_damping() const { return last_damping_; }  // [N s/m] this tick's added damping
  const ForceOutputCounters& counters() const { return counters_; }

 private:
  void Latch(const char* reason);
  void Disengage();

  ForceOutputSettings s_;
  Eigen::Vector3d last_ = Eigen::Vector3d::Zero();
  bool fault_ = false;
  const char* fault_reason_ = "";
  bool engaged_ = false;
  int32_t quiet_ticks_ = 0;
  double authority_ = 0.0;
  double energy_ = 0.0;
  double last_damping_ = 0.0;
  ForceOutputCounters counters_;
};

}  // namespace somasim::haptic
