// Real-time privileges for the haptic node's 1 kHz loop (SPEC §7): SCHED_FIFO for the loop's
// thread and all memory locked. Neither is granted to an ordinary user by default; a lab grants
// them (docs/haptic_node.md: limits.d rtprio and memlock, or CAP_SYS_NICE and CAP_IPC_LOCK).
// When refused, the result says why and how to grant it, and the caller logs it and runs on
// without: the loop still works, with a worse wake-up latency. Nothing here fails the process.
#pragma once

#include <string>

namespace somasim::app {

struct RealtimeResult {
  bool applied = false;
  std::string detail;  // what was done, or why not and how to grant it
};

// SCHED_FIFO at `priority` (1..99) for the calling thread. Throws std::invalid_argument for a
// priority outside 1..99.
RealtimeResult SetFifoScheduling(int priority);

// mlockall(MCL_CURRENT | MCL_FUTURE), tried only when it cannot make later allocations fail: the
// process may lock without limit (RLIMIT_MEMLOCK infinite, or CAP_IPC_LOCK as root). Otherwise
// refused with the limit named.
RealtimeResult LockAllMemory();

}  // namespace somasim::app
