#include "server/contact/rigid_body.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>
#include <string>

#include "server/contact/triangle_queries.h"

namespace somasim::contact {
namespace {

// Grasp hysteresis on the jaw opening, as Grasp's defaults.
constexpr double kCloseBelow = 0.2;
constexpr double kOpenAbove = 0.4;

void RequirePositive(const char* name, double value, double max = 1e300) {
  if (!(std::isfinite(value) && value > 0.0 && value <= max)) {
    throw std::invalid_argument(std::string("rigid sphere: ") + name + " = " +
                                std::to_string(value) +
                                ", must be finite, > 0 and <= " + std::to_string(max));
  }
}

}  // namespace

RigidSphere::RigidSphere(const RigidSphereSettings& settings, const Eigen::Vector3d& position)
    : settings_(settings), position_(position) {
  RequirePositive("radius", settings.radius, 0.2);
  RequirePositive("density", settings.density);
  RequirePositive("tissue_stiffness", settings.tissue_stiffness);
  RequirePositive("tool_stiffness", settings.tool_stiffness);
  RequirePositive("grasp_stiffness", settings.grasp_stiffness);
  if (!(std::isfinite(settings.damping) && settings.damping >= 0.0)) {
    throw std::invalid_argument("rigid sphere: damping must be finite and >= 0 N s/m");
  }
  if (settings.max_tissue_contacts <= 0) {
    throw std::invalid_argument("rigid sphere: max_tissue_contacts must be > 0");
  }
  if (!position.allFinite()) throw std::invalid_argument("rigid sphere: position is not finite");
  const double r = settings.radius;
  mass_ = settings.density * 4.0 / 3.0 * std::numbers::pi * r * r * r;
  const auto contacts = static_cast<size_t>(settings.max_tissue_contacts);
  attachments_.resize(3 * contacts);
  directions_.resize(3 * contacts);
  candidates_.resize(contacts);
}

void RigidSphere::CollectTissueContacts(const AabbTree& tree, const mesh::Points& positions) {
  num_attachments_ = 0;
  const double r = settings_.radius;
  const int32_t found =
      std::min(tree.SphereQuery(position_, r, {candidates_.data(), candidates_.size()}),
               static_cast<int32_t>(candidates_.size()));
  for (int32_t k = 0; k < found; ++k) {
    const auto tri = tree.triangles().col(candidates_[static_cast<size_t>(k)]);
    const Eigen::Vector3d a = positions.col(tri[0]), b = positions.col(tri[1]),
                          c = positions.col(tri[2]);
    const Eigen::Vector3d w = ClosestPointBarycentric(position_, a, b, c);
    const Eigen::Vector3d p = w[0] * a + w[1] * b + w[2] * c;
    Eigen::Vector3d out = p - position_;
    const double d = out.norm();
    if (d >= r) continue;
    if (d > 0.0) {
      out /= d;
    } else {  // the centre on the triangle: push the triangle along its normal
      out = (b - a).cross(c - a).normalized();
      if (!out.allFinite()) continue;
    }
    // The triangle's touching point belongs at the sphere's surface: p + (r - d) out.
    for (int corner = 0; corner < 3; ++corner) {
      if (!(w[corner] > 0.0)) continue;
      const auto i = static_cast<size_t>(num_attachments_++);
      attachments_[i].node = tri[corner];
      attachments_[i].target = positions.col(tri[corner]) + (r - d) * out;
      attachments_[i].stiffness = w[corner] * settings_.tissue_stiffness;
      directions_[i] = out;
    }
  }
}

void RigidSphere::UpdateTool(const ToolShape& shape, const ToolPose& pose) {
  if (!ToolPoseError(pose).empty()) return;
  const Eigen::Quaterniond q = pose.orientation.normalized();
  tool_orientation_ = q;
  pushed_ = false;
  if (shape.kind == ToolKind::kCamera) {
    grasped_ = false;
    last_tip_ = pose.tip;
    return;
  }
  if (shape.kind == ToolKind::kGrasper) {
    const bool was_closed = jaws_closed_;
    if (pose.jaw_opening < kCloseBelow) jaws_closed_ = true;
    if (pose.jaw_opening > kOpenAbove) jaws_closed_ = false;
    if (!jaws_closed_) grasped_ = false;
    if (jaws_closed_ && !was_closed) {
      const Eigen::Vector3d jaw_end = PointOnShaft(pose, shape.jaw_length);
      const double gap = (position_ - ClosestPointOnSegment(position_, pose.tip, jaw_end)).norm() -
                         settings_.radius;
      if (gap <= shape.grasp_radius) {
        grasped_ = true;
        grasp_offset_ = q.inverse() * (position_ - pose.tip);
        grasp_rotation_ = q.inverse() * orientation_;
      }
    }
  } else {
    jaws_closed_ = false;
    grasped_ = false;
  }
  if (grasped_) {
    grasp_target_ = pose.tip + q * grasp_offset_;
  } else {
    // The tip pushes the sphere where the path it swept since the last update comes within the
    // radius of the centre (continuous: a fast tip cannot pass through the sphere unnoticed).
    const Eigen::Vector3d from =
        last_tip_.allFinite() && last_tip_.x() < 1e299 ? last_tip_ : pose.tip;
    const Eigen::Vector3d nearest = ClosestPointOnSegment(position_, from, pose.tip);
    Eigen::Vector3d away = position_ - nearest;
    const double d = away.norm();
    if (d < settings_.radius) {
      pushed_ = true;
      push_direction_ = d > 0.0 ? Eigen::Vector3d(away / d) : ShaftAxis(pose) * -1.0;
      push_target_ = nearest + settings_.radius * push_direction_;
    }
  }
  last_tip_ = pose.tip;
}

bool RigidSphere::Step(double dt, const Eigen::Vector3d& gravity,
                       const mesh::Points& tissue_positions) {
  if (!(std::isfinite(dt) && dt > 0.0) || !gravity.allFinite()) return false;
  // Forces at the start of the step and the stiffness of each spring on the centre.
  Eigen::Vector3d force = mass_ * gravity - settings_.damping * velocity_;
  Eigen::Matrix3d stiffness = Eigen::Matrix3d::Zero();
  double damping = settings_.damping;
  for (int32_t k = 0; k < num_attachments_; ++k) {
    const auto i = static_cast<size_t>(k);
    const models::Attachment& a = attachments_[i];
    const Eigen::Vector3d& n = directions_[i];
    // The tissue spring, normal only (frictionless): its tissue end where the step left it.
    const double stretch = n.dot(tissue_positions.col(a.node) - a.target);
    force += a.stiffness * stretch * n;
    stiffness += a.stiffness * n * n.transpose();
  }
  Eigen::Vector3d tool = Eigen::Vector3d::Zero();
  Eigen::Matrix3d tool_stiffness = Eigen::Matrix3d::Zero();
  if (pushed_) {
    const double depth = push_direction_.dot(push_target_ - position_);
    tool = settings_.tool_stiffness * std::max(depth, 0.0) * push_direction_;
    tool_stiffness = settings_.tool_stiffness * push_direction_ * push_direction_.transpose();
  } else if (grasped_) {
    tool = settings_.grasp_stiffness * (grasp_target_ - position_);
    tool_stiffness = settings_.grasp_stiffness * Eigen::Matrix3d::Identity();
    // Critical damping of the held sphere on its spring, so it neither rings nor lags.
    const double grasp_damping = 2.0 * std::sqrt(settings_.grasp_stiffness * mass_);
    damping += grasp_damping;
    force -= grasp_damping * velocity_;
  }
  force += tool;
  stiffness += tool_stiffness;
  // Implicit Euler: (m + dt c + dt² K) Δv = dt (f - dt K v).
  const Eigen::Matrix3d system =
      (mass_ + dt * damping) * Eigen::Matrix3d::Identity() + dt * dt * stiffness;
  const Eigen::Vector3d dv = system.inverse() * (dt * (force - dt * stiffness * velocity_));
  const Eigen::Vector3d v = velocity_ + dv;
  const Eigen::Vector3d x = position_ + dt * v;
  if (!v.allFinite() || !x.allFinite()) return false;
  velocity_ = v;
  position_ = x;
  if (grasped_) orientation_ = tool_orientation_ * grasp_rotation_;
  // The sphere on the tool: the opposite of the tool's springs at the new position.
  tool_force_ = -(tool - tool_stiffness * (dt * v));
  return true;
}

}  // namespace somasim::contact
