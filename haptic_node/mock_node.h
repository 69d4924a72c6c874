// somasim-haptic with the mock device (`--device mock --script FILE`): the mock haptic node of
// automated tests and the demo. It plays a scripted tool trajectory (mock_script.h) as tool
// commands at 1 kHz, evaluates the newest local force model it has received for the driven tool
// at the scripted position and passes it through the same output stage as an arm's force
// (force_output.h: SPEC §7's staleness rule, engagement, clamp, rate limit, passivity), logs the
// forces, and watches the server's heartbeat: a server silent for the lease (500 ms) is lost.
// The arm through shared memory: shm_node.h.
#pragma once

#include <cstdint>
#include <string>

namespace somasim::haptic {

inline constexpr int kExitOk = 0;
inline constexpr int kExitUsage = 2;
inline constexpr int kExitBadScript = 3;
inline constexpr int kExitIo = 4;
inline constexpr int kExitDds = 5;
inline constexpr int kExitNoServer = 6;    // no heartbeat within --wait-server
inline constexpr int kExitServerLost = 7;  // the server fell silent during the script
inline constexpr int kExitBug = 70;

struct MockNodeOptions {
  std::string device = "mock";
  std::string script;
  std::string session = "default";
  std::string station = "station-1";
  uint32_t domain = 0;
  std::string dds_config;
  double rate = 1000.0;       // [Hz] commands and force evaluations
  double wait_server = 10.0;  // [s] for the first heartbeat
  std::string forces;         // CSV of the rendered force per tick ("" = none)
  std::string report;         // JSON report at the end ("" = none)
  bool stop_at_script_end = true;
};

int HapticMain(int argc, char** argv);

}  // namespace somasim::haptic
