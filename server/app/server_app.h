// somasim-server (SPEC §1): runs a session's physics and publishes it over Cyclone DDS in the
// session's partition, as four threads that never wait on each other (docs/architecture.md):
// the physics (server/runner/physics_runner.h: no DDS, no allocation per tick), the tool link's
// intake and force-model writer (server/net/tool_link.h), and the publisher
// (server/net/publisher.h: description, topologies, frames, rigid bodies, heartbeat, metrics,
// events, instructor commands). Its report: server/app/report.h.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "common/app/exit_codes.h"

namespace somasim::server {

// Exit codes (common/app/exit_codes.h; also in --help).
using app::kExitBadInput;
using app::kExitBug;
using app::kExitDds;
using app::kExitIo;
using app::kExitOk;
using app::kExitUsage;

struct ServerOptions {
  std::string scene = "builtin:liver";  // a .scene.txtpb file or builtin:NAME
  std::string session = "default";      // the DDS partition
  bool headless = true;                 // the server never opens a window (accepted for clarity)
  double duration = 0.0;                // [s] of session time; 0 = until SIGINT/SIGTERM
  uint32_t domain = 0;                  // DDS domain id
  std::string dds_config;               // Cyclone XML file; "" = CYCLONEDDS_URI or defaults
  double frame_rate = 60.0;             // [Hz] mesh frames
  uint32_t keyframe_interval = 30;      // a keyframe every this many frames (0.5 s at 60 Hz)
  bool realtime = true;                 // pace session time to the wall clock
  std::string report;                   // JSON report written at the end ("" = none)
  // At the end, each organ's last published frame: DIR/<organ>.f32 (3 × num_nodes float32, the
  // exact values a subscriber holds) and DIR/<organ>.frame (its frame number, text).
  std::string dump_final;
  // The session's recording (docs/recording.md): a new file ("" = none) and the trainee's
  // pseudonym in its header ([A-Za-z0-9_-], at most 32; never a person's name).
  std::string record;
  std::string trainee;
  // Replay mode (somasim-replay --publish): session time runs at `speed` × the wall clock, and
  // starts being published at the checkpoint nearest to `replay_from` [s] (fast-forwarded to it).
  double speed = 1.0;
  double replay_from = 0.0;
  int rt_priority = 0;  // SCHED_FIFO priority of the physics thread; 0 = normal
  bool verbose = false;
};

// The whole program: parses argv (--help, --version), runs, returns the exit code.
int ServerMain(int argc, char** argv);

// somasim-replay --publish: re-publishes the recording at `file` as a server would (the session
// description, topologies, frames, events, heartbeat, metrics) in options.session, driven by
// the recording's inputs instead of tool commands; instructors may pause and resume it. Returns
// an exit code: 0 replayed to its end (every checkpoint reproduced), 1 diverged, 3 a recording
// refused, 4 an I/O error, 5 DDS.
int ReplayServerMain(const ServerOptions& options, const std::string& file);

}  // namespace somasim::server
