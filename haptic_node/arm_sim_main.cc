// somasim-arm-sim --arm NAME --config FILE --script FILE: emulates an arm's driver on the arm's
// shared memory (common/arm_shm/arm_abi.h) for tests and for labs without their arm yet. Its arm
// (haptic_node/arm_sim.h) follows a scripted hand (a mock script, haptic_node/mock_script.h: the
// positions are the scene's, mapped back into the arm's frame by the configuration; jaw is the
// gripper; buttons are the arm's buttons) under the node's torques, with the watchdog a real
// driver must have (the node's heartbeat still for 10 ms: zero torque). Writes its state every
// tick (2 kHz by default); checks the block's header every 100 ms (a corrupted header: zero
// torque, exit 8). Exit codes: 0 done, 2 usage, 3 bad script, 4 I/O, 8 the block is unusable,
// 70 bug.
#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <exception>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "common/app/exit_codes.h"
#include "common/app/log.h"
#include "common/app/realtime.h"
#include "common/app/scheduling.h"
#include "common/app/signals.h"
#include "common/arm_shm/arm_shm.h"
#include "haptic_node/arm_sim.h"
#include "haptic_node/kinematics.h"
#include "haptic_node/mock_script.h"

namespace somasim::haptic {
namespace {

using app::Log;
using app::LogLevel;
using Clock = std::chrono::steady_clock;

using app::kExitArmBlock;  // exit codes: common/app/exit_codes.h
using app::kExitBadInput;
using app::kExitIo;
using app::kExitOk;
using app::kExitUsage;

int64_t Ns(Clock::time_point t) {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(t.time_since_epoch()).count();
}

// The command line.
struct Options {
  std::string arm_name, config_path, script_path, torques_path, report_path;
  double rate = 2000.0;   // driver cycles per second
  double duration = 0.0;  // seconds to run; 0: the script's duration + 1 s
  int rt_priority = 79;   // SCHED_FIFO priority of the cycle; 0: do not ask
};

// Parses the command line into *o. An exit code when the program stops there (help, or bad
// usage), else nothing.
std::optional<int> ParseOptions(int argc, char** argv, Options* o) {
  CLI::App cli{
      "somasim-arm-sim: emulates a haptic arm's driver on /somasim-arm-NAME (tests, and labs "
      "before their arm arrives).\nExit codes: 0 done, 2 usage, 3 bad script, 4 I/O, 8 the "
      "shared block is unusable, 70 bug."};
  cli.add_option("--arm", o->arm_name, "the arm's name: /somasim-arm-NAME")->required();
  cli.add_option("--config", o->config_path, "the arm's configuration (*.arm.txtpb)")->required();
  cli.add_option("--script", o->script_path,
                 "the hand's trajectory: a mock script (scene positions, jaw = gripper, "
                 "buttons)")
      ->required();
  cli.add_option("--rate", o->rate, "driver cycles per second")
      ->check(CLI::Range(100.0, 20000.0))
      ->capture_default_str();
  cli.add_option("--duration", o->duration, "seconds to run (0: the script's duration + 1 s)")
      ->check(CLI::Range(0.0, 86400.0));
  cli.add_option("--torques", o->torques_path,
                 "CSV per cycle: monotonic ns, node heartbeat, watchdog tripped, applied torque "
                 "norm [N m], handle x y z [m] (arm frame), the force the applied torques "
                 "render [N] (the node's Cartesian force; 0 while tripped or disabled); kept "
                 "in memory and written when it stops (the first 10 minutes)");
  cli.add_option("--report", o->report_path, "JSON report at the end");
  cli.add_option("--rt-priority", o->rt_priority,
                 "SCHED_FIFO priority of the driver's cycle, as a real driver's (0: do not ask)")
      ->check(CLI::Range(0, 99))
      ->capture_default_str();
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? kExitOk : kExitUsage;
  }
  if (const std::string bad = arm_shm::ArmNameError(o->arm_name); !bad.empty()) {
    std::fprintf(stderr, "somasim-arm-sim: --arm \"%s\" %s\n", o->arm_name.c_str(), bad.c_str());
    return kExitUsage;
  }
  return std::nullopt;
}

// What the driver runs on: the arm's kinematics, the hand's script, the shared block and the
// torques file (closed when not asked for).
struct Inputs {
  std::unique_ptr<ArmKinematics> kinematics;
  std::unique_ptr<MockScript> script;
  std::unique_ptr<arm_shm::ArmBlock> block;
  std::ofstream torques;
};

// Loads and creates the inputs. An exit code when one fails (it says why on stderr), else
// nothing.
std::optional<int> LoadInputs(const Options& o, Inputs* in) {
  try {
    in->kinematics = std::make_unique<ArmKinematics>(ArmKinematics::Load(o.config_path));
  } catch (const ArmConfigError& e) {
    std::fprintf(stderr, "somasim-arm-sim: --config %s\n", e.what());
    return kExitUsage;
  }
  try {
    in->script = std::make_unique<MockScript>(MockScript::Load(o.script_path));
  } catch (const ScriptError& e) {
    std::fprintf(stderr, "somasim-arm-sim: --script %s\n", e.what());
    return kExitBadInput;
  }
  try {
    in->block =
        arm_shm::ArmBlock::Create(o.arm_name, static_cast<uint32_t>(in->kinematics->num_joints()));
  } catch (const arm_shm::ArmShmError& e) {
    std::fprintf(stderr, "somasim-arm-sim: %s\n", e.what());
    return kExitArmBlock;
  }
  if (!o.torques_path.empty()) {
    in->torques.open(o.torques_path);
    if (!in->torques) {
      std::fprintf(stderr, "somasim-arm-sim: cannot write %s\n", o.torques_path.c_str());
      return kExitIo;
    }
    in->torques << "monotonic_ns,node_heartbeat,tripped,torque_norm,x,y,z,force_n\n";
  }
  return std::nullopt;
}

// One driver cycle as the torques file records it.
struct Cycle {
  int64_t ns;
  uint64_t node_heartbeat;
  int tripped;
  double torque, x, y, z, force;
};

// A driver runs its cycle in real time; here the emulation asks for the same (and says when
// it is refused: then on the fair scheduler with a short slice).
void SetDriverScheduling(int rt_priority) {
  if (rt_priority > 0) {
    const app::RealtimeResult rt = app::SetFifoScheduling(rt_priority);
    Log(rt.applied ? LogLevel::kInfo : LogLevel::kWarning,
        rt.applied ? "realtime" : "realtime_refused", {{"detail", rt.detail}});
    if (!rt.applied) app::SetSchedulerSlice(app::kWireSlice);
  } else {
    app::SetSchedulerSlice(app::kWireSlice);
  }
}

// What the driver's cycles counted, and how it stopped.
struct RunStats {
  uint64_t cycles = 0, torn = 0, trips = 0, header_checks = 0;
  int exit_code = kExitOk;
};

// The driver's cycles until the duration is over, a stop is asked for or the block becomes
// unusable: the arm follows the scripted hand under the node's torques, its state written each
// cycle, each cycle recorded while *record has room.
RunStats RunDriver(const Options& o, Inputs* in, std::vector<Cycle>* record) {
  const ArmKinematics& kinematics = *in->kinematics;
  const MockScript& script = *in->script;
  arm_shm::ArmBlock& block = *in->block;
  const double rate = o.rate;
  const bool torques = static_cast<bool>(in->torques);
  RunStats stats;
  ArmSimulator sim(kinematics, ArmSimSettings{});
  const auto period =
      std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / rate));
  const double dt = 1.0 / rate;
  const Clock::time_point start = Clock::now();
  Clock::time_point next = start;
  uint64_t heartbeat = 0;
  bool was_tripped = true;
  somasim_arm_command_t command{};
  Log(LogLevel::kInfo, "running",
      {{"arm", o.arm_name}, {"joints", kinematics.num_joints()}, {"rate_hz", rate}});
  while (!app::StopRequested()) {
    const Clock::time_point now = Clock::now();
    const double t = std::chrono::duration<double>(now - start).count();
    if (t > o.duration) break;
    // The header, every 100 ms: a corrupted block stops the arm.
    if (stats.cycles % static_cast<uint64_t>(rate / 10.0) == 0) {
      ++stats.header_checks;
      if (block.HeaderProblem() != nullptr) {
        const std::string bad = block.HeaderError();
        Log(LogLevel::kError, "block_unusable", {{"reason", bad}, {"monotonic_ns", Ns(now)}});
        stats.exit_code = kExitArmBlock;
        break;
      }
    }
    const arm_shm::ReadResult read = arm_shm::ReadCommand(block.block().command, &command, 4);
    if (read == arm_shm::ReadResult::kTorn) ++stats.torn;
    const ScriptSample hand = script.At(t);
    sim.Step(t, dt, read == arm_shm::ReadResult::kOk ? &command : nullptr,
             kinematics.PositionToArm(hand.position));
    if (sim.watchdog_tripped() && !was_tripped) {
      ++stats.trips;
      Log(LogLevel::kWarning, "watchdog", {{"monotonic_ns", Ns(now)}, {"t", t}});
    }
    was_tripped = sim.watchdog_tripped();
    arm_shm::WriteState(&block.block().state, sim.State(++heartbeat, static_cast<uint64_t>(Ns(now)),
                                                        hand.buttons, hand.jaw));
    if (torques && record->size() < record->capacity()) {
      const ArmPose pose = sim.Pose();
      record->push_back({Ns(now), command.heartbeat, sim.watchdog_tripped() ? 1 : 0,
                         sim.applied_torque().norm(), pose.position.x(), pose.position.y(),
                         pose.position.z(),
                         sim.watchdog_tripped() || command.enable == 0
                             ? 0.0
                             : std::sqrt(command.force[0] * command.force[0] +
                                         command.force[1] * command.force[1] +
                                         command.force[2] * command.force[2])});
    }
    ++stats.cycles;
    next += period;
    const Clock::time_point after = Clock::now();
    if (after > next + period) {
      next = after;  // late: start afresh rather than burst
    } else {
      std::this_thread::sleep_until(next);
    }
  }
  return stats;
}

int Main(int argc, char** argv) {
  app::SetLogProcess("arm-sim");
  Options o;
  if (const std::optional<int> exit_code = ParseOptions(argc, argv, &o)) return *exit_code;
  Inputs in;
  if (const std::optional<int> exit_code = LoadInputs(o, &in)) return *exit_code;
  app::InstallStopSignals();
  if (o.duration == 0.0) o.duration = in.script->duration() + 1.0;
  // The per-cycle record is kept in memory, sized now, and written when the driver stops: file
  // writes in the cycle could block it (a busy disk) past the node's 10 ms watchdog. At most
  // the first 10 minutes are recorded.
  std::vector<Cycle> record;
  if (in.torques) {
    record.reserve(static_cast<size_t>(std::min(o.duration, 600.0) * o.rate) + 16);
  }
  SetDriverScheduling(o.rt_priority);
  const RunStats stats = RunDriver(o, &in, &record);
  // Stopping: zero torque is the arm's own business; its last state stays for the node to see
  // its heartbeat stop.
  for (const Cycle& c : record) {
    in.torques << c.ns << ',' << c.node_heartbeat << ',' << c.tripped << ',' << c.torque << ','
               << c.x << ',' << c.y << ',' << c.z << ',' << c.force << '\n';
  }
  if (in.torques) in.torques.flush();
  Log(LogLevel::kInfo, "stopped",
      {{"cycles", stats.cycles},
       {"torn_reads", stats.torn},
       {"watchdog_trips", stats.trips},
       {"header_checks", stats.header_checks}});
  if (!o.report_path.empty()) {
    nlohmann::ordered_json r = {{"arm", o.arm_name},
                                {"cycles", stats.cycles},
                                {"torn_reads", stats.torn},
                                {"watchdog_trips", stats.trips},
                                {"exit_code", stats.exit_code}};
    std::ofstream(o.report_path) << r.dump(2) << "\n";
  }
  return stats.exit_code;
}

}  // namespace
}  // namespace somasim::haptic

int main(int argc, char** argv) {
  try {
    return somasim::haptic::Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-arm-sim: internal error: %s\n", e.what());
    return 70;
  }
}
