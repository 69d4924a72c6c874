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

int Demo(int argc, char** argv) {
  std::string scene = "builtin:liver";
  std::string script = std::string(SOMASIM_SOURCE_DIR) + "/haptic_node/scripts/demo.txt";
  std::string dds_config = std::string(SOMASIM_SOURCE_DIR) + "/deploy/cyclonedds-loopback.xml";
  std::string out_dir = "demo";
  double duration = 20.0;
  uint32_t domain = 0;
  CLI::App cli{"somasim-demo: the headless demo session (server + mock haptic node on loopback)"};
  cli.add_option("--scene", scene, "the server's scene")->capture_default_str();
  cli.add_option("--script", script, "the mock haptic node's script")->capture_default_str();
  cli.add_option("--duration", duration, "seconds of session time")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  cli.add_option("--out", out_dir, "folder for logs, forces and the report")->capture_default_str();
  cli.add_option("--dds-config", dds_config, "Cyclone DDS configuration")->capture_default_str();
  cli.add_option("--domain", domain, "DDS domain id")->check(CLI::Range(0, 232));
  bool arm = false;
  std::string arm_config = std::string(SOMASIM_SOURCE_DIR) + "/haptic_node/arms/seed002.arm.txtpb";
  cli.add_flag("--arm", arm,
               "drive the session with an arm: somasim-haptic --device shm and the emulated arm "
               "somasim-arm-sim, whose hand plays the script (default palpate.txt)");
  cli.add_option("--arm-config", arm_config, "with --arm: the arm's configuration")
      ->capture_default_str();
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? 0 : 2;
  }
  if (arm && cli.get_option("--script")->count() == 0) {
    script = std::string(SOMASIM_SOURCE_DIR) + "/haptic_node/scripts/palpate.txt";
  }
  somasim::app::InstallStopSignals();
  const fs::path out(out_dir);
  std::error_code ec;
  fs::create_directories(out, ec);
  if (ec) {
    std::fprintf(stderr, "somasim-demo: cannot create %s: %s\n", out_dir.c_str(),
                 ec.message().c_str());
    return 4;
  }
  const fs::path bin = fs::read_symlink("/proc/self/exe").parent_path();
  const std::string session = "demo-" + std::to_string(getpid());
  const std::string dur = std::to_string(duration);
  std::printf("somasim demo: session %s, scene %s, %.1f s, script %s\n", session.c_str(),
              scene.c_str(), duration, script.c_str());
  std::printf("  logs, forces and reports in %s/\n", out.c_str());
  std::fflush(stdout);
  const auto t0 = std::chrono::steady_clock::now();
  somasim::app::ChildProcess server(
      {(bin / "somasim-server").string(), "--scene", scene, "--session", session, "--headless",
       "--duration", dur, "--domain", std::to_string(domain), "--dds-config", dds_config,
       "--report", (out / "server_report.json").string(), "--verbose", "--record",
       (out / (session + ".somarec")).string()},
      (out / "server.log").string());
  const std::string arm_name = "demo-" + std::to_string(getpid());
  std::vector<std::string> haptic_args = {(bin / "somasim-haptic").string(),
                                          "--session",
                                          session,
                                          "--domain",
                                          std::to_string(domain),
                                          "--dds-config",
                                          dds_config,
                                          "--report",
                                          (out / "haptic_report.json").string()};
  if (arm) {
    for (const char* a : {"--device", "shm", "--tool", "probe", "--arm"}) haptic_args.push_back(a);
    haptic_args.push_back(arm_name);
    haptic_args.push_back("--arm-config");
    haptic_args.push_back(arm_config);
  } else {
    for (const std::string& a :
         {std::string("--device"), std::string("mock"), std::string("--script"), script,
          std::string("--wait-server"), std::string("120"), std::string("--forces"),
          (out / "forces.csv").string()}) {
      haptic_args.push_back(a);
    }
  }
  somasim::app::ChildProcess haptic(haptic_args, (out / "haptic.log").string());
  // With --arm: the emulated arm, its hand playing the script once the node has found the
  // server; the session ends when the hand's script does.
  std::unique_ptr<somasim::app::ChildProcess> arm_sim;
  const auto start_arm = [&] {
    arm_sim = std::make_unique<somasim::app::ChildProcess>(
        std::vector<std::string>{(bin / "somasim-arm-sim").string(), "--arm", arm_name, "--config",
                                 arm_config, "--script", script, "--torques",
                                 (out / "arm.csv").string(), "--report",
                                 (out / "arm_report.json").string()},
        (out / "arm.log").string());
  };
  // Wait for them; SIGINT/SIGTERM passes on to them.
  const auto limit = std::chrono::seconds(static_cast<int>(10 * duration) + 300);
  int server_rc = -1;
  int haptic_rc = -1;
  int arm_rc = arm ? -1 : 0;
  while (server_rc < 0 || haptic_rc < 0 || arm_rc < 0) {
    if (somasim::app::StopRequested()) {
      server.Signal(SIGTERM);
      haptic.Signal(SIGTERM);
      if (arm_sim) arm_sim->Signal(SIGTERM);
      if (!arm_sim) arm_rc = arm_rc < 0 ? 0 : arm_rc;
    }
    if (std::chrono::steady_clock::now() - t0 > limit) {
      std::fprintf(stderr, "somasim-demo: the session did not finish within %lld s\n",
                   static_cast<long long>(limit.count()));
      return 70;
    }
    if (arm && !arm_sim && arm_rc < 0) {
      std::ifstream log(out / "haptic.log");
      bool found = false;
      for (std::string line; !found && std::getline(log, line);) {
        found = line.find("server_found") != std::string::npos;
      }
      if (found) start_arm();
    }
    if (arm_sim && arm_rc < 0) {
      arm_rc = arm_sim->Wait(std::chrono::milliseconds(50));
      if (arm_rc >= 0) {  // the hand's script is done: so is the session
        haptic.Signal(SIGTERM);
        server.Signal(SIGTERM);
      }
    }
    if (server_rc < 0) server_rc = server.Wait(std::chrono::milliseconds(50));
    if (haptic_rc < 0) {
      haptic_rc = haptic.Wait(std::chrono::milliseconds(50));
      if (haptic_rc >= 0 && server_rc < 0) {
        // The trainee's script is done: the session ends with it (a physics slower than real
        // time has not reached --duration yet).
        server.Signal(SIGTERM);
      }
      if (haptic_rc >= 0 && arm_sim && arm_rc < 0) arm_sim->Signal(SIGTERM);
      if (haptic_rc >= 0 && !arm_sim) arm_rc = arm_rc < 0 ? 0 : arm_rc;
    }
    if (server_rc >= 0 && haptic_rc < 0) haptic.Signal(SIGTERM);
  }
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const nlohmann::json s = ReadJson(out / "server_report.json");
  const nlohmann::json h = ReadJson(out / "haptic_report.json");
  nlohmann::ordered_json report;
  report["session"] = session;
  report["scene"] = scene;
  report["script"] = script;
  report["wall_time_s"] = wall;
  report["server_exit_code"] = server_rc;
  report["haptic_exit_code"] = haptic_rc;
  report["server"] = s;
  report["haptic"] = h;
  std::ofstream(out / "demo_report.json") << report.dump(2) << "\n";
  const auto num = [](const nlohmann::json& j, const char* key) {
    return j.contains(key) && j[key].is_number() ? j[key].get<double>() : 0.0;
  };
  std::printf("\n== somasim demo summary ==\n");
  std::printf("session time     %.2f s in %.2f s wall (real-time factor %.2f)\n",
              num(s, "sim_time_s"), num(s, "wall_time_s"), num(s, "realtime_factor"));
  std::printf("physics          %.0f organ steps, %.0f rejected\n", num(s, "organ_steps"),
              num(s, "rejected_steps"));
  if (s.contains("step_time_us")) {
    const nlohmann::json& p = s["step_time_us"];
    std::printf("step time        p50 %.0f us, p90 %.0f us, p99 %.0f us, max %.0f us\n",
                num(p, "p50"), num(p, "p90"), num(p, "p99"), num(p, "max"));
  }
  std::printf("frames           %.0f published; %.0f force models\n", num(s, "frames_published"),
              num(s, "force_models_published"));
  std::printf("tool commands    %.0f received, %.0f rejected\n", num(s, "tool_commands_received"),
              num(s, "tool_commands_rejected"));
  if (arm) {
    const nlohmann::json loop = h.contains("loop") ? h["loop"] : nlohmann::json::object();
    const nlohmann::json period =
        h.contains("period_error_us") ? h["period_error_us"] : nlohmann::json::object();
    std::printf(
        "haptic node      %.0f ticks with the arm; period error p99 %.0f us, max %.0f us;"
        " %.0f over 2 ms; %s\n",
        num(loop, "ticks"), num(period, "p99"), num(period, "max"), num(h, "periods_over_2ms"),
        h.contains("realtime") && h["realtime"].value("sched_fifo", false) ? "SCHED_FIFO"
                                                                           : "no SCHED_FIFO");
    std::printf("force            max %.2f N at the arm; %.0f force models taken; %.0f faults\n",
                num(h, "max_force_n"), num(h, "force_models_taken"), num(loop, "faults"));
  } else {
    std::printf("haptic node      %.0f ticks at %.0f Hz; %.0f force models received\n",
                num(h, "ticks"), num(h, "rate_hz"), num(h, "force_models_received"));
    std::printf("force            max %.2f N, mean in contact %.2f N, contact time %.2f s\n",
                num(h, "max_force_n"), num(h, "mean_force_in_contact_n"), num(h, "contact_time_s"));
  }
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
  std::printf("report           %s\n", (out / "demo_report.json").c_str());
  if (server_rc != 0) {
    std::fprintf(stderr, "somasim-demo: the server exited with %d (see %s)\n", server_rc,
                 (out / "server.log").c_str());
    return server_rc;
  }
  if (haptic_rc != 0) {
    std::fprintf(stderr, "somasim-demo: the haptic node exited with %d (see %s)\n", haptic_rc,
                 (out / "haptic.log").c_str());
    return haptic_rc;
  }
  if (arm_rc != 0) {
    std::fprintf(stderr, "somasim-demo: the emulated arm exited with %d (see %s)\n", arm_rc,
                 (out / "arm.log").c_str());
    return arm_rc;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Demo(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-demo: %s\n", e.what());
    return 70;
  }
}
