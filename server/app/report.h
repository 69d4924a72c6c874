// somasim-server's report at the end of a session (--report FILE, docs/running_a_lab.md): what
// the session was, how its physics ran (steps, step-time percentiles, real-time factor), what
// was published and received, the events, per tool the force the server saw, per organ its
// cuts, and the recording's outcome.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>

#include "server/app/server_app.h"
#include "server/net/publisher.h"
#include "server/net/tool_link.h"
#include "server/runner/physics_runner.h"

namespace somasim::server {

nlohmann::ordered_json ServerReport(const ServerOptions& options, uint64_t server_id,
                                    const runner::PhysicsRunner& runner,
                                    const net::Publisher& publisher, const net::ToolLink& link,
                                    const Recorder* recorder);

}  // namespace somasim::server
