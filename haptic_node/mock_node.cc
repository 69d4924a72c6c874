#include "haptic_node/mock_node.h"

#include <CLI/CLI.hpp>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <thread>
#include <vector>

#include "common/app/log.h"
#include "common/app/scheduling.h"
#include "common/app/signals.h"
#include "common/arm_shm/arm_shm.h"
#include "common/dds/topics.h"
#include "haptic_node/force_output.h"
#include "haptic_node/mock_script.h"
#include "haptic_node/shm_node.h"
#include "server/contact/force_model_wire.h"

#ifndef SOMASIM_VERSION
#define SOMASIM_VERSION "0.0.0"
#endif
#ifndef SOMASIM_SOURCE_DIR
#define SOMASIM_SOURCE_DIR "."
#endif

namespace somasim::haptic {
namespace {

using Clock = std::chrono::steady_clock;
using app::Log;
using app::LogLevel;

constexpr uint32_t kEmergencyStopButton = 2;  // idl/tool.idl ToolCommand.buttons bit 1

double Seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }
int64_t MonotonicNs(Clock::time_point t) {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(t.time_since_epoch()).count();
}

struct ToolModel {
  contact::LocalForceModel model;
  Clock::time_point received;
  bool valid = false;
};

int Run(const MockNodeOptions& options, const MockScript& script, const std::string& config) {
  // The tick loop and Cyclone's threads wait on the clock and the wire: a short fair-scheduler
  // slice wakes them promptly next to a busy physics (common/app/scheduling.h).
  if (const app::SliceResult r = app::SetSchedulerSlice(app::kWireSlice); r.applied) {
    Log(LogLevel::kInfo, "scheduler_slice", {{"slice_us", app::SchedulerSliceUs()}});
  } else {
    Log(LogLevel::kWarning, "scheduler_slice_not_applied", {{"detail", r.detail}});
  }
  std::unique_ptr<dds::Domain> domain;
  if (!config.empty()) domain = std::make_unique<dds::Domain>(options.domain, config);
  dds::Participant participant(options.domain);
  dds::Topics topics(participant);
  dds::Writer<somasim_wire_ToolCommand> commands(participant, topics.tool_command,
                                                 dds::ToolCommandQos(options.session));
  dds::Reader<somasim_wire_ForceModel> models(participant, topics.force_model,
                                              dds::ForceModelQos(options.session));
  dds::Reader<somasim_wire_Heartbeat> heartbeats(participant, topics.heartbeat,
                                                 dds::HeartbeatQos(options.session));

  // Wait for the server's first heartbeat.
  const Clock::time_point wait_start = Clock::now();
  Clock::time_point last_heartbeat{};
  uint64_t server_id = 0;
  bool found = false;
  while (!found && !app::StopRequested()) {
    heartbeats.Take([&](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) {
      if (h.format_version != dds::kWireFormatVersion) return;
      found = true;
      server_id = h.server_id;
    });
    if (found) break;
    if (Seconds(Clock::now() - wait_start) > options.wait_server) {
      Log(LogLevel::kError, "no_server",
          {{"session", options.session}, {"waited_s", options.wait_server}});
      return kExitNoServer;
    }
    heartbeats.WaitForData(std::chrono::milliseconds(50));
  }
  if (!found) return kExitOk;  // stopped while waiting
  last_heartbeat = Clock::now();
  Log(LogLevel::kInfo, "server_found", {{"server_id", server_id}, {"session", options.session}});

  std::unique_ptr<std::ofstream> forces;
  if (!options.forces.empty()) {
    forces = std::make_unique<std::ofstream>(options.forces);
    if (!*forces) {
      Log(LogLevel::kError, "io", {{"error", "cannot write " + options.forces}});
      return kExitIo;
    }
    *forces << "time_s,tool,x_m,y_m,z_m,fx_n,fy_n,fz_n,in_contact,grasping,model_age_ms\n";
  }

  std::vector<ToolModel> tool_models(script.tools().size());
  ForceOutputSettings output_settings;
  output_settings.dt = 1.0 / options.rate;
  ForceOutput output(output_settings);
  const std::vector<std::string>& tools = script.tools();
  const auto period = std::chrono::duration_cast<Clock::duration>(
      std::chrono::duration<double>(1.0 / options.rate));
  const double dt = 1.0 / options.rate;
  const Clock::time_point start = Clock::now();
  Clock::time_point next = start;
  uint64_t sequence = 0;
  uint64_t ticks = 0;
  uint64_t models_received = 0;
  uint64_t models_rejected = 0;
  uint64_t late_ticks = 0;
  double max_force = 0.0;
  double force_sum = 0.0;
  double contact_time = 0.0;
  bool lost = false;
  Clock::time_point lost_at{};
  Eigen::Vector3d previous = script.At(0.0).position;
  somasim_wire_ToolCommand c{};
  const std::string station = options.station;
  while (!app::StopRequested()) {
    const Clock::time_point now = Clock::now();
    const double t = Seconds(now - start);
    if (options.stop_at_script_end && t > script.duration() + 0.2) break;
    const ScriptSample s = script.At(t);
    // The command.
    c.tool = dds::CString(tools[static_cast<size_t>(s.tool)]);
    c.format_version = dds::kWireFormatVersion;
    c.station = dds::CString(station);
    c.seq = ++sequence;
    c.sender_time_ns = MonotonicNs(now);
    for (int i = 0; i < 3; ++i) c.position[i] = s.position[i];
    c.orientation[0] = s.orientation.w();
    c.orientation[1] = s.orientation.x();
    c.orientation[2] = s.orientation.y();
    c.orientation[3] = s.orientation.z();
    c.jaw_closure = s.jaw;
    c.buttons = s.buttons;
    commands.TryWrite(c);
    // Models and heartbeats that arrived.
    models.Take([&](const somasim_wire_ForceModel& w, const dds_sample_info_t&) {
      ++models_received;
      const std::string id = w.tool == nullptr ? "" : w.tool;
      for (size_t k = 0; k < tools.size(); ++k) {
        if (tools[k] != id) continue;
        contact::LocalForceModel m;
        const std::string error = contact::FromWire(w, dds::kWireFormatVersion, &m);
        if (!error.empty()) {
          if (++models_rejected <= 10) {
            Log(LogLevel::kWarning, "force_model_dropped", {{"tool", id}, {"reason", error}});
          }
          return;
        }
        if (tool_models[k].valid && m.sequence <= tool_models[k].model.sequence &&
            w.server_id == server_id) {
          return;  // older than what we hold
        }
        tool_models[k].model = m;
        tool_models[k].received = now;
        tool_models[k].valid = true;
      }
    });
    heartbeats.Take([&](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) {
      if (h.format_version != dds::kWireFormatVersion) return;
      last_heartbeat = now;
      if (h.server_id != server_id) {
        Log(LogLevel::kWarning, "server_restarted", {{"server_id", h.server_id}});
        server_id = h.server_id;
      }
    });
    if (now - last_heartbeat > dds::kLease) {
      lost = true;
      lost_at = now;
      Log(LogLevel::kError, "server_lost",
          {{"silent_ms", 1e3 * Seconds(now - last_heartbeat)}, {"monotonic_ns", MonotonicNs(now)}});
      break;
    }
    // The force the arm would render.
    const Eigen::Vector3d velocity = (s.position - previous) / dt;
    previous = s.position;
    Eigen::Vector3d f = Eigen::Vector3d::Zero();
    bool in_contact = false;
    bool grasping = false;
    double age_ms = -1.0;
    const ToolModel& tm = tool_models[static_cast<size_t>(s.tool)];
    ForceInput fi;
    fi.velocity = velocity;
    fi.emergency_stop = (s.buttons & kEmergencyStopButton) != 0;
    if (tm.valid) {
      const Clock::duration age = now - tm.received;
      age_ms = 1e3 * Seconds(age);
      const contact::ForceSample fs =
          contact::EvaluateLocalForceModel(tm.model, s.position, velocity);
      fi.desired = fs.force;
      fi.model_age = Seconds(age);
      in_contact = tm.model.in_contact && fs.in_contact;
      grasping = tm.model.grasping;
    }
    // The one output stage every rendered force passes (force_output.h), as with an arm.
    f = output.Tick(fi);
    const double magnitude = f.norm();
    max_force = std::max(max_force, magnitude);
    if (in_contact || grasping) {
      contact_time += dt;
      force_sum += magnitude * dt;
    }
    if (forces) {
      *forces << t << ',' << tools[static_cast<size_t>(s.tool)] << ',' << s.position.x() << ','
              << s.position.y() << ',' << s.position.z() << ',' << f.x() << ',' << f.y() << ','
              << f.z() << ',' << (in_contact ? 1 : 0) << ',' << (grasping ? 1 : 0) << ',' << age_ms
              << '\n';
    }
    ++ticks;
    next += period;
    const Clock::time_point after = Clock::now();
    if (after > next + period) {
      ++late_ticks;  // a tick more than a period late: start afresh rather than burst
      next = after;
    } else {
      std::this_thread::sleep_until(next);
    }
  }
  const double wall = Seconds(Clock::now() - start);
  nlohmann::ordered_json r;
  r["session"] = options.session;
  r["script"] = options.script;
  r["script_duration_s"] = script.duration();
  r["wall_time_s"] = wall;
  r["ticks"] = ticks;
  r["rate_hz"] = wall > 0.0 ? static_cast<double>(ticks) / wall : 0.0;
  r["late_ticks"] = late_ticks;
  r["commands_sent"] = sequence;
  r["force_models_received"] = models_received;
  r["force_models_rejected"] = models_rejected;
  r["stale_ticks"] = output.counters().stale_ticks;
  r["clamped_ticks"] = output.counters().clamped_ticks;
  r["rate_limited_ticks"] = output.counters().rate_limited_ticks;
  r["damped_ticks"] = output.counters().damped_ticks;
  r["faults"] = output.counters().faults;
  r["max_force_n"] = max_force;
  r["mean_force_in_contact_n"] = contact_time > 0.0 ? force_sum / contact_time : 0.0;
  r["contact_time_s"] = contact_time;
  r["server_lost"] = lost;
  if (lost) r["server_lost_monotonic_ns"] = MonotonicNs(lost_at);
  Log(LogLevel::kInfo, "done",
      {{"ticks", ticks},
       {"max_force_n", max_force},
       {"contact_time_s", contact_time},
       {"server_lost", lost}});
  if (!options.report.empty()) {
    std::ofstream out(options.report);
    out << r.dump(2) << "\n";
    if (!out) return kExitIo;
  }
  return lost ? kExitServerLost : kExitOk;
}

}  // namespace

int HapticMain(int argc, char** argv) {
  app::SetLogProcess("haptic");
  MockNodeOptions options;
  ShmNodeOptions shm;
  CLI::App cli{
      "somasim-haptic: the 1 kHz haptic node. --device shm drives an arm through its shared\n"
      "memory (docs/haptic_node.md); --device mock plays a scripted trajectory\n"
      "(docs/mock_scripts.md). Exit codes: 0 done, 2 usage, 3 bad script, 4 I/O, 5 DDS,\n"
      "6 no server, 7 server lost, 8 the arm's shared memory is unusable, 70 bug."};
  cli.set_version_flag("--version", std::string("somasim-haptic ") + SOMASIM_VERSION);
  cli.add_option("--device", options.device, "shm (an arm) or mock (a script)")
      ->check(CLI::IsMember({"shm", "mock"}))
      ->capture_default_str();
  cli.add_option("--script", options.script, "mock: the script");
  cli.add_option("--arm", shm.arm, "shm: the arm's name (/somasim-arm-NAME)");
  cli.add_option("--arm-config", shm.arm_config,
                 "shm: the arm's configuration (*.arm.txtpb; default haptic_node/arms/NAME)");
  cli.add_option("--tool", shm.tool, "shm: the scene's tool the arm drives")->capture_default_str();
  cli.add_option("--duration", shm.duration, "shm: seconds to run (0: until SIGINT/SIGTERM)")
      ->check(CLI::Range(0.0, 1e7))
      ->capture_default_str();
  cli.add_option("--rt-priority", shm.rt_priority,
                 "shm: SCHED_FIFO priority of the loop (0: do not ask)")
      ->check(CLI::Range(0, 99))
      ->capture_default_str();
  cli.add_option("--spin-us", shm.spin_us, "shm: microseconds spun before each deadline")
      ->check(CLI::Range(0, 500))
      ->capture_default_str();
  cli.add_option("--arm-timeout-ms", shm.arm_timeout_ms,
                 "shm: how long the driver's heartbeat may be still before a fault (SPEC: 10; "
                 "raise it only where the host stalls, e.g. tests on a shared VM)")
      ->check(CLI::Range(2.0, 1000.0))
      ->capture_default_str();
  cli.add_option("--session", options.session, "the session's name (its DDS partition)")
      ->capture_default_str();
  cli.add_option("--station", options.station, "this station's name, for logs")
      ->capture_default_str();
  cli.add_option("--domain", options.domain, "DDS domain id")->check(CLI::Range(0, 232));
  cli.add_option("--dds-config", options.dds_config, "Cyclone DDS XML configuration");
  cli.add_option("--rate", options.rate, "commands per second")
      ->check(CLI::Range(10.0, 10000.0))
      ->capture_default_str();
  cli.add_option("--wait-server", options.wait_server, "seconds to wait for the server")
      ->check(CLI::Range(0.0, 3600.0))
      ->capture_default_str();
  cli.add_option("--forces", options.forces, "CSV of the rendered force, one row per tick");
  cli.add_option("--report", options.report, "JSON report at the end");
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? kExitOk : kExitUsage;
  }
  if (const std::string bad = dds::SessionNameError(options.session); !bad.empty()) {
    std::fprintf(stderr, "somasim-haptic: --session \"%s\" %s\n", options.session.c_str(),
                 bad.c_str());
    return kExitUsage;
  }
  if (options.device == "shm") {
    if (!options.script.empty()) {
      std::fprintf(stderr, "somasim-haptic: --script is for --device mock\n");
      return kExitUsage;
    }
    if (shm.arm.empty()) {
      std::fprintf(stderr, "somasim-haptic: --device shm needs --arm NAME\n");
      return kExitUsage;
    }
    if (const std::string bad = arm::ArmNameError(shm.arm); !bad.empty()) {
      std::fprintf(stderr, "somasim-haptic: --arm \"%s\" %s\n", shm.arm.c_str(), bad.c_str());
      return kExitUsage;
    }
    if (shm.arm_config.empty()) {
      shm.arm_config =
          std::string(SOMASIM_SOURCE_DIR) + "/haptic_node/arms/" + shm.arm + ".arm.txtpb";
    }
    if (shm.tool.empty()) {
      std::fprintf(stderr, "somasim-haptic: --tool must name the scene's tool\n");
      return kExitUsage;
    }
    shm.session = options.session;
    shm.station = options.station;
    shm.domain = options.domain;
    shm.rate = options.rate;
    shm.report = options.report;
    app::InstallStopSignals();
    std::string config;
    try {
      config = dds::ReadDdsConfig(options.dds_config);
    } catch (const std::runtime_error& e) {
      std::fprintf(stderr, "somasim-haptic: %s\n", e.what());
      return kExitIo;
    }
    try {
      return RunShmNode(shm, config);
    } catch (const dds::DdsError& e) {
      std::fprintf(stderr, "somasim-haptic: DDS: %s\n", e.what());
      return kExitDds;
    }
  }
  if (options.script.empty()) {
    std::fprintf(stderr, "somasim-haptic: --device mock needs --script FILE\n");
    return kExitUsage;
  }
  app::InstallStopSignals();
  std::unique_ptr<MockScript> script;
  try {
    script = std::make_unique<MockScript>(MockScript::Load(options.script));
  } catch (const ScriptError& e) {
    std::fprintf(stderr, "somasim-haptic: %s\n", e.what());
    return e.line() == 0 ? kExitIo : kExitBadScript;
  }
  std::string config;
  try {
    config = dds::ReadDdsConfig(options.dds_config);
  } catch (const std::runtime_error& e) {
    std::fprintf(stderr, "somasim-haptic: %s\n", e.what());
    return kExitIo;
  }
  try {
    return Run(options, *script, config);
  } catch (const dds::DdsError& e) {
    std::fprintf(stderr, "somasim-haptic: DDS: %s\n", e.what());
    return kExitDds;
  }
}

}  // namespace somasim::haptic
