// The fair scheduler's slice of the calling thread: how the processes that wait on the wire (the
// server's DDS and publisher threads, viewers, the haptic node, the benchmarks' subscriber) ask to
// be woken promptly without real-time privileges.
//
// Since Linux 6.12 the EEVDF scheduler takes a per-thread slice request: sched_setattr with
// SCHED_OTHER and sched_runtime = the slice, 0.1–100 ms, no privilege needed. A shorter slice
// gives a woken thread an earlier virtual deadline, so it preempts a CPU-bound thread (the
// physics) instead of waiting out that thread's slice: next to a busy physics thread the frame
// latency's tail shrinks several times (docs/benchmarks.md, BM_FrameLatency against
// BM_FrameLatencyDefaultSlice). Threads the calling thread creates afterwards inherit the
// request (Cyclone's receive threads among them).
//
// Older kernels accept the call and ignore the slice: the result then says it was not applied,
// read back with sched_getattr, and the caller logs it. Nothing here fails the process.
#pragma once

#include <chrono>
#include <string>

namespace somasim::app {

struct SliceResult {
  bool applied = false;  // the kernel reports the requested slice for the thread
  std::string detail;    // why not, when not applied (for the log)
};

// Asks for `slice` on the calling thread; slice 0 returns the thread to the kernel's default.
// Throws std::invalid_argument for a slice outside 0 or [100 µs, 100 ms] (the kernel's range).
SliceResult SetSchedulerSlice(std::chrono::microseconds slice);

// The calling thread's slice [µs] as the kernel reports it: its request, else the kernel's base
// slice; 0 on kernels before 6.12; -1 when it cannot be read.
long long SchedulerSliceUs();

// Says in the log what SetSchedulerSlice did for `threads` (e.g. "physics thread"):
// `scheduler_slice` with the slice, or `scheduler_slice_not_applied` with why.
void LogSchedulerSlice(const SliceResult& r, const char* threads);

// The slice the wire's waiting threads ask for.
inline constexpr std::chrono::microseconds kWireSlice{100};

}  // namespace somasim::app
