#include "haptic_node/arm_sim.h"

#include <algorithm>
#include <cmath>

namespace somasim::haptic {

ArmSimulator::ArmSimulator(const ArmKinematics& kinematics, const ArmSimSettings& settings)
    : kinematics_(kinematics), s_(settings) {
  const double home[kMaxJoints] = {};
  q_ = kinematics_.JointsFromEncoders(home);
}

void ArmSimulator::Step(double now, double dt, const somasim_arm_command_t* command,
                        const Eigen::Vector3d& hand_target) {
  const int n = kinematics_.num_joints();
  // The watchdog: the node's heartbeat must move at least every s_.watchdog seconds.
  if (command != nullptr && command->heartbeat != last_heartbeat_) {
    last_heartbeat_ = command->heartbeat;
    heartbeat_changed_ = now;
  }
  tripped_ = heartbeat_changed_ < 0.0 || now - heartbeat_changed_ > s_.watchdog;
  bool usable = !tripped_ && command != nullptr && command->enable == 1 &&
                command->num_joints == static_cast<uint32_t>(n);
  for (int i = 0; usable && i < n; ++i) usable = std::isfinite(command->torque[i]);
  applied_.setZero();
  if (usable) {
    for (int i = 0; i < n; ++i) {
      const double limit = kinematics_.max_torque(i);
      applied_[i] = std::clamp(command->torque[i], -limit, limit);
    }
  }
  // The hand: a spring and damper on the handle's point.
  Jacobian j;
  const ArmPose pose = kinematics_.Forward(q_, &j);
  const Eigen::Vector3d velocity = j * qd_;
  const Eigen::Vector3d hand =
      s_.hand_stiffness * (hand_target - pose.position) - s_.hand_damping * velocity;
  const JointVector hand_torque = j.transpose() * hand;
  for (int i = 0; i < n; ++i) {
    const double acceleration =
        (applied_[i] + hand_torque[i] - s_.joint_friction * qd_[i]) / s_.joint_inertia;
    qd_[i] += acceleration * dt;  // semi-implicit Euler
    q_[i] += qd_[i] * dt;
    if (q_[i] < kinematics_.joint_min(i) || q_[i] > kinematics_.joint_max(i)) {
      q_[i] = std::clamp(q_[i], kinematics_.joint_min(i), kinematics_.joint_max(i));
      qd_[i] = 0.0;  // the mechanical stop
    }
  }
}

somasim_arm_state_t ArmSimulator::State(uint64_t heartbeat, uint64_t time_ns, uint32_t buttons,
                                        double gripper) const {
  somasim_arm_state_t s{};
  s.driver_time_ns = time_ns;
  s.heartbeat = heartbeat;
  s.buttons = buttons;
  s.num_joints = static_cast<uint32_t>(kinematics_.num_joints());
  for (int i = 0; i < kinematics_.num_joints(); ++i)
    s.joint[i] = q_[i] + kinematics_.home_offset(i);
  s.gripper = gripper;
  return s;
}

}  // namespace somasim::haptic
