// The haptic node's per-tick pieces (issue 9), measured one tick at a time so that the p99 the
// issue sets targets for is a counter (targets: tick compute ≤ 20 µs p99, shm hand-off ≤ 1 µs
// p99 one way). The loop period and the pose's way to the server: haptic_loop_bench.cc.
//
// BM_HapticShmHandoff: one command written into a real /somasim-arm-* block and read back
// (a whole seqlock record each way; same thread, so the cost, not the cross-core latency).
// BM_HapticTickCompute: one tick of the node's loop (haptic_loop.h) from the arm's state to its
// torques on the seed-002 arm, exactly as the loop runs it: check the header, read the state,
// read the newest model from its slot, HapticLoop::Tick (device checks, encoders to joints,
// forward kinematics with the Jacobian, into the scene, the local force model at the tool tip,
// the output stage, back into the arm's frame, Jᵀ F), write the command. A probe pressing 2 mm.
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "common/arm_shm/arm_shm.h"
#include "common/force_model/local_force_model.h"
#include "common/lockfree/latest_slot.h"
#include "haptic_node/haptic_loop.h"
#include "haptic_node/kinematics.h"

namespace somasim::haptic {
namespace {

using Clock = std::chrono::steady_clock;

// Per-iteration times [ns] -> p50 and p99 counters [µs].
void Percentiles(benchmark::State& state, std::vector<double>* ns) {
  if (ns->empty()) return;
  std::sort(ns->begin(), ns->end());
  const auto at = [&](double q) {
    return (*ns)[static_cast<size_t>(q * static_cast<double>(ns->size() - 1))] * 1e-3;
  };
  state.counters["p50_us"] = at(0.5);
  state.counters["p99_us"] = at(0.99);
  state.counters["max_us"] = ns->back() * 1e-3;
}

void BM_HapticShmHandoff(benchmark::State& state) {
  const std::string name = "bench-" + std::to_string(getpid());
  arm_shm::ArmBlock::Unlink(name);
  auto block = arm_shm::ArmBlock::Create(name, 6);
  somasim_arm_command_t out{}, in{};
  out.enable = 1;
  out.num_joints = 6;
  std::vector<double> ns;
  ns.reserve(1 << 20);
  for (auto _ : state) {
    const Clock::time_point t0 = Clock::now();
    ++out.heartbeat;
    arm_shm::WriteCommand(&block->block().command, out);
    const arm_shm::ReadResult r = arm_shm::ReadCommand(block->block().command, &in);
    const Clock::time_point t1 = Clock::now();
    benchmark::DoNotOptimize(r);
    benchmark::DoNotOptimize(in.heartbeat);
    if (ns.size() < ns.capacity()) {
      ns.push_back(static_cast<double>(
          std::chrono::duration_cast<std::chrono::nanoseconds>(t1 - t0).count()));
    }
  }
  Percentiles(state, &ns);
  arm_shm::ArmBlock::Unlink(name);
}
BENCHMARK(BM_HapticShmHandoff);

// BM_HapticShmHandoffOneWay: the hand-off across cores, one way: a writer thread (the node)
// writes a command stamped with steady_clock every ~20 µs; this thread (the driver) polls the
// record and, for each new heartbeat, takes now − the stamp. Counters p50/p99/max_us over the
// hand-offs; one iteration = one hand-off received.
void BM_HapticShmHandoffOneWay(benchmark::State& state) {
  const std::string name = "bench-ow-" + std::to_string(getpid());
  arm_shm::ArmBlock::Unlink(name);
  auto block = arm_shm::ArmBlock::Create(name, 6);
  std::atomic<bool> stop{false};
  std::thread writer([&] {
    somasim_arm_command_t out{};
    out.enable = 1;
    out.num_joints = 6;
    while (!stop.load(std::memory_order_relaxed)) {
      ++out.heartbeat;
      out.node_time_ns = static_cast<uint64_t>(
          std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch())
              .count());
      arm_shm::WriteCommand(&block->block().command, out);
      const Clock::time_point until = Clock::now() + std::chrono::microseconds(20);
      while (Clock::now() < until) {
      }
    }
  });
  std::vector<double> ns;
  ns.reserve(1 << 20);
  uint64_t last = 0;
  somasim_arm_command_t in{};
  for (auto _ : state) {
    for (;;) {
      if (arm_shm::ReadCommand(block->block().command, &in) == arm_shm::ReadResult::kOk &&
          in.heartbeat != last) {
        break;
      }
    }
    const int64_t now =
        std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch())
            .count();
    // The first sample read may be one written before this iteration began: count only the
    // next ones (a writer 20 µs apart, so a sample seen within 20 µs of its stamp is fresh).
    if (last != 0 && ns.size() < ns.capacity()) {
      ns.push_back(static_cast<double>(now - static_cast<int64_t>(in.node_time_ns)));
    }
    last = in.heartbeat;
  }
  stop = true;
  writer.join();
  Percentiles(state, &ns);
  arm_shm::ArmBlock::Unlink(name);
}
BENCHMARK(BM_HapticShmHandoffOneWay)->Iterations(200000);

void BM_HapticTickCompute(benchmark::State& state) {
  const ArmKinematics k = ArmKinematics::Load(std::string(SOMASIM_ARMS_DIR) + "/seed002.arm.txtpb");
  const std::string name = "bench-tick-" + std::to_string(getpid());
  arm_shm::ArmBlock::Unlink(name);
  auto block = arm_shm::ArmBlock::Create(name, 6);
  HapticLoopSettings settings;
  settings.output.max_force = k.max_force();
  HapticLoop loop(k, settings);
  lockfree::LatestSlot<ReceivedForceModel> slot;
  somasim_arm_state_t s{};
  s.num_joints = 6;
  int64_t now = 1'000'000'000;
  const auto tick = [&] {
    ++s.heartbeat;
    arm_shm::WriteState(&block->block().state, s);  // the driver's part, outside the timing below
    now += 1'000'000;
    HapticLoopInput in;
    in.now_ns = now;
    in.header_problem = block->HeaderProblem();
    in.read = arm_shm::ReadState(block->block().state, &in.state);
    ReceivedForceModel model;
    uint64_t version = 0;
    const bool have = slot.Read(&model, &version) && version > 0;
    in.model = have ? &model : nullptr;
    arm_shm::WriteCommand(&block->block().command, loop.Tick(in));
  };
  // A probe pressing 2 mm into a surface through the arm's home pose, engaged.
  const ArmPose home = k.ToScene(k.Forward(k.JointsFromEncoders(s.joint)));
  force_model::LocalForceModel m;
  m.in_contact = true;
  force_model::Vec(m.contact_point) = home.position - Eigen::Vector3d(0, 0, 0.01);
  m.contact_stiffness = 600.0;
  for (int i = 0; i < 50; ++i) {
    slot.Write({m, now});
    tick();
  }
  force_model::Vec(m.contact_point) = home.position + Eigen::Vector3d(0, 0, 0.002);
  for (int i = 0; i < 600; ++i) {
    slot.Write({m, now});
    tick();
  }
  std::vector<double> ns;
  ns.reserve(1 << 20);
  for (auto _ : state) {
    ++s.heartbeat;
    arm_shm::WriteState(&block->block().state, s);
    slot.Write({m, now});
    now += 1'000'000;
    const Clock::time_point t0 = Clock::now();
    HapticLoopInput in;
    in.now_ns = now;
    in.header_problem = block->HeaderProblem();
    in.read = arm_shm::ReadState(block->block().state, &in.state);
    ReceivedForceModel model;
    uint64_t version = 0;
    const bool have = slot.Read(&model, &version) && version > 0;
    in.model = have ? &model : nullptr;
    arm_shm::WriteCommand(&block->block().command, loop.Tick(in));
    const Clock::time_point t1 = Clock::now();
    if (ns.size() < ns.capacity()) {
      ns.push_back(static_cast<double>(
          std::chrono::duration_cast<std::chrono::nanoseconds>(t1 - t0).count()));
    }
  }
  state.counters["force_n"] = loop.arm_force().norm();  // 1.2 N: the press was rendered
  Percentiles(state, &ns);
  arm_shm::ArmBlock::Unlink(name);
}
BENCHMARK(BM_HapticTickCompute);

}  // namespace
}  // namespace somasim::haptic
