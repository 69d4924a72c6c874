// Surgical tools (SPEC §5.1, seed 002 §3.1): shape, dimensions and pose. A tool is a rigid
// instrument whose frame has its origin at the tip and its shaft along +z towards the handle
// (the way a laparoscopic instrument enters through its port). What touches tissue:
//   probe    the tip point (seed 002's line-segment tool: the tip leads, the shaft follows);
//   grasper  the tip point, and jaws along the shaft's last jaw_length that hold tissue when
//            closed (jaw opening 0);
//   scalpel  the tip point, and the blade PQ (P the tip, Q blade_length up the shaft), whose
//            sweep between steps cuts (SPEC §5.3, the cutting issue);
//   camera   the laparoscope: a pose only, no contact.
// Pure.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>

namespace somasim::contact {

enum class ToolKind { kProbe, kGrasper, kScalpel, kCamera };
const char* ToolKindName(ToolKind kind);

struct ToolShape {
  ToolKind kind = ToolKind::kProbe;
  double shaft_length = 0.30;    // [m] tip to handle, (0, 2]
  double shaft_radius = 0.0025;  // [m] (0, 0.05]: a 5 mm instrument
  double jaw_length = 0.015;     // [m] grasper jaws, (0, shaft_length]
  double blade_length = 0.010;   // [m] scalpel blade PQ, (0, shaft_length]
  // Grasper: surface nodes within this of the jaws' segment are held when the jaws close [m],
  // (0, 0.05].
  double grasp_radius = 0.003;
};

// Empty when the shape is usable, otherwise what is wrong (field, value, allowed range).
std::string ToolShapeError(const ToolShape& shape);

struct ToolPose {
  Eigen::Vector3d tip = Eigen::Vector3d::Zero();                    // [m] in the scene frame
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();  // tool frame → scene frame
  double jaw_opening = 1.0;  // grasper: 0 closed .. 1 fully open
};

// Empty when the pose is usable (finite; |orientation| within 1e-3 of 1; jaw in [0, 1]).
std::string ToolPoseError(const ToolPose& pose);

// The shaft's axis in the scene frame (unit; tip → handle).
Eigen::Vector3d ShaftAxis(const ToolPose& pose);
// A point `distance` [m] up the shaft from the tip.
Eigen::Vector3d PointOnShaft(const ToolPose& pose, double distance);

}  // namespace somasim::contact
