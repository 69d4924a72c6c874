#include "haptic_node/haptic_node.h"

#include <poll.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <memory>
#include <thread>

#include "common/app/log.h"
#include "common/app/realtime.h"
#include "common/app/scheduling.h"
#include "common/app/signals.h"
#include "common/dds/topics.h"
#include "common/force_model/force_model_wire.h"
#include "haptic_node/loop_thread.h"

namespace somasim::haptic {
namespace {

using app::Log;
using app::LogLevel;

constexpr int64_t kSecond = 1000000000;

// The wire thread's side of the node: DDS in and out, the server's heartbeat, the logs.
class Wire {
 public:
  Wire(const NodeOptions& o, NodeShared& shared)
      : o_(o),
        shared_(shared),
        participant_(o.domain),
        topics_(participant_),
        commands_(participant_, topics_.tool_command, dds::ToolCommandQos(o.session)),
        models_(participant_, topics_.force_model, dds::ForceModelQos(o.session)),
        heartbeats_(participant_, topics_.heartbeat, dds::HeartbeatQos(o.session)) {
    held_.resize(o.tools.size());
  }

  // Before the loop starts (the mock's run): the server's first heartbeat, up to wait_server.
  // kExitOk when it came, kExitNoServer when not, -1 when stopped while waiting.
  int WaitForServer() {
    const int64_t start = MonotonicNs();
    while (!app::StopRequested()) {
      TakeHeartbeats();
      if (server_alive_) return app::kExitOk;
      if (1e-9 * static_cast<double>(MonotonicNs() - start) > o_.wait_server) {
        Log(LogLevel::kError, "no_server", {{"session", o_.session}, {"waited_s", o_.wait_server}});
        return app::kExitNoServer;
      }
      heartbeats_.WaitForData(std::chrono::milliseconds(50));
    }
    return -1;
  }

  // One pass after the loop woke us (or 5 ms): pose out, models and heartbeats in.
  void Exchange() {
    SendPose();
    TakeModels();
    TakeHeartbeats();
  }

  // Whether the server fell silent for the lease just now (logged once per silence).
  bool ServerLost() {
    const int64_t t = MonotonicNs();
    if (!server_alive_ || t - last_heartbeat_ <= std::chrono::nanoseconds(dds::kLease).count()) {
      return false;
    }
    server_alive_ = false;
    lost_at_ = t;
    Log(LogLevel::kError, "server_lost",
        {{"silent_ms", 1e-6 * static_cast<double>(t - last_heartbeat_)}, {"monotonic_ns", t}});
    return true;
  }

  void Report(nlohmann::ordered_json* r) const {
    (*r)["commands_sent"] = sequence_;
    (*r)["tool_commands_sent"] = sequence_;
    (*r)["tool_command_write_failures"] = write_failures_;
    (*r)["force_models_received"] = models_received_;
    (*r)["force_models_taken"] = models_taken_;
    (*r)["force_models_rejected"] = models_rejected_;
    (*r)["server_id"] = server_id_;
  }
  int64_t lost_at() const { return lost_at_; }
  uint64_t models_taken() const { return models_taken_; }
  uint64_t commands_sent() const { return sequence_; }

 private:
  void SendPose() {
    ToolPoseSample pose;
    uint64_t version = 0;
    if (!shared_.pose.Read(&pose, &version) || version == pose_version_ || pose.valid == 0) return;
    pose_version_ = version;
    if (pose.tool >= o_.tools.size()) return;
    somasim_wire_ToolCommand c{};
    c.tool = dds::CString(o_.tools[pose.tool]);
    c.format_version = dds::kWireFormatVersion;
    c.station = dds::CString(o_.station);
    c.seq = ++sequence_;
    c.sender_time_ns = pose.time_ns;
    for (int i = 0; i < 3; ++i) c.position[i] = pose.position[i];
    for (int i = 0; i < 4; ++i) c.orientation[i] = pose.orientation[i];
    c.jaw_closure = pose.jaw;
    c.buttons = pose.buttons;
    if (commands_.TryWrite(c) != DDS_RETCODE_OK) ++write_failures_;
  }

  // The server's models for the node's tools: checked, newer than what is held, into the slot.
  void TakeModels() {
    models_.Take([&](const somasim_wire_ForceModel& w, const dds_sample_info_t&) {
      ++models_received_;
      if (w.tool == nullptr) return;
      const auto it = std::find(o_.tools.begin(), o_.tools.end(), w.tool);
      if (it == o_.tools.end()) return;
      const auto k = static_cast<size_t>(it - o_.tools.begin());
      force_model::LocalForceModel m;
      const std::string error = force_model::FromWire(w, dds::kWireFormatVersion, &m);
      if (!error.empty()) {
        if (++models_rejected_ <= 10) {
          Log(LogLevel::kWarning, "force_model_dropped", {{"tool", *it}, {"reason", error}});
        }
        return;
      }
      Held& held = held_[k];
      if (held.valid && m.sequence <= held.sequence && w.server_id == server_id_) return;
      held = {true, m.sequence};
      ++models_taken_;
      shared_.models[k].Write({m, MonotonicNs()});
    });
  }

  void TakeHeartbeats() {
    heartbeats_.Take([&](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) {
      if (h.format_version != dds::kWireFormatVersion) return;
      last_heartbeat_ = MonotonicNs();
      if (!server_alive_) {
        Log(LogLevel::kInfo, server_id_ == 0 ? "server_found" : "server_back",
            {{"server_id", h.server_id}, {"session", o_.session}});
      } else if (h.server_id != server_id_) {
        Log(LogLevel::kWarning, "server_restarted", {{"server_id", h.server_id}});
      }
      server_alive_ = true;
      server_id_ = h.server_id;
    });
  }

  struct Held {
    bool valid = false;
    uint64_t sequence = 0;
  };
  const NodeOptions& o_;
  NodeShared& shared_;
  dds::Participant participant_;
  dds::Topics topics_;
  dds::Writer<somasim_wire_ToolCommand> commands_;
  dds::Reader<somasim_wire_ForceModel> models_;
  dds::Reader<somasim_wire_Heartbeat> heartbeats_;
  std::vector<Held> held_;  // per tool: the newest model taken
  uint64_t pose_version_ = 0;
  uint64_t sequence_ = 0;
  uint64_t write_failures_ = 0;
  uint64_t models_received_ = 0;
  uint64_t models_taken_ = 0;
  uint64_t models_rejected_ = 0;
  uint64_t server_id_ = 0;
  bool server_alive_ = false;
  int64_t last_heartbeat_ = 0;
  int64_t lost_at_ = 0;
};

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

// What the wire thread logs of the loop: real-time scheduling once, the device starting and
// stopping, each fault as it latches and clears, the counters every second.
class StatusLog {
 public:
  StatusLog(const NodeOptions& o, const LoopTiming& timing, const Device& device)
      : o_(o), timing_(timing), device_(device) {}
  void Update(const LoopStatus& s, const Wire& wire) {
    const int64_t t = MonotonicNs();
    if (!fifo_logged_ && s.ticks.load(std::memory_order_relaxed) > 0) {
      fifo_logged_ = true;
      if (timing_.fifo.applied) {
        Log(LogLevel::kInfo, "realtime", {{"detail", timing_.fifo.detail}});
      } else if (o_.rt_priority > 0) {
        Log(LogLevel::kWarning, "realtime_refused", {{"detail", timing_.fifo.detail}});
      }
    }
    if (s.running.load(std::memory_order_relaxed) != running_logged_) {
      running_logged_ = !running_logged_;
      Log(LogLevel::kInfo, running_logged_ ? "arm_running" : "arm_waiting",
          {{"device", o_.device}});
    }
    const bool fault = s.fault.load(std::memory_order_acquire);
    if (fault != fault_logged_) {
      fault_logged_ = fault;
      if (fault) {
        nlohmann::ordered_json f = {{"reason", std::string(s.fault_reason.load())},
                                    {"monotonic_ns", t}};
        if (const std::string detail = device_.FaultDetail(); !detail.empty()) f["header"] = detail;
        Log(LogLevel::kError, "fault", f);
      } else {
        Log(LogLevel::kInfo, "fault_cleared", {{"monotonic_ns", t}});
      }
    }
    if (t - last_counters_ >= kSecond) {
      last_counters_ = t;
      nlohmann::ordered_json counters = Counters(s);
      counters["force_models"] = wire.models_taken();
      counters["tool_commands"] = wire.commands_sent();
      Log(LogLevel::kInfo, "counters", counters);
    }
  }

 private:
  const NodeOptions& o_;
  const LoopTiming& timing_;
  const Device& device_;
  bool fifo_logged_ = false;
  bool running_logged_ = false;
  bool fault_logged_ = false;
  int64_t last_counters_ = MonotonicNs();
};

// The rendered forces the loop left in its ring, as CSV rows.
void WriteForces(NodeShared& shared, const NodeOptions& o, std::ofstream* out) {
  ForceRecord r;
  while (shared.forces.Pop(&r)) {
    if (out == nullptr) continue;
    const std::string& tool = r.tool < o.tools.size() ? o.tools[r.tool] : o.tools.front();
    *out << r.time << ',' << tool << ',' << r.position[0] << ',' << r.position[1] << ','
         << r.position[2] << ',' << r.force[0] << ',' << r.force[1] << ',' << r.force[2] << ','
         << (r.in_contact ? 1 : 0) << ',' << (r.grasping ? 1 : 0) << ',' << r.model_age_ms << '\n';
  }
}

nlohmann::ordered_json Report(const NodeOptions& o, const NodeShared& shared, const LoopTiming& lt,
                              const Wire& wire, const app::RealtimeResult& locked, double wall,
                              bool lost) {
  const LoopStatus& s = shared.status;
  nlohmann::ordered_json r;
  r["device"] = o.device;
  r["session"] = o.session;
  for (const auto& [key, value] : o.report_info.items()) r[key] = value;
  r["wall_time_s"] = wall;
  r["ticks"] = s.ticks.load();
  r["rate_hz"] = wall > 0.0 ? static_cast<double>(s.ticks.load()) / wall : 0.0;
  r["late_ticks"] = s.overruns.load();
  wire.Report(&r);
  r["stale_ticks"] = s.stale_ticks.load();
  r["clamped_ticks"] = s.clamped_ticks.load();
  r["rate_limited_ticks"] = s.rate_limited_ticks.load();
  r["damped_ticks"] = s.damped_ticks.load();
  r["faults"] = s.faults.load();
  r["max_force_n"] = s.max_force.load();
  const double contact = s.contact_time.load();
  r["mean_force_in_contact_n"] = contact > 0.0 ? s.force_sum.load() / contact : 0.0;
  r["contact_time_s"] = contact;
  r["forces_rows_dropped"] = s.forces_dropped.load();
  r["server_lost"] = lost;
  if (lost) r["server_lost_monotonic_ns"] = wire.lost_at();
  r["realtime"] = {{"sched_fifo", lt.fifo.applied},
                   {"detail", lt.fifo.detail},
                   {"memory_locked", locked.applied},
                   {"memory_detail", locked.detail}};
  r["loop"] = Counters(s);
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
  return r;
}

}  // namespace

int RunNode(const NodeOptions& o, Device& device, HapticLoop& loop, const std::string& config) {
  if (o.tools.empty() || o.tools.size() > kMaxNodeTools) {
    std::fprintf(stderr, "somasim-haptic: a node drives 1 to %zu tools, not %zu\n", kMaxNodeTools,
                 o.tools.size());
    return app::kExitUsage;
  }
  // The loop and Cyclone's threads wait on the clock and the wire: a short fair-scheduler slice
  // wakes them promptly next to a busy physics (common/app/scheduling.h).
  app::LogSchedulerSlice(app::SetSchedulerSlice(app::kWireSlice), "haptic node");
  std::unique_ptr<dds::Domain> domain;
  if (!config.empty()) domain = std::make_unique<dds::Domain>(o.domain, config);
  auto shared = std::make_unique<NodeShared>();
  Wire wire(o, *shared);
  if (o.wait_for_server) {
    const int rc = wire.WaitForServer();
    if (rc != app::kExitOk) return rc < 0 ? app::kExitOk : rc;
  }
  std::unique_ptr<std::ofstream> forces;
  if (!o.forces.empty()) {
    forces = std::make_unique<std::ofstream>(o.forces);
    if (!*forces) {
      Log(LogLevel::kError, "io", {{"error", "cannot write " + o.forces}});
      return app::kExitIo;
    }
    *forces << "time_s,tool,x_m,y_m,z_m,fx_n,fy_n,fz_n,in_contact,grasping,model_age_ms\n";
    shared->record_forces = true;
  }
  app::RealtimeResult locked;
  if (o.lock_memory) {
    locked = app::LockAllMemory();
    Log(locked.applied ? LogLevel::kInfo : LogLevel::kWarning,
        locked.applied ? "memory_locked" : "memory_not_locked", {{"detail", locked.detail}});
  }
  shared->wake_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (shared->wake_fd < 0) {
    std::fprintf(stderr, "somasim-haptic: eventfd: %s\n", std::strerror(errno));
    return app::kExitIo;
  }
  auto timing = std::make_unique<LoopTiming>();
  const LoopThreadOptions lo{o.rate, o.rt_priority, o.spin_us};
  std::thread loop_thread([&] { RunLoopThread(lo, device, loop, *shared, *timing); });
  // Whatever ends the wire thread (an exception from DDS included), the loop is stopped (it
  // writes its disabling command) and joined before anything it uses goes.
  struct StopLoop {
    NodeShared& shared;
    std::thread& thread;
    ~StopLoop() {
      shared.stop.store(true);
      if (thread.joinable()) thread.join();
    }
  } stop_loop{*shared, loop_thread};

  const int64_t start = MonotonicNs();
  StatusLog status_log(o, *timing, device);
  bool lost = false;
  while (!app::StopRequested()) {
    if (o.duration > 0.0 && 1e-9 * static_cast<double>(MonotonicNs() - start) >= o.duration) break;
    if (shared->status.finished.load(std::memory_order_acquire)) break;
    pollfd p{shared->wake_fd, POLLIN, 0};
    if (poll(&p, 1, 5) > 0) {
      uint64_t n = 0;
      [[maybe_unused]] const ssize_t r = read(shared->wake_fd, &n, sizeof n);
    }
    wire.Exchange();
    if (wire.ServerLost() && o.stop_on_server_lost) {
      lost = true;
      break;
    }
    WriteForces(*shared, o, forces.get());
    status_log.Update(shared->status, wire);
  }
  shared->stop.store(true);
  loop_thread.join();
  close(shared->wake_fd);  // (the guard above then has nothing left to join)
  WriteForces(*shared, o, forces.get());

  const double wall = 1e-9 * static_cast<double>(MonotonicNs() - start);
  const nlohmann::ordered_json r = Report(o, *shared, *timing, wire, locked, wall, lost);
  Log(LogLevel::kInfo, "done",
      {{"ticks", r["ticks"]},
       {"max_force_n", r["max_force_n"]},
       {"contact_time_s", r["contact_time_s"]},
       {"period_error_p99_us", r["period_error_us"]["p99"]},
       {"faults", r["faults"]},
       {"server_lost", lost}});
  if (!o.report.empty()) {
    std::ofstream out(o.report);
    out << r.dump(2) << "\n";
    if (!out) return app::kExitIo;
  }
  return lost ? app::kExitServerLost : app::kExitOk;
}

}  // namespace somasim::haptic
