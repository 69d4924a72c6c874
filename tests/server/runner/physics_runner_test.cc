// The server's physics thread (server/runner/physics_runner.h) without DDS: commands through its
// ring reach the session in order, the force model of each commanded tool comes out of its slot
// with the command it used and what a grasp holds, positions, topologies after a cut and the
// session's events come out of their buffers, a full command ring refuses rather than blocks,
// pause and reset are honoured, a run stops at its duration — and a tick allocates nothing.
#include "server/runner/physics_runner.h"

#include <gtest/gtest.h>
#include <poll.h>
#include <unistd.h>

#include <thread>

#include "tests/support/allocation_counter.h"

namespace somasim::runner {
namespace {

using server::ServerDefaultScene;

struct Rig {
  Rig() : session(ServerDefaultScene("kidney424"), scene::SceneLines("kidney"), ".") {
    RunnerOptions o;
    o.realtime = false;
    runner = std::make_unique<PhysicsRunner>(session, o, nullptr);
  }
  // The top of the kidney (its highest surface node).
  Eigen::Vector3d Top() const {
    const server::SessionOrgan& o = session.organ(0);
    Eigen::Vector3d top(0.0, 0.0, -1e9);
    for (Eigen::Index j = 0; j < o.built.triangles.size(); ++j) {
      const Eigen::Vector3d p = o.state->positions.col(o.built.triangles.data()[j]);
      if (p.z() > top.z()) top = p;
    }
    return top;
  }
  bool Command(int32_t tool, const Eigen::Vector3d& tip, double jaw_opening, uint32_t buttons) {
    ToolCommandMsg m;
    m.tool = tool;
    m.input.pose.tip = tip;
    m.input.pose.jaw_opening = jaw_opening;
    m.input.buttons = buttons;
    m.input.sequence = ++seq;
    return runner->PushCommand(m);
  }
  server::Session session;
  std::unique_ptr<PhysicsRunner> runner;
  uint64_t seq = 0;
};

TEST(PhysicsRunner, CommandsInForceModelsAndPositionsOut) {
  Rig r;
  const Eigen::Vector3d top = r.Top();
  EXPECT_FALSE(r.runner->positions(0).Take());  // nothing new before a tick
  for (int i = 0; i < 40; ++i) {
    ASSERT_TRUE(r.Command(0, top + Eigen::Vector3d(0, 0, 0.005 - 0.0002 * i), 1.0, 0));
    r.runner->Tick();
  }
  ToolOutput out;
  uint64_t version = 0;
  ASSERT_TRUE(r.runner->tool_output(0).Read(&out, &version));
  EXPECT_EQ(version, 40u);  // one per tick of a commanded tool
  EXPECT_EQ(out.command_seq, r.seq);
  EXPECT_TRUE(out.model.in_contact);
  EXPECT_EQ(out.organ, 0);
  EXPECT_EQ(out.num_held, 0);
  ASSERT_TRUE(r.runner->tool_output(1).Read(&out, &version));
  EXPECT_EQ(version, 0u);  // the grasper was never commanded
  // The physics woke the force-model writer.
  pollfd p{r.runner->tool_wake_fd(), POLLIN, 0};
  EXPECT_EQ(poll(&p, 1, 0), 1);
  ASSERT_TRUE(r.runner->positions(0).Take());
  const PositionsSnapshot& snapshot = r.runner->positions(0).front();
  EXPECT_DOUBLE_EQ(snapshot.sim_time, r.session.time());
  const auto& x = r.session.organ(0).state->positions;
  EXPECT_TRUE(std::equal(snapshot.positions.begin(), snapshot.positions.end(), x.data()));
  EXPECT_EQ(r.runner->counters().ticks.load(), 40u);
  EXPECT_EQ(r.runner->counters().commands_applied.load(), 40u);
  // Contact began: the event came through the ring.
  SessionEventRecord e;
  bool began = false;
  while (r.runner->events().Pop(&e)) began |= e.kind == SessionEventRecord::Kind::kContactBegins;
  EXPECT_TRUE(began);
  EXPECT_GT(r.runner->tool_stats()[0].contact_time, 0.0);
}

TEST(PhysicsRunner, AGraspHandsOnTheNodesItHolds) {
  Rig r;
  const Eigen::Vector3d top = r.Top();
  const int32_t grasper = r.session.ToolIndex("grasper");
  for (int i = 0; i < 20; ++i) {
    r.Command(grasper, top + Eigen::Vector3d(0, 0, 0.001), i < 5 ? 1.0 : 0.0, 0);
    r.runner->Tick();
  }
  ToolOutput out;
  uint64_t version = 0;
  ASSERT_TRUE(r.runner->tool_output(grasper).Read(&out, &version));
  ASSERT_TRUE(out.model.grasping);
  ASSERT_GT(out.num_held, 0);
  const int32_t n = r.session.organ(0).built.model->num_nodes();
  for (int32_t i = 0; i < out.num_held; ++i) {
    EXPECT_GE(out.held[i], 0);
    EXPECT_LT(out.held[i], n);
  }
  std::array<int32_t, kMaxHeld> held{};
  EXPECT_EQ(r.session.HeldNodes(grasper, held), out.num_held);
}

TEST(PhysicsRunner, ACutHandsOnTheNewTopologyAndAResetTheOld) {
  Rig r;
  const Eigen::Vector3d top = r.Top();
  const int32_t scalpel = r.session.ToolIndex("scalpel");
  for (int i = 0; i <= 60; ++i) {
    const double u = i / 60.0;
    r.Command(scalpel, top + Eigen::Vector3d(-0.02 + 0.04 * u, 0.0, -0.006), 1.0, 4);
    r.runner->Tick();
  }
  r.Command(scalpel, top + Eigen::Vector3d(0.03, 0.0, 0.03), 1.0, 0);
  r.runner->Tick();
  ASSERT_GT(r.session.organ(0).topology_version, 1u) << "the stroke cut nothing";
  ASSERT_TRUE(r.runner->topology(0).Take());
  const TopologySnapshot& t = r.runner->topology(0).front();
  EXPECT_EQ(t.version, r.session.organ(0).topology_version);
  EXPECT_TRUE(
      std::equal(t.alive.begin(), t.alive.end(), r.session.organ(0).cutter->alive_flags().begin()));
  EXPECT_LT(std::count(t.alive.begin(), t.alive.end(), uint8_t{1}),
            static_cast<long>(t.alive.size()));
}

TEST(PhysicsRunner, AFullCommandRingRefusesInsteadOfBlocking) {
  Rig r;
  int accepted = 0;
  for (int i = 0; i < 1000; ++i) accepted += r.Command(0, r.Top(), 1.0, 0) ? 1 : 0;
  EXPECT_EQ(accepted, 256);
  r.runner->Tick();  // takes them all
  EXPECT_TRUE(r.Command(0, r.Top(), 1.0, 0));
}

TEST(PhysicsRunner, RunsToItsDurationHonouringPauseAndReset) {
  server::Session session(ServerDefaultScene("kidney424"), scene::SceneLines("kidney"), ".");
  RunnerOptions o;
  o.realtime = false;
  o.duration = 0.5;
  PhysicsRunner runner(session, o, nullptr);
  runner.SetPaused(true);
  std::thread physics([&] { runner.Run(); });
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  EXPECT_EQ(runner.counters().ticks.load(), 0u);  // paused
  runner.RequestReset();
  runner.SetPaused(false);
  physics.join();
  EXPECT_NEAR(session.time(), 0.5, 1e-9);
  EXPECT_EQ(runner.counters().ticks.load(), 50u);  // 10 ms ticks
  SessionEventRecord e;
  bool reset = false;
  while (runner.events().Pop(&e)) reset |= e.kind == SessionEventRecord::Kind::kReset;
  EXPECT_TRUE(reset);
  EXPECT_GT(runner.wall_time(), 0.0);
  EXPECT_EQ(runner.total().count(), 50u);
}

// The physics thread's tick — commands in, the step, every hand-off out — allocates nothing.
TEST(PhysicsRunner, ATickAllocatesNothing) {
  Rig r;
  const Eigen::Vector3d top = r.Top();
  for (int i = 0; i < 5; ++i) {
    r.Command(0, top + Eigen::Vector3d(0, 0, 0.002), 1.0, 0);
    r.runner->Tick();
  }
  const somasim::testing::AllocationCounter count;
  for (int i = 0; i < 50; ++i) {
    r.Command(0, top + Eigen::Vector3d(0, 0, 0.002 - 0.0001 * i), 1.0, 0);
    r.runner->Tick();
  }
  EXPECT_EQ(count.count(), 0);
}

}  // namespace
}  // namespace somasim::runner
