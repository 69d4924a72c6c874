#include "haptic_node/shm_node.h"

#include <poll.h>
#include <sys/eventfd.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <thread>

#include "common/app/log.h"
#include "common/app/realtime.h"
#include "common/app/scheduling.h"
#include "common/app/signals.h"
#include "common/arm_shm/arm_shm.h"
#include "common/dds/topics.h"
#include "haptic_node/haptic_loop.h"
#include "haptic_node/latest_slot.h"
#include "haptic_node/mock_node.h"
#include "haptic_node/period_stats.h"
#include "server/contact/force_model_wire.h"

namespace somasim::haptic {
namespace {

using app::Log;
using app::LogLevel;

int64_t MonotonicNs() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1000000000 + ts.tv_nsec;
}

timespec ToTimespec(int64_t ns) {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(ns / 1000000000);
  ts.tv_nsec = static_cast<long>(ns % 1000000000);
  return ts;
}

// What the loop tells the wire thread, lock-free: relaxed atomics (counters, flags) the loop
// stores each tick.
struct LoopStatus {
  std::atomic<uint64_t> ticks{0};
  std::atomic<uint64_t> overruns{0};  // ticks that ended past the next deadline
  std::atomic<uint64_t> stale_ticks{0};
  std::atomic<uint64_t> faults{0};
  std::atomic<uint64_t> torn_reads{0};
  std::atomic<uint64_t> bad_states{0};
  std::atomic<uint64_t> clamped_ticks{0};
  std::atomic<uint64_t> damped_ticks{0};
  std::atomic<uint64_t> emergency_stop_ticks{0};
  std::atomic<uint64_t> clutch_ticks{0};
  std::atomic<bool> running{false};  // the arm's driver seen alive
  std::atomic<bool> fault{false};
  std::atomic<bool> engaged{false};
  std::atomic<const char*> fault_reason{""};
  std::atomic<double> force{0.0};  // [N] |rendered force|, arm frame
};

struct Shared {
  LatestSlot<PackedForceModel> model;
  LatestSlot<ToolPoseSample> pose;
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

void RunLoop(const ShmNodeOptions& o, arm::ArmBlock& block, HapticLoop& loop, Shared& shared,
             LoopTiming& timing) {
  if (o.rt_priority > 0) timing.fifo = app::SetFifoScheduling(o.rt_priority);
  if (!timing.fifo.applied) app::SetSchedulerSlice(app::kWireSlice);
  // Before the loop: its stack touched, so no page faults on it later.
  {
    volatile char stack[64 * 1024];
    for (size_t i = 0; i < sizeof stack; i += 4096) stack[i] = 0;
  }
  const auto period = static_cast<int64_t>(1e9 / o.rate);
  const int64_t spin = int64_t{1000} * o.spin_us;
  const uint64_t one = 1;
  somasim_arm_state_t state{};
  PackedForceModel model{};
  bool have_model = false;
  int64_t next = MonotonicNs() + period;
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
    }
    previous_start = now;

    HapticLoopInput in;
    in.now_ns = now;
    in.header_problem = block.HeaderProblem();
    in.read = arm::ReadState(block.block().state, &state);
    in.state = state;
    uint64_t version = 0;
    PackedForceModel newest;
    if (shared.model.Read(&newest, &version) && version > 0) {
      model = newest;
      have_model = true;
    }
    in.model = have_model ? &model : nullptr;
    const somasim_arm_command_t& command = loop.Tick(in);
    if (in.header_problem == nullptr) arm::WriteCommand(&block.block().command, command);
    shared.pose.Write(loop.tool());
    [[maybe_unused]] const ssize_t w = write(shared.wake_fd, &one, sizeof one);

    LoopStatus& s = shared.status;
    const ForceOutputCounters& oc = loop.output().counters();
    const HapticLoopCounters& lc = loop.counters();
    s.ticks.store(lc.ticks, std::memory_order_relaxed);
    s.stale_ticks.store(oc.stale_ticks, std::memory_order_relaxed);
    s.faults.store(oc.faults, std::memory_order_relaxed);
    s.torn_reads.store(lc.torn_reads, std::memory_order_relaxed);
    s.bad_states.store(lc.bad_states, std::memory_order_relaxed);
    s.clamped_ticks.store(oc.clamped_ticks, std::memory_order_relaxed);
    s.damped_ticks.store(oc.damped_ticks, std::memory_order_relaxed);
    s.emergency_stop_ticks.store(lc.emergency_stop_ticks, std::memory_order_relaxed);
    s.clutch_ticks.store(lc.clutch_ticks, std::memory_order_relaxed);
    s.running.store(loop.phase() == LoopPhase::kRunning, std::memory_order_relaxed);
    s.fault_reason.store(loop.fault_reason(), std::memory_order_relaxed);
    s.fault.store(loop.fault(), std::memory_order_release);
    s.engaged.store(loop.output().engaged(), std::memory_order_relaxed);
    s.force.store(loop.arm_force().norm(), std::memory_order_relaxed);

    next += period;
    if (MonotonicNs() > next) {  // past the next deadline already: start afresh, never burst
      s.overruns.fetch_add(1, std::memory_order_relaxed);
      next = MonotonicNs() + period;
    }
  }
  // The last command: motors disabled (the driver's watchdog would also see the heartbeat stop).
  somasim_arm_command_t last{};
  last.node_time_ns = static_cast<uint64_t>(MonotonicNs());
  last.heartbeat = loop.counters().ticks + 1;
  last.num_joints = static_cast<uint32_t>(block.num_joints());
  if (block.HeaderProblem() == nullptr) arm::WriteCommand(&block.block().command, last);
}

nlohmann::ordered_json Counters(const LoopStatus& s) {
  return {{"ticks", s.ticks.load()},
          {"overruns", s.overruns.load()},
          {"stale_ticks", s.stale_ticks.load()},
          {"faults", s.faults.load()},
          {"torn_reads", s.torn_reads.load()},
          {"bad_device_ticks", s.bad_states.load()},
          {"clamped_ticks", s.clamped_ticks.load()},
          {"damped_ticks", s.damped_ticks.load()},
          {"emergency_stop_ticks", s.emergency_stop_ticks.load()},
          {"clutch_ticks", s.clutch_ticks.load()},
          {"arm_running", s.running.load()},
          {"engaged", s.engaged.load()},
          {"fault", s.fault.load()},
          {"fault_reason", std::string(s.fault_reason.load())},
          {"force_n", s.force.load()}};
}

}  // namespace

int RunShmNode(const ShmNodeOptions& o, const std::string& dds_config) {
  std::unique_ptr<ArmKinematics> kinematics;
  try {
    kinematics = std::make_unique<ArmKinematics>(ArmKinematics::Load(o.arm_config));
  } catch (const ArmConfigError& e) {
    std::fprintf(stderr, "somasim-haptic: --arm-config %s\n", e.what());
    return kExitUsage;
  }
  std::unique_ptr<arm::ArmBlock> block;
  try {
    block = arm::ArmBlock::Create(o.arm, static_cast<uint32_t>(kinematics->num_joints()));
  } catch (const arm::ArmShmError& e) {
    std::fprintf(stderr, "somasim-haptic: %s\n", e.what());
    return kExitArmBlock;
  }
  HapticLoopSettings settings;
  settings.output.dt = 1.0 / o.rate;
  settings.output.max_force = kinematics->max_force();
  settings.arm_timeout = 1e-3 * o.arm_timeout_ms;
  HapticLoop loop(*kinematics, settings);

  std::unique_ptr<dds::Domain> domain;
  if (!dds_config.empty()) domain = std::make_unique<dds::Domain>(o.domain, dds_config);
  dds::Participant participant(o.domain);
  dds::Topics topics(participant);
  dds::Writer<somasim_wire_ToolCommand> commands(participant, topics.tool_command,
                                                 dds::ToolCommandQos(o.session));
  dds::Reader<somasim_wire_ForceModel> models(participant, topics.force_model,
                                              dds::ForceModelQos(o.session));
  dds::Reader<somasim_wire_Heartbeat> heartbeats(participant, topics.heartbeat,
                                                 dds::HeartbeatQos(o.session));

  const app::RealtimeResult locked = app::LockAllMemory();
  Log(locked.applied ? LogLevel::kInfo : LogLevel::kWarning,
      locked.applied ? "memory_locked" : "memory_not_locked", {{"detail", locked.detail}});
  if (const app::SliceResult r = app::SetSchedulerSlice(app::kWireSlice); !r.applied) {
    Log(LogLevel::kWarning, "scheduler_slice_not_applied", {{"detail", r.detail}});
  }

  auto shared = std::make_unique<Shared>();
  shared->wake_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (shared->wake_fd < 0) {
    std::fprintf(stderr, "somasim-haptic: eventfd: %s\n", std::strerror(errno));
    return kExitIo;
  }
  auto timing = std::make_unique<LoopTiming>();
  Log(LogLevel::kInfo, "arm",
      {{"arm", o.arm},
       {"shm", block->object_name()},
       {"config", kinematics->name()},
       {"joints", kinematics->num_joints()},
       {"max_force_n", kinematics->max_force()},
       {"tool", o.tool},
       {"session", o.session},
       {"rate_hz", o.rate}});
  std::thread loop_thread([&] { RunLoop(o, *block, loop, *shared, *timing); });
  // Whatever ends the wire thread (an exception from DDS included), the loop is stopped (it
  // writes its disabling command) and joined before anything it uses goes.
  struct StopLoop {
    Shared& shared;
    std::thread& thread;
    ~StopLoop() {
      shared.stop.store(true);
      if (thread.joinable()) thread.join();
    }
  } stop_loop{*shared, loop_thread};

  // The wire thread.
  const int64_t start = MonotonicNs();
  int64_t last_counters = start;
  int64_t last_heartbeat = 0;
  uint64_t server_id = 0;
  bool server_alive = false;
  bool fault_logged = false;
  bool running_logged = false;
  bool fifo_logged = false;
  uint64_t pose_version = 0;
  uint64_t sequence = 0;
  uint64_t models_received = 0, models_rejected = 0, models_taken = 0;
  uint64_t write_failures = 0;
  double max_force = 0.0;  // [N] at the arm, as the loop reports it (sampled here)
  PackedForceModel held{};
  bool holding = false;
  somasim_wire_ToolCommand c{};
  const std::string tool = o.tool;
  const std::string station = o.station;
  while (!app::StopRequested()) {
    const int64_t now = MonotonicNs();
    if (o.duration > 0.0 && 1e-9 * static_cast<double>(now - start) >= o.duration) break;
    pollfd p{shared->wake_fd, POLLIN, 0};
    if (poll(&p, 1, 5) > 0) {
      uint64_t n = 0;
      [[maybe_unused]] const ssize_t r = read(shared->wake_fd, &n, sizeof n);
    }
    // The tool pose, as a tool command.
    ToolPoseSample pose;
    uint64_t version = 0;
    if (shared->pose.Read(&pose, &version) && version != pose_version && pose.valid != 0) {
      pose_version = version;
      c.tool = dds::CString(tool);
      c.format_version = dds::kWireFormatVersion;
      c.station = dds::CString(station);
      c.seq = ++sequence;
      c.sender_time_ns = pose.time_ns;
      for (int i = 0; i < 3; ++i) c.position[i] = pose.position[i];
      for (int i = 0; i < 4; ++i) c.orientation[i] = pose.orientation[i];
      c.jaw_closure = pose.jaw;
      c.buttons = pose.buttons;
      if (commands.TryWrite(c) != DDS_RETCODE_OK) ++write_failures;
    }
    // The server's models for the driven tool.
    models.Take([&](const somasim_wire_ForceModel& w, const dds_sample_info_t&) {
      ++models_received;
      if (w.tool == nullptr || tool != w.tool) return;
      contact::LocalForceModel m;
      const std::string error = contact::FromWire(w, dds::kWireFormatVersion, &m);
      if (!error.empty()) {
        if (++models_rejected <= 10) {
          Log(LogLevel::kWarning, "force_model_dropped", {{"tool", tool}, {"reason", error}});
        }
        return;
      }
      if (holding && m.sequence <= held.sequence && w.server_id == server_id) return;
      held = Pack(m, MonotonicNs());
      holding = true;
      ++models_taken;
      shared->model.Write(held);
    });
    heartbeats.Take([&](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) {
      if (h.format_version != dds::kWireFormatVersion) return;
      last_heartbeat = MonotonicNs();
      if (!server_alive) {
        Log(LogLevel::kInfo, server_id == 0 ? "server_found" : "server_back",
            {{"server_id", h.server_id}, {"session", o.session}});
      } else if (h.server_id != server_id) {
        Log(LogLevel::kWarning, "server_restarted", {{"server_id", h.server_id}});
      }
      server_alive = true;
      server_id = h.server_id;
    });
    const int64_t t = MonotonicNs();
    if (server_alive && t - last_heartbeat > std::chrono::nanoseconds(dds::kLease).count()) {
      server_alive = false;
      Log(LogLevel::kError, "server_lost",
          {{"silent_ms", 1e-6 * static_cast<double>(t - last_heartbeat)}, {"monotonic_ns", t}});
    }
    // The loop's state and counters.
    LoopStatus& s = shared->status;
    max_force = std::max(max_force, s.force.load(std::memory_order_relaxed));
    if (!fifo_logged && s.ticks.load(std::memory_order_relaxed) > 0) {
      fifo_logged = true;
      if (timing->fifo.applied) {
        Log(LogLevel::kInfo, "realtime", {{"detail", timing->fifo.detail}});
      } else {
        Log(LogLevel::kWarning, "realtime_refused",
            {{"detail",
              timing->fifo.detail.empty() ? "not asked (--rt-priority 0)" : timing->fifo.detail}});
      }
    }
    if (s.running.load(std::memory_order_relaxed) != running_logged) {
      running_logged = !running_logged;
      Log(LogLevel::kInfo, running_logged ? "arm_running" : "arm_waiting", {{"arm", o.arm}});
    }
    const bool fault = s.fault.load(std::memory_order_acquire);
    if (fault != fault_logged) {
      fault_logged = fault;
      if (fault) {
        nlohmann::ordered_json f = {{"reason", std::string(s.fault_reason.load())},
                                    {"monotonic_ns", t}};
        if (const std::string header = block->HeaderError(); !header.empty()) f["header"] = header;
        Log(LogLevel::kError, "fault", f);
      } else {
        Log(LogLevel::kInfo, "fault_cleared", {{"monotonic_ns", t}});
      }
    }
    if (t - last_counters >= 1000000000) {
      last_counters = t;
      nlohmann::ordered_json counters = Counters(s);
      counters["force_models"] = models_taken;
      counters["tool_commands"] = sequence;
      Log(LogLevel::kInfo, "counters", counters);
    }
  }
  shared->stop.store(true);
  loop_thread.join();
  close(shared->wake_fd);  // (the guard above then has nothing left to join)

  const double wall = 1e-9 * static_cast<double>(MonotonicNs() - start);
  const LoopTiming& lt = *timing;
  nlohmann::ordered_json r;
  r["device"] = "shm";
  r["arm"] = o.arm;
  r["session"] = o.session;
  r["tool"] = o.tool;
  r["wall_time_s"] = wall;
  r["realtime"] = {{"sched_fifo", lt.fifo.applied},
                   {"detail", lt.fifo.detail},
                   {"memory_locked", locked.applied},
                   {"memory_detail", locked.detail}};
  r["loop"] = Counters(shared->status);
  r["period_error_us"] = {{"count", lt.period_error.count()},
                          {"p50", lt.period_error.Quantile(0.5)},
                          {"p99", lt.period_error.Quantile(0.99)},
                          {"p999", lt.period_error.Quantile(0.999)},
                          {"max", lt.period_error.max_us()}};
  r["lateness_us"] = {{"p50", lt.lateness.Quantile(0.5)},
                      {"p99", lt.lateness.Quantile(0.99)},
                      {"p999", lt.lateness.Quantile(0.999)},
                      {"max", lt.lateness.max_us()}};
  r["periods_over_2ms"] = lt.periods_over_2ms;
  r["max_force_n"] = max_force;
  r["tool_commands_sent"] = sequence;
  r["tool_command_write_failures"] = write_failures;
  r["force_models_received"] = models_received;
  r["force_models_taken"] = models_taken;
  r["force_models_rejected"] = models_rejected;
  r["server_id"] = server_id;
  Log(LogLevel::kInfo, "done",
      {{"ticks", shared->status.ticks.load()},
       {"period_error_p99_us", lt.period_error.Quantile(0.99)},
       {"periods_over_2ms", lt.periods_over_2ms},
       {"faults", shared->status.faults.load()}});
  if (!o.report.empty()) {
    std::ofstream out(o.report);
    out << r.dump(2) << "\n";
    if (!out) return kExitIo;
  }
  return kExitOk;
}

}  // namespace somasim::haptic
