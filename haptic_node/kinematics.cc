#include "haptic_node/kinematics.h"

#include <google/protobuf/io/zero_copy_stream_impl_lite.h>
#include <google/protobuf/text_format.h>

#include <cmath>
#include <fstream>
#include <sstream>

#include "common/scene/first_error.h"
#include "idl/arm.pb.h"

namespace somasim::haptic {

namespace {

Eigen::Vector3d V(const arm::Vec3& v) { return {v.x(), v.y(), v.z()}; }

}  // namespace

Eigen::Matrix3d RotationFromRpy(const Eigen::Vector3d& rpy) {
  return (Eigen::AngleAxisd(rpy.z(), Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(rpy.y(), Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(rpy.x(), Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

ArmKinematics ArmKinematics::FromText(const std::string& text, const std::string& file) {
  arm::Arm config;
  google::protobuf::TextFormat::Parser parser;
  scene::FirstError errors("not an arm configuration in protobuf text format");
  parser.RecordErrorsTo(&errors);
  google::protobuf::io::ArrayInputStream input(text.data(), static_cast<int>(text.size()));
  if (text.size() > (1u << 20)) throw ArmConfigError(file + ": larger than 1 MiB: not an arm");
  if (!parser.Parse(&input, &config)) {
    throw ArmConfigError(file + ":" + std::to_string(std::max(errors.line(), 0)) + ": " +
                         errors.message());
  }
  return FromConfig(config, file);
}

ArmKinematics ArmKinematics::Load(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ArmConfigError(path + ": cannot open the file");
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) throw ArmConfigError(path + ": cannot read the file");
  return FromText(text.str(), path);
}

ArmKinematics ArmKinematics::FromConfig(const arm::Arm& c, const std::string& file) {
  const auto fail = [&](const std::string& field, const std::string& message) {
    throw ArmConfigError(file + ": " + field + ": " + message);
  };
  const auto finite = [&](const std::string& field, const Eigen::Vector3d& v) {
    if (!v.allFinite()) fail(field, "not finite");
  };
  if (c.format_version() != 1) {
    fail("format_version", std::to_string(c.format_version()) + " is not supported (1 is)");
  }
  if (c.joint_size() < 1 || c.joint_size() > kMaxJoints) {
    fail("joint", "an arm has 1.." + std::to_string(kMaxJoints) + " joints, not " +
                      std::to_string(c.joint_size()));
  }
  ArmKinematics k;
  k.name_ = c.name();
  k.num_joints_ = c.joint_size();
  for (int i = 0; i < c.joint_size(); ++i) {
    const arm::Joint& j = c.joint(i);
    const std::string at = "joint[" + std::to_string(i) + "]";
    Joint& out = k.joints_[static_cast<size_t>(i)];
    out.prismatic = j.type() == arm::Joint::PRISMATIC;
    if (j.type() != arm::Joint::PRISMATIC && j.type() != arm::Joint::REVOLUTE) {
      fail(at + ".type", "unknown joint type " + std::to_string(j.type()));
    }
    finite(at + ".origin", V(j.origin()));
    finite(at + ".rpy", V(j.rpy()));
    finite(at + ".axis", V(j.axis()));
    if (V(j.axis()).norm() < 1e-9) fail(at + ".axis", "zero length (a joint needs an axis)");
    out.offset = Eigen::Isometry3d::Identity();
    out.offset.translation() = V(j.origin());
    out.offset.linear() = RotationFromRpy(V(j.rpy()));
    out.axis = V(j.axis()).normalized();
    const std::pair<const char*, double> values[] = {{"home_offset", j.home_offset()},
                                                     {"min", j.min()},
                                                     {"max", j.max()},
                                                     {"max_torque", j.max_torque()}};
    for (const auto& [field, value] : values) {
      if (!std::isfinite(value)) fail(at + "." + field, "not finite");
    }
    if (!(j.min() < j.max())) {
      fail(at + ".min", std::to_string(j.min()) + " is not below max " + std::to_string(j.max()));
    }
    if (j.max_torque() <= 0.0) fail(at + ".max_torque", "must be > 0");
    out.home_offset = j.home_offset();
    out.min = j.min();
    out.max = j.max();
    out.max_torque = j.max_torque();
  }
  finite("tip", V(c.tip()));
  k.tip_ = V(c.tip());
  finite("tool_rpy", V(c.tool_rpy()));
  k.tool_rotation_ = RotationFromRpy(V(c.tool_rpy()));
  if (!std::isfinite(c.scale()) || c.scale() <= 0.0) fail("scale", "must be finite and > 0");
  finite("scene_origin", V(c.scene_origin()));
  finite("scene_rpy", V(c.scene_rpy()));
  if (!std::isfinite(c.force_scale()) || c.force_scale() <= 0.0) {
    fail("force_scale", "must be finite and > 0");
  }
  if (!std::isfinite(c.max_force()) || c.max_force() <= 0.0 || c.max_force() > 100.0) {
    fail("max_force", "must be in (0, 100] N");
  }
  k.scale_ = c.scale();
  k.scene_origin_ = V(c.scene_origin());
  k.scene_rotation_ = RotationFromRpy(V(c.scene_rpy()));
  k.force_scale_ = c.force_scale();
  k.max_force_ = c.max_force();
  return k;
}

JointVector ArmKinematics::JointsFromEncoders(const double* encoders) const {
  JointVector q = JointVector::Zero();
  for (int i = 0; i < num_joints_; ++i) {
    q[i] = encoders[i] - joints_[static_cast<size_t>(i)].home_offset;
  }
  return q;
}

bool ArmKinematics::InRange(const JointVector& q) const {
  for (int i = 0; i < num_joints_; ++i) {
    const Joint& j = joints_[static_cast<size_t>(i)];
    if (!(q[i] >= j.min && q[i] <= j.max)) return false;
  }
  return true;
}

ArmPose ArmKinematics::Forward(const JointVector& q, Jacobian* jacobian) const {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  std::array<Eigen::Vector3d, kMaxJoints> origins, axes;
  for (int i = 0; i < num_joints_; ++i) {
    const Joint& j = joints_[static_cast<size_t>(i)];
    t = t * j.offset;
    origins[static_cast<size_t>(i)] = t.translation();
    axes[static_cast<size_t>(i)] = t.linear() * j.axis;
    if (j.prismatic) {
      t.translate(q[i] * j.axis);
    } else {
      t.rotate(Eigen::AngleAxisd(q[i], j.axis));
    }
  }
  ArmPose pose;
  pose.position = t * tip_;
  pose.rotation = t.linear() * tool_rotation_;
  if (jacobian != nullptr) {
    jacobian->setZero();
    for (int i = 0; i < num_joints_; ++i) {
      const Eigen::Vector3d& a = axes[static_cast<size_t>(i)];
      jacobian->col(i) = joints_[static_cast<size_t>(i)].prismatic
                             ? a
                             : a.cross(pose.position - origins[static_cast<size_t>(i)]).eval();
    }
  }
  return pose;
}

ArmPose ArmKinematics::ToScene(const ArmPose& arm) const {
  ArmPose scene;
  scene.position = scene_origin_ + scale_ * (scene_rotation_ * arm.position);
  scene.rotation = scene_rotation_ * arm.rotation;
  return scene;
}

Eigen::Vector3d ArmKinematics::PositionToArm(const Eigen::Vector3d& scene_position) const {
  return scene_rotation_.transpose() * (scene_position - scene_origin_) / scale_;
}

Eigen::Vector3d ArmKinematics::VelocityToScene(const Eigen::Vector3d& arm_velocity) const {
  return scale_ * (scene_rotation_ * arm_velocity);
}

Eigen::Vector3d ArmKinematics::ForceToArm(const Eigen::Vector3d& scene_force) const {
  return force_scale_ * (scene_rotation_.transpose() * scene_force);
}

bool ArmKinematics::Torques(const Jacobian& jacobian, const Eigen::Vector3d& arm_force,
                            JointVector* tau) const {
  tau->setZero();
  bool clamped = false;
  for (int i = 0; i < num_joints_; ++i) {
    const double limit = joints_[static_cast<size_t>(i)].max_torque;
    double t = jacobian.col(i).dot(arm_force);
    if (std::abs(t) > limit) {
      t = std::copysign(limit, t);
      clamped = true;
    }
    (*tau)[i] = t;
  }
  return clamped;
}

}  // namespace somasim::haptic
