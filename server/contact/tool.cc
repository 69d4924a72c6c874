#include "server/contact/tool.h"

#include <cmath>
#include <sstream>

namespace somasim::contact {
namespace {

// Appends "name = value, not in (lo, hi]" when value is outside (lo, hi] or not finite.
void CheckRange(const char* name, double value, double lo, double hi, std::ostringstream* out) {
  if (std::isfinite(value) && value > lo && value <= hi) return;
  if (out->tellp() > 0) *out << "; ";
  *out << name << " = " << value << " m, not in (" << lo << ", " << hi << "]";
}

}  // namespace

const char* ToolKindName(ToolKind kind) {
  switch (kind) {
    case ToolKind::kProbe:
      return "probe";
    case ToolKind::kGrasper:
      return "grasper";
    case ToolKind::kScalpel:
      return "scalpel";
    case ToolKind::kCamera:
      return "camera";
  }
  return "unknown";
}

std::string ToolShapeError(const ToolShape& shape) {
  std::ostringstream out;
  CheckRange("shaft_length", shape.shaft_length, 0.0, 2.0, &out);
  CheckRange("shaft_radius", shape.shaft_radius, 0.0, 0.05, &out);
  const double shaft = std::isfinite(shape.shaft_length) ? shape.shaft_length : 2.0;
  CheckRange("jaw_length", shape.jaw_length, 0.0, shaft, &out);
  CheckRange("blade_length", shape.blade_length, 0.0, shaft, &out);
  CheckRange("grasp_radius", shape.grasp_radius, 0.0, 0.05, &out);
  return out.str();
}

std::string ToolPoseError(const ToolPose& pose) {
  if (!pose.tip.allFinite()) return "tool tip is not finite";
  if (!pose.orientation.coeffs().allFinite()) return "tool orientation is not finite";
  const double norm = pose.orientation.norm();
  if (std::abs(norm - 1.0) > 1e-3) {
    std::ostringstream out;
    out << "tool orientation is not a unit quaternion (|q| = " << norm << ")";
    return out.str();
  }
  if (!std::isfinite(pose.jaw_opening) || pose.jaw_opening < 0.0 || pose.jaw_opening > 1.0) {
    std::ostringstream out;
    out << "jaw opening = " << pose.jaw_opening << ", not in [0, 1]";
    return out.str();
  }
  return {};
}

Eigen::Vector3d ShaftAxis(const ToolPose& pose) {
  return pose.orientation.normalized() * Eigen::Vector3d::UnitZ();
}

Eigen::Vector3d PointOnShaft(const ToolPose& pose, double distance) {
  return pose.tip + distance * ShaftAxis(pose);
}

}  // namespace somasim::contact
