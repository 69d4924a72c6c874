// somasim-haptic --device shm --arm NAME --arm-config FILE --session NAME: the haptic node with
// a real arm (or somasim-arm-sim) through the arm's shared memory (common/arm_shm/arm_abi.h).
//
// Threads:
//  - the loop, 1 kHz (SCHED_FIFO where permitted, said when not): sleeps to an absolute
//    deadline (clock_nanosleep TIMER_ABSTIME) less a short spin, spins to it, then one
//    HapticLoop tick (haptic_loop.h): the arm's header and state, the newest force model from
//    its slot, the command written to the arm. It hands the tool pose to the wire thread through
//    a slot and wakes it with an eventfd. No lock, no allocation, no logging, no DDS call.
//  - the wire thread (the process's main thread): sends the tool pose as tool commands, takes
//    the server's force models for the driven tool (checked, then into the loop's slot with the
//    node's receive time), watches the server's heartbeat, and logs the loop's counters
//    (overruns, stale ticks, faults) every second and each fault as it latches.
// At the end (--duration, SIGINT or SIGTERM) the loop writes a last command with the motors
// disabled, and --report gets the loop's timing (period error percentiles, periods over 2 ms).
#pragma once

#include <cstdint>
#include <string>

namespace somasim::haptic {

inline constexpr int kExitArmBlock = 8;  // the arm's shared memory cannot be made or used

struct ShmNodeOptions {
  std::string arm;         // the arm's name: /somasim-arm-NAME
  std::string arm_config;  // its configuration file (*.arm.txtpb)
  std::string tool = "probe";
  std::string session = "default";
  std::string station = "station-1";
  uint32_t domain = 0;
  double rate = 1000.0;          // [Hz] the loop
  double duration = 0.0;         // [s] 0: until SIGINT or SIGTERM
  int rt_priority = 80;          // SCHED_FIFO priority of the loop; 0: do not ask
  int spin_us = 50;              // [µs] spun before each deadline
  double arm_timeout_ms = 10.0;  // [ms] the driver's heartbeat may be still this long (SPEC)
  std::string report;            // JSON report at the end ("" = none)
};

// Runs the node; returns the process's exit code (mock_node.h's codes, and kExitArmBlock).
int RunShmNode(const ShmNodeOptions& options, const std::string& dds_config);

}  // namespace somasim::haptic
