// The haptic node's 1 kHz thread, the same for every device (devices.h): it sleeps to an
// absolute deadline (clock_nanosleep TIMER_ABSTIME) less a short spin, spins to it, then one
// tick — the device read, the newest force model of the tool it drives from its slot,
// HapticLoop::Tick (haptic_loop.h), the command written — hands the tool pose to the wire
// thread through a slot, wakes it with an eventfd, stores its counters in relaxed atomics and,
// when asked, the rendered force into a ring another thread writes to a file. No lock, no
// allocation, no logging, no DDS call, no file I/O.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <string>

#include "common/app/realtime.h"
#include "common/lockfree/latest_slot.h"
#include "common/lockfree/spsc_ring.h"
#include "haptic_node/devices.h"
#include "haptic_node/haptic_loop.h"
#include "haptic_node/period_stats.h"

namespace somasim::haptic {

// The most tools a node drives (a script's tools; an arm drives one).
inline constexpr size_t kMaxNodeTools = 16;

// What the loop tells the wire thread, lock-free: relaxed atomics the loop stores each tick.
struct LoopStatus {
  std::atomic<uint64_t> ticks{0};
  std::atomic<uint64_t> overruns{0};  // ticks that ended past the next deadline
  std::atomic<uint64_t> stale_ticks{0};
  std::atomic<uint64_t> faults{0};
  std::atomic<uint64_t> torn_reads{0};
  std::atomic<uint64_t> bad_states{0};
  std::atomic<uint64_t> clamped_ticks{0};
  std::atomic<uint64_t> rate_limited_ticks{0};
  std::atomic<uint64_t> damped_ticks{0};
  std::atomic<uint64_t> emergency_stop_ticks{0};
  std::atomic<uint64_t> clutch_ticks{0};
  std::atomic<uint64_t> forces_dropped{0};  // force rows the ring had no room for
  std::atomic<bool> running{false};         // the device seen alive
  std::atomic<bool> fault{false};
  std::atomic<bool> engaged{false};
  std::atomic<bool> finished{false};  // the device has nothing more to do
  std::atomic<const char*> fault_reason{""};
  std::atomic<double> force{0.0};         // [N] |rendered force|, device frame
  std::atomic<double> max_force{0.0};     // [N] the largest so far
  std::atomic<double> contact_time{0.0};  // [s] ticks in contact or grasping
  std::atomic<double> force_sum{0.0};     // [N s] |force| over those ticks
};

// One tick's rendered force, for the forces file.
struct ForceRecord {
  double time = 0.0;  // [s] since the loop's first tick
  uint32_t tool = 0;
  double position[3] = {};  // [m] the tool in the scene
  double force[3] = {};     // [N] rendered, device frame
  bool in_contact = false;
  bool grasping = false;
  double model_age_ms = -1.0;  // -1: no model
};

// Everything the loop thread and the wire thread share.
struct NodeShared {
  std::array<lockfree::LatestSlot<ReceivedForceModel>, kMaxNodeTools> models;  // per tool
  lockfree::LatestSlot<ToolPoseSample> pose;
  lockfree::SpscRing<ForceRecord, 8192> forces;
  bool record_forces = false;  // set before the thread starts
  LoopStatus status;
  std::atomic<bool> stop{false};
  int wake_fd = -1;  // eventfd: the loop wakes the wire thread after each tick
};

struct LoopTiming {
  MicrosecondHistogram period_error;  // |period - nominal| [µs]
  MicrosecondHistogram lateness;      // wake-up after the deadline [µs]
  uint64_t periods_over_2ms = 0;
  app::RealtimeResult fifo;
};

struct LoopThreadOptions {
  double rate = 1000.0;  // [Hz]
  int rt_priority = 0;   // SCHED_FIFO priority; 0: do not ask
  int spin_us = 0;       // [µs] spun before each deadline
};

// The thread's body: ticks until shared.stop, then the device's last command (Device::Stop).
void RunLoopThread(const LoopThreadOptions& options, Device& device, HapticLoop& loop,
                   NodeShared& shared, LoopTiming& timing);

int64_t MonotonicNs();

}  // namespace somasim::haptic
