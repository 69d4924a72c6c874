#include "haptic_node/haptic_loop.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "common/checks/finite.h"
#include "common/checks/tool_pose.h"

namespace somasim::haptic {

HapticLoop::HapticLoop(const ArmKinematics& kinematics, const HapticLoopSettings& settings)
    : HapticLoop(settings) {
  kinematics_ = &kinematics;
  command_.num_joints = static_cast<uint32_t>(kinematics.num_joints());
}

HapticLoop::HapticLoop(const HapticLoopSettings& settings)
    : s_(settings), output_(settings.output) {
  checks::RequireFinitePositive("haptic loop", "arm_timeout", s_.arm_timeout);
  checks::RequireFinitePositive("haptic loop", "velocity_cutoff", s_.velocity_cutoff);
  checks::RequireFinitePositive("haptic loop", "rearm_after", s_.rearm_after);
  command_.num_joints = 0;
}

const char* HapticLoop::fault_reason() const {
  if (!output_.fault()) return "";
  return device_problem_ != nullptr ? device_problem_ : output_.fault_reason();
}

const char* CartesianStateProblem(const CartesianState& s) {
  switch (checks::CheckToolPose(s.position, s.orientation, s.gripper)) {
    case checks::ToolPoseProblem::kPosition:
      return "the device's position is not finite or beyond 10 m";
    case checks::ToolPoseProblem::kOrientation:
      return "the device's orientation is not a unit quaternion";
    case checks::ToolPoseProblem::kGrip:
      return "the device's gripper is not in [0, 1]";
    case checks::ToolPoseProblem::kNone:
      break;
  }
  return nullptr;
}

const char* HapticLoop::CheckDevice(const HapticLoopInput& in, bool* have_state) {
  const double nominal = s_.output.dt;
  const char* problem = in.header_problem;
  *have_state = false;
  if (problem == nullptr) {
    switch (in.read) {
      case arm_shm::ReadResult::kTorn:
        // A driver preempted mid-write (by this loop, on its core) leaves its record odd for a
        // while: a tick without news. Torn for as long as the heartbeat may be still: the
        // driver died mid-write.
        ++counters_.torn_reads;
        if (static_cast<double>(++torn_streak_) * nominal > s_.arm_timeout) {
          problem = "torn reads of the arm's state (its driver died mid-write?)";
        }
        break;
      case arm_shm::ReadResult::kNoData:
        if (phase_ == LoopPhase::kRunning) problem = "the arm's state vanished";
        break;
      case arm_shm::ReadResult::kOk:
        torn_streak_ = 0;
        problem = kinematics_ != nullptr ? arm_shm::StateProblem(in.state, command_.num_joints)
                                         : CartesianStateProblem(in.cartesian);
        *have_state = problem == nullptr;
        break;
    }
  }
  if (*have_state) {
    const uint64_t heartbeat = kinematics_ != nullptr ? in.state.heartbeat : in.cartesian.heartbeat;
    if (!seen_heartbeat_ || heartbeat != last_heartbeat_) {
      if (seen_heartbeat_) phase_ = LoopPhase::kRunning;  // the device is alive
      seen_heartbeat_ = true;
      last_heartbeat_ = heartbeat;
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
      *have_state = false;
    }
  }
  return problem;
}

HapticLoop::DevicePose HapticLoop::Pose(const HapticLoopInput& in) {
  DevicePose pose;
  if (kinematics_ != nullptr) {
    const JointVector q = kinematics_->JointsFromEncoders(in.state.joint);
    const ArmPose arm_pose = kinematics_->Forward(q, &jacobian_);
    const ArmPose scene_pose = kinematics_->ToScene(arm_pose);
    pose.position = arm_pose.position;
    pose.scene_position = scene_pose.position;
    pose.scene_rotation = scene_pose.rotation;
    pose.buttons = in.state.buttons;
    pose.jaw = in.state.gripper;
  } else {
    const CartesianState& c = in.cartesian;
    pose.position = Eigen::Vector3d(c.position[0], c.position[1], c.position[2]);
    pose.scene_position = pose.position;
    pose.scene_rotation =
        Eigen::Quaterniond(c.orientation[0], c.orientation[1], c.orientation[2], c.orientation[3])
            .normalized()
            .toRotationMatrix();
    pose.buttons = c.buttons;
    pose.jaw = c.gripper;
  }
  return pose;
}

void HapticLoop::FollowDevice(const DevicePose& pose, double dt, int64_t now_ns) {
  if (have_pose_) {
    const Eigen::Vector3d raw = (pose.position - last_arm_position_) / dt;
    const double alpha = dt / (dt + 1.0 / (2.0 * M_PI * s_.velocity_cutoff));
    velocity_ += alpha * (raw - velocity_);
  }
  last_arm_position_ = pose.position;
  // 3. The clutch.
  const bool clutch = (pose.buttons & SOMASIM_ARM_BUTTON_CLUTCH) != 0;
  if (clutch) {
    ++counters_.clutch_ticks;  // the tool stays where it is
  } else {
    if (clutched_) {  // released: the tool follows from where it was left
      offset_position_ = tool_position_ - pose.scene_position;
      offset_rotation_ = tool_rotation_ * pose.scene_rotation.transpose();
    }
    tool_position_ = pose.scene_position + offset_position_;
    tool_rotation_ = offset_rotation_ * pose.scene_rotation;
  }
  // A fault clears when the operator presses and releases the clutch on a usable device.
  if (!clutch && clutched_ && output_.fault() && healthy_since_ns_ >= 0 &&
      1e-9 * static_cast<double>(now_ns - healthy_since_ns_) >= s_.rearm_after) {
    output_.ClearFault();
    device_problem_ = nullptr;
    ++counters_.fault_clears;
  }
  clutched_ = clutch;
  have_pose_ = true;
  tool_.jaw = pose.jaw;
}

ForceInput HapticLoop::ModelForce(const HapticLoopInput& in, bool estop, bool device_ok) {
  ForceInput fi;
  fi.velocity = velocity_;
  fi.emergency_stop = estop;
  fi.device_ok = device_ok;
  if (in.model != nullptr && have_pose_) {
    fi.model_age = std::max(0.0, 1e-9 * static_cast<double>(in.now_ns - in.model->received_ns));
    if (!clutched_) {
      const Eigen::Vector3d tool_velocity =
          kinematics_ != nullptr ? kinematics_->VelocityToScene(velocity_) : velocity_;
      const force_model::LocalForceModel& model = in.model->model;
      const force_model::ForceSample sample =
          force_model::EvaluateLocalForceModel(model, tool_position_, tool_velocity);
      // An unusable model reaches the output stage as what it is: not a force (it latches).
      scene_force_ = sample.invalid
                         ? Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN())
                         : sample.force;
      fi.desired = kinematics_ != nullptr ? kinematics_->ForceToArm(scene_force_) : scene_force_;
      in_contact_ = model.in_contact && sample.in_contact;
      grasping_ = model.grasping;
    }
  }
  return fi;
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
  bool have_state = false;
  const char* problem = CheckDevice(in, &have_state);
  const bool waiting = phase_ == LoopPhase::kWaitingForArm;
  // Silence and a missing or torn state before the device runs are not faults; a bad header or
  // bad values always are.
  const bool device_ok =
      problem == nullptr || (waiting && (in.read != arm_shm::ReadResult::kOk || have_state));
  if (problem != nullptr) ++counters_.bad_states;

  command_.node_time_ns = static_cast<uint64_t>(in.now_ns);
  command_.heartbeat = ++heartbeat_;
  command_.enable = 0;
  for (double& t : command_.torque) t = 0.0;
  for (double& f : command_.force) f = 0.0;
  command_.reserved = 0.0;
  scene_force_.setZero();
  arm_force_.setZero();
  in_contact_ = false;
  grasping_ = false;

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

  // 2–3. The pose, from a usable state, and the clutch.
  const DevicePose pose = have_state ? Pose(in) : DevicePose{};
  const uint32_t buttons = have_state ? pose.buttons : tool_.buttons;
  const bool estop = (buttons & SOMASIM_ARM_BUTTON_EMERGENCY_STOP) != 0;
  if (have_state) FollowDevice(pose, dt, in.now_ns);
  if (device_ok) {
    if (healthy_since_ns_ < 0) healthy_since_ns_ = in.now_ns;
  } else {
    healthy_since_ns_ = -1;
  }
  tool_.time_ns = in.now_ns;
  tool_.tool = in.tool;
  for (int i = 0; i < 3; ++i) tool_.position[i] = tool_position_[i];
  const Eigen::Quaterniond o(tool_rotation_);
  tool_.orientation[0] = o.w();
  tool_.orientation[1] = o.x();
  tool_.orientation[2] = o.y();
  tool_.orientation[3] = o.z();
  tool_.buttons = buttons;
  tool_.valid = have_pose_ ? 1 : 0;

  // 4. The force.
  if (estop) ++counters_.emergency_stop_ticks;
  const ForceInput fi = ModelForce(in, estop, device_ok);
  if (!device_ok && !output_.fault()) device_problem_ = problem;
  arm_force_ = output_.Tick(fi);

  // 5. The command.
  if (!output_.fault() && !estop && have_pose_) {
    if (kinematics_ != nullptr) {
      JointVector tau;
      if (kinematics_->Torques(jacobian_, arm_force_, &tau)) ++counters_.torque_clamped_ticks;
      for (uint32_t k = 0; k < command_.num_joints; ++k) command_.torque[k] = tau[k];
    }
    for (int i = 0; i < 3; ++i) command_.force[i] = arm_force_[i];
    command_.enable = 1;
  }
  return command_;
}

}  // namespace somasim::haptic
