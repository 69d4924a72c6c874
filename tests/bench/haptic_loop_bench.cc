// The haptic node's loop in a running session (issue 9), end to end: somasim-server on the
// built-in liver (the demo's organ: its physics keeps a core busy), somasim-haptic --device shm
// and somasim-arm-sim (the seed-002 arm, its hand playing palpate.txt, then holding) over
// Cyclone DDS on loopback (domains 216..219), for SOMASIM_BENCH_HAPTIC_SECONDS (default 60) s.
//   BM_HapticLoopPeriod  from the node's --report: the loop's period error (|period − 1 ms|)
//                        p50/p99/p999/max [µs] and the count of periods over 2 ms
//                        (period_p50_us ... periods_over_2ms), the wake-up lateness p99
//                        (lateness_p99_us), sched_fifo (1 when the loop got SCHED_FIFO),
//                        overruns; and the tool pose's way to the server: this process
//                        subscribes to the tool commands as the server does, and takes
//                        now − sender_time_ns for each (the node's tick time on the same
//                        monotonic clock): pose_latency_p50/p99/max_us, poses. steal_pct: the
//                        CPU time the hypervisor gave other guests meanwhile. The baseline,
//                        in the same run: a bare SCHED_FIFO 1 kHz timer thread in this process
//                        (baseline_period_p99/p999/max_us, baseline_over_2ms): what the machine
//                        gives any real-time loop. Time column: the period error p99.
// One iteration = one whole measurement (Iterations(1)).
#include <benchmark/benchmark.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdlib>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "common/app/child_process.h"
#include "common/app/realtime.h"
#include "common/arm_shm/arm_shm.h"
#include "common/dds/topics.h"
#include "haptic_node/period_stats.h"
#include "tests/bench/bench_programs.h"

namespace somasim::haptic {
namespace {

using bench::BinPath;
using bench::TempDir;

double Seconds() {
  const char* env = std::getenv("SOMASIM_BENCH_HAPTIC_SECONDS");
  const double s = env != nullptr ? std::atof(env) : 60.0;
  return s > 1.0 ? s : 60.0;
}

double StealTicks(double* total) {
  std::ifstream in("/proc/stat");
  std::string cpu;
  in >> cpu;
  double steal = 0.0;
  *total = 0.0;
  for (int field = 0; field < 8 && in; ++field) {
    double v = 0.0;
    in >> v;
    *total += v;
    if (field == 7) steal = v;
  }
  return steal;
}

void BM_HapticLoopPeriod(benchmark::State& state) {
  static uint32_t run = 0;
  const uint32_t domain = 216 + (run++ % 4);
  const std::string dir = TempDir("haptic-loop-" + std::to_string(domain));
  const std::string config = dir + "/loopback.xml";
  std::ofstream(config) << dds::LoopbackConfig();
  const std::string session = "bench-haptic";
  const std::string arm = "bench-" + std::to_string(getpid());
  const std::string arm_config = std::string(SOMASIM_ARMS_DIR) + "/seed002.arm.txtpb";
  const std::string script = std::string(SOMASIM_SCRIPTS_DIR) + "/palpate.txt";
  const double seconds = Seconds();
  for (auto _ : state) {
    dds::Domain dds_domain(domain, dds::LoopbackConfig());
    dds::Participant participant(domain);
    dds::Topics topics(participant);
    dds::Reader<somasim_wire_ToolCommand> poses(participant, topics.tool_command,
                                                dds::ToolCommandQos(session));
    app::ChildProcess server(
        {BinPath("somasim-server"), "--scene", "builtin:liver", "--session", session, "--domain",
         std::to_string(domain), "--dds-config", config, "--headless"},
        dir + "/server.log");
    app::ChildProcess node(
        {BinPath("somasim-haptic"), "--device", "shm", "--arm", arm, "--arm-config", arm_config,
         "--tool", "probe", "--session", session, "--domain", std::to_string(domain),
         "--dds-config", config, "--report", dir + "/node.json"},
        dir + "/node.log");
    // The arm once the node has found the server (the liver takes a few seconds to build).
    const auto found = std::chrono::steady_clock::now() + std::chrono::seconds(120);
    while (bench::ReadText(dir + "/node.log").find("server_found") == std::string::npos &&
           std::chrono::steady_clock::now() < found) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    app::ChildProcess sim({BinPath("somasim-arm-sim"), "--arm", arm, "--config", arm_config,
                           "--script", script, "--duration", std::to_string(seconds + 5)},
                          dir + "/arm.log");
    double total0 = 0.0;
    const double steal0 = StealTicks(&total0);
    // The baseline in the same run: a bare SCHED_FIFO 1 kHz timer thread in this process (an
    // absolute-time sleep per period, nothing else), what the machine itself gives.
    std::atomic<bool> stop_baseline{false};
    MicrosecondHistogram baseline;
    uint64_t baseline_over_2ms = 0;
    bool baseline_fifo = false;
    std::thread timer([&] {
      baseline_fifo = app::SetFifoScheduling(80).applied;
      timespec ts{};
      clock_gettime(CLOCK_MONOTONIC, &ts);
      int64_t next = ts.tv_sec * 1'000'000'000LL + ts.tv_nsec + 1'000'000;
      int64_t previous = 0;
      while (!stop_baseline.load(std::memory_order_relaxed)) {
        const timespec wake{static_cast<time_t>(next / 1'000'000'000),
                            static_cast<long>(next % 1'000'000'000)};
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &wake, nullptr);
        clock_gettime(CLOCK_MONOTONIC, &ts);
        const int64_t now = ts.tv_sec * 1'000'000'000LL + ts.tv_nsec;
        if (previous != 0) {
          const int64_t period = now - previous;
          baseline.Add(period > 1'000'000 ? period - 1'000'000 : 1'000'000 - period);
          if (period > 2'000'000) ++baseline_over_2ms;
        }
        previous = now;
        next += 1'000'000;
        if (now > next) next = now + 1'000'000;
      }
    });
    std::vector<double> latency_us;
    latency_us.reserve(200000);
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
    while (std::chrono::steady_clock::now() < end) {
      poses.WaitForData(std::chrono::milliseconds(20));
      poses.Take([&](const somasim_wire_ToolCommand& c, const dds_sample_info_t&) {
        const int64_t now = std::chrono::duration_cast<std::chrono::nanoseconds>(
                                std::chrono::steady_clock::now().time_since_epoch())
                                .count();
        latency_us.push_back(1e-3 * static_cast<double>(now - c.sender_time_ns));
      });
    }
    stop_baseline = true;
    timer.join();
    double total1 = 0.0;
    const double steal1 = StealTicks(&total1);
    node.Signal(SIGTERM);
    node.Wait(std::chrono::seconds(10));
    sim.Signal(SIGTERM);
    sim.Wait(std::chrono::seconds(10));
    server.Signal(SIGTERM);
    server.Wait(std::chrono::seconds(10));
    arm_shm::ArmBlock::Unlink(arm);
    nlohmann::json r;
    try {
      r = nlohmann::json::parse(bench::ReadText(dir + "/node.json"));
    } catch (const nlohmann::json::exception&) {
      const std::string error = "no report from the node: " + bench::ReadText(dir + "/node.log");
      state.SkipWithError(error.c_str());
      return;
    }
    const nlohmann::json& p = r["period_error_us"];
    state.SetIterationTime(p["p99"].get<double>() * 1e-6);
    state.counters["period_p50_us"] = p["p50"].get<double>();
    state.counters["period_p99_us"] = p["p99"].get<double>();
    state.counters["period_p999_us"] = p["p999"].get<double>();
    state.counters["period_max_us"] = p["max"].get<double>();
    state.counters["periods"] = p["count"].get<double>();
    state.counters["periods_over_2ms"] = r["periods_over_2ms"].get<double>();
    state.counters["lateness_p99_us"] = r["lateness_us"]["p99"].get<double>();
    state.counters["overruns"] = r["loop"]["overruns"].get<double>();
    state.counters["sched_fifo"] = r["realtime"]["sched_fifo"].get<bool>() ? 1.0 : 0.0;
    state.counters["max_force_n"] = r["max_force_n"].get<double>();
    state.counters["baseline_period_p99_us"] = baseline.Quantile(0.99);
    state.counters["baseline_period_p999_us"] = baseline.Quantile(0.999);
    state.counters["baseline_period_max_us"] = baseline.max_us();
    state.counters["baseline_over_2ms"] = static_cast<double>(baseline_over_2ms);
    state.counters["baseline_fifo"] = baseline_fifo ? 1.0 : 0.0;
    state.counters["steal_pct"] =
        total1 > total0 ? 100.0 * (steal1 - steal0) / (total1 - total0) : 0.0;
    std::sort(latency_us.begin(), latency_us.end());
    if (!latency_us.empty()) {
      const auto at = [&](double q) {
        return latency_us[static_cast<size_t>(q * static_cast<double>(latency_us.size() - 1))];
      };
      state.counters["pose_latency_p50_us"] = at(0.5);
      state.counters["pose_latency_p99_us"] = at(0.99);
      state.counters["pose_latency_max_us"] = latency_us.back();
    }
    state.counters["poses"] = static_cast<double>(latency_us.size());
  }
}
BENCHMARK(BM_HapticLoopPeriod)->Iterations(1)->UseManualTime()->Unit(benchmark::kMicrosecond);

}  // namespace
}  // namespace somasim::haptic
