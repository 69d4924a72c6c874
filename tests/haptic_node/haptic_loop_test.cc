// The haptic loop's tick (haptic_node/haptic_loop.h) with the seed-002 arm, the node's clock
// given: it waits for the driver without a fault; a driver that falls silent for 10 ms (not
// less, and not when the node itself was held up), torn reads for as long (one is a driver
// preempted mid-write: no fault), bad state values or a bad
// header latch a fault that zeroes and disables the motors, cleared only by the clutch on a
// usable device; the clutch holds the tool while the arm moves; the emergency stop zeroes force
// in the same tick; a contact model's force reaches the motors as J^T F, clamped to the arm's
// 8 N whatever the model says (1e9 N), a NaN model latches, a stale model ramps to zero in 60 ms;
// ticks allocate nothing. Also the loop's timing histogram.
#include "haptic_node/haptic_loop.h"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <string>
#include <thread>

#include "haptic_node/period_stats.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::haptic {
namespace {

using Eigen::Vector3d;

const std::string kArm = std::string(SOMASIM_ARMS_DIR) + "/seed002.arm.txtpb";
constexpr int64_t kMs = 1000000;

// A driver and a clock: ticks at 1 kHz, the driver's heartbeat moving each tick unless stilled.
class Bench {
 public:
  Bench() : k_(ArmKinematics::Load(kArm)), loop_(k_, Settings(k_)) { state_.num_joints = 6; }
  static HapticLoopSettings Settings(const ArmKinematics& k) {
    HapticLoopSettings s;
    s.output.max_force = k.max_force();
    return s;
  }
  const somasim_arm_command_t& Tick() {
    now_ += kMs;
    if (driver_alive_) ++state_.heartbeat;
    HapticLoopInput in;
    in.now_ns = now_;
    in.header_problem = header_problem_;
    in.read = read_;
    in.state = state_;
    in.model = has_model_ ? &model_ : nullptr;
    return loop_.Tick(in);
  }
  void Ticks(int n) {
    for (int i = 0; i < n; ++i) Tick();
  }
  // A fresh model: a contact plane `depth` [m] above the tool, normal +z in the scene.
  void Press(double depth, double stiffness = 300.0, double limit = 10.0) {
    force_model::LocalForceModel m;
    m.sequence = ++sequence_;
    m.in_contact = true;
    force_model::Vec(m.contact_point) = ToolPosition() + Vector3d(0, 0, depth);
    force_model::Vec(m.normal) = Vector3d::UnitZ();
    m.contact_stiffness = stiffness;
    m.force_limit = limit;
    model_ = {m, now_};
    has_model_ = true;
  }
  void Refresh() { model_.received_ns = now_; }
  Vector3d ToolPosition() const {
    return Vector3d(loop_.tool().position[0], loop_.tool().position[1], loop_.tool().position[2]);
  }
  // Engages out of contact, then presses `depth` (fresh models) until the authority is full.
  void EngageAndPress(double depth) {
    Ticks(3);
    ASSERT_EQ(loop_.phase(), LoopPhase::kRunning);
    for (int i = 0; i < 30; ++i) {
      Press(-0.01);
      Tick();
    }
    for (int i = 0; i < 700; ++i) {
      Press(depth);
      Tick();
    }
    ASSERT_TRUE(loop_.output().engaged());
    ASSERT_EQ(loop_.output().authority(), 1.0);
  }

  ArmKinematics k_;
  HapticLoop loop_;
  somasim_arm_state_t state_{};
  arm_shm::ReadResult read_ = arm_shm::ReadResult::kOk;
  const char* header_problem_ = nullptr;
  bool driver_alive_ = true;
  ReceivedForceModel model_;
  bool has_model_ = false;
  uint64_t sequence_ = 0;
  int64_t now_ = 1000 * kMs;
};

TEST(HapticLoop, WaitsForTheDriverWithoutAFaultThenFollowsTheArm) {
  Bench b;
  b.read_ = arm_shm::ReadResult::kNoData;
  b.Ticks(50);
  EXPECT_EQ(b.loop_.phase(), LoopPhase::kWaitingForArm);
  EXPECT_FALSE(b.loop_.fault());
  EXPECT_EQ(b.Tick().enable, 0u);
  EXPECT_EQ(b.loop_.tool().valid, 0u);
  // A driver's state that does not move yet (a driver from an earlier run, gone): still waiting.
  b.read_ = arm_shm::ReadResult::kOk;
  b.driver_alive_ = false;
  b.Ticks(50);
  EXPECT_EQ(b.loop_.phase(), LoopPhase::kWaitingForArm);
  EXPECT_FALSE(b.loop_.fault());
  b.driver_alive_ = true;
  const somasim_arm_command_t& c = b.Tick();
  EXPECT_EQ(b.loop_.phase(), LoopPhase::kRunning);
  EXPECT_EQ(c.enable, 1u);
  EXPECT_EQ(c.num_joints, 6u);
  EXPECT_EQ(b.loop_.tool().valid, 1u);
  // At home the tool is where the configuration maps the arm's home (-0.03, 0, 0.10).
  EXPECT_NEAR((b.ToolPosition() - Vector3d(-0.03, 0, 0.10)).norm(), 0.0, 1e-12);
  // The heartbeat moves by one per tick.
  const uint64_t beat = c.heartbeat;
  EXPECT_EQ(b.Tick().heartbeat, beat + 1);
}

TEST(HapticLoop, ASilentDriverLatchesAFaultAfterTenMillisecondsNotBefore) {
  Bench b;
  b.EngageAndPress(0.005);
  EXPECT_GT(b.loop_.arm_force().norm(), 1.0);
  b.driver_alive_ = false;
  for (int ms = 1; ms <= 10; ++ms) {
    b.Refresh();
    EXPECT_EQ(b.Tick().enable, 1u) << ms << " ms";
    EXPECT_FALSE(b.loop_.fault()) << ms << " ms";
  }
  b.Refresh();
  const somasim_arm_command_t& c = b.Tick();
  EXPECT_TRUE(b.loop_.fault());
  EXPECT_EQ(c.enable, 0u);
  for (int j = 0; j < 6; ++j) EXPECT_EQ(c.torque[j], 0.0);
  EXPECT_STREQ(b.loop_.fault_reason(), "the arm's heartbeat stopped");
  // The driver coming back does not clear it.
  b.driver_alive_ = true;
  b.Ticks(1000);
  EXPECT_TRUE(b.loop_.fault());
  EXPECT_EQ(b.Tick().enable, 0u);
}

TEST(HapticLoop, ANodeHeldUpByItsHostDoesNotBlameTheDriver) {
  Bench b;
  b.EngageAndPress(0.005);
  // The host stalls 30 ms; the node wakes first and sees the heartbeat it saw 30 ms ago.
  b.driver_alive_ = false;
  b.now_ += 30 * kMs;
  b.Refresh();
  b.Tick();
  b.driver_alive_ = true;  // the driver runs again at once
  b.Refresh();
  b.Ticks(5);
  EXPECT_FALSE(b.loop_.fault()) << b.loop_.fault_reason();
}

TEST(HapticLoop, TornReadsBadStatesAndABadHeaderLatchAFault) {
  struct Case {
    const char* name;
    void (*spoil)(Bench*);
    const char* reason;
  };
  const Case cases[] = {
      {"torn",
       [](Bench* b) {
         b->read_ = arm_shm::ReadResult::kTorn;
         b->Ticks(10);  // a driver preempted mid-write: ticks without news, no fault yet
         EXPECT_FALSE(b->loop_.fault());
       },
       "torn reads"},
      {"nan joint", [](Bench* b) { b->state_.joint[2] = std::numeric_limits<double>::quiet_NaN(); },
       "a bad joint value"},
      {"joints", [](Bench* b) { b->state_.num_joints = 5; }, "another num_joints"},
      {"gripper", [](Bench* b) { b->state_.gripper = 3.0; }, "a bad gripper value"},
      {"buttons", [](Bench* b) { b->state_.buttons = 0x100; }, "unknown button bits"},
      {"header", [](Bench* b) { b->header_problem_ = "bad magic"; }, "bad magic"},
      {"vanished", [](Bench* b) { b->read_ = arm_shm::ReadResult::kNoData; }, "vanished"},
  };
  for (const Case& c : cases) {
    Bench b;
    b.EngageAndPress(0.005);
    c.spoil(&b);
    b.Refresh();
    const somasim_arm_command_t& command = b.Tick();
    EXPECT_TRUE(b.loop_.fault()) << c.name;
    EXPECT_EQ(command.enable, 0u) << c.name;
    EXPECT_EQ(b.loop_.arm_force().norm(), 0.0) << c.name;
    EXPECT_NE(std::string(b.loop_.fault_reason()).find(c.reason), std::string::npos)
        << c.name << ": " << b.loop_.fault_reason();
  }
  // A corrupted header or garbage from the driver latch even before the driver runs.
  Bench early;
  early.header_problem_ = "bad magic";
  early.Tick();
  EXPECT_TRUE(early.loop_.fault());
}

TEST(HapticLoop, OnlyTheClutchOnAUsableDeviceClearsAFaultAndForceReturnsGradually) {
  Bench b;
  b.EngageAndPress(0.005);
  b.header_problem_ = "bad magic";
  b.Tick();
  ASSERT_TRUE(b.loop_.fault());
  b.header_problem_ = nullptr;
  // The clutch too soon after the device became usable does nothing.
  b.Ticks(100);
  b.state_.buttons = SOMASIM_ARM_BUTTON_CLUTCH;
  b.Ticks(10);
  b.state_.buttons = 0;
  b.Tick();
  EXPECT_TRUE(b.loop_.fault());
  b.Ticks(500);
  b.state_.buttons = SOMASIM_ARM_BUTTON_CLUTCH;
  b.Ticks(10);
  b.state_.buttons = 0;
  b.Press(0.005);
  b.Tick();
  EXPECT_FALSE(b.loop_.fault());
  EXPECT_EQ(b.loop_.counters().fault_clears, 1u);
  // Pressing into tissue: force stays zero (not engaged) until the asked force is small ...
  for (int i = 0; i < 100; ++i) {
    b.Press(0.005);
    b.Tick();
    EXPECT_EQ(b.loop_.arm_force().norm(), 0.0);
  }
  // ... then rises over the engagement ramp, never by more than 0.25 N a tick.
  for (int i = 0; i < 30; ++i) {
    b.Press(-0.01);  // out of contact
    b.Tick();
  }
  EXPECT_TRUE(b.loop_.output().engaged());
  double last = 0.0;
  for (int i = 0; i < 600; ++i) {
    b.Press(0.005);
    b.Tick();
    const double f = b.loop_.arm_force().norm();
    EXPECT_LE(f - last, 0.25 + 1e-12);
    last = f;
  }
  EXPECT_GT(last, 1.0);
}

TEST(HapticLoop, TheClutchHoldsTheToolWhileTheArmMovesAndFollowsFromThereOnRelease) {
  Bench b;
  b.Ticks(3);
  const Vector3d start = b.ToolPosition();
  b.state_.buttons = SOMASIM_ARM_BUTTON_CLUTCH;
  b.Tick();
  EXPECT_TRUE(b.loop_.clutched());
  // The arm moves (base yaw 0.1 rad, shoulder 0.05 rad); the tool stays.
  b.state_.joint[0] = 0.1;
  b.state_.joint[1] = 0.05;
  b.Ticks(20);
  EXPECT_EQ((b.ToolPosition() - start).norm(), 0.0);
  b.Press(0.003);  // a model pressing: no force while clutched
  b.Tick();
  EXPECT_EQ(b.loop_.scene_force().norm(), 0.0);
  b.state_.buttons = 0;
  b.Tick();
  EXPECT_FALSE(b.loop_.clutched());
  EXPECT_NEAR((b.ToolPosition() - start).norm(), 0.0, 1e-12);  // released where it was held
  // From there the tool moves as the arm does.
  const ArmPose before = b.k_.ToScene(b.k_.Forward(b.k_.JointsFromEncoders(b.state_.joint)));
  b.state_.joint[0] = 0.0;
  b.Tick();
  const ArmPose after = b.k_.ToScene(b.k_.Forward(b.k_.JointsFromEncoders(b.state_.joint)));
  EXPECT_NEAR((b.ToolPosition() - start - (after.position - before.position)).norm(), 0.0, 1e-12);
}

TEST(HapticLoop, TheEmergencyStopZeroesForceInTheSameTick) {
  Bench b;
  b.EngageAndPress(0.005);
  EXPECT_GT(b.loop_.arm_force().norm(), 1.0);
  b.state_.buttons = SOMASIM_ARM_BUTTON_EMERGENCY_STOP;
  b.Refresh();
  const somasim_arm_command_t& c = b.Tick();
  EXPECT_EQ(c.enable, 0u);
  EXPECT_EQ(b.loop_.arm_force().norm(), 0.0);
  for (int j = 0; j < 6; ++j) EXPECT_EQ(c.torque[j], 0.0);
  EXPECT_EQ(b.loop_.tool().buttons, SOMASIM_ARM_BUTTON_EMERGENCY_STOP);  // the server sees it
}

TEST(HapticLoop, AContactModelsForceReachesTheMotorsAsJTransposeF) {
  Bench b;
  b.EngageAndPress(0.005);
  const somasim_arm_command_t& c = b.Tick();
  // 300 N/m x 5 mm = 1.5 N up in the scene; the arm's frame is the scene's (no rotation).
  const Vector3d f = b.loop_.arm_force();
  EXPECT_NEAR(f.z(), 1.5, 0.05);
  EXPECT_NEAR(std::hypot(f.x(), f.y()), 0.0, 1e-9);
  Jacobian j;
  b.k_.Forward(b.k_.JointsFromEncoders(b.state_.joint), &j);
  JointVector tau;
  b.k_.Torques(j, f, &tau);
  for (int k = 0; k < 6; ++k) EXPECT_NEAR(c.torque[k], tau[k], 1e-12) << k;
  for (int i = 0; i < 3; ++i) EXPECT_EQ(c.force[i], f[i]);
  EXPECT_GT(std::abs(c.torque[1]), 0.1);  // the shoulder carries it
}

TEST(HapticLoop, HugeModelsAreClampedToTheArmsLimitAndNaNModelsLatch) {
  Bench b;
  b.EngageAndPress(0.005);
  double max = 0.0;
  for (int i = 0; i < 200; ++i) {
    b.Press(0.005, 2e11, 1e9);  // 1e9 N
    b.Tick();
    max = std::max(max, b.loop_.arm_force().norm());
  }
  EXPECT_NEAR(max, 8.0, 1e-9);
  EXPECT_FALSE(b.loop_.fault());
  b.Press(0.005);
  b.model_.model.contact_stiffness = std::numeric_limits<double>::quiet_NaN();
  b.Tick();
  EXPECT_TRUE(b.loop_.fault());
  EXPECT_EQ(b.loop_.arm_force().norm(), 0.0);
  b.Press(0.005);
  b.model_.model.normal[0] = std::numeric_limits<double>::infinity();
  b.Tick();
  EXPECT_TRUE(b.loop_.fault());
}

TEST(HapticLoop, AStaleModelRampsForceToZeroWithin60MillisecondsOfIt) {
  Bench b;
  b.EngageAndPress(0.005);
  const int64_t received = b.model_.received_ns;
  double previous = b.loop_.arm_force().norm();
  for (int i = 0; i < 80; ++i) {
    b.Tick();
    const double f = b.loop_.arm_force().norm();
    const double age = 1e-9 * static_cast<double>(b.now_ - received);
    if (age > 0.010) {
      EXPECT_LE(f, previous + 1e-12);
    }
    if (age >= 0.060) {
      EXPECT_EQ(f, 0.0) << age;
    }
    previous = f;
  }
  EXPECT_FALSE(b.loop_.fault());
}

TEST(HapticLoop, TicksAllocateNothing) {
  Bench b;
  b.EngageAndPress(0.005);
  testing::AllocationCounter counter;
  for (int i = 0; i < 2000; ++i) {
    if (i % 3 == 0) b.Press(0.004 + 1e-6 * i);
    b.state_.buttons = (i / 500) % 2 == 1 ? SOMASIM_ARM_BUTTON_CLUTCH : 0u;
    b.Tick();
  }
  b.read_ = arm_shm::ReadResult::kTorn;
  b.Tick();
  EXPECT_EQ(counter.count(), 0);
}

TEST(MicrosecondHistogram, QuantilesCountsAndTheMaximum) {
  MicrosecondHistogram h(100);
  EXPECT_EQ(h.Quantile(0.5), 0.0);
  for (int i = 0; i < 1000; ++i) h.Add(int64_t{1000} * (i % 10));  // 0..9 µs
  h.Add(-5);                                                       // counts as 0
  h.Add(int64_t{1000} * 500);                                      // beyond the last bin
  EXPECT_EQ(h.count(), 1002u);
  EXPECT_EQ(h.Quantile(0.5), 5.0);  // the bin's upper edge
  EXPECT_EQ(h.Quantile(0.99), 10.0);
  EXPECT_EQ(h.Quantile(1.0), 500.0);
  EXPECT_EQ(h.max_us(), 500.0);
  EXPECT_EQ(h.CountAbove(9), 1u);
  EXPECT_EQ(h.CountAbove(8), 101u);
}

}  // namespace
}  // namespace somasim::haptic
