// The arm simulator (issue 9): what `somasim-arm-sim` runs in place of a real arm and its
// driver. Simulated joints (each a light inertia with viscous friction, within its range) move
// under the node's commanded torques and a simulated hand: a spring and damper pulling the
// handle's point towards where a scripted hand wants it. The driver-side watchdog every real
// driver must have: when the node's heartbeat has not changed for 10 ms, or the node disables,
// or sends torques that are not finite or for another joint count, the applied torques are zero.
// Pure (the caller passes the time, the command it read and the hand's target), allocation-free.
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "common/arm_shm/arm_abi.h"
#include "haptic_node/kinematics.h"

namespace somasim::haptic {

struct ArmSimSettings {
  double joint_inertia = 0.004;   // [kg m²] (or kg for a prismatic joint), each joint
  double joint_friction = 0.02;   // [N m s/rad]
  double hand_stiffness = 300.0;  // [N/m] the hand holding the handle
  double hand_damping = 4.0;      // [N s/m]
  double watchdog = 0.010;        // [s] the node's heartbeat may be still this long
};

class ArmSimulator {
 public:
  // Starts at home (every encoder 0).
  ArmSimulator(const ArmKinematics& kinematics, const ArmSimSettings& settings);

  // Advances by dt [s] to time `now` [s] (the simulator's clock). `command` is the node's last
  // whole command read this cycle (nullptr: none could be read); `hand_target` the handle's
  // point the hand pulls towards [m], in the arm's frame.
  void Step(double now, double dt, const somasim_arm_command_t* command,
            const Eigen::Vector3d& hand_target);

  // The driver's state for the node: encoders (q + home offset), the given buttons and gripper.
  somasim_arm_state_t State(uint64_t heartbeat, uint64_t time_ns, uint32_t buttons,
                            double gripper) const;

  const JointVector& q() const { return q_; }
  const JointVector& applied_torque() const { return applied_; }  // [N m], after the watchdog
  bool watchdog_tripped() const { return tripped_; }              // torques held at zero
  ArmPose Pose() const { return kinematics_.Forward(q_); }

 private:
  const ArmKinematics& kinematics_;
  ArmSimSettings s_;
  JointVector q_ = JointVector::Zero();
  JointVector qd_ = JointVector::Zero();
  JointVector applied_ = JointVector::Zero();
  uint64_t last_heartbeat_ = 0;
  double heartbeat_changed_ = -1.0;  // [s] when the node's heartbeat last moved (< 0: never)
  bool tripped_ = true;              // until the node's heartbeat is seen moving
};

}  // namespace somasim::haptic
