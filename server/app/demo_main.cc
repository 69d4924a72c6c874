// somasim-demo: the README's main job. Runs the headless demo session on loopback — a
// somasim-server on the built-in liver and a mock haptic node playing the demo script
// (palpate, grasp and pull, incision) — waits for both, then prints a summary and writes a
// JSON report (steps, step-time percentiles, frames, forces, contact time, events) and records
// the session (OUT/<session>.somarec, for somasim-replay). The session
// ends at --duration of session time or when the script ends, whichever comes first. With
// --arm the session is driven as a station with an arm is: somasim-haptic --device shm and the
// emulated arm somasim-arm-sim, whose hand plays the script (palpate.txt by default).
// Exit code: 0 when both processes finished cleanly, else the first failure's.
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/app/child_process.h"
#include "common/app/exit_codes.h"
#include "common/app/signals.h"

#ifndef SOMASIM_SOURCE_DIR
#define SOMASIM_SOURCE_DIR "."
#endif

namespace {

namespace fs = std::filesystem;

nlohmann::json ReadJson(const fs::path& path) {
  std::ifstream in(path);
  if (!in) return nlohmann::json::object();
  try {
    return nlohmann::json::parse(in);
  } catch (const nlohmann::json::exception&) {
    return nlohmann::json::object();
  }
}

struct DemoOptions {
  std::string scene = "builtin:liver";
  std::string script = std::string(SOMASIM_SOURCE_DIR) + "/haptic_node/scripts/demo.txt";
  std::string dds_config = std::string(SOMASIM_SOURCE_DIR) + "/deploy/cyclonedds-loopback.xml";
  std::string out_dir = "demo";
  double duration = 20.0;
  uint32_t domain = 0;
  bool arm = false;
  std::string arm_config = std::string(SOMASIM_SOURCE_DIR) + "/haptic_node/arms/seed002.arm.txtpb";
};

// The command line into `o`; an exit code when the program ends here (help, a usage error),
// else -1.
int ParseOptions(int argc, char** argv, DemoOptions* o) {
  CLI::App cli{"somasim-demo: the headless demo session (server + mock haptic node on loopback)"};
  cli.add_option("--scene", o->scene, "the server's scene")->capture_default_str();
  cli.add_option("--script", o->script, "the mock haptic node's script")->capture_default_str();
  cli.add_option("--duration", o->duration, "seconds of session time")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  cli.add_option("--out", o->out_dir, "folder for logs, forces and the report")
      ->capture_default_str();
  cli.add_option("--dds-config", o->dds_config, "Cyclone DDS configuration")->capture_default_str();
  cli.add_option("--domain", o->domain, "DDS domain id")->check(CLI::Range(0, 232));
  cli.add_flag("--arm", o->arm,
               "drive the session with an arm: somasim-haptic --device shm and the emulated arm "
               "somasim-arm-sim, whose hand plays the script (default palpate.txt)");
  cli.add_option("--arm-config", o->arm_config, "with --arm: the arm's configuration")
      ->capture_default_str();
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? somasim::app::kExitOk : somasim::app::kExitUsage;
  }
  if (o->arm && cli.get_option("--script")->count() == 0) {
    o->script = std::string(SOMASIM_SOURCE_DIR) + "/haptic_node/scripts/palpate.txt";
  }
  return -1;
}

// The demo's three processes: the server, the haptic node and (with --arm) the emulated arm,
// with their exit codes (-1 while running).
struct Processes {
  std::unique_ptr<somasim::app::ChildProcess> server;
  std::unique_ptr<somasim::app::ChildProcess> haptic;
  std::unique_ptr<somasim::app::ChildProcess> arm_sim;
  int server_rc = -1;
  int haptic_rc = -1;
  int arm_rc = -1;
};

void StartServerAndNode(const DemoOptions& o, const fs::path& bin, const fs::path& out,
                        const std::string& session, const std::string& arm_name, Processes* p) {
  p->server = std::make_unique<somasim::app::ChildProcess>(
      std::vector<std::string>{(bin / "somasim-server").string(), "--scene", o.scene, "--session",
                               session, "--headless", "--duration", std::to_string(o.duration),
                               "--domain", std::to_string(o.domain), "--dds-config", o.dds_config,
                               "--report", (out / "server_report.json").string(), "--verbose",
                               "--record", (out / (session + ".somarec")).string()},
      (out / "server.log").string());
  std::vector<std::string> haptic_args = {(bin / "somasim-haptic").string(),
                                          "--session",
                                          session,
                                          "--domain",
                                          std::to_string(o.domain),
                                          "--dds-config",
                                          o.dds_config,
                                          "--report",
                                          (out / "haptic_report.json").string()};
  if (o.arm) {
    for (const std::string& a :
         {std::string("--device"), std::string("shm"), std::string("--tool"), std::string("probe"),
          std::string("--arm"), arm_name, std::string("--arm-config"), o.arm_config}) {
      haptic_args.push_back(a);
    }
  } else {
    for (const std::string& a :
         {std::string("--device"), std::string("mock"), std::string("--script"), o.script,
          std::string("--wait-server"), std::string("120"), std::string("--forces"),
          (out / "forces.csv").string()}) {
      haptic_args.push_back(a);
    }
  }
  p->haptic =
      std::make_unique<somasim::app::ChildProcess>(haptic_args, (out / "haptic.log").string());
  p->arm_rc = o.arm ? -1 : 0;
}

// Waits for every process; SIGINT/SIGTERM passes on to them. With --arm the emulated arm starts
// (its hand playing the script) once the node has found the server, and the session ends when
// the hand's script does. False when the session did not finish in time.
bool WaitForAll(const DemoOptions& o, const fs::path& bin, const fs::path& out,
                const std::string& arm_name, Processes* p) {
  const auto t0 = std::chrono::steady_clock::now();
  const auto limit = std::chrono::seconds(static_cast<int>(10 * o.duration) + 300);
  while (p->server_rc < 0 || p->haptic_rc < 0 || p->arm_rc < 0) {
    if (somasim::app::StopRequested()) {
      p->server->Signal(SIGTERM);
      p->haptic->Signal(SIGTERM);
      if (p->arm_sim) p->arm_sim->Signal(SIGTERM);
      if (!p->arm_sim) p->arm_rc = p->arm_rc < 0 ? 0 : p->arm_rc;
    }
    if (std::chrono::steady_clock::now() - t0 > limit) {
      std::fprintf(stderr, "somasim-demo: the session did not finish within %lld s\n",
                   static_cast<long long>(limit.count()));
      return false;
    }
    if (o.arm && !p->arm_sim && p->arm_rc < 0) {
      std::ifstream log(out / "haptic.log");
      bool found = false;
      for (std::string line; !found && std::getline(log, line);) {
        found = line.find("server_found") != std::string::npos;
      }
      if (found) {
        p->arm_sim = std::make_unique<somasim::app::ChildProcess>(
            std::vector<std::string>{(bin / "somasim-arm-sim").string(), "--arm", arm_name,
                                     "--config", o.arm_config, "--script", o.script, "--torques",
                                     (out / "arm.csv").string(), "--report",
                                     (out / "arm_report.json").string()},
            (out / "arm.log").string());
      }
    }
    if (p->arm_sim && p->arm_rc < 0) {
      p->arm_rc = p->arm_sim->Wait(std::chrono::milliseconds(50));
      if (p->arm_rc >= 0) {  // the hand's script is done: so is the session
        p->haptic->Signal(SIGTERM);
        p->server->Signal(SIGTERM);
      }
    }
    if (p->server_rc < 0) p->server_rc = p->server->Wait(std::chrono::milliseconds(50));
    if (p->haptic_rc < 0) {
      p->haptic_rc = p->haptic->Wait(std::chrono::milliseconds(50));
      if (p->haptic_rc >= 0 && p->server_rc < 0) {
        // The trainee's script is done: the session ends with it (a physics slower than real
        // time has not reached --duration yet).
        p->server->Signal(SIGTERM);
      }
      if (p->haptic_rc >= 0 && p->arm_sim && p->arm_rc < 0) p->arm_sim->Signal(SIGTERM);
      if (p->haptic_rc >= 0 && !p->arm_sim) p->arm_rc = p->arm_rc < 0 ? 0 : p->arm_rc;
    }
    if (p->server_rc >= 0 && p->haptic_rc < 0) p->haptic->Signal(SIGTERM);
  }
  return true;
}

double Num(const nlohmann::json& j, const char* key) {
  return j.contains(key) && j[key].is_number() ? j[key].get<double>() : 0.0;
}

// The summary: the server's physics, frames, commands, the haptic node's loop and forces.
void PrintRun(const nlohmann::json& s, const nlohmann::json& h, bool arm) {
  std::printf("\n== somasim demo summary ==\n");
  std::printf("session time     %.2f s in %.2f s wall (real-time factor %.2f)\n",
              Num(s, "sim_time_s"), Num(s, "wall_time_s"), Num(s, "realtime_factor"));
  std::printf("physics          %.0f organ steps, %.0f rejected\n", Num(s, "organ_steps"),
              Num(s, "rejected_steps"));
  if (s.contains("step_time_us")) {
    const nlohmann::json& p = s["step_time_us"];
    std::printf("step time        p50 %.0f us, p90 %.0f us, p99 %.0f us, max %.0f us\n",
                Num(p, "p50"), Num(p, "p90"), Num(p, "p99"), Num(p, "max"));
  }
  std::printf("frames           %.0f published; %.0f force models\n", Num(s, "frames_published"),
              Num(s, "force_models_published"));
  std::printf("tool commands    %.0f received, %.0f rejected\n", Num(s, "tool_commands_received"),
              Num(s, "tool_commands_rejected"));
  if (arm) {
    const nlohmann::json loop = h.contains("loop") ? h["loop"] : nlohmann::json::object();
    const nlohmann::json period =
        h.contains("period_error_us") ? h["period_error_us"] : nlohmann::json::object();
    std::printf(
        "haptic node      %.0f ticks with the arm; period error p99 %.0f us, max %.0f us;"
        " %.0f over 2 ms; %s\n",
        Num(loop, "ticks"), Num(period, "p99"), Num(period, "max"), Num(h, "periods_over_2ms"),
        h.contains("realtime") && h["realtime"].value("sched_fifo", false) ? "SCHED_FIFO"
                                                                           : "no SCHED_FIFO");
    std::printf("force            max %.2f N at the arm; %.0f force models taken; %.0f faults\n",
                Num(h, "max_force_n"), Num(h, "force_models_taken"), Num(loop, "faults"));
  } else {
    std::printf("haptic node      %.0f ticks at %.0f Hz; %.0f force models received\n",
                Num(h, "ticks"), Num(h, "rate_hz"), Num(h, "force_models_received"));
    std::printf("force            max %.2f N, mean in contact %.2f N, contact time %.2f s\n",
                Num(h, "max_force_n"), Num(h, "mean_force_in_contact_n"), Num(h, "contact_time_s"));
  }
}

// The summary's second half: events, cuts, the recording.
void PrintOutcome(const nlohmann::json& s) {
  if (s.contains("events") && s["events"].is_object()) {
    std::printf("events          ");
    for (const auto& [name, count] : s["events"].items()) {
      std::printf(" %s %d;", name.c_str(), count.get<int>());
    }
    std::printf("\n");
  }
  if (s.contains("organs") && s["organs"].is_array()) {
    for (const auto& o : s["organs"]) {
      if (!o.contains("elements_cut") || o["elements_cut"].get<int64_t>() == 0) continue;
      std::printf("cut              %s: %lld elements removed, topology version %u\n",
                  o.value("id", std::string("?")).c_str(),
                  static_cast<long long>(o["elements_cut"].get<int64_t>()),
                  o.value("topology_version", 0U));
    }
  }
  if (s.contains("recording") && s["recording"].is_object()) {
    const auto& rec = s["recording"];
    if (rec.value("failed", false)) {
      std::printf("recording        FAILED: %s\n", rec.value("error", std::string()).c_str());
    } else {
      std::printf("recording        %s (%.1f MB); replay it: somasim-replay %s\n",
                  rec.value("file", std::string()).c_str(),
                  static_cast<double>(rec.value("bytes", uint64_t{0})) / 1e6,
                  rec.value("file", std::string()).c_str());
    }
  }
}

int Demo(int argc, char** argv) {
  DemoOptions o;
  if (const int rc = ParseOptions(argc, argv, &o); rc >= 0) return rc;
  somasim::app::InstallStopSignals();
  const fs::path out(o.out_dir);
  std::error_code ec;
  fs::create_directories(out, ec);
  if (ec) {
    std::fprintf(stderr, "somasim-demo: cannot create %s: %s\n", o.out_dir.c_str(),
                 ec.message().c_str());
    return somasim::app::kExitIo;
  }
  const fs::path bin = fs::read_symlink("/proc/self/exe").parent_path();
  const std::string session = "demo-" + std::to_string(getpid());
  std::printf("somasim demo: session %s, scene %s, %.1f s, script %s\n", session.c_str(),
              o.scene.c_str(), o.duration, o.script.c_str());
  std::printf("  logs, forces and reports in %s/\n", out.c_str());
  std::fflush(stdout);
  const auto t0 = std::chrono::steady_clock::now();
  const std::string arm_name = "demo-" + std::to_string(getpid());
  Processes p;
  StartServerAndNode(o, bin, out, session, arm_name, &p);
  if (!WaitForAll(o, bin, out, arm_name, &p)) return somasim::app::kExitBug;
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const nlohmann::json s = ReadJson(out / "server_report.json");
  const nlohmann::json h = ReadJson(out / "haptic_report.json");
  nlohmann::ordered_json report;
  report["session"] = session;
  report["scene"] = o.scene;
  report["script"] = o.script;
  report["wall_time_s"] = wall;
  report["server_exit_code"] = p.server_rc;
  report["haptic_exit_code"] = p.haptic_rc;
  report["server"] = s;
  report["haptic"] = h;
  std::ofstream(out / "demo_report.json") << report.dump(2) << "\n";
  PrintRun(s, h, o.arm);
  PrintOutcome(s);
  std::printf("report           %s\n", (out / "demo_report.json").c_str());
  const std::pair<int, const char*> outcomes[] = {{p.server_rc, "the server"},
                                                  {p.haptic_rc, "the haptic node"},
                                                  {p.arm_rc, "the emulated arm"}};
  const char* logs[] = {"server.log", "haptic.log", "arm.log"};
  for (size_t i = 0; i < 3; ++i) {
    if (outcomes[i].first == 0) continue;
    std::fprintf(stderr, "somasim-demo: %s exited with %d (see %s)\n", outcomes[i].second,
                 outcomes[i].first, (out / logs[i]).c_str());
    return outcomes[i].first;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Demo(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-demo: %s\n", e.what());
    return somasim::app::kExitBug;
  }
}
