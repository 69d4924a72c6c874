// somasim-haptic's command line: which device, the session, and the node's options; then the
// device and the loop made for it, run by RunNode (haptic_node.h).
#include <CLI/CLI.hpp>
#include <cstdio>
#include <memory>
#include <string>

#include "common/app/log.h"
#include "common/app/signals.h"
#include "common/arm_shm/arm_shm.h"
#include "common/dds/topics.h"
#include "haptic_node/devices.h"
#include "haptic_node/haptic_node.h"
#include "haptic_node/kinematics.h"
#include "haptic_node/mock_script.h"

#ifndef SOMASIM_VERSION
#define SOMASIM_VERSION "0.0.0"
#endif
#ifndef SOMASIM_SOURCE_DIR
#define SOMASIM_SOURCE_DIR "."
#endif

namespace somasim::haptic {
namespace {

// What only one device takes.
struct DeviceOptions {
  std::string script;      // mock
  std::string arm;         // shm: the arm's name, /somasim-arm-NAME
  std::string arm_config;  // shm: its configuration (*.arm.txtpb)
  std::string tool = "probe";
  double arm_timeout_ms = 10.0;  // [ms] the driver's heartbeat may be still this long (SPEC)
};

void AddOptions(CLI::App& cli, NodeOptions* o, DeviceOptions* d, std::string* dds_config) {
  cli.add_option("--device", o->device, "shm (an arm) or mock (a script)")
      ->check(CLI::IsMember({"shm", "mock"}))
      ->capture_default_str();
  cli.add_option("--script", d->script, "mock: the script");
  cli.add_option("--arm", d->arm, "shm: the arm's name (/somasim-arm-NAME)");
  cli.add_option("--arm-config", d->arm_config,
                 "shm: the arm's configuration (*.arm.txtpb; default haptic_node/arms/NAME)");
  cli.add_option("--tool", d->tool, "shm: the scene's tool the arm drives")->capture_default_str();
  cli.add_option("--duration", o->duration, "shm: seconds to run (0: until SIGINT/SIGTERM)")
      ->check(CLI::Range(0.0, 1e7))
      ->capture_default_str();
  cli.add_option("--rt-priority", o->rt_priority,
                 "shm: SCHED_FIFO priority of the loop (0: do not ask)")
      ->check(CLI::Range(0, 99))
      ->capture_default_str();
  cli.add_option("--spin-us", o->spin_us, "shm: microseconds spun before each deadline")
      ->check(CLI::Range(0, 500))
      ->capture_default_str();
  cli.add_option("--arm-timeout-ms", d->arm_timeout_ms,
                 "shm: how long the driver's heartbeat may be still before a fault (SPEC: 10; "
                 "raise it only where the host stalls, e.g. tests on a shared VM)")
      ->check(CLI::Range(2.0, 1000.0))
      ->capture_default_str();
  cli.add_option("--session", o->session, "the session's name (its DDS partition)")
      ->capture_default_str();
  cli.add_option("--station", o->station, "this station's name, for logs")->capture_default_str();
  cli.add_option("--domain", o->domain, "DDS domain id")->check(CLI::Range(0, 232));
  cli.add_option("--dds-config", *dds_config, "Cyclone DDS XML configuration");
  cli.add_option("--rate", o->rate, "loop ticks (and tool commands) per second")
      ->check(CLI::Range(10.0, 10000.0))
      ->capture_default_str();
  cli.add_option("--wait-server", o->wait_server, "mock: seconds to wait for the server")
      ->check(CLI::Range(0.0, 3600.0))
      ->capture_default_str();
  cli.add_option("--forces", o->forces, "CSV of the rendered force, one row per tick");
  cli.add_option("--report", o->report, "JSON report at the end");
}

// --device shm: the arm's kinematics and shared memory, the loop on them.
int RunArm(NodeOptions o, DeviceOptions d, const std::string& config) {
  if (d.arm.empty()) {
    std::fprintf(stderr, "somasim-haptic: --device shm needs --arm NAME\n");
    return app::kExitUsage;
  }
  if (const std::string bad = arm_shm::ArmNameError(d.arm); !bad.empty()) {
    std::fprintf(stderr, "somasim-haptic: --arm \"%s\" %s\n", d.arm.c_str(), bad.c_str());
    return app::kExitUsage;
  }
  if (d.arm_config.empty()) {
    d.arm_config = std::string(SOMASIM_SOURCE_DIR) + "/haptic_node/arms/" + d.arm + ".arm.txtpb";
  }
  if (d.tool.empty()) {
    std::fprintf(stderr, "somasim-haptic: --tool must name the scene's tool\n");
    return app::kExitUsage;
  }
  std::unique_ptr<ArmKinematics> kinematics;
  try {
    kinematics = std::make_unique<ArmKinematics>(ArmKinematics::Load(d.arm_config));
  } catch (const ArmConfigError& e) {
    std::fprintf(stderr, "somasim-haptic: --arm-config %s\n", e.what());
    return app::kExitUsage;
  }
  std::unique_ptr<arm_shm::ArmBlock> block;
  try {
    block = arm_shm::ArmBlock::Create(d.arm, static_cast<uint32_t>(kinematics->num_joints()));
  } catch (const arm_shm::ArmShmError& e) {
    std::fprintf(stderr, "somasim-haptic: %s\n", e.what());
    return app::kExitArmBlock;
  }
  HapticLoopSettings settings;
  settings.output.dt = 1.0 / o.rate;
  settings.output.max_force = kinematics->max_force();
  settings.arm_timeout = 1e-3 * d.arm_timeout_ms;
  HapticLoop loop(*kinematics, settings);
  ArmDevice device(*block);
  o.tools = {d.tool};
  o.lock_memory = true;
  o.report_info["arm"] = d.arm;
  o.report_info["tool"] = d.tool;
  app::Log(app::LogLevel::kInfo, "arm",
           {{"arm", d.arm},
            {"shm", block->object_name()},
            {"config", kinematics->name()},
            {"joints", kinematics->num_joints()},
            {"max_force_n", kinematics->max_force()},
            {"tool", d.tool},
            {"session", o.session},
            {"rate_hz", o.rate}});
  return RunNode(o, device, loop, config);
}

// --device mock: the script's emulated Cartesian device; the run waits for the server, ends
// with the script and when the server is lost.
int RunMock(NodeOptions o, const DeviceOptions& d, const std::string& config) {
  std::unique_ptr<MockScript> script;
  try {
    script = std::make_unique<MockScript>(MockScript::Load(d.script));
  } catch (const ScriptError& e) {
    std::fprintf(stderr, "somasim-haptic: %s\n", e.what());
    return e.line() == 0 ? app::kExitIo : app::kExitBadInput;
  }
  HapticLoopSettings settings;
  settings.output.dt = 1.0 / o.rate;
  HapticLoop loop(settings);
  ScriptDevice device(*script);
  o.tools = script->tools();
  o.wait_for_server = true;
  o.stop_on_server_lost = true;
  o.rt_priority = 0;  // a script on a shared test machine: no SCHED_FIFO, no spinning
  o.spin_us = 0;
  o.report_info["script"] = d.script;
  o.report_info["script_duration_s"] = script->duration();
  return RunNode(o, device, loop, config);
}

}  // namespace

int HapticMain(int argc, char** argv) {
  app::SetLogProcess("haptic");
  NodeOptions o;
  o.rt_priority = 80;
  o.spin_us = 50;
  DeviceOptions d;
  CLI::App cli{
      "somasim-haptic: the 1 kHz haptic node. --device shm drives an arm through its shared\n"
      "memory (docs/haptic_node.md); --device mock plays a scripted trajectory\n"
      "(docs/mock_scripts.md). Exit codes: 0 done, 2 usage, 3 bad script, 4 I/O, 5 DDS,\n"
      "6 no server, 7 server lost, 8 the arm's shared memory is unusable, 70 bug."};
  cli.set_version_flag("--version", std::string("somasim-haptic ") + SOMASIM_VERSION);
  std::string dds_config;
  AddOptions(cli, &o, &d, &dds_config);
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? app::kExitOk : app::kExitUsage;
  }
  if (const std::string bad = dds::SessionNameError(o.session); !bad.empty()) {
    std::fprintf(stderr, "somasim-haptic: --session \"%s\" %s\n", o.session.c_str(), bad.c_str());
    return app::kExitUsage;
  }
  if (o.device == "shm" && !d.script.empty()) {
    std::fprintf(stderr, "somasim-haptic: --script is for --device mock\n");
    return app::kExitUsage;
  }
  if (o.device == "mock" && d.script.empty()) {
    std::fprintf(stderr, "somasim-haptic: --device mock needs --script FILE\n");
    return app::kExitUsage;
  }
  app::InstallStopSignals();
  std::string config;
  try {
    config = dds::ReadDdsConfig(dds_config);
  } catch (const std::runtime_error& e) {
    std::fprintf(stderr, "somasim-haptic: %s\n", e.what());
    return app::kExitIo;
  }
  try {
    return o.device == "shm" ? RunArm(o, d, config) : RunMock(o, d, config);
  } catch (const dds::DdsError& e) {
    std::fprintf(stderr, "somasim-haptic: DDS: %s\n", e.what());
    return app::kExitDds;
  }
}

}  // namespace somasim::haptic
