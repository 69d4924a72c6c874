#include "haptic_node/haptic_loop.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace somasim::haptic {

PackedForceModel Pack(const contact::LocalForceModel& m, int64_t received_ns) {
  PackedForceModel p;
  p.sequence = m.sequence;
  p.received_ns = received_ns;
  p.sim_time = m.sim_time;
  p.in_contact = m.in_contact ? 1 : 0;
  p.grasping = m.grasping ? 1 : 0;
  for (int i = 0; i < 3; ++i) {
    p.contact_point[i] = m.contact_point[i];
    p.normal[i] = m.normal[i];
    p.grasp_anchor[i] = m.grasp_anchor[i];
    p.bias_force[i] = m.bias_force[i];
    for (int j = 0; j < 3; ++j) p.grasp_stiffness[3 * i + j] = m.grasp_stiffness(i, j);
  }
  p.contact_stiffness = m.contact_stiffness;
  p.damping = m.damping;
  p.force_limit = m.force_limit;
  return p;
}

contact::LocalForceModel Unpack(const PackedForceModel& p) {
  contact::LocalForceModel m;
  m.sequence = p.sequence;
  m.sim_time = p.sim_time;
  m.in_contact = p.in_contact != 0;
  m.grasping = p.grasping != 0;
  for (int i = 0; i < 3; ++i) {
    m.contact_point[i] = p.contact_point[i];
    m.normal[i] = p.normal[i];
    m.grasp_anchor[i] = p.grasp_anchor[i];
    m.bias_force[i] = p.bias_force[i];
    for (int j = 0; j < 3; ++j) m.grasp_stiffness(i, j) = p.grasp_stiffness[3 * i + j];
  }
  m.contact_stiffness = p.contact_stiffness;
  m.damping = p.damping;
  m.force_limit = p.force_limit;
  return m;
}

HapticLoop::HapticLoop(const ArmKinematics& kinematics, const HapticLoopSettings& settings)
    : kinematics_(kinematics), s_(settings), output_(settings.output) {
  const std::pair<const char*, double> positive[] = {{"arm_timeout", s_.arm_timeout},
                                                     {"velocity_cutoff", s_.velocity_cutoff},
                                                     {"rearm_after", s_.rearm_after}};
  for (const auto& [name, value] : positive) {
    if (!std::isfinite(value) || value <= 0.0) {
      throw std::invalid_argument(std::string("haptic loop: ") + name + " must be finite and > 0");
    }
  }
  command_.num_joints = static_cast<uint32_t>(kinematics_.num_joints());
}

const char* HapticLoop::fault_reason() const {
  if (!output_.fault()) return "";
  return device_problem_ != nullptr ? device_problem_ : output_.fault_reason();
}

const somasim_arm_command_t& HapticLoop::Tick(const HapticLoopInput& in) {
  ++counters_.ticks;
  const double nominal = s_.output.dt;
  const double dt = last_now_ns_ == 0
                        ? nominal
                        : std::clamp(1e-9 * static_cast<double>(in.now_ns - last_now_ns_),
                                     0.1 * nominal, 10.0 * nominal);
  last_now_ns_ = in.now_ns;

  // 1. The device.
  const char* problem = in.header_problem;
  bool have_state = false;
  if (problem == nullptr) {
    switch (in.read) {
      case arm::ReadResult::kTorn:
        // A driver preempted mid-write (by this loop, on its core) leaves its record odd for a
        // while: a tick without news. Torn for as long as the heartbeat may be still: the
        // driver died mid-write.
        ++counters_.torn_reads;
        if (static_cast<double>(++torn_streak_) * nominal > s_.arm_timeout) {
          problem = "torn reads of the arm's state (its driver died mid-write?)";
        }
        break;
      case arm::ReadResult::kNoData:
        if (phase_ == LoopPhase::kRunning) problem = "the arm's state vanished";
        break;
      case arm::ReadResult::kOk:
        torn_streak_ = 0;
        problem = arm::StateProblem(in.state, command_.num_joints);
        have_state = problem == nullptr;
        break;
    }
  }
  if (have_state) {
    if (!seen_heartbeat_ || in.state.heartbeat != last_heartbeat_) {
      if (seen_heartbeat_) phase_ = LoopPhase::kRunning;  // the driver is alive
      seen_heartbeat_ = true;
      last_heartbeat_ = in.state.heartbeat;
      heartbeat_changed_ns_ = in.now_ns;
      still_ticks_ = 0;
    } else {
      ++still_ticks_;
    }
    // Still for arm_timeout on the clock and over as many of our own ticks: a node that was
    // itself held up (a stalled host wakes the node before the driver) does not blame the arm.
    if (phase_ == LoopPhase::kRunning &&
        1e-9 * static_cast<double>(in.now_ns - heartbeat_changed_ns_) > s_.arm_timeout &&
        static_cast<double>(still_ticks_) * nominal >= s_.arm_timeout) {
      problem = "the arm's heartbeat stopped";
      have_state = false;
    }
  }
  const bool waiting = phase_ == LoopPhase::kWaitingForArm;
  // Silence and a missing or torn state before the driver runs are not faults; a bad header or
  // bad values always are.
  const bool device_ok =
      problem == nullptr || (waiting && (in.read != arm::ReadResult::kOk || have_state));
  if (problem != nullptr) ++counters_.bad_states;

  command_.node_time_ns = static_cast<uint64_t>(in.now_ns);
  command_.heartbeat = ++heartbeat_;
  command_.enable = 0;
  for (double& t : command_.torque) t = 0.0;
  for (double& f : command_.force) f = 0.0;
  command_.reserved = 0.0;
  scene_force_.setZero();
  arm_force_.setZero();

  if (waiting) {
    ++counters_.waiting_ticks;
    if (!device_ok) {  // a corrupted block or garbage from the driver: latch, even now
      if (!output_.fault()) device_problem_ = problem;
      ForceInput fi;
      fi.device_ok = false;
      output_.Tick(fi);
    }
    return command_;
  }

  // 2. The pose, from a usable state.
  const uint32_t buttons = have_state ? in.state.buttons : tool_.buttons;
  const bool clutch = (buttons & SOMASIM_ARM_BUTTON_CLUTCH) != 0;
  const bool estop = (buttons & SOMASIM_ARM_BUTTON_EMERGENCY_STOP) != 0;
  if (have_state) {
    const JointVector q = kinematics_.JointsFromEncoders(in.state.joint);
    const ArmPose arm_pose = kinematics_.Forward(q, &jacobian_);
    const ArmPose scene_pose = kinematics_.ToScene(arm_pose);
    if (have_pose_) {
      const Eigen::Vector3d raw = (arm_pose.position - last_arm_position_) / dt;
      const double alpha = dt / (dt + 1.0 / (2.0 * M_PI * s_.velocity_cutoff));
      velocity_ += alpha * (raw - velocity_);
    }
    last_arm_position_ = arm_pose.position;
    // 3. The clutch.
    if (clutch) {
      ++counters_.clutch_ticks;  // the tool stays where it is
    } else {
      if (clutched_) {  // released: the tool follows from where it was left
        offset_position_ = tool_position_ - scene_pose.position;
        offset_rotation_ = tool_rotation_ * scene_pose.rotation.transpose();
      }
      tool_position_ = scene_pose.position + offset_position_;
      tool_rotation_ = offset_rotation_ * scene_pose.rotation;
    }
    // A fault clears when the operator presses and releases the clutch on a usable device.
    if (!clutch && clutched_ && output_.fault() && healthy_since_ns_ >= 0 &&
        1e-9 * static_cast<double>(in.now_ns - healthy_since_ns_) >= s_.rearm_after) {
      output_.ClearFault();
      device_problem_ = nullptr;
      ++counters_.fault_clears;
    }
    clutched_ = clutch;
    have_pose_ = true;
    tool_.jaw = in.state.gripper;
  }
  if (device_ok) {
    if (healthy_since_ns_ < 0) healthy_since_ns_ = in.now_ns;
  } else {
    healthy_since_ns_ = -1;
  }
  tool_.time_ns = in.now_ns;
  for (int i = 0; i < 3; ++i) tool_.position[i] = tool_position_[i];
  const Eigen::Quaterniond o(tool_rotation_);
  tool_.orientation[0] = o.w();
  tool_.orientation[1] = o.x();
  tool_.orientation[2] = o.y();
  tool_.orientation[3] = o.z();
  tool_.buttons = buttons;
  tool_.valid = have_pose_ ? 1 : 0;

  // 4. The force.
  ForceInput fi;
  fi.velocity = velocity_;
  fi.emergency_stop = estop;
  fi.device_ok = device_ok;
  if (estop) ++counters_.emergency_stop_ticks;
  if (in.model != nullptr && have_pose_) {
    fi.model_age = std::max(0.0, 1e-9 * static_cast<double>(in.now_ns - in.model->received_ns));
    if (!clutched_) {
      const contact::LocalForceModel model = Unpack(*in.model);
      const Eigen::Vector3d tool_velocity = kinematics_.VelocityToScene(velocity_);
      const contact::ForceSample sample =
          contact::EvaluateLocalForceModel(model, tool_position_, tool_velocity);
      // An unusable model reaches the output stage as what it is: not a force (it latches).
      scene_force_ = sample.invalid
                         ? Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN())
                         : sample.force;
      fi.desired = kinematics_.ForceToArm(scene_force_);
    }
  }
  if (!device_ok && !output_.fault()) device_problem_ = problem;
  arm_force_ = output_.Tick(fi);

  // 5. The command.
  if (!output_.fault() && !estop && have_pose_) {
    JointVector tau;
    if (kinematics_.Torques(jacobian_, arm_force_, &tau)) ++counters_.torque_clamped_ticks;
    for (uint32_t k = 0; k < command_.num_joints; ++k) command_.torque[k] = tau[k];
    for (int i = 0; i < 3; ++i) command_.force[i] = arm_force_[i];
    command_.enable = 1;
  }
  return command_;
}

}  // namespace somasim::haptic
