// The one check of a tool's pose as a device or a peer gives it (SPEC §7: bad input is refused
// by name), shared by the haptic loop (a Cartesian device's state) and the server's intake (a
// station's ToolCommand). Pure, allocation-free: each caller words its own message.
#pragma once

#include <cmath>

namespace somasim::checks {

enum class ToolPoseProblem { kNone, kPosition, kOrientation, kGrip };

// position [m] finite and within 10 m of the scene's origin; orientation (w x y z) finite and a
// unit quaternion to 1e-3; grip (a jaw's closure or a gripper, 0 open .. 1 closed) in [0, 1].
inline ToolPoseProblem CheckToolPose(const double (&position)[3], const double (&orientation)[4],
                                     double grip) {
  const double p2 =
      position[0] * position[0] + position[1] * position[1] + position[2] * position[2];
  if (!std::isfinite(position[0]) || !std::isfinite(position[1]) || !std::isfinite(position[2]) ||
      !(std::sqrt(p2) <= 10.0)) {
    return ToolPoseProblem::kPosition;
  }
  double q2 = 0.0;
  for (const double c : orientation) {
    if (!std::isfinite(c)) return ToolPoseProblem::kOrientation;
    q2 += c * c;
  }
  if (std::abs(std::sqrt(q2) - 1.0) > 1e-3) return ToolPoseProblem::kOrientation;
  if (!(grip >= 0.0 && grip <= 1.0)) return ToolPoseProblem::kGrip;
  return ToolPoseProblem::kNone;
}

}  // namespace somasim::checks
