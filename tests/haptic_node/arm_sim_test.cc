// The arm simulator (haptic_node/arm_sim.h) and somasim-arm-sim. The simulated arm: its
// watchdog zeroes the torques once the node's heartbeat has been still for 10 ms (not before);
// it never applies torques that are not finite, for another joint count, or while disabled, and
// clamps them to the motors' limits; the hand pulls the handle to its target; a node rendering
// F = 2 N through J^T F displaces the handle against the hand by F / K. The program, on real
// shared memory with this test as the node: it applies the node's torques, and when the node
// stops (as a killed node does) the torque is zero within 20 ms; a corrupted header stops it;
// bad command lines are refused by name.
#include "haptic_node/arm_sim.h"

#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>
#include <thread>

#include "common/arm_shm/arm_shm.h"
#include "tests/server/app/session_client.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::haptic {
namespace {

using Eigen::Vector3d;
using std::chrono::milliseconds;
using std::chrono::seconds;

const std::string kArm = std::string(SOMASIM_ARMS_DIR) + "/seed002.arm.txtpb";

somasim_arm_command_t Command(uint64_t heartbeat, double torque0) {
  somasim_arm_command_t c{};
  c.heartbeat = heartbeat;
  c.enable = 1;
  c.num_joints = 6;
  c.torque[0] = torque0;
  return c;
}

TEST(ArmSimulator, WatchdogZeroesTorqueTenMillisecondsAfterTheNodesHeartbeatStops) {
  const ArmKinematics k = ArmKinematics::Load(kArm);
  ArmSimulator sim(k, ArmSimSettings{});
  const Vector3d hand = k.Forward(sim.q()).position;
  const double dt = 5e-4;
  double t = 0.0;
  EXPECT_TRUE(sim.watchdog_tripped());      // no node heard yet
  for (int i = 0; i < 200; ++i, t += dt) {  // 0.1 s of a live node, heartbeat every 1 ms
    const somasim_arm_command_t c = Command(1 + static_cast<uint64_t>(i / 2), 0.3);
    sim.Step(t, dt, &c, hand);
  }
  EXPECT_FALSE(sim.watchdog_tripped());
  EXPECT_NEAR(sim.applied_torque()[0], 0.3, 1e-15);
  const somasim_arm_command_t frozen = Command(101, 0.3);  // its last write, then it stops
  sim.Step(t, dt, &frozen, hand);
  const double frozen_at = t;
  t += dt;
  while (t - frozen_at <= 0.010 - 1e-12) {
    sim.Step(t, dt, &frozen, hand);
    EXPECT_FALSE(sim.watchdog_tripped()) << 1e3 * (t - frozen_at) << " ms";
    t += dt;
  }
  for (int i = 0; i < 4; ++i, t += dt) sim.Step(t, dt, &frozen, hand);
  EXPECT_TRUE(sim.watchdog_tripped());
  EXPECT_EQ(sim.applied_torque().norm(), 0.0);
  // Nothing read at all (torn or no data) is as silent as a still heartbeat.
  for (int i = 0; i < 40; ++i, t += dt) sim.Step(t, dt, nullptr, hand);
  EXPECT_EQ(sim.applied_torque().norm(), 0.0);
}

TEST(ArmSimulator, NeverAppliesBadTorquesAndClampsToTheMotors) {
  const ArmKinematics k = ArmKinematics::Load(kArm);
  ArmSimulator sim(k, ArmSimSettings{});
  const Vector3d hand = k.Forward(sim.q()).position;
  const double dt = 5e-4;
  uint64_t beat = 0;
  double t = 0.0;
  const auto step = [&](somasim_arm_command_t c) {
    c.heartbeat = ++beat;
    sim.Step(t, dt, &c, hand);
    t += dt;
    return sim.applied_torque();
  };
  somasim_arm_command_t c = Command(0, 0.5);
  EXPECT_NEAR(step(c)[0], 0.5, 1e-15);
  c.torque[1] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(step(c).norm(), 0.0) << "a NaN torque";
  c = Command(0, std::numeric_limits<double>::infinity());
  EXPECT_EQ(step(c).norm(), 0.0) << "an infinite torque";
  c = Command(0, 0.5);
  c.num_joints = 3;
  EXPECT_EQ(step(c).norm(), 0.0) << "another arm's joint count";
  c = Command(0, 0.5);
  c.enable = 0;
  EXPECT_EQ(step(c).norm(), 0.0) << "disabled";
  c = Command(0, 1e9);
  c.torque[4] = -1e9;
  const JointVector clamped = step(c);
  EXPECT_EQ(clamped[0], k.max_torque(0));
  EXPECT_EQ(clamped[4], -k.max_torque(4));
}

TEST(ArmSimulator, TheHandPullsTheHandleToItsTarget) {
  const ArmKinematics k = ArmKinematics::Load(kArm);
  ArmSimulator sim(k, ArmSimSettings{});
  const Vector3d target = k.Forward(sim.q()).position + Vector3d(0.02, -0.01, 0.015);
  for (int i = 0; i < 4000; ++i) sim.Step(5e-4 * i, 5e-4, nullptr, target);  // 2 s
  EXPECT_LT((k.Forward(sim.q()).position - target).norm(), 2e-3);
}

// The node renders F through J^T F every tick; at rest the hand's spring balances it, so the
// handle sits F / K from where the hand holds it: the sign and size of the whole chain.
TEST(ArmSimulator, ANodesJTransposeFTorquesPushTheHandleByFOverK) {
  const ArmKinematics k = ArmKinematics::Load(kArm);
  const ArmSimSettings settings;
  ArmSimulator sim(k, settings);
  const Vector3d hand = k.Forward(sim.q()).position;
  const Vector3d force(0.0, 1.2, -1.6);  // [N], 2 N
  const double dt = 5e-4;
  for (int i = 0; i < 8000; ++i) {  // 4 s
    Jacobian j;
    k.Forward(sim.q(), &j);
    JointVector tau;
    k.Torques(j, force, &tau);
    somasim_arm_command_t c = Command(1 + static_cast<uint64_t>(i), 0.0);
    for (int n = 0; n < 6; ++n) c.torque[n] = tau[n];
    sim.Step(dt * i, dt, &c, hand);
  }
  const Vector3d moved = k.Forward(sim.q()).position - hand;
  EXPECT_LT((moved - force / settings.hand_stiffness).norm(), 0.1 * force.norm() / 300.0)
      << moved.transpose();
}

TEST(ArmSimulator, StepsAllocateNothing) {
  const ArmKinematics k = ArmKinematics::Load(kArm);
  ArmSimulator sim(k, ArmSimSettings{});
  const somasim_arm_command_t c = Command(1, 0.1);
  const somasim::testing::AllocationCounter count;
  for (int i = 0; i < 1000; ++i) sim.Step(5e-4 * i, 5e-4, &c, Vector3d::Zero());
  EXPECT_EQ(count.count(), 0);
}

// ---- somasim-arm-sim on real shared memory ----------------------------------------------------

struct Row {
  int64_t ns = 0;
  uint64_t node_heartbeat = 0;
  int tripped = 0;
  double torque = 0.0;
};

std::vector<Row> ReadTorques(const std::string& path) {
  std::vector<Row> rows;
  std::ifstream in(path);
  std::string line;
  std::getline(in, line);  // header
  while (std::getline(in, line)) {
    std::replace(line.begin(), line.end(), ',', ' ');
    std::istringstream fields(line);
    Row r;
    if (fields >> r.ns >> r.node_heartbeat >> r.tripped >> r.torque) rows.push_back(r);
  }
  return rows;
}

int64_t NowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

// The block somasim-arm-sim makes, once it has made it (3 s at most; nullptr if it never does).
std::unique_ptr<arm_shm::ArmBlock> AttachWhenMade(const std::string& name) {
  for (int i = 0; i < 300; ++i) {
    try {
      return arm_shm::ArmBlock::Open(name, 100);
    } catch (const arm_shm::ArmShmError&) {
      std::this_thread::sleep_for(milliseconds(10));
    }
  }
  return nullptr;
}

// This test is the node: it commands torque for a second through the block, then stops dead (a
// node killed with -9 writes nothing more). The simulated driver applies the torque while the
// heartbeat moves and none from 20 ms after the node's last write on (watchdog 10 ms + a cycle
// + scheduling). A latency bound: skipped under the sanitizers.
TEST(ArmSimProgram, TorqueGoesToZeroWithin20MillisecondsOfTheNodesLastWrite) {
  if (somasim::testing::kUnderSanitizer) GTEST_SKIP() << "a latency bound";
  const std::string dir = testing::TempDir("armsim");
  const std::string name = "test-" + std::to_string(getpid());
  arm_shm::ArmBlock::Unlink(name);
  std::ofstream(dir + "/hold.txt") << "somasim-script 1\ntool probe\nkey 0 -0.03 0 0.10\n";
  auto sim = testing::StartProgram("somasim-arm-sim",
                                   {"--arm", name, "--config", kArm, "--script", dir + "/hold.txt",
                                    "--duration", "4", "--torques", dir + "/torques.csv"},
                                   dir + "/sim.log");
  std::unique_ptr<arm_shm::ArmBlock> block = AttachWhenMade(name);
  ASSERT_TRUE(block) << testing::ReadText(dir + "/sim.log");
  somasim_arm_state_t state{};
  for (int i = 0;
       i < 300 && arm_shm::ReadState(block->block().state, &state) != arm_shm::ReadResult::kOk;
       ++i) {
    std::this_thread::sleep_for(milliseconds(1));
  }
  EXPECT_EQ(arm_shm::StateError(state, 6), "");
  auto next = std::chrono::steady_clock::now();
  int64_t stopped = 0;                             // the node's last write
  for (uint64_t beat = 1; beat <= 1000; ++beat) {  // 1 s at 1 kHz
    arm_shm::WriteCommand(&block->block().command, Command(beat, 0.2));
    stopped = NowNs();
    next += milliseconds(1);
    std::this_thread::sleep_until(next);
  }
  std::this_thread::sleep_for(milliseconds(200));
  sim->Signal(SIGTERM);
  ASSERT_EQ(sim->Wait(seconds(10)), 0) << testing::ReadText(dir + "/sim.log");
  const std::vector<Row> rows = ReadTorques(dir + "/torques.csv");
  ASSERT_GT(rows.size(), 1000u);
  int applied = 0;
  int64_t zero_at = -1;
  for (const Row& r : rows) {
    if (r.ns < stopped - 500'000'000 && r.ns > stopped - 900'000'000) {
      applied += std::abs(r.torque - 0.2) < 1e-12 ? 1 : 0;
    }
    if (r.ns > stopped - 2'000'000 && zero_at < 0 && r.torque == 0.0) zero_at = r.ns;
    if (zero_at >= 0 && r.ns > zero_at) {
      EXPECT_EQ(r.torque, 0.0) << "torque again after the watchdog";
    }
  }
  EXPECT_GT(applied, 500) << "the node's torque was not applied";
  ASSERT_GE(zero_at, 0);
  std::printf("torque zero %.1f ms after the node's last write\n",
              1e-6 * static_cast<double>(zero_at - stopped));
  EXPECT_LT(zero_at - stopped, 20'000'000);
  arm_shm::ArmBlock::Unlink(name);
}

TEST(ArmSimProgram, StopsOnACorruptedHeaderAndRefusesBadCommandLines) {
  const std::string dir = testing::TempDir("armsim-bad");
  const std::string name = "bad-" + std::to_string(getpid());
  arm_shm::ArmBlock::Unlink(name);
  std::ofstream(dir + "/hold.txt") << "somasim-script 1\ntool probe\nkey 0 -0.03 0 0.10\n";
  auto sim = testing::StartProgram(
      "somasim-arm-sim",
      {"--arm", name, "--config", kArm, "--script", dir + "/hold.txt", "--duration", "20"},
      dir + "/sim.log");
  std::unique_ptr<arm_shm::ArmBlock> block = AttachWhenMade(name);
  ASSERT_TRUE(block);
  block->block().abi_version = 7;
  EXPECT_EQ(sim->Wait(seconds(10)), 8) << testing::ReadText(dir + "/sim.log");
  EXPECT_NE(testing::ReadText(dir + "/sim.log").find("abi_version is 7"), std::string::npos);
  arm_shm::ArmBlock::Unlink(name);
  const auto run = [&](const std::vector<std::string>& args, const std::string& log) {
    auto p = testing::StartProgram("somasim-arm-sim", args, dir + "/" + log);
    const int rc = p->Wait(seconds(10));
    return std::make_pair(rc, testing::ReadText(dir + "/" + log));
  };
  auto [rc, text] = run({"--arm", "a/b", "--config", kArm, "--script", dir + "/hold.txt"}, "1");
  EXPECT_EQ(rc, 2);
  EXPECT_NE(text.find("--arm"), std::string::npos) << text;
  std::tie(rc, text) = run({"--arm", "x", "--config", dir + "/none", "--script", "s"}, "2");
  EXPECT_EQ(rc, 2);
  EXPECT_NE(text.find("--config"), std::string::npos) << text;
  std::ofstream(dir + "/bad.txt") << "somasim-script 1\ntool probe\nkey 0 0 0 nan\n";
  std::tie(rc, text) = run({"--arm", "x", "--config", kArm, "--script", dir + "/bad.txt"}, "3");
  EXPECT_EQ(rc, 3);
  EXPECT_NE(text.find("bad.txt:3"), std::string::npos) << text;
}

}  // namespace
}  // namespace somasim::haptic
