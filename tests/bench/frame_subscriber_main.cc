// somasim-bench-subscriber: the subscriber the wire benchmarks (tests/bench/wire_bench.cc,
// issue 7) start as child processes. It joins a session like a viewer does (topology + mesh
// frames, SPEC §1), decodes every frame with FrameDecoder, and measures each frame's
// server-to-subscriber latency: steady_clock now at the take − the frame's sender_time_ns (the
// server's steady_clock at the write; CLOCK_MONOTONIC, so comparable between processes of one
// host only). It blocks in WaitForData between frames, so it takes no CPU from the server it
// measures beyond receiving and decoding.
//
// At the end (--seconds after the first frame, --frames applied, or SIGTERM/SIGINT) it prints
// one JSON line on stdout:
//   {"frames": received, "applied": n, "latency_us": {"p50", "p90", "p99", "max"},
//    "short_slice": whether the 100 µs scheduler slice (common/app/scheduling.h) applies,
//    "waited": n, "bad": n, "stale": n, "no_topology": n, "nodes": num_nodes of the last frame}
// Exit codes: 0 done, 2 usage, 5 DDS, 70 bug.
#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstdint>
#include <cstdio>
#include <exception>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/app/exit_codes.h"
#include "common/app/scheduling.h"
#include "common/dds/dds.h"
#include "common/dds/topics.h"
#include "common/wire/frame_codec.h"
#include "common/wire/mesh_frame_view.h"

namespace {

using somasim::app::kExitBug;  // exit codes: common/app/exit_codes.h
using somasim::app::kExitDds;
using somasim::app::kExitOk;
using somasim::app::kExitUsage;

volatile std::sig_atomic_t g_stop = 0;

extern "C" void OnStopSignal(int /*signal*/) { g_stop = 1; }

void InstallStopSignals() {
  struct sigaction action {};
  action.sa_handler = OnStopSignal;
  sigemptyset(&action.sa_mask);
  sigaction(SIGTERM, &action, nullptr);
  sigaction(SIGINT, &action, nullptr);
}

struct Options {
  uint32_t domain = 0;
  std::string session = "default";
  std::string dds_config;
  double seconds = 6.0;        // [s] after the first frame
  uint64_t frames = 0;         // 0: no limit
  bool default_slice = false;  // keep the kernel's default scheduler slice (the baseline)
};

struct Organ {
  uint32_t topology_version = 0;
  std::unique_ptr<somasim::wire::FrameDecoder> decoder;
};

struct Counts {
  uint64_t frames = 0;  // received (latency measured for each)
  uint64_t applied = 0;
  uint64_t waited = 0;
  uint64_t stale = 0;
  uint64_t bad = 0;
  uint64_t no_topology = 0;  // frames of an organ whose topology had not arrived yet
  uint32_t nodes = 0;        // num_nodes of the last frame (its size: 12 bytes per node)
};

// The q-quantile (nearest rank) of sorted values; 0 when empty.
double Quantile(const std::vector<double>& sorted, double q) {
  if (sorted.empty()) return 0.0;
  const auto n = static_cast<double>(sorted.size());
  auto rank = static_cast<size_t>(q * n);
  rank = std::min(rank, sorted.size() - 1);
  return sorted[rank];
}

int64_t NowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

int Run(const Options& options) {
  namespace dds = somasim::dds;
  namespace wire = somasim::wire;
  // As a viewer does: a short scheduler slice for this thread and Cyclone's (created below).
  const somasim::app::SliceResult slice =
      options.default_slice ? somasim::app::SliceResult{}
                            : somasim::app::SetSchedulerSlice(somasim::app::kWireSlice);
  const dds::Domain domain(options.domain, dds::ReadDdsConfig(options.dds_config));
  const dds::Participant participant(options.domain);
  const dds::Topics topics(participant);
  dds::Reader<somasim_wire_OrganTopology> topology(participant, topics.topology,
                                                   dds::TopologyQos(options.session));
  dds::Reader<somasim_wire_MeshFrame> frames(participant, topics.frame,
                                             dds::FrameQos(options.session));

  std::map<std::string, Organ> organs;
  Counts counts;
  // Latency [µs] of every received frame; reserved for 60 Hz × the run (+ margin) so that the
  // receive path does not allocate in the common case.
  std::vector<double> latency_us;
  latency_us.reserve(static_cast<size_t>(std::max(1.0, options.seconds) * 60.0 * 4.0) + 1024);

  using Clock = std::chrono::steady_clock;
  Clock::time_point first_frame{};
  bool started = false;
  // Without any frame, give up after --seconds plus a generous margin (a server builds
  // gallbladder5400 for ~1 min on a loaded 2-core VM).
  const Clock::time_point give_up =
      Clock::now() + std::chrono::duration_cast<Clock::duration>(
                         std::chrono::duration<double>(options.seconds + 600.0));

  const auto on_topology = [&organs](const somasim_wire_OrganTopology& t,
                                     const dds_sample_info_t& /*info*/) {
    Organ& o = organs[t.organ];
    if (t.version != o.topology_version || !o.decoder) {
      o.topology_version = t.version;
      o.decoder = std::make_unique<wire::FrameDecoder>(static_cast<int32_t>(t.num_nodes));
    }
  };
  const auto on_frame = [&](const somasim_wire_MeshFrame& f, const dds_sample_info_t& /*info*/) {
    const int64_t now_ns = NowNs();
    latency_us.push_back(static_cast<double>(now_ns - f.sender_time_ns) * 1e-3);
    ++counts.frames;
    counts.nodes = f.num_nodes;
    if (!started) {
      started = true;
      first_frame = Clock::now();
    }
    auto it = organs.find(f.organ);
    if (it == organs.end() || !it->second.decoder) {
      ++counts.no_topology;
      return;
    }
    switch (it->second.decoder->Apply(wire::ViewOf(f))) {
      case wire::FrameDecoder::Result::kApplied:
        ++counts.applied;
        break;
      case wire::FrameDecoder::Result::kWaitingForKeyframe:
        ++counts.waited;
        break;
      case wire::FrameDecoder::Result::kStale:
        ++counts.stale;
        break;
      case wire::FrameDecoder::Result::kBad:
        ++counts.bad;
        break;
    }
  };

  while (g_stop == 0) {
    const Clock::time_point now = Clock::now();
    if (started && now - first_frame >= std::chrono::duration<double>(options.seconds)) break;
    if (!started && now >= give_up) break;
    if (options.frames > 0 && counts.applied >= options.frames) break;
    // Block until a frame arrives (100 ms at most, to notice the end and signals). The topology
    // is taken first so that a frame arriving with its organ's first topology can be decoded.
    const bool has_frames = frames.WaitForData(std::chrono::milliseconds(100));
    topology.Take(on_topology);
    if (has_frames) frames.Take(on_frame, 256);
  }

  std::sort(latency_us.begin(), latency_us.end());
  nlohmann::ordered_json out;
  out["frames"] = counts.frames;
  out["applied"] = counts.applied;
  out["latency_us"] = {{"p50", Quantile(latency_us, 0.50)},
                       {"p90", Quantile(latency_us, 0.90)},
                       {"p99", Quantile(latency_us, 0.99)},
                       {"max", latency_us.empty() ? 0.0 : latency_us.back()}};
  out["waited"] = counts.waited;
  out["bad"] = counts.bad;
  out["stale"] = counts.stale;
  out["no_topology"] = counts.no_topology;
  out["nodes"] = counts.nodes;
  out["short_slice"] = slice.applied;
  if (!options.default_slice && !slice.applied) out["slice_detail"] = slice.detail;
  std::printf("%s\n", out.dump().c_str());
  std::fflush(stdout);
  return kExitOk;
}

int Main(int argc, char** argv) {
  Options options;
  CLI::App cli{
      "somasim-bench-subscriber: receives a session's mesh frames, decodes them and prints their "
      "server-to-subscriber latency as one JSON line (wire benchmarks, issue 7).\n"
      "Exit codes: 0 done, 2 usage, 5 DDS, 70 bug."};
  cli.add_option("--domain", options.domain, "DDS domain id")->check(CLI::Range(0, 232));
  cli.add_option("--session", options.session, "the session's name (its DDS partition)")
      ->capture_default_str();
  cli.add_option("--dds-config", options.dds_config,
                 "Cyclone DDS XML configuration file; default: CYCLONEDDS_URI or Cyclone's "
                 "defaults");
  cli.add_option("--seconds", options.seconds,
                 "stop this many seconds after the first frame (or this + 600 s without one: the "
                 "server may take a minute to build its scene)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cli.add_flag("--default-slice", options.default_slice,
               "keep the kernel's default scheduler slice (the baseline of the short one)");
  cli.add_option("--frames", options.frames, "stop after this many frames applied (0: no limit)")
      ->capture_default_str();
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? kExitOk : kExitUsage;
  }
  InstallStopSignals();
  try {
    return Run(options);
  } catch (const somasim::dds::DdsError& e) {
    std::fprintf(stderr, "somasim-bench-subscriber: DDS: %s\n", e.what());
    return kExitDds;
  } catch (const std::runtime_error& e) {
    std::fprintf(stderr, "somasim-bench-subscriber: %s\n", e.what());
    return kExitUsage;
  }
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-bench-subscriber: %s\n", e.what());
    return kExitBug;
  } catch (...) {
    return kExitBug;
  }
}
