#include "server/net/wire_adapters.h"

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <string_view>

#include "common/checks/tool_pose.h"
#include "common/dds/topics.h"
#include "common/force_model/force_model_wire.h"

namespace somasim::net {

std::string CheckToolCommand(const somasim_wire_ToolCommand& c, const server::Session& session,
                             int32_t* tool, server::ToolCommandInput* input) {
  if (c.format_version != dds::kWireFormatVersion) {
    return "format_version " + std::to_string(c.format_version) + " is not " +
           std::to_string(dds::kWireFormatVersion);
  }
  // A view: a command's path allocates nothing until it is refused.
  const std::string_view id = c.tool == nullptr ? std::string_view() : std::string_view(c.tool);
  *tool = session.ToolIndex(id);
  if (*tool < 0) return "unknown tool \"" + std::string(id.substr(0, 64)) + "\"";
  switch (checks::CheckToolPose(c.position, c.orientation, c.jaw_closure)) {
    case checks::ToolPoseProblem::kPosition:
      return "position is not finite or beyond 10 m";
    case checks::ToolPoseProblem::kOrientation:
      return "orientation is not a unit quaternion";
    case checks::ToolPoseProblem::kGrip:
      return "jaw_closure is not in [0, 1]";
    case checks::ToolPoseProblem::kNone:
      break;
  }
  input->pose.tip = Eigen::Vector3d(c.position[0], c.position[1], c.position[2]);
  input->pose.orientation =
      Eigen::Quaterniond(c.orientation[0], c.orientation[1], c.orientation[2], c.orientation[3])
          .normalized();
  input->pose.jaw_opening = 1.0 - c.jaw_closure;
  input->buttons = c.buttons;
  input->sequence = c.seq;
  return "";
}

// The runner hands on as many held nodes as the wire carries: none is dropped here.
static_assert(static_cast<uint32_t>(runner::kMaxHeld) == force_model::kMaxHeldNodes);

void ToolOutputToWire(const runner::ToolOutput& out, somasim_wire_ForceModel* wire) {
  force_model::ToWire(out.model, wire);
  wire->command_seq = out.command_seq;
  force_model::HeldNodesToWire({out.held, static_cast<size_t>(out.num_held)}, wire);
}

const char* EventText(server::SessionEventRecord::Kind kind) {
  using Kind = server::SessionEventRecord::Kind;
  switch (kind) {
    case Kind::kGrasp:
      return "grasp";
    case Kind::kRelease:
      return "release";
    case Kind::kContactBegins:
      return "contact begins";
    case Kind::kContactEnds:
      return "contact ends";
    case Kind::kStepRejected:
      return "step rejected";
    case Kind::kForceModelRefused:
      return "force model refused";
    case Kind::kReset:
      return "reset";
    case Kind::kCut:
      return "cut";
  }
  return "event";
}

}  // namespace somasim::net
