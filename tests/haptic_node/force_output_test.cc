// The haptic node's output stage (haptic_node/force_output.h), tick by tick: NaN/Inf and 1e9 N
// models, ten times the limit, a stale model, the emergency stop, a device found unusable,
// engagement on start and after a fault, the per-tick rate limit, and a stiff virtual wall hit
// at speed with 0-50 ms of model delay that stays passive (the hand never leaves faster than it
// came) because the passivity observer adds damping, while without it the delayed wall throws
// the hand back.
#include "haptic_node/force_output.h"

#include <gtest/gtest.h>

#include <cmath>
#include <deque>
#include <limits>
#include <stdexcept>

#include "tests/support/allocation_counter.h"

namespace somasim::haptic {
namespace {

using Eigen::Vector3d;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

ForceInput Desired(const Vector3d& f, double age = 0.0) {
  ForceInput in;
  in.desired = f;
  in.model_age = age;
  return in;
}

// Ticks with no force until the stage has engaged and its authority is full.
void Engage(ForceOutput* out, const ForceOutputSettings& s) {
  const int ticks = s.engage_ticks + static_cast<int>(std::ceil(s.engage_ramp / s.dt)) + 2;
  for (int i = 0; i < ticks; ++i) out->Tick(Desired(Vector3d::Zero()));
  ASSERT_TRUE(out->engaged());
  ASSERT_EQ(out->authority(), 1.0);
}

// Ticks toward a constant desired force until the output has reached it (or the limit).
Vector3d Settle(ForceOutput* out, const Vector3d& f, int ticks = 200) {
  Vector3d last = Vector3d::Zero();
  for (int i = 0; i < ticks; ++i) last = out->Tick(Desired(f));
  return last;
}

TEST(ForceOutput, NonFiniteModelsGiveZeroAndLatchAFaultUntilCleared) {
  const ForceOutputSettings s;
  for (const double bad : {kNaN, kInf, -kInf}) {
    ForceOutput out(s);
    Engage(&out, s);
    EXPECT_GT(Settle(&out, Vector3d(0, 0, 2)).z(), 1.99);
    EXPECT_EQ(out.Tick(Desired(Vector3d(0, bad, 2))), Vector3d::Zero());  // at once, not ramped
    EXPECT_TRUE(out.fault());
    EXPECT_STREQ(out.fault_reason(), "a non-finite desired force");
    // Good models again: still zero while the fault is latched.
    EXPECT_EQ(Settle(&out, Vector3d(0, 0, 2)), Vector3d::Zero());
    out.ClearFault();
    // Cleared with a large force still asked for: nothing until it has been small for a while.
    EXPECT_EQ(Settle(&out, Vector3d(0, 0, 2), 50), Vector3d::Zero());
    for (int i = 0; i < s.engage_ticks; ++i) out.Tick(Desired(Vector3d::Zero()));
    EXPECT_TRUE(out.engaged());
    EXPECT_EQ(out.counters().faults, 1u);
  }
  ForceOutput out(s);
  Engage(&out, s);
  ForceInput nan_velocity = Desired(Vector3d(0, 0, 1));
  nan_velocity.velocity.x() = kNaN;
  EXPECT_EQ(out.Tick(nan_velocity), Vector3d::Zero());
  EXPECT_STREQ(out.fault_reason(), "a non-finite device velocity");
  ForceOutput age(s);
  Engage(&age, s);
  EXPECT_EQ(age.Tick(Desired(Vector3d(0, 0, 1), kNaN)), Vector3d::Zero());
  EXPECT_TRUE(age.fault());
}

TEST(ForceOutput, HugeModelsAreClampedToTheArmsLimitAndRiseAtTheRateLimit) {
  const ForceOutputSettings s;
  for (const double magnitude : {10.0 * s.max_force, 1e9}) {
    ForceOutput out(s);
    Engage(&out, s);
    const Vector3d dir = Vector3d(1, 2, -2).normalized();
    Vector3d last = Vector3d::Zero();
    for (int i = 0; i < 100; ++i) {
      const Vector3d f = out.Tick(Desired(magnitude * dir));
      EXPECT_LE(f.norm(), s.max_force + 1e-12);
      EXPECT_LE((f - last).norm(), s.max_step + 1e-12) << "tick " << i;
      last = f;
    }
    EXPECT_NEAR(last.norm(), s.max_force, 1e-9);
    EXPECT_NEAR(last.normalized().dot(dir), 1.0, 1e-12);  // the direction kept
    EXPECT_GT(out.counters().clamped_ticks, 0u);
    EXPECT_FALSE(out.fault());
  }
}

// The model stops coming (the server died): from 10 ms of age the force never rises and it is
// zero by 60 ms, even while the hand pushes deeper into the old model.
TEST(ForceOutput, AStaleModelRampsToZeroWithin60Milliseconds) {
  const ForceOutputSettings s;
  ForceOutput out(s);
  Engage(&out, s);
  Settle(&out, Vector3d(0, 0, 4));
  double previous = 4.0;
  for (int ms = 1; ms <= 80; ++ms) {
    const double age = 1e-3 * ms;
    const double deeper = 4.0 + 0.05 * ms;  // the hand pushes on: the old model says more
    const double f = out.Tick(Desired(Vector3d(0, 0, deeper), age)).norm();
    if (age > s.fresh) {
      EXPECT_LE(f, previous + 1e-12) << ms << " ms";
    }
    if (age >= 0.060 - 1e-12) {
      EXPECT_EQ(f, 0.0) << ms << " ms";
    }
    previous = f;
  }
  EXPECT_GT(out.counters().stale_ticks, 0u);
  EXPECT_FALSE(out.fault());  // staleness is not a fault: fresh models bring the force back,
  // gradually (a paused server that continues never jolts the hand): over engage_ramp, not at
  // the rate limit, even while the model asks for the arm's limit at once.
  const double first = out.Tick(Desired(Vector3d(0, 0, 8))).norm();
  EXPECT_LE(first, 8.0 * s.dt / s.engage_ramp + 1e-12);
  double last = first;
  for (int i = 1; i < 100; ++i) {
    const double f = out.Tick(Desired(Vector3d(0, 0, 8))).norm();
    EXPECT_LE(f - last, 8.0 * s.dt / s.engage_ramp + 1e-12) << i;
    last = f;
  }
  EXPECT_GT(Settle(&out, Vector3d(0, 0, 1), 600).z(), 0.99);
}

TEST(ForceOutput, TheEmergencyStopZeroesAtOnceAndReengagesGradually) {
  const ForceOutputSettings s;
  ForceOutput out(s);
  Engage(&out, s);
  Settle(&out, Vector3d(3, 0, 0));
  ForceInput stop = Desired(Vector3d(3, 0, 0));
  stop.emergency_stop = true;
  EXPECT_EQ(out.Tick(stop), Vector3d::Zero());  // the same tick, no ramp
  EXPECT_FALSE(out.engaged());
  EXPECT_FALSE(out.fault());
  // Released with the force still asked for: nothing until it has been small, then a ramp.
  EXPECT_EQ(Settle(&out, Vector3d(3, 0, 0), 100), Vector3d::Zero());
  for (int i = 0; i < s.engage_ticks; ++i) out.Tick(Desired(Vector3d::Zero()));
  ASSERT_TRUE(out.engaged());
  Vector3d last = Vector3d::Zero();
  for (int i = 0; i < 100; ++i) {
    const Vector3d f = out.Tick(Desired(Vector3d(3, 0, 0)));
    EXPECT_LE(f.x(), 3.0 * out.authority() + 1e-12);  // within the authority's ramp
    EXPECT_LE((f - last).norm(), s.max_step + 1e-12);
    last = f;
  }
  EXPECT_LT(last.x(), 3.0);  // 0.1 s into a 0.5 s ramp
}

TEST(ForceOutput, AnUnusableDeviceStopsCommandingAndLatches) {
  const ForceOutputSettings s;
  ForceOutput out(s);
  Engage(&out, s);
  Settle(&out, Vector3d(0, 1, 0));
  ForceInput in = Desired(Vector3d(0, 1, 0));
  in.device_ok = false;
  EXPECT_EQ(out.Tick(in), Vector3d::Zero());
  EXPECT_TRUE(out.fault());
  in.device_ok = true;
  EXPECT_EQ(out.Tick(in), Vector3d::Zero());  // latched
}

TEST(ForceOutput, StartsDisengagedWhileALargeForceIsAskedFor) {
  const ForceOutputSettings s;
  ForceOutput out(s);
  for (int i = 0; i < 500; ++i) {
    EXPECT_EQ(out.Tick(Desired(Vector3d(0, 0, 5))), Vector3d::Zero()) << i;
  }
  EXPECT_FALSE(out.engaged());
  ForceOutput none(s);  // no model at all: zero, not engaged by a force
  EXPECT_EQ(none.Tick(ForceInput{}), Vector3d::Zero());
}

TEST(ForceOutput, RefusesBadSettingsByName) {
  ForceOutputSettings s;
  s.max_force = kNaN;
  EXPECT_THROW(ForceOutput{s}, std::invalid_argument);
  s = {};
  s.max_step = 0.0;
  try {
    ForceOutput out(s);
    ADD_FAILURE();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("max_step"), std::string::npos);
  }
  s = {};
  s.engage_ticks = 0;
  EXPECT_THROW(ForceOutput{s}, std::invalid_argument);
}

// A 0.5 kg hand-and-arm moving at 0.2 m/s into a 1500 N/m wall whose force comes `delay` late
// (the model's age): returns the largest speed it leaves with, and the observer's lowest
// energy while the controller was not damping.
struct WallResult {
  double exit_speed = 0.0;
  // Σ |F|² dt² / 2m: the energy a force held over each tick gives a mass beyond F·v dt (the
  // observer sees the velocity at the tick's start; the sampled plant is this much active).
  double hold_energy = 0.0;
  double lowest_undamped_energy = 0.0;
  uint64_t damped_ticks = 0;
};

WallResult HitWall(double delay, bool passivity) {
  ForceOutputSettings s;
  if (!passivity) s.max_damping = 1e-12;  // the controller can add nothing
  ForceOutput out(s);
  const double m = 0.5, k = 1500.0, dt = s.dt;
  double x = -0.12, v = 0.2;  // [m], [m/s]: reaches the wall at 0.6 s, after engagement
  const int lag = static_cast<int>(std::lround(delay / dt));
  std::deque<double> history(static_cast<size_t>(lag) + 1, x);
  WallResult r;
  for (int i = 0; i < 3000; ++i) {
    history.push_back(x);
    history.pop_front();
    const double seen = history.front();  // the position the model was made from
    ForceInput in;
    in.desired = Vector3d(-k * std::max(seen, 0.0), 0, 0);
    in.model_age = 0.0;  // received just now: the delay is in what the model says
    in.velocity = Vector3d(v, 0, 0);
    const double f = out.Tick(in).x();
    if (out.last_damping() == 0.0) {
      r.lowest_undamped_energy = std::min(r.lowest_undamped_energy, out.observed_energy());
    }
    r.hold_energy += f * f * dt * dt / (2.0 * m);
    v += f / m * dt;  // semi-implicit Euler
    x += v * dt;
    if (x < -0.01 && v < 0.0) r.exit_speed = std::max(r.exit_speed, -v);
  }
  r.damped_ticks = out.counters().damped_ticks;
  return r;
}

TEST(ForceOutput, AStiffWallHitAtSpeedStaysPassiveWithUpTo50MillisecondsOfDelay) {
  const ForceOutputSettings s;
  for (const double delay : {0.0, 0.005, 0.010, 0.025, 0.050}) {
    const WallResult with = HitWall(delay, true);
    // Passive up to the energy the observer lends and the sampled plant's hold energy:
    // ½ m v_out² <= ½ m v_in² + epsilon + Σ |F|² dt² / 2m.
    const double bound =
        std::sqrt(0.2 * 0.2 + 2.0 * (s.passivity_epsilon + with.hold_energy) / 0.5);
    EXPECT_LE(with.exit_speed, bound + 1e-9) << "delay " << delay << ": the wall threw the hand";
    EXPECT_GE(with.lowest_undamped_energy, -s.passivity_epsilon - 1e-9) << "delay " << delay;
    std::printf("delay %2.0f ms: exit speed %.3f m/s (in 0.200, bound %.3f), damped ticks %llu\n",
                1e3 * delay, with.exit_speed, bound,
                static_cast<unsigned long long>(with.damped_ticks));
  }
  // Without the controller the late wall is active: the hand leaves faster than it came.
  for (const double delay : {0.010, 0.025, 0.050}) {
    const double without = HitWall(delay, false).exit_speed;
    std::printf("delay %2.0f ms without the passivity controller: exit speed %.3f m/s\n",
                1e3 * delay, without);
    EXPECT_GT(without, 0.2 * 1.1) << "delay " << delay;
  }
}

// A model that adds energy: it pushes a slowly moving hand the way the hand moves, harder than
// the controller's largest damping (max_damping · 3 mm/s = 0.18 N) can take back, so the
// observer goes into deficit by millijoules.
void BuildEnergyDeficit(ForceOutput* out) {
  for (int i = 0; i < 300; ++i) {
    ForceInput in = Desired(Vector3d(4, 0, 0));
    in.velocity = Vector3d(0.003, 0, 0);
    out->Tick(in);
  }
  ASSERT_LT(out->observed_energy(), -0.001);
}

// SPEC §7: zero within 60 ms of the last good model and never rising while stale — the
// passivity controller included. A deficit left by an active model must not keep rendering
// damping once the model has gone stale.
TEST(ForceOutput, AnEnergyDeficitRendersNothingOnceTheModelIsStale) {
  const ForceOutputSettings s;
  ForceOutput out(s);
  Engage(&out, s);
  BuildEnergyDeficit(&out);
  double previous = out.Tick(Desired(Vector3d(4, 0, 0))).norm();
  for (int ms = 1; ms <= 3500; ++ms) {
    const double age = 1e-3 * ms;
    ForceInput in = Desired(Vector3d(4, 0, 0), age);
    // The hand drifts slowly, then moves at 0.1 m/s three seconds on.
    in.velocity = Vector3d(ms < 3000 ? 0.003 : 0.1, 0, 0);
    const double f = out.Tick(in).norm();
    if (age > s.fresh) {
      EXPECT_LE(f, previous + 1e-12) << ms << " ms: rising while stale";
    }
    if (age >= 0.060 - 1e-12) {
      ASSERT_EQ(f, 0.0) << ms << " ms after the last model";
    }
    previous = f;
  }
  EXPECT_EQ(out.observed_energy(), 0.0);  // nothing rendered: the balance starts again
  // Fresh models again: force comes back from a clean balance, without the old deficit's
  // damping against the hand.
  for (int i = 0; i < 600; ++i) {
    ForceInput in = Desired(Vector3d::Zero());
    in.velocity = Vector3d(0.1, 0, 0);
    EXPECT_EQ(out.Tick(in), Vector3d::Zero()) << i;
  }
}

// A fault latched while in deficit, cleared by the operator (the clutch pressed and released):
// the re-engaged stage starts from a clean energy balance, and renders nothing while it is
// disengaged.
TEST(ForceOutput, AFaultClearedByTheClutchReengagesWithACleanEnergyBalance) {
  const ForceOutputSettings s;
  ForceOutput out(s);
  Engage(&out, s);
  BuildEnergyDeficit(&out);
  ForceInput bad = Desired(Vector3d(4, 0, 0));
  bad.device_ok = false;
  EXPECT_EQ(out.Tick(bad), Vector3d::Zero());
  EXPECT_TRUE(out.fault());
  out.ClearFault();
  EXPECT_EQ(out.observed_energy(), 0.0);
  // Disengaged until the desired force has been small for engage_ticks: nothing rendered,
  // however the hand moves.
  for (int i = 0; i < 5; ++i) {
    ForceInput in = Desired(Vector3d(4, 0, 0));
    in.velocity = Vector3d(0.1, 0, 0);
    EXPECT_EQ(out.Tick(in), Vector3d::Zero()) << i;
    EXPECT_FALSE(out.engaged());
  }
  // Re-engaged with no force asked for and the hand moving: no damping from the old deficit.
  for (int i = 0; i < 1000; ++i) {
    ForceInput in = Desired(Vector3d::Zero());
    in.velocity = Vector3d(0.1, 0, 0);
    EXPECT_EQ(out.Tick(in), Vector3d::Zero()) << i;
  }
  EXPECT_TRUE(out.engaged());
  EXPECT_EQ(out.observed_energy(), 0.0);
  EXPECT_EQ(out.last_damping(), 0.0);
}

TEST(ForceOutput, TicksAllocateNothing) {
  const ForceOutputSettings s;
  ForceOutput out(s);
  Engage(&out, s);
  const somasim::testing::AllocationCounter count;
  for (int i = 0; i < 1000; ++i) out.Tick(Desired(Vector3d(0, 0, 0.001 * i), 0.0001 * i));
  EXPECT_EQ(count.count(), 0);
}

}  // namespace
}  // namespace somasim::haptic
