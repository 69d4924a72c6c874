#include "haptic_node/loop_thread.h"

#include <time.h>
#include <unistd.h>

#include <cerrno>

#include "common/app/scheduling.h"

namespace somasim::haptic {
namespace {

timespec ToTimespec(int64_t ns) {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(ns / 1000000000);
  ts.tv_nsec = static_cast<long>(ns % 1000000000);
  return ts;
}

// The tick's counters and force statistics into the status the wire thread reads.
void Publish(const HapticLoop& loop, double dt, LoopStatus* s) {
  const ForceOutputCounters& oc = loop.output().counters();
  const HapticLoopCounters& lc = loop.counters();
  constexpr auto kRelaxed = std::memory_order_relaxed;
  s->ticks.store(lc.ticks, kRelaxed);
  s->stale_ticks.store(oc.stale_ticks, kRelaxed);
  s->faults.store(oc.faults, kRelaxed);
  s->torn_reads.store(lc.torn_reads, kRelaxed);
  s->bad_states.store(lc.bad_states, kRelaxed);
  s->clamped_ticks.store(oc.clamped_ticks, kRelaxed);
  s->rate_limited_ticks.store(oc.rate_limited_ticks, kRelaxed);
  s->damped_ticks.store(oc.damped_ticks, kRelaxed);
  s->emergency_stop_ticks.store(lc.emergency_stop_ticks, kRelaxed);
  s->clutch_ticks.store(lc.clutch_ticks, kRelaxed);
  s->running.store(loop.phase() == LoopPhase::kRunning, kRelaxed);
  s->fault_reason.store(loop.fault_reason(), kRelaxed);
  s->fault.store(loop.fault(), std::memory_order_release);
  s->engaged.store(loop.output().engaged(), kRelaxed);
  const double f = loop.arm_force().norm();
  s->force.store(f, kRelaxed);
  if (f > s->max_force.load(kRelaxed)) s->max_force.store(f, kRelaxed);
  if (loop.in_contact() || loop.grasping()) {
    s->contact_time.store(s->contact_time.load(kRelaxed) + dt, kRelaxed);
    s->force_sum.store(s->force_sum.load(kRelaxed) + f * dt, kRelaxed);
  }
}

}  // namespace

int64_t MonotonicNs() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1000000000 + ts.tv_nsec;
}

void RunLoopThread(const LoopThreadOptions& o, Device& device, HapticLoop& loop, NodeShared& shared,
                   LoopTiming& timing) {
  if (o.rt_priority > 0) timing.fifo = app::SetFifoScheduling(o.rt_priority);
  if (!timing.fifo.applied) app::SetSchedulerSlice(app::kWireSlice);
  // Before the loop: its stack touched, so no page faults on it later.
  {
    volatile char stack[64 * 1024];
    for (size_t i = 0; i < sizeof stack; i += 4096) stack[i] = 0;
  }
  const auto period = static_cast<int64_t>(1e9 / o.rate);
  const double dt = 1.0 / o.rate;
  const int64_t spin = int64_t{1000} * o.spin_us;
  const uint64_t one = 1;
  ReceivedForceModel model{};
  uint32_t model_tool = UINT32_MAX;  // the tool `model` is for
  int64_t next = MonotonicNs() + period;
  int64_t first = 0;
  int64_t previous_start = 0;
  while (!shared.stop.load(std::memory_order_relaxed)) {
    // An absolute-time sleep to just before the deadline, then a spin to it.
    const timespec wake = ToTimespec(next - spin);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &wake, nullptr) == EINTR) {
    }
    int64_t now = MonotonicNs();
    while (now < next) now = MonotonicNs();
    timing.lateness.Add(now - next);
    if (previous_start != 0) {
      const int64_t p = now - previous_start;
      timing.period_error.Add(p > period ? p - period : period - p);
      if (p > 2000000) ++timing.periods_over_2ms;
    } else {
      first = now;
    }
    previous_start = now;

    HapticLoopInput in;
    in.now_ns = now;
    device.Read(now, &in);
    // The newest model of the tool the device drives (none for a tool the node does not know).
    bool have_model = false;
    if (in.tool < kMaxNodeTools) {
      // Straight into the loop's copy: Read leaves it untouched when nothing new can be had.
      uint64_t version = 0;
      if (shared.models[in.tool].Read(&model, &version) && version > 0) model_tool = in.tool;
      have_model = model_tool == in.tool;
    }
    in.model = have_model ? &model : nullptr;
    device.Write(in, loop.Tick(in));
    shared.pose.Write(loop.tool());
    [[maybe_unused]] const ssize_t w = write(shared.wake_fd, &one, sizeof one);

    LoopStatus& s = shared.status;
    Publish(loop, dt, &s);
    if (shared.record_forces) {
      ForceRecord r;
      r.time = 1e-9 * static_cast<double>(now - first);
      r.tool = in.tool;
      for (int i = 0; i < 3; ++i) {
        r.position[i] = loop.tool().position[i];
        r.force[i] = loop.arm_force()[i];
      }
      r.in_contact = loop.in_contact();
      r.grasping = loop.grasping();
      r.model_age_ms = have_model ? 1e-6 * static_cast<double>(now - model.received_ns) : -1.0;
      if (!shared.forces.Push(r)) s.forces_dropped.fetch_add(1, std::memory_order_relaxed);
    }
    if (device.finished(now)) s.finished.store(true, std::memory_order_release);

    next += period;
    if (MonotonicNs() > next) {  // past the next deadline already: start afresh, never burst
      s.overruns.fetch_add(1, std::memory_order_relaxed);
      next = MonotonicNs() + period;
    }
  }
  device.Stop(loop.counters().ticks + 1, MonotonicNs());
}

}  // namespace somasim::haptic
