#include "server/net/wire_adapters.h"

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>

#include "common/dds/topics.h"
#include "common/force_model/force_model_wire.h"

namespace somasim::net {

std::string CheckToolCommand(const somasim_wire_ToolCommand& c, const server::Session& session,
                             int32_t* tool, server::ToolCommandInput* input) {
  if (c.format_version != dds::kWireFormatVersion) {
    return "format_version " + std::to_string(c.format_version) + " is not " +
           std::to_string(dds::kWireFormatVersion);
  }
  const std::string id = c.tool == nullptr ? std::string() : std::string(c.tool);
  *tool = session.ToolIndex(id);
  if (*tool < 0) return "unknown tool \"" + id.substr(0, 64) + "\"";
  const Eigen::Vector3d p(c.position[0], c.position[1], c.position[2]);
  if (!p.allFinite() || p.norm() > 10.0) return "position is not finite or beyond 10 m";
  const Eigen::Vector4d q(c.orientation[0], c.orientation[1], c.orientation[2], c.orientation[3]);
  if (!q.allFinite() || std::abs(q.norm() - 1.0) > 1e-3) {
    return "orientation is not a unit quaternion";
  }
  if (!std::isfinite(c.jaw_closure) || c.jaw_closure < 0.0 || c.jaw_closure > 1.0) {
    return "jaw_closure is not in [0, 1]";
  }
  input->pose.tip = p;
  input->pose.orientation = Eigen::Quaterniond(q[0], q[1], q[2], q[3]).normalized();
  input->pose.jaw_opening = 1.0 - c.jaw_closure;
  input->buttons = c.buttons;
  input->sequence = c.seq;
  return "";
}

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
