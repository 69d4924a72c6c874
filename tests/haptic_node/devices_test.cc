// The devices of the haptic node (haptic_node/devices.h) through the one tick
// (haptic_loop.h) and the one loop thread (loop_thread.h): the mock script's emulated Cartesian
// device runs the same HapticLoop::Tick as an arm — it starts once its heartbeat moves, its
// pose and tool reach the server's tool pose, a contact model's force is rendered through the
// output stage (engagement, clamp), the script's emergency-stop bit zeroes it, a device state
// that is not a pose latches a fault — and the loop thread with that device allocates nothing
// while it ticks, hands the pose over, and records the forces in its ring.
#include "haptic_node/devices.h"

#include <gtest/gtest.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <limits>
#include <memory>
#include <thread>

#include "haptic_node/loop_thread.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::haptic {
namespace {

using Eigen::Vector3d;
constexpr int64_t kMs = 1000000;

// A probe held at (0, 0, 0.05) for 2 s, then the grasper at (0.01, 0, 0.05) with the
// emergency stop pressed from 3 s.
const char* kScript = R"(somasim-script 1
tool probe
key 0 0 0 0.05
key 2 0 0 0.05
tool grasper
key 2.5 0.01 0 0.05 jaw 0.5
key 3 0.01 0 0.05 jaw 0.5 buttons 2
key 4 0.01 0 0.05 jaw 0.5 buttons 2
)";

// A contact plane `depth` [m] above the point p, normal +z, received at `now`.
ReceivedForceModel Pressing(const Vector3d& p, double depth, int64_t now, uint64_t seq) {
  force_model::LocalForceModel m;
  m.sequence = seq;
  m.in_contact = true;
  force_model::Vec(m.contact_point) = p + Vector3d(0, 0, depth);
  m.contact_stiffness = 300.0;
  m.force_limit = 10.0;
  return {m, now};
}

struct Rig {
  Rig() : script(MockScript::Parse(kScript, "test")), device(script), loop(Settings()) {}
  static HapticLoopSettings Settings() { return {}; }
  const somasim_arm_command_t& Tick(const ReceivedForceModel* model = nullptr) {
    now += kMs;
    in = HapticLoopInput{};
    in.now_ns = now;
    device.Read(now, &in);
    in.model = model;
    return loop.Tick(in);
  }
  MockScript script;
  ScriptDevice device;
  HapticLoop loop;
  HapticLoopInput in;
  int64_t now = 1000 * kMs;
};

TEST(ScriptDevice, DrivesTheSameTickAsAnArmFromItsPoseToTheRenderedForce) {
  Rig r;
  r.Tick();
  EXPECT_EQ(r.loop.phase(), LoopPhase::kWaitingForArm);  // the heartbeat has not moved yet
  r.Tick();
  EXPECT_EQ(r.loop.phase(), LoopPhase::kRunning);
  EXPECT_EQ(r.loop.tool().valid, 1u);
  EXPECT_EQ(r.loop.tool().tool, 0u);  // the probe
  EXPECT_EQ(
      Vector3d(r.loop.tool().position[0], r.loop.tool().position[1], r.loop.tool().position[2]),
      Vector3d(0, 0, 0.05));
  // Out of contact until engaged, then pressed 5 mm: 300 N/m × 5 mm = 1.5 N up, reached over
  // the engagement ramp.
  const Vector3d p(0, 0, 0.05);
  for (int i = 0; i < 30; ++i) {
    const ReceivedForceModel away = Pressing(p, -0.01, r.now, 1);
    r.Tick(&away);
  }
  ASSERT_TRUE(r.loop.output().engaged());
  for (int i = 0; i < 700; ++i) {
    const ReceivedForceModel press = Pressing(p, 0.005, r.now, 2);
    r.Tick(&press);
  }
  EXPECT_NEAR(r.loop.arm_force().z(), 1.5, 1e-9);
  EXPECT_TRUE(r.loop.in_contact());
  const somasim_arm_command_t& c = r.Tick();
  EXPECT_EQ(c.num_joints, 0u);  // a Cartesian device: a force, no torques
  // The script switches to the grasper at 2.5 s and presses the emergency stop at 3 s: the
  // force is zero at once.
  while (r.device.ScriptTime(r.now + kMs) < 2.6) r.Tick();
  EXPECT_EQ(r.loop.tool().tool, 1u);
  EXPECT_DOUBLE_EQ(r.loop.tool().jaw, 0.5);
  while (r.device.ScriptTime(r.now + kMs) < 3.0) {
    const ReceivedForceModel press = Pressing(Vector3d(0.01, 0, 0.05), 0.005, r.now, 3);
    r.Tick(&press);
  }
  EXPECT_GT(r.loop.arm_force().norm(), 0.1);
  const ReceivedForceModel press = Pressing(Vector3d(0.01, 0, 0.05), 0.005, r.now, 4);
  const somasim_arm_command_t& stopped = r.Tick(&press);
  EXPECT_EQ(r.loop.arm_force().norm(), 0.0);
  EXPECT_EQ(stopped.enable, 0u);
  EXPECT_FALSE(r.device.finished(r.now));
  while (r.device.ScriptTime(r.now) <= 4.2) r.Tick();
  EXPECT_TRUE(r.device.finished(r.now));
}

TEST(ScriptDevice, ADeviceStateThatIsNotAPoseLatchesAFault) {
  for (int bad = 0; bad < 4; ++bad) {
    Rig r;
    r.Tick();
    r.Tick();
    ASSERT_FALSE(r.loop.fault());
    r.now += kMs;
    HapticLoopInput in;
    in.now_ns = r.now;
    r.device.Read(r.now, &in);
    if (bad == 0) in.cartesian.position[1] = std::numeric_limits<double>::quiet_NaN();
    if (bad == 1) in.cartesian.position[2] = 11.0;
    if (bad == 2) in.cartesian.orientation[0] = 0.5;
    if (bad == 3) in.cartesian.gripper = 1.5;
    r.loop.Tick(in);
    EXPECT_TRUE(r.loop.fault()) << bad;
    EXPECT_STRNE(r.loop.fault_reason(), "") << bad;
    EXPECT_EQ(r.loop.arm_force().norm(), 0.0);
  }
}

TEST(ScriptDevice, TicksAllocateNothing) {
  Rig r;
  const ReceivedForceModel press = Pressing(Vector3d(0, 0, 0.05), 0.005, r.now, 1);
  r.Tick(&press);
  const somasim::testing::AllocationCounter count;
  for (int i = 0; i < 3000; ++i) r.Tick(&press);
  EXPECT_EQ(count.count(), 0);
}

// The loop thread itself with the script's device: it hands poses and forces over, the wire
// side's models reach it through the slots, and it allocates nothing while it runs.
TEST(LoopThread, TicksTheDeviceWithoutAllocatingAndHandsThePoseAndForcesOver) {
  const MockScript script = MockScript::Parse(kScript, "test");
  ScriptDevice device(script);
  HapticLoop loop{HapticLoopSettings{}};
  auto shared = std::make_unique<NodeShared>();
  shared->record_forces = true;
  shared->wake_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  ASSERT_GE(shared->wake_fd, 0);
  shared->models[0].Write(Pressing(Vector3d(0, 0, 0.05), 0.005, MonotonicNs(), 1));
  auto timing = std::make_unique<LoopTiming>();
  std::thread thread([&] { RunLoopThread({1000.0, 0, 0}, device, loop, *shared, *timing); });
  // Counted once the thread runs (making a thread allocates; its ticks must not).
  while (shared->status.ticks.load() < 5) std::this_thread::yield();
  auto count = std::make_unique<somasim::testing::AllocationCounter>();
  // The wire side: keeps the model fresh and drains the ring, as the node's wire thread does.
  uint64_t rows = 0;
  ForceRecord record;
  const auto until = std::chrono::steady_clock::now() + std::chrono::milliseconds(400);
  while (std::chrono::steady_clock::now() < until) {
    shared->models[0].Write(Pressing(Vector3d(0, 0, 0.05), 0.005, MonotonicNs(), 2));
    while (shared->forces.Pop(&record)) ++rows;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  const int64_t allocations = count->count();
  shared->stop = true;
  thread.join();
  count.reset();
  close(shared->wake_fd);
  while (shared->forces.Pop(&record)) ++rows;
  const uint64_t ticks = shared->status.ticks.load();
  EXPECT_GT(ticks, 20u);  // about 400 on a quiet machine; no timing is asserted here
  EXPECT_EQ(rows + shared->status.forces_dropped.load(), ticks);
  EXPECT_EQ(allocations, 0);
  ToolPoseSample pose;
  uint64_t version = 0;
  ASSERT_TRUE(shared->pose.Read(&pose, &version));
  EXPECT_EQ(version, ticks);
  EXPECT_EQ(pose.valid, 1u);
  EXPECT_DOUBLE_EQ(pose.position[2], 0.05);
  EXPECT_GT(shared->status.contact_time.load(), 0.1);  // pressed from the second tick on
  EXPECT_TRUE(record.in_contact);
  EXPECT_GE(record.model_age_ms, 0.0);
}

}  // namespace
}  // namespace somasim::haptic
