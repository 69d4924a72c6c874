// The viewer's benchmark of issue 8, end to end: an Xvfb display (Mesa's software renderer, no
// GPU), the real somasim-server on builtin:<organ> paced to real time at 60 frames/s, and
// somasim-viewer (960 × 720) drawing 600 frames of the complete scene, over Cyclone DDS on
// loopback (domains 192, 193).
//   BM_ViewerFrame/liver4055, BM_ViewerFrame/gallbladder5400
//     Counters from the viewer's --report: frame_p50_ms / frame_p99_ms (between draws of the
//     scene, each draw finished with glFinish), latency_p50_ms / latency_p99_ms (a server
//     frame's write to the end of the draw that first shows it: same host, one steady clock),
//     frames. The time column is the frame p50.
// One iteration = one whole run (Iterations(1)): ~15 s of wall time each.
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "common/app/child_process.h"
#include "common/dds/dds.h"
#include "tests/bench/bench_programs.h"

namespace somasim::viewer {
namespace {

using bench::BinPath;
using bench::ReadText;
using bench::TempDir;

void ViewerFrame(benchmark::State& bench, const std::string& organ, uint32_t domain) {
  const std::string dir = TempDir("viewer-" + organ);
  const std::string config = dir + "/loopback.xml";
  std::ofstream(config) << dds::LoopbackConfig();
  // Xvfb on a free display.
  std::unique_ptr<app::ChildProcess> xvfb;
  std::string display;
  for (int attempt = 0; attempt < 8 && !xvfb; ++attempt) {
    const int n = 150 + static_cast<int>((getpid() * 5 + attempt * 97) % 140);
    if (std::filesystem::exists("/tmp/.X" + std::to_string(n) + "-lock")) continue;
    auto p = std::make_unique<app::ChildProcess>(
        std::vector<std::string>{"/usr/bin/Xvfb", ":" + std::to_string(n), "-screen", "0",
                                 "1280x1024x24", "-nolisten", "tcp"},
        dir + "/xvfb.log");
    for (int i = 0; i < 500 && p->Wait(std::chrono::milliseconds(0)) == -1; ++i) {
      if (std::filesystem::exists("/tmp/.X11-unix/X" + std::to_string(n))) {
        display = ":" + std::to_string(n);
        xvfb = std::move(p);
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
  }
  if (!xvfb) {
    bench.SkipWithError("Xvfb did not start");
    return;
  }
  setenv("DISPLAY", display.c_str(), 1);
  // Stopped with SIGTERM on every way out, so that Xvfb removes its lock file (the
  // ChildProcess destructor's SIGKILL would leave /tmp/.X<n>-lock behind).
  struct StopGently {
    app::ChildProcess& p;
    ~StopGently() {
      p.Signal(SIGTERM);
      p.Wait(std::chrono::seconds(10));
    }
  } stop_xvfb{*xvfb};
  const std::string session = "viewer-bench";
  for (auto _ : bench) {
    app::ChildProcess server({BinPath("somasim-server"), "--scene", "builtin:" + organ, "--session",
                              session, "--domain", std::to_string(domain), "--dds-config", config},
                             dir + "/server.log");
    app::ChildProcess viewer({BinPath("somasim-viewer"), "--session", session, "--domain",
                              std::to_string(domain), "--dds-config", config, "--frames", "600",
                              "--report", dir + "/viewer.json", "--timeout", "120"},
                             dir + "/viewer.log");
    const int rc = viewer.Wait(std::chrono::seconds(180));
    server.Signal(SIGTERM);
    server.Wait(std::chrono::seconds(30));
    if (rc != 0) {
      bench.SkipWithError(
          ("viewer exit " + std::to_string(rc) + ": " + ReadText(dir + "/viewer.log")).c_str());
      return;
    }
    const nlohmann::json report = nlohmann::json::parse(ReadText(dir + "/viewer.json"));
    const double p50 = report["frame_ms"]["p50"].get<double>();
    bench.SetIterationTime(p50 * 1e-3);
    bench.counters["frame_p50_ms"] = p50;
    bench.counters["frame_p99_ms"] = report["frame_ms"]["p99"].get<double>();
    bench.counters["latency_p50_ms"] = report["latency_ms"]["p50"].get<double>();
    bench.counters["latency_p99_ms"] = report["latency_ms"]["p99"].get<double>();
    bench.counters["frames"] = report["frames_drawn_with_scene"].get<double>();
  }
}

BENCHMARK_CAPTURE(ViewerFrame, liver4055, std::string("liver4055"), 192)
    ->Name("BM_ViewerFrame/liver4055")
    ->Iterations(1)
    ->UseManualTime()
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(ViewerFrame, gallbladder5400, std::string("gallbladder5400"), 193)
    ->Name("BM_ViewerFrame/gallbladder5400")
    ->Iterations(1)
    ->UseManualTime()
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace somasim::viewer
