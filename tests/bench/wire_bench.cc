// The wire benchmarks of issue 7, end to end over Cyclone DDS on loopback: they start the real
// somasim-server and somasim-bench-subscriber (tests/bench/frame_subscriber_main.cc) as child
// processes, each on its own domain id (170..189, one per run, so leftovers of an earlier run
// cannot cross), all with the loopback Cyclone configuration (dds::LoopbackConfig()).
//   BM_FrameLatency/gallbladder5400  server-to-subscriber latency of mesh frames: the server
//                                    on builtin:gallbladder5400 (an implicit mass-spring shell of
//                                    5400 nodes, 5 ms steps), paced to real time, 60 frames/s,
//                                    every frame a keyframe (all 5400 nodes: the largest frame,
//                                    the worst case); 1 subscriber for ~20 s of frames, with the
//                                    100 µs scheduler slice a viewer asks for
//                                    (common/app/scheduling.h). Counters:
//                                    latency_p50/p90/p99/max_us, frames, short_slice (1 when the
//                                    kernel applied it), steal_pct (the CPU time the hypervisor
//                                    gave other guests meanwhile). The time column is the p50.
//   BM_FrameLatencyDefaultSlice/gallbladder5400  the same with the subscriber on the kernel's
//                                    default slice: the baseline the short slice is measured
//                                    against in the same run.
//   BM_PublishOverhead/N             the physics step time of the same server with N = 0, 1, 8
//                                    subscribers, from the server's --report: 2 s of session
//                                    time run --as-fast-as-possible (the physics thread never
//                                    idles: paced runs mix in how fast an idle vCPU wakes, which
//                                    made 8 subscribers come out 24 % *faster* than none), with
//                                    the publisher at 60 frames/s of wall time and the default
//                                    keyframe interval. For N > 0, nine rounds of runs 0, N, N, 0
//                                    (a linear drift of the shared VM cancels within a round);
//                                    overhead_pct = 100 × (median over the rounds of
//                                    Σ mean_N / Σ mean_0 − 1), overhead_p50_pct the same with the
//                                    p50s, round_min_pct / round_max_pct the rounds' scatter.
//                                    Counters also: step_mean_us, step_p50_us (runs with N
//                                    subscribers), baseline_mean_us. Time column: the mean step.
// One iteration = one whole measurement (Iterations(1)): each takes several seconds of wall time.
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
#include "tests/bench/bench_programs.h"

namespace somasim::wire {
namespace {

constexpr const char* kOrgan = "gallbladder5400";
// [s] of frames the latency subscriber takes: ~1200 frames, so that the p99 is the 12th
// slowest frame, not the 4th (6 s before 2026-11-24: one slow moment decided the p99).
constexpr double kLatencySeconds = 20.0;
// [s] of session time per overhead run: 400 steps of 5 ms, ~1 s of wall time as fast as the
// 2-core VM steps them.
constexpr double kOverheadSeconds = 2.0;
constexpr int kOverheadRounds = 9;  // of 0, N, N, 0 runs per /N (odd: a median)

using bench::BinPath;
using bench::ReadText;
using bench::TempDir;

// The loopback Cyclone configuration, as a file every child gets with --dds-config.
std::string LoopbackConfigFile() {
  static const std::string path = [] {
    std::string p = TempDir("dds") + "/loopback.xml";
    std::ofstream(p) << dds::LoopbackConfig();
    return p;
  }();
  return path;
}

// The machine's CPU time so far from /proc/stat's "cpu" line [ticks]: all of it, and the part
// the hypervisor gave to other guests (steal). {0, 0} when unreadable.
struct CpuTicks {
  double total = 0.0;
  double steal = 0.0;
};
CpuTicks ReadCpuTicks() {
  std::ifstream in("/proc/stat");
  std::string cpu;
  CpuTicks t;
  in >> cpu;
  for (int field = 0; field < 8 && in; ++field) {
    double v = 0.0;
    in >> v;
    t.total += v;
    if (field == 7) t.steal = v;
  }
  return cpu == "cpu" ? t : CpuTicks{};
}
// The share of the machine's CPU time stolen by other guests between `a` and `b` [%].
double StealPercent(const CpuTicks& a, const CpuTicks& b) {
  const double total = b.total - a.total;
  return total > 0.0 ? 100.0 * (b.steal - a.steal) / total : 0.0;
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

void FrameLatency(benchmark::State& state, bool default_slice) {
  const uint32_t domain = NextDomain();
  const std::string session = "bench-latency-" + std::to_string(domain);
  const std::string config = LoopbackConfigFile();
  const std::string dir = TempDir("latency-" + std::to_string(domain));
  for (auto _ : state) {
    std::vector<std::string> server_args = ServerArgs(domain, session, config);
    server_args.insert(server_args.end(), {"--keyframe-interval", "1"});
    // The subscriber first, so that it has joined when the first frame goes out.
    std::vector<std::string> subscriber_args =
        SubscriberArgs(domain, session, config, kLatencySeconds);
    if (default_slice) subscriber_args.emplace_back("--default-slice");
    auto subscriber = Start("somasim-bench-subscriber", subscriber_args, dir + "/subscriber.log");
    const CpuTicks before = ReadCpuTicks();
    auto server = Start("somasim-server", server_args, dir + "/server.log");
    const int sub_rc = subscriber->Wait(std::chrono::seconds(900));
    const CpuTicks after = ReadCpuTicks();
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
    state.counters["short_slice"] = r.value("short_slice", false) ? 1.0 : 0.0;
    // A VM's neighbours take its CPUs for milliseconds at a time: the tail follows the steal.
    state.counters["steal_pct"] = StealPercent(before, after);
  }
}

void BM_FrameLatency(benchmark::State& state) { FrameLatency(state, false); }
void BM_FrameLatencyDefaultSlice(benchmark::State& state) { FrameLatency(state, true); }

struct OverheadRun {
  double mean_us = 0.0;  // the server's step-time mean and p50 [µs]
  double p50_us = 0.0;
  double p99_us = 0.0;
  double frames_published = 0.0;
  double min_frames_received = 0.0;  // over the subscribers (0 without any)
};

// One server run of kOverheadSeconds of session time, as fast as possible, with `subscribers`
// subscribers started before it. Throws std::runtime_error naming the logs when a process fails.
OverheadRun RunOverhead(int subscribers, const std::string& tag) {
  const uint32_t domain = NextDomain();
  const std::string session = "bench-overhead-" + std::to_string(domain);
  const std::string config = LoopbackConfigFile();
  const std::string dir = TempDir("overhead-" + tag + "-" + std::to_string(domain));
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
  server_args.insert(server_args.end(), {"--duration", std::to_string(kOverheadSeconds),
                                         "--as-fast-as-possible", "--report", report});
  auto server = Start("somasim-server", server_args, dir + "/server.log");
  const int server_rc = server->Wait(std::chrono::seconds(900));
  OverheadRun run;
  bool subs_ok = true;
  for (size_t i = 0; i < subs.size(); ++i) {
    subs[i]->Signal(SIGTERM);
    subs_ok = subs_ok && subs[i]->Wait(std::chrono::seconds(10)) == 0;
    if (!subs_ok) continue;
    const double frames =
        SubscriberResult(dir + "/subscriber" + std::to_string(i) + ".log").at("frames");
    run.min_frames_received = i == 0 ? frames : std::min(run.min_frames_received, frames);
  }
  if (server_rc != 0 || !subs_ok) {
    throw std::runtime_error("server exit " + std::to_string(server_rc) +
                             (subs_ok ? "" : ", a subscriber failed") + "; logs in " + dir);
  }
  const nlohmann::json r = nlohmann::json::parse(ReadText(report));
  const nlohmann::json& step = r.at("step_time_us");
  run.mean_us = step.at("mean").get<double>();
  run.p50_us = step.at("p50").get<double>();
  run.p99_us = step.at("p99").get<double>();
  run.frames_published = r.at("frames_published").get<double>();
  return run;
}

void BM_PublishOverhead(benchmark::State& state) {
  const auto subscribers = static_cast<int>(state.range(0));
  for (auto _ : state) {
    try {
      if (subscribers == 0) {
        const OverheadRun run = RunOverhead(0, "0");
        state.SetIterationTime(run.mean_us * 1e-6);
        state.counters["step_mean_us"] = run.mean_us;
        state.counters["step_p50_us"] = run.p50_us;
        state.counters["step_p99_us"] = run.p99_us;
        state.counters["frames_published"] = run.frames_published;
        continue;
      }
      // Rounds of 0, N, N, 0: a linear drift of the machine's speed cancels within a round; the
      // median over the rounds drops a round that the VM's neighbours disturbed.
      const std::string n = std::to_string(subscribers);
      std::vector<double> mean_ratios;  // Σ mean_N / Σ mean_0 per round
      std::vector<double> p50_ratios;
      double mean = 0.0;  // [µs] over every run with N subscribers, and without
      double base_mean = 0.0;
      double p50 = 0.0;
      double frames_published = 1e300;
      double min_frames_received = 1e300;
      for (int round = 0; round < kOverheadRounds; ++round) {
        const std::string r = n + "-" + std::to_string(round);
        double with_sum = 0.0;
        double base_sum = 0.0;
        double with_p50 = 0.0;
        double base_p50 = 0.0;
        int k = 0;
        for (const int subs : {0, subscribers, subscribers, 0}) {
          const OverheadRun run = RunOverhead(subs, r + "-" + std::to_string(k++));
          (subs == 0 ? base_sum : with_sum) += run.mean_us;
          (subs == 0 ? base_p50 : with_p50) += run.p50_us;
          if (subs == 0) continue;
          frames_published = std::min(frames_published, run.frames_published);
          min_frames_received = std::min(min_frames_received, run.min_frames_received);
        }
        mean_ratios.push_back(with_sum / base_sum);
        p50_ratios.push_back(with_p50 / base_p50);
        mean += with_sum / (2.0 * kOverheadRounds);
        base_mean += base_sum / (2.0 * kOverheadRounds);
        p50 += with_p50 / (2.0 * kOverheadRounds);
      }
      const auto median = [](std::vector<double> v) {
        std::sort(v.begin(), v.end());
        return v[v.size() / 2];
      };
      const auto [lo, hi] = std::minmax_element(mean_ratios.begin(), mean_ratios.end());
      state.SetIterationTime(mean * 1e-6);
      state.counters["step_mean_us"] = mean;
      state.counters["step_p50_us"] = p50;
      state.counters["baseline_mean_us"] = base_mean;
      state.counters["overhead_pct"] = 100.0 * (median(mean_ratios) - 1.0);
      state.counters["overhead_p50_pct"] = 100.0 * (median(p50_ratios) - 1.0);
      // How far the rounds scatter: the resolution of this machine, not an overhead.
      state.counters["round_min_pct"] = 100.0 * (*lo - 1.0);
      state.counters["round_max_pct"] = 100.0 * (*hi - 1.0);
      state.counters["frames_published"] = frames_published;
      state.counters["min_frames_received"] = min_frames_received;
    } catch (const std::exception& e) {
      state.SkipWithError(e.what());
      return;
    }
  }
}

BENCHMARK(BM_FrameLatency)
    ->Name(std::string("BM_FrameLatency/") + kOrgan)
    ->Iterations(1)
    ->UseManualTime()
    ->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_FrameLatencyDefaultSlice)
    ->Name(std::string("BM_FrameLatencyDefaultSlice/") + kOrgan)
    ->Iterations(1)
    ->UseManualTime()
    ->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_PublishOverhead)
    ->Arg(0)
    ->Arg(1)
    ->Arg(8)
    ->Iterations(1)
    ->UseManualTime()
    ->Unit(benchmark::kMicrosecond);

}  // namespace
}  // namespace somasim::wire
