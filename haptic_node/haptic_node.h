// somasim-haptic: the haptic node of a training station (SPEC §1), the same process whatever
// the device (`--device shm`: an arm through its shared memory, docs/arm_abi.md; `--device
// mock`: the mock script's emulated device, docs/mock_scripts.md, for the automated tests and
// the demo). Two threads of its own:
//  - the loop, 1 kHz (loop_thread.h): the device, HapticLoop::Tick, the command; no lock, no
//    allocation, no logging, no DDS call, no file I/O;
//  - the wire thread (the process's main thread): sends the tool pose as tool commands, takes
//    the server's force models for the node's tools (checked, then into the loop's slots with
//    the node's receive time), watches the server's heartbeat (a server silent for the lease is
//    lost), logs the loop's counters every second and each fault as it latches, and writes the
//    rendered forces (--forces) from the loop's ring.
// At the end (--duration, the script's end, SIGINT or SIGTERM; with --device mock also the
// server lost) the loop writes a last command with the motors disabled, and --report gets the
// loop's counters, timing (period error percentiles, periods over 2 ms) and forces.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/app/exit_codes.h"
#include "haptic_node/devices.h"
#include "haptic_node/haptic_loop.h"

namespace somasim::haptic {

struct NodeOptions {
  std::string device = "mock";  // for the report: "shm" or "mock"
  std::string session = "default";
  std::string station = "station-1";
  uint32_t domain = 0;
  std::vector<std::string> tools;  // the scene's tools the device drives (HapticLoopInput::tool)
  double rate = 1000.0;            // [Hz] the loop
  double duration = 0.0;           // [s] 0: until the device finishes, SIGINT or SIGTERM
  int rt_priority = 0;             // SCHED_FIFO priority of the loop; 0: do not ask
  int spin_us = 0;                 // [µs] spun before each deadline
  bool lock_memory = false;        // mlockall before the loop starts
  // The mock's run: no tick before the server's first heartbeat (exit kExitNoServer after
  // `wait_server` seconds without one), and a server silent for the lease ends it
  // (kExitServerLost). An arm's node keeps its arm safe and waits for the server to return.
  bool wait_for_server = false;
  double wait_server = 10.0;  // [s]
  bool stop_on_server_lost = false;
  std::string forces;                  // CSV of the rendered force per tick ("" = none)
  std::string report;                  // JSON report at the end ("" = none)
  nlohmann::ordered_json report_info;  // the device's own fields, copied into the report
};

// Runs the node with `device` and `loop` (made for it) until it ends; returns the exit code
// (common/app/exit_codes.h). Throws dds::DdsError when DDS cannot be set up.
int RunNode(const NodeOptions& options, Device& device, HapticLoop& loop,
            const std::string& dds_config);

// The whole program: parses argv (--help, --version), runs, returns the exit code.
int HapticMain(int argc, char** argv);

}  // namespace somasim::haptic
