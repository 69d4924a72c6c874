// The wire benchmarks of issue 7, end to end over Cyclone DDS on loopback: they start the real
// somasim-server and somasim-bench-subscriber (tests/bench/frame_subscriber_main.cc) as child
// processes, each on its own domain id (170..189, one per run, so leftovers of an earlier run
// cannot cross), all with the loopback Cyclone configuration (dds::LoopbackConfig()).
//   BM_FrameLatency/gallbladder5400  server-to-subscriber latency of mesh frames: the server
//                                    on builtin:gallbladder5400, paced to real time, 60 frames/s,
//                                    every frame a keyframe (all 5400 nodes: the largest frame,
//                                    the worst case); 1 subscriber for ~6 s of frames.
//                                    Counters: latency_p50/p90/p99/max_us, frames. The time
//                                    column is the p50 latency (manual time).
//   BM_PublishOverhead/N             the physics step time of the same server with N = 0, 1, 8
//                                    subscribers (1 s of session time, 60 frames/s, default
//                                    keyframe interval), from the server's --report. Counters:
//                                    step_mean_us, step_p50_us, and for N > 0 overhead_pct =
//                                    100 × (mean_N / mean_0 − 1) against /0 of the same run
//                                    (overhead_p50_pct: the same with the p50s). The
//                                    time column is the mean step time (manual time).
// One iteration = one whole run (Iterations(1)): each takes several seconds of wall time.
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "common/app/child_process.h"
#include "common/dds/dds.h"

namespace somasim::wire {
namespace {

constexpr const char* kOrgan = "gallbladder5400";
constexpr double kLatencySeconds = 6.0;  // [s] of frames the latency subscriber takes
// [s] of session time per overhead run: 100 steps of 10 ms. Short because the server steps
// gallbladder5400 (corotational FEM) ~30x slower than real time on the 2-core VM.
constexpr double kOverheadSeconds = 1.0;

// The step-time mean and p50 [µs] of BM_PublishOverhead/0 in this process (registered first),
// the baseline of /1 and /8; 0 when /0 has not run (filtered out).
double g_baseline_step_mean_us = 0.0;
double g_baseline_step_p50_us = 0.0;

// The programs live beside this benchmark (build/bin).
std::string BinPath(const std::string& program) {
  return (std::filesystem::read_symlink("/proc/self/exe").parent_path() / program).string();
}

// A fresh folder for this process's files.
std::string TempDir(const std::string& name) {
  const std::filesystem::path dir =
      std::filesystem::temp_directory_path() / ("somasim-bench-" + std::to_string(getpid())) / name;
  std::filesystem::create_directories(dir);
  return dir.string();
}

std::string ReadText(const std::string& path) {
  std::ifstream in(path);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

// The loopback Cyclone configuration, as a file every child gets with --dds-config.
std::string LoopbackConfigFile() {
  static const std::string path = [] {
    std::string p = TempDir("dds") + "/loopback.xml";
    std::ofstream(p) << dds::LoopbackConfig();
    return p;
  }();
  return path;
}

// A different domain id per run, 170..189.
uint32_t NextDomain() {
  static uint32_t next = 0;
  return 170 + (next++ % 20);
}

std::unique_ptr<app::ChildProcess> Start(const std::string& program,
                                         const std::vector<std::string>& args,
                                         const std::string& log) {
  std::vector<std::string> argv{BinPath(program)};
  argv.insert(argv.end(), args.begin(), args.end());
  return std::make_unique<app::ChildProcess>(argv, log);
}

// The subscriber's result: the last line of its output that is a JSON object.
nlohmann::json SubscriberResult(const std::string& log) {
  std::istringstream lines(ReadText(log));
  std::string line;
  std::string last;
  while (std::getline(lines, line)) {
    if (!line.empty() && line.front() == '{') last = line;
  }
  if (last.empty()) throw std::runtime_error("no JSON result in " + log);
  return nlohmann::json::parse(last);
}

std::vector<std::string> ServerArgs(uint32_t domain, const std::string& session,
                                    const std::string& config) {
  return {"--scene",      std::string("builtin:") + kOrgan,
          "--session",    session,
          "--domain",     std::to_string(domain),
          "--dds-config", config,
          "--frame-rate", "60"};
}

std::vector<std::string> SubscriberArgs(uint32_t domain, const std::string& session,
                                        const std::string& config, double seconds) {
  return {"--domain",  std::to_string(domain), "--session", session, "--dds-config", config,
          "--seconds", std::to_string(seconds)};
}

void BM_FrameLatency(benchmark::State& state) {
  const uint32_t domain = NextDomain();
  const std::string session = "bench-latency-" + std::to_string(domain);
  const std::string config = LoopbackConfigFile();
  const std::string dir = TempDir("latency-" + std::to_string(domain));
  for (auto _ : state) {
    std::vector<std::string> server_args = ServerArgs(domain, session, config);
    server_args.insert(server_args.end(), {"--keyframe-interval", "1"});
    // The subscriber first, so that it has joined when the first frame goes out.
    auto subscriber =
        Start("somasim-bench-subscriber", SubscriberArgs(domain, session, config, kLatencySeconds),
              dir + "/subscriber.log");
    auto server = Start("somasim-server", server_args, dir + "/server.log");
    const int sub_rc = subscriber->Wait(std::chrono::seconds(900));
    server->Signal(SIGTERM);
    const int server_rc = server->Wait(std::chrono::seconds(30));
    if (sub_rc != 0 || server_rc != 0) {
      state.SkipWithError(("subscriber exit " + std::to_string(sub_rc) + ", server exit " +
                           std::to_string(server_rc) + "; logs in " + dir)
                              .c_str());
      return;
    }
    const nlohmann::json r = SubscriberResult(dir + "/subscriber.log");
    const nlohmann::json& l = r.at("latency_us");
    state.SetIterationTime(l.at("p50").get<double>() * 1e-6);
    state.counters["latency_p50_us"] = l.at("p50").get<double>();
    state.counters["latency_p90_us"] = l.at("p90").get<double>();
    state.counters["latency_p99_us"] = l.at("p99").get<double>();
    state.counters["latency_max_us"] = l.at("max").get<double>();
    state.counters["frames"] = r.at("frames").get<double>();
    state.counters["applied"] = r.at("applied").get<double>();
    state.counters["bad"] = r.at("bad").get<double>();
    state.counters["nodes"] = r.at("nodes").get<double>();
  }
}

void BM_PublishOverhead(benchmark::State& state) {
  const auto subscribers = static_cast<int>(state.range(0));
  const uint32_t domain = NextDomain();
  const std::string session = "bench-overhead-" + std::to_string(domain);
  const std::string config = LoopbackConfigFile();
  const std::string dir = TempDir("overhead-" + std::to_string(domain));
  for (auto _ : state) {
    // The subscribers first (they wait for the server), each until SIGTERM.
    std::vector<std::unique_ptr<app::ChildProcess>> subs;
    subs.reserve(static_cast<size_t>(subscribers));
    for (int i = 0; i < subscribers; ++i) {
      subs.push_back(Start("somasim-bench-subscriber",
                           SubscriberArgs(domain, session, config, 3600.0),
                           dir + "/subscriber" + std::to_string(i) + ".log"));
    }
    // Let them create their readers before the server starts (it builds its scene first too).
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    std::vector<std::string> server_args = ServerArgs(domain, session, config);
    const std::string report = dir + "/report.json";
    server_args.insert(server_args.end(),
                       {"--duration", std::to_string(kOverheadSeconds), "--report", report});
    auto server = Start("somasim-server", server_args, dir + "/server.log");
    const int server_rc = server->Wait(std::chrono::seconds(900));
    double min_frames = 0.0;
    bool subs_ok = true;
    for (size_t i = 0; i < subs.size(); ++i) {
      subs[i]->Signal(SIGTERM);
      subs_ok = subs_ok && subs[i]->Wait(std::chrono::seconds(10)) == 0;
      if (!subs_ok) continue;
      const double frames =
          SubscriberResult(dir + "/subscriber" + std::to_string(i) + ".log").at("frames");
      min_frames = i == 0 ? frames : std::min(min_frames, frames);
    }
    if (server_rc != 0 || !subs_ok) {
      state.SkipWithError(("server exit " + std::to_string(server_rc) +
                           (subs_ok ? "" : ", a subscriber failed") + "; logs in " + dir)
                              .c_str());
      return;
    }
    const nlohmann::json r = nlohmann::json::parse(ReadText(report));
    const nlohmann::json& step = r.at("step_time_us");
    const double mean = step.at("mean").get<double>();
    const double p50 = step.at("p50").get<double>();
    state.SetIterationTime(mean * 1e-6);
    state.counters["step_mean_us"] = mean;
    state.counters["step_p50_us"] = p50;
    state.counters["step_p99_us"] = step.at("p99").get<double>();
    state.counters["frames_published"] = r.at("frames_published").get<double>();
    state.counters["realtime_factor"] = r.at("realtime_factor").get<double>();
    state.counters["fell_behind"] = r.at("fell_behind_real_time").get<double>();
    if (subscribers > 0) state.counters["min_frames_received"] = min_frames;
    if (subscribers == 0) {
      g_baseline_step_mean_us = mean;
      g_baseline_step_p50_us = p50;
    } else if (g_baseline_step_mean_us > 0.0 && g_baseline_step_p50_us > 0.0) {
      state.counters["overhead_pct"] = 100.0 * (mean / g_baseline_step_mean_us - 1.0);
      // The median is less sensitive to the other users' bursts on the shared machine.
      state.counters["overhead_p50_pct"] = 100.0 * (p50 / g_baseline_step_p50_us - 1.0);
    }
  }
}

BENCHMARK(BM_FrameLatency)
    ->Name(std::string("BM_FrameLatency/") + kOrgan)
    ->Iterations(1)
    ->UseManualTime()
    ->Unit(benchmark::kMicrosecond);
// /0 first: the baseline of /1 and /8 in the same run.
BENCHMARK(BM_PublishOverhead)
    ->Arg(0)
    ->Arg(1)
    ->Arg(8)
    ->Iterations(1)
    ->UseManualTime()
    ->Unit(benchmark::kMicrosecond);

}  // namespace
}  // namespace somasim::wire
