// The server's samples and its session's types, each way, with every check a sample from the
// network needs (SPEC §7: a bad sample is dropped and counted, never applied). Pure: no DDS
// calls, no allocation on the per-tick conversions.
#pragma once

#include <cstdint>
#include <string>

#include "idl/session.h"
#include "idl/tool.h"
#include "server/runner/physics_runner.h"
#include "server/session/session.h"

namespace somasim::net {

// What a tool command must be to move a tool: this wire format, a tool of the session, a
// position within 10 m, a unit quaternion (1e-3), a jaw closure in [0, 1]. Returns "" when
// usable (and fills `tool` and `input`), else what is wrong.
std::string CheckToolCommand(const somasim_wire_ToolCommand& c, const server::Session& session,
                             int32_t* tool, server::ToolCommandInput* input);

// A tool's output of a tick into a ForceModel sample: the model, the command it used, the
// grasped nodes. The tool, organ and server fields are the caller's. Allocation-free.
void ToolOutputToWire(const runner::ToolOutput& out, somasim_wire_ForceModel* wire);

// The short name of an event kind ("grasp", "contact begins", ...): the report's key.
const char* EventText(server::SessionEventRecord::Kind kind);

}  // namespace somasim::net
