// A haptic arm's kinematics from its configuration file (idl/arm.proto, *.arm.txtpb): joint
// values from encoder values (homing offsets), forward kinematics of the handle's point, the
// positional Jacobian, joint torques J^T F for a force at the handle, and the mapping between
// the arm's workspace and the scene. Checked once when loaded; every per-tick call is
// allocation-free (fixed-size matrices of kMaxJoints columns).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <stdexcept>
#include <string>

#include "common/arm_shm/arm_abi.h"

namespace somasim::arm {
class Arm;
}  // namespace somasim::arm

namespace somasim::haptic {

// A configuration that cannot be used: what() is "FILE:LINE: message" for text that does not
// parse, "FILE: FIELD: message" for a value out of range.
class ArmConfigError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

inline constexpr int kMaxJoints = SOMASIM_ARM_MAX_JOINTS;
using JointVector = Eigen::Matrix<double, kMaxJoints, 1>;  // the first num_joints() used
using Jacobian = Eigen::Matrix<double, 3, kMaxJoints>;     // [m/rad or m/m], arm frame

struct ArmPose {
  Eigen::Vector3d position = Eigen::Vector3d::Zero();      // [m] the handle's point
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  // the tool frame (shaft +z)
};

class ArmKinematics {
 public:
  // Parses and checks a configuration (`file` names it in errors). Throws ArmConfigError.
  static ArmKinematics FromText(const std::string& text, const std::string& file);
  static ArmKinematics Load(const std::string& path);

  int num_joints() const { return num_joints_; }
  const std::string& name() const { return name_; }
  double max_force() const { return max_force_; }      // [N] at the handle
  double force_scale() const { return force_scale_; }  // arm N per scene N
  double scale() const { return scale_; }              // scene m per arm m
  double max_torque(int joint) const { return joints_[static_cast<size_t>(joint)].max_torque; }
  double home_offset(int joint) const { return joints_[static_cast<size_t>(joint)].home_offset; }
  double joint_min(int joint) const { return joints_[static_cast<size_t>(joint)].min; }
  double joint_max(int joint) const { return joints_[static_cast<size_t>(joint)].max; }

  // q = encoder - home_offset, for the first num_joints() values.
  JointVector JointsFromEncoders(const double* encoders) const;
  // Whether every q is within its joint's [min, max].
  bool InRange(const JointVector& q) const;
  // The handle's pose in the arm's base frame, and (when asked) d position / d q.
  ArmPose Forward(const JointVector& q, Jacobian* jacobian = nullptr) const;
  // The arm's pose in the scene: position scene_origin + scale R p, rotation R · rotation.
  ArmPose ToScene(const ArmPose& arm) const;
  // A scene position [m] in the arm's frame (the inverse of ToScene's position).
  Eigen::Vector3d PositionToArm(const Eigen::Vector3d& scene_position) const;
  // A velocity [m/s] in the arm's frame, in the scene's.
  Eigen::Vector3d VelocityToScene(const Eigen::Vector3d& arm_velocity) const;
  // The force the arm renders for a scene force [N]: force_scale Rᵀ F, in the arm's frame.
  Eigen::Vector3d ForceToArm(const Eigen::Vector3d& scene_force) const;
  // Joint torques τ = Jᵀ F for a force F [N] at the handle in the arm's frame, each clamped to
  // its motor's max_torque (keeping its sign); returns whether any was clamped. Unused joints 0.
  bool Torques(const Jacobian& jacobian, const Eigen::Vector3d& arm_force, JointVector* tau) const;

 private:
  struct Joint {
    bool prismatic = false;
    Eigen::Isometry3d offset = Eigen::Isometry3d::Identity();  // previous link -> joint frame
    Eigen::Vector3d axis = Eigen::Vector3d::UnitZ();           // unit, joint frame
    double home_offset = 0.0;
    double min = 0.0, max = 0.0;
    double max_torque = 0.0;
  };
  ArmKinematics() = default;
  static ArmKinematics FromConfig(const arm::Arm& config, const std::string& file);

  std::string name_;
  int num_joints_ = 0;
  std::array<Joint, kMaxJoints> joints_{};
  Eigen::Vector3d tip_ = Eigen::Vector3d::Zero();
  Eigen::Matrix3d tool_rotation_ = Eigen::Matrix3d::Identity();  // last link -> tool frame
  double scale_ = 1.0;
  Eigen::Vector3d scene_origin_ = Eigen::Vector3d::Zero();
  Eigen::Matrix3d scene_rotation_ = Eigen::Matrix3d::Identity();
  double force_scale_ = 1.0;
  double max_force_ = 1.0;
};

// R = Rz(yaw) Ry(pitch) Rx(roll) for rpy = (roll, pitch, yaw) [rad] (fixed axes, as URDF).
Eigen::Matrix3d RotationFromRpy(const Eigen::Vector3d& rpy);

}  // namespace somasim::haptic
