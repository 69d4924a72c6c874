// The session's physics (server/session/session.h) on small built-in organs.
#include "server/session/session.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "common/mesh/geometry.h"
#include "tests/support/allocation_counter.h"

namespace somasim::server {
namespace {

scene::Scene KidneyScene() { return ServerDefaultScene("kidney424"); }

// The surface node with the largest z: a place to press from above.
Eigen::Vector3d TopOf(const Session& session, int32_t organ) {
  const SessionOrgan& o = session.organ(organ);
  Eigen::Vector3d top(0.0, 0.0, -1e9);
  for (Eigen::Index j = 0; j < o.built.triangles.size(); ++j) {
    const Eigen::Vector3d p = o.state->positions.col(o.built.triangles.data()[j]);
    if (p.z() > top.z()) top = p;
  }
  return top;
}

ToolCommandInput At(const Eigen::Vector3d& tip, double jaw_opening, uint64_t sequence) {
  ToolCommandInput c;
  c.pose.tip = tip;
  c.pose.jaw_opening = jaw_opening;
  c.sequence = sequence;
  return c;
}

TEST(Session, DefaultSceneHasFourToolsAndTicksAtTheFemStep) {
  const Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  EXPECT_EQ(session.num_organs(), 1);
  EXPECT_EQ(session.num_tools(), 4);
  EXPECT_EQ(session.ToolIndex("probe"), 0);
  EXPECT_EQ(session.ToolIndex("grasper"), 1);
  EXPECT_EQ(session.ToolIndex("scalpel"), 2);
  EXPECT_EQ(session.ToolIndex("laparoscope"), 3);
  EXPECT_EQ(session.tool(3).shape.kind, contact::ToolKind::kCamera);
  EXPECT_EQ(session.ToolIndex("nope"), -1);
  EXPECT_EQ(session.OrganIndex("kidney424"), 0);
  EXPECT_DOUBLE_EQ(session.dt(), 0.01);
  EXPECT_EQ(session.tool(1).shape.kind, contact::ToolKind::kGrasper);
}

TEST(Session, PressingTheProbeGivesContactEventsAndAPushingForceModel) {
  Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  const Eigen::Vector3d top = TopOf(session, 0);
  bool began = false;
  for (int i = 0; i <= 40; ++i) {
    // From 1 cm above to 3 mm below the top over 0.4 s.
    const double depth = -0.01 + 0.013 * i / 40.0;
    session.SetToolCommand(0, At(top - depth * Eigen::Vector3d::UnitZ(), 1.0, 1 + i));
    session.Step();
    for (const SessionEventRecord& e : session.TakeEvents()) {
      if (e.kind == SessionEventRecord::Kind::kContactBegins) {
        began = true;
        EXPECT_EQ(e.tool, 0);
        EXPECT_EQ(e.organ, 0);
      }
    }
  }
  EXPECT_TRUE(began);
  const force_model::LocalForceModel& m = session.tool(0).force_model;
  EXPECT_TRUE(m.in_contact);
  EXPECT_EQ(session.tool(0).force_organ, 0);
  EXPECT_EQ(m.sequence, 41u);
  EXPECT_GT(m.contact_stiffness, 0.0);
  const force_model::ForceSample f = force_model::EvaluateLocalForceModel(
      m, session.tool(0).command.pose.tip, Eigen::Vector3d::Zero());
  EXPECT_GT(f.force.z(), 0.1);  // the tissue pushes the probe up [N]
  EXPECT_EQ(session.organ_steps(), 41u);
  EXPECT_EQ(session.rejected_steps(), 0u);
  // Lifting the probe ends the contact.
  session.SetToolCommand(0, At(top + 0.02 * Eigen::Vector3d::UnitZ(), 1.0, 100));
  bool ended = false;
  for (int i = 0; i < 5; ++i) {
    session.Step();
    for (const SessionEventRecord& e : session.TakeEvents()) {
      ended |= e.kind == SessionEventRecord::Kind::kContactEnds;
    }
  }
  EXPECT_TRUE(ended);
  EXPECT_FALSE(session.tool(0).force_model.in_contact);
}

TEST(Session, GraspingAndPullingLiftsTheTissueAndReleaseLetsGo) {
  Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  const Eigen::Vector3d top = TopOf(session, 0);
  const int32_t g = session.ToolIndex("grasper");
  uint64_t seq = 0;
  // Reach 1 mm into the surface with open jaws, close, pull up 5 mm.
  for (int i = 0; i < 10; ++i) {
    session.SetToolCommand(g, At(top - 0.001 * Eigen::Vector3d::UnitZ(), 1.0, ++seq));
    session.Step();
  }
  for (int i = 0; i < 10; ++i) {
    session.SetToolCommand(g, At(top - 0.001 * Eigen::Vector3d::UnitZ(), 0.0, ++seq));
    session.Step();
  }
  bool grasped = false;
  for (const SessionEventRecord& e : session.TakeEvents()) {
    if (e.kind == SessionEventRecord::Kind::kGrasp) {
      grasped = true;
      EXPECT_GT(e.detail, 0);  // nodes held
    }
  }
  ASSERT_TRUE(grasped);
  for (int i = 0; i < 50; ++i) {
    session.SetToolCommand(
        g, At(top + (0.005 * i / 50.0 - 0.001) * Eigen::Vector3d::UnitZ(), 0.0, ++seq));
    session.Step();
  }
  const force_model::LocalForceModel& m = session.tool(g).force_model;
  EXPECT_TRUE(m.grasping);
  const force_model::ForceSample f = force_model::EvaluateLocalForceModel(
      m, session.tool(g).command.pose.tip, Eigen::Vector3d::Zero());
  EXPECT_LT(f.force.z(), -0.05);                      // the tissue pulls the jaws down [N]
  EXPECT_GT(TopOf(session, 0).z(), top.z() + 0.001);  // and is lifted
  session.SetToolCommand(g, At(top + 0.004 * Eigen::Vector3d::UnitZ(), 1.0, ++seq));
  session.Step();
  bool released = false;
  for (const SessionEventRecord& e : session.TakeEvents()) {
    released |= e.kind == SessionEventRecord::Kind::kRelease;
  }
  EXPECT_TRUE(released);
  EXPECT_FALSE(session.tool(g).force_model.grasping);
}

// Seed 001's liver on the EFG model (tests/data/scenes/liver288_efg.scene.txtpb) runs like a FEM
// organ: the probe pressing its top and sliding on it meets it, moves it, and gets a pushing
// force model from the model's LocalStiffness (no FemCompliance: that is the FEM's; no cutter:
// the EFG cuts through its own hook, SessionCut below). The contact's springs change every tick,
// which the model takes by a low-rank update: it factorises only on the first step (the step system
// and the static one).
TEST(Session, AnEfgOrganIsPressedByTheProbeAndGivesAForceModel) {
  scene::SceneLines lines;
  const scene::Scene s = scene::LoadSceneFile(
      std::string(SOMASIM_TEST_DATA_DIR) + "/scenes/liver288_efg.scene.txtpb", &lines);
  Session session(s, lines, ".");
  ASSERT_EQ(session.num_organs(), 1);
  const SessionOrgan& o = session.organ(0);
  EXPECT_EQ(o.built.model_name, "efg");
  ASSERT_NE(o.built.efg, nullptr);
  EXPECT_EQ(o.compliance, nullptr);
  EXPECT_EQ(o.cutter, nullptr);
  EXPECT_DOUBLE_EQ(session.dt(), 0.001);
  const Eigen::Vector3d top = TopOf(session, 0);
  const mesh::Points rest = o.state->positions;
  double slowest = 0.0;            // [s] the slowest step, reported
  int slow = 0;                    // steps over 5 ms (the model factorised again), reported
  std::vector<double> in_contact;  // [s] the other steps in contact, reported
  for (int i = 0; i <= 300; ++i) {
    // From 2 mm above to 4 mm below the top over 0.2 s, then 3 mm sideways over 0.1 s.
    const double depth = -0.002 + 0.006 * std::min(i, 200) / 200.0;
    const double slide = 0.003 * std::max(i - 200, 0) / 100.0;
    session.SetToolCommand(
        0,
        At(top - depth * Eigen::Vector3d::UnitZ() + slide * Eigen::Vector3d::UnitX(), 1.0, 1 + i));
    const auto start = std::chrono::steady_clock::now();
    session.Step();
    const double took =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    slowest = std::max(slowest, took);
    slow += took > 0.005 ? 1 : 0;
    if (took <= 0.005 && session.tool(0).force_model.in_contact) {
      in_contact.push_back(took);
    }
  }
  std::sort(in_contact.begin(), in_contact.end());
  std::printf(
      "EFG liver288 pressed 4 mm and slid 3 mm in 301 steps: slowest %.1f ms, %d over 5 ms; "
      "median step in contact %.0f us, slowest %.0f us; %lld factorisations\n",
      1e3 * slowest, slow, in_contact.empty() ? 0.0 : 1e6 * in_contact[in_contact.size() / 2],
      in_contact.empty() ? 0.0 : 1e6 * in_contact.back(),
      static_cast<long long>(o.built.efg->Factorisations(*o.state)));
  EXPECT_EQ(session.rejected_steps(), 0u);
  const force_model::LocalForceModel& m = session.tool(0).force_model;
  EXPECT_TRUE(m.in_contact);
  EXPECT_EQ(session.tool(0).force_organ, 0);
  const force_model::ForceSample f = force_model::EvaluateLocalForceModel(
      m, session.tool(0).command.pose.tip, Eigen::Vector3d::Zero());
  EXPECT_GT(f.force.z(), 0.1);  // the tissue pushes the probe up [N]
  EXPECT_GT((o.state->positions - rest).colwise().norm().maxCoeff(), 1e-3);  // pressed in [m]
  // The contact's corner springs (barycentric shares of K_t, changing every tick) cost no
  // factorisation: A0 and the static K_s once, on the first step.
  ASSERT_GT(o.num_attachments, 0);
  EXPECT_LE(o.built.efg->Factorisations(*o.state), 2);
}

// Seed 001's hybrid liver (tests/data/scenes/liver288_efg_hybrid.scene.txtpb) runs as the EFG
// organ does: the probe pressing its top and sliding on it meets it, moves it, and gets a pushing
// force model from the hybrid's LocalStiffness (no FemCompliance, no cutter). The surgical region
// follows the tool: the touched node ends up in it.
TEST(Session, AnEfgHybridOrganIsPressedByTheProbeAndGivesAForceModel) {
  scene::SceneLines lines;
  const scene::Scene s = scene::LoadSceneFile(
      std::string(SOMASIM_TEST_DATA_DIR) + "/scenes/liver288_efg_hybrid.scene.txtpb", &lines);
  Session session(s, lines, ".");
  ASSERT_EQ(session.num_organs(), 1);
  const SessionOrgan& o = session.organ(0);
  EXPECT_EQ(o.built.model_name, "efg_hybrid");
  ASSERT_NE(o.built.efg_hybrid, nullptr);
  EXPECT_EQ(o.built.efg, nullptr);
  EXPECT_EQ(o.built.fem, nullptr);
  EXPECT_EQ(o.compliance, nullptr);
  EXPECT_EQ(o.cutter, nullptr);
  EXPECT_DOUBLE_EQ(session.dt(), 0.001);
  const Eigen::Vector3d top = TopOf(session, 0);
  int32_t top_node = 0;  // the surface node at `top`
  for (Eigen::Index j = 0; j < o.built.triangles.size(); ++j) {
    const int32_t i = o.built.triangles.data()[j];
    if (o.state->positions.col(i) == top) top_node = i;
  }
  const mesh::Points rest = o.state->positions;
  double slowest = 0.0;            // [s] the slowest step, reported
  int slow = 0;                    // steps over 5 ms (a partition or factorisation), reported
  std::vector<double> in_contact;  // [s] the other steps in contact, reported
  for (int i = 0; i <= 300; ++i) {
    // From 2 mm above to 4 mm below the top over 0.2 s, then 3 mm sideways over 0.1 s.
    const double depth = -0.002 + 0.006 * std::min(i, 200) / 200.0;
    const double slide = 0.003 * std::max(i - 200, 0) / 100.0;
    session.SetToolCommand(
        0,
        At(top - depth * Eigen::Vector3d::UnitZ() + slide * Eigen::Vector3d::UnitX(), 1.0, 1 + i));
    const auto start = std::chrono::steady_clock::now();
    session.Step();
    const double took =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    slowest = std::max(slowest, took);
    slow += took > 0.005 ? 1 : 0;
    if (took <= 0.005 && session.tool(0).force_model.in_contact) {
      in_contact.push_back(took);
    }
  }
  std::sort(in_contact.begin(), in_contact.end());
  const models::meshless::EfgHybridModel& hybrid = *o.built.efg_hybrid;
  std::printf(
      "EFG hybrid liver288 pressed 4 mm and slid 3 mm in 301 steps: slowest %.1f ms, %d over "
      "5 ms; median step in contact %.0f us, slowest %.0f us; region of %d nodes, %lld "
      "partitions, %lld factorisations, %lld far solves\n",
      1e3 * slowest, slow, in_contact.empty() ? 0.0 : 1e6 * in_contact[in_contact.size() / 2],
      in_contact.empty() ? 0.0 : 1e6 * in_contact.back(), hybrid.RegionNodes(*o.state),
      static_cast<long long>(hybrid.Partitions(*o.state)),
      static_cast<long long>(hybrid.Factorisations(*o.state)),
      static_cast<long long>(hybrid.FarSolves(*o.state)));
  EXPECT_EQ(session.rejected_steps(), 0u);
  const force_model::LocalForceModel& m = session.tool(0).force_model;
  EXPECT_TRUE(m.in_contact);
  EXPECT_EQ(session.tool(0).force_organ, 0);
  const force_model::ForceSample f = force_model::EvaluateLocalForceModel(
      m, session.tool(0).command.pose.tip, Eigen::Vector3d::Zero());
  EXPECT_GT(f.force.z(), 0.1);  // the tissue pushes the probe up [N]
  EXPECT_GT((o.state->positions - rest).colwise().norm().maxCoeff(), 1e-3);  // pressed in [m]
  ASSERT_GT(o.num_attachments, 0);
  EXPECT_GE(hybrid.Partitions(*o.state), 1);
  EXPECT_GT(hybrid.RegionNodes(*o.state), 0);
  EXPECT_LE(hybrid.RegionNodes(*o.state), 400);  // max_region_nodes' default
  EXPECT_TRUE(hybrid.InRegion(*o.state, top_node)) << top_node;
}

TEST(Session, StepAllocatesNothing) {
  Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  const Eigen::Vector3d top = TopOf(session, 0);
  for (int i = 0; i < 3; ++i) session.Step();  // warm up
  testing::AllocationCounter counter;
  for (int i = 0; i < 20; ++i) {
    session.SetToolCommand(0, At(top - 0.0002 * i * Eigen::Vector3d::UnitZ(), 1.0, 1 + i));
    session.Step();
    (void)session.TakeEvents();
  }
  EXPECT_EQ(counter.count(), 0);
}

TEST(Session, OrgansWithDifferentStepsAdvanceAtTheirOwnRate) {
  scene::Scene s = ServerDefaultScene("kidney424");
  scene::Organ* patch = s.add_organ();
  *patch = scene::DefaultScene("tissue45").organ(0);
  patch->set_id("patch");
  patch->mutable_model()->set_dt(0.001);
  // Move the patch away from the kidney.
  Session session(s, scene::SceneLines("two"), ".");
  EXPECT_DOUBLE_EQ(session.dt(), 0.001);
  for (int i = 0; i < 100; ++i) session.Step();
  EXPECT_NEAR(session.time(), 0.1, 1e-12);
  EXPECT_NEAR(session.organ(0).time, 0.1, 1e-9);  // 10 steps of 10 ms
  EXPECT_NEAR(session.organ(1).time, 0.1, 1e-9);  // 100 steps of 1 ms
  EXPECT_EQ(session.organ_steps(), 110u);
}

TEST(Session, ARigidStoneRestsOnAKidneyInASceneWithTwoOrgans) {
  scene::Scene s = ServerDefaultScene("kidney424");
  scene::Organ* patch = s.add_organ();
  *patch = scene::DefaultScene("tissue45").organ(0);
  patch->set_id("patch");
  scene::RigidBody* stone = s.add_rigid_body();
  stone->set_id("stone");
  // On top of the kidney, touching it.
  const Session probe_session(ServerDefaultScene("kidney424"), scene::SceneLines("k"), ".");
  const Eigen::Vector3d centre = TopOf(probe_session, 0) + 0.004 * Eigen::Vector3d::UnitZ();
  stone->mutable_sphere()->mutable_center()->set_x(centre.x());
  stone->mutable_sphere()->mutable_center()->set_y(centre.y());
  stone->mutable_sphere()->mutable_center()->set_z(centre.z());
  stone->mutable_sphere()->set_radius(0.004);
  Session session(s, scene::SceneLines("stone"), ".");
  ASSERT_EQ(session.num_rigid(), 1);
  EXPECT_EQ(session.rigid(0).organ, 0);
  for (int i = 0; i < 100; ++i) session.Step();
  EXPECT_EQ(session.rejected_steps(), 0u);
  const Eigen::Vector3d p = session.rigid(0).sphere->position();
  EXPECT_TRUE(p.allFinite());
  // Held by the kidney's surface: it sinks a little under its weight, never falls through.
  EXPECT_LT((p - centre).norm(), 0.003);
}

TEST(Session, ResetReturnsToRestAndTimeZero) {
  Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  const mesh::Points rest = session.organ(0).state->positions;
  for (int i = 0; i < 20; ++i) session.Step();
  EXPECT_GT((session.organ(0).state->positions - rest).norm(), 0.0);
  (void)session.TakeEvents();
  session.Reset();
  const auto events = session.TakeEvents();
  ASSERT_EQ(events.size(), 1u);
  EXPECT_EQ(events[0].kind, SessionEventRecord::Kind::kReset);
  EXPECT_EQ(session.time(), 0.0);
  EXPECT_EQ((session.organ(0).state->positions - rest).norm(), 0.0);
}

}  // namespace
}  // namespace somasim::server

namespace somasim::server {
namespace {

TEST(Session, ARejectedStepLeavesTheOrganAtRestAndIsReported) {
  // An explicit mass-spring patch at 50 ms: far beyond its stable step, so it diverges.
  scene::Scene s = scene::DefaultScene("tissue45");
  s.clear_analysis();
  s.mutable_organ(0)->mutable_model()->mutable_mass_spring()->set_implicit(false);
  s.mutable_organ(0)->mutable_model()->set_dt(0.05);
  s.mutable_organ(0)->mutable_material()->set_youngs_modulus(5e6);
  Session session(s, scene::SceneLines("unstable"), ".");
  int rejected = 0;
  for (int i = 0; i < 40; ++i) {
    session.Step();
    for (const SessionEventRecord& e : session.TakeEvents()) {
      if (e.kind != SessionEventRecord::Kind::kStepRejected) continue;
      ++rejected;
      EXPECT_EQ(e.organ, 0);
      EXPECT_EQ(session.organ(0).state->velocities.norm(), 0.0);
    }
    ASSERT_TRUE(session.organ(0).state->positions.allFinite());
  }
  EXPECT_GT(rejected, 0);
  EXPECT_EQ(session.rejected_steps(), static_cast<uint64_t>(rejected));
}

// Seed 002's closed surfaces run in the server as it runs them: an implicit mass-spring shell with
// every node anchored to its rest position, so the shell keeps its shape under gravity, gives way
// under the probe with a force of the order of a palpation, and comes back when let go.
TEST(Session, ClosedSurfaceBuiltinIsAnAnchoredShellThatHoldsItsShapeAndRecovers) {
  const scene::Scene s = ServerDefaultScene("spleen600");
  ASSERT_EQ(s.organ_size(), 1);
  const scene::Model& model = s.organ(0).model();
  ASSERT_TRUE(model.has_mass_spring());
  EXPECT_TRUE(model.mass_spring().implicit());
  EXPECT_GT(model.mass_spring().anchor_stiffness(), 1.0);     // [N/m]
  EXPECT_LT(model.mass_spring().anchor_stiffness(), 1000.0);  // soft tissue, not steel
  Session session(s, scene::SceneLines("spleen"), ".");
  EXPECT_DOUBLE_EQ(session.dt(), 0.005);
  const mesh::Points rest = session.organ(0).state->positions;
  const auto max_offset = [&] {
    return (session.organ(0).state->positions - rest).colwise().norm().maxCoeff();  // [m]
  };
  for (int i = 0; i < 200; ++i) session.Step();  // 1 s under gravity
  EXPECT_GT(max_offset(), 0.0);
  const double sag = max_offset();
  EXPECT_LT(sag, 0.002) << "the anchored shell sags by millimetres at most";

  // Press 4 mm into the top over 0.2 s and hold for 0.1 s.
  const Eigen::Vector3d top = TopOf(session, 0);
  uint64_t seq = 0;
  for (int i = 0; i <= 60; ++i) {
    const double depth = -0.004 + 0.008 * std::min(i, 40) / 40.0;
    session.SetToolCommand(0, At(top - depth * Eigen::Vector3d::UnitZ(), 1.0, ++seq));
    session.Step();
  }
  const force_model::LocalForceModel& m = session.tool(0).force_model;
  ASSERT_TRUE(m.in_contact);
  const force_model::ForceSample f = force_model::EvaluateLocalForceModel(
      m, session.tool(0).command.pose.tip, Eigen::Vector3d::Zero());
  EXPECT_GT(f.force.z(), 0.05) << "the tissue pushes the probe up [N]";
  EXPECT_LT(f.force.z(), 5.0) << "a palpation, not a wall [N]";
  const double dent = max_offset();
  EXPECT_GT(dent, 0.002) << "the probe dents the surface";

  // Lift away; after 1 s the shell is back within a millimetre of where gravity left it.
  session.SetToolCommand(0, At(top + 0.03 * Eigen::Vector3d::UnitZ(), 1.0, ++seq));
  for (int i = 0; i < 200; ++i) session.Step();
  EXPECT_LT(max_offset(), 0.002);
  EXPECT_EQ(session.rejected_steps(), 0u);
  std::printf(
      "spleen600: sag %.2f mm, probe 4 mm deep: force %.3f N, dent %.2f mm; 1 s after: %.2f mm\n",
      1e3 * sag, f.force.z(), 1e3 * dent, 1e3 * max_offset());
}

}  // namespace
}  // namespace somasim::server

namespace somasim::server {
namespace {

// A vertical scalpel (the blade 10 mm up the shaft from the tip) 4 mm into the top of the
// kidney, drawn 2 cm along x in 0.8 s with the cut button held.
struct Incision {
  Eigen::Vector3d start;
  Eigen::Vector3d end;
};

Incision AcrossTheTop(const Session& session) {
  const Eigen::Vector3d top = TopOf(session, 0);
  const Eigen::Vector3d depth(0.0, 0.0, -0.004);
  return {top + depth + Eigen::Vector3d(-0.01, 0.0, 0.0),
          top + depth + Eigen::Vector3d(0.01, 0.0, 0.0)};
}

ToolCommandInput Blade(const Eigen::Vector3d& tip, bool cut, uint64_t sequence) {
  ToolCommandInput c = At(tip, 1.0, sequence);
  c.buttons = cut ? kCutButton : 0;
  return c;
}

TEST(SessionCut, AScalpelStrokeCutsTheFemOrganAndBumpsItsTopology) {
  Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  const int32_t s = session.ToolIndex("scalpel");
  const Incision cut = AcrossTheTop(session);
  const int32_t num_nodes = session.organ(0).built.model->num_nodes();
  ASSERT_NE(session.organ(0).cutter, nullptr);
  EXPECT_EQ(session.organ(0).topology_version, 1u);
  uint64_t seq = 0;
  int32_t cut_events = 0;
  int32_t removed = 0;
  const int steps = 80;
  for (int i = 0; i <= steps; ++i) {
    const double u = static_cast<double>(i) / steps;
    session.SetToolCommand(s, Blade((1.0 - u) * cut.start + u * cut.end, true, ++seq));
    session.Step();
    for (const SessionEventRecord& e : session.TakeEvents()) {
      cut_events += e.kind == SessionEventRecord::Kind::kCut ? 1 : 0;
    }
    // The engaged blade does not push: no contact force on the scalpel.
    EXPECT_FALSE(session.tool(s).force_model.in_contact) << "tick " << i;
  }
  const SessionOrgan& o = session.organ(0);
  EXPECT_EQ(cut_events, 0) << "the incision's event comes when it ends";
  EXPECT_GT(o.elements_cut, 4);
  EXPECT_EQ(o.cutter->num_tets() - o.cutter->num_alive(), o.elements_cut);
  EXPECT_GT(o.topology_version, 3u) << "the wound forms progressively under the blade";
  const uint32_t version = o.topology_version;
  EXPECT_EQ(o.built.model->num_nodes(), num_nodes);  // vertex-preserving
  EXPECT_EQ(session.rejected_steps(), 0u);
  EXPECT_TRUE(o.state->positions.allFinite());
  // The FEM state dropped exactly the cutter's removed elements.
  for (int32_t e = 0; e < o.cutter->num_tets(); ++e) {
    ASSERT_EQ(o.built.fem->ElementAlive(*o.state, e), o.cutter->alive(e)) << "element " << e;
  }
  // The re-extracted surface has inner faces.
  mesh::Triangles triangles;
  std::vector<uint8_t> inner;
  o.cutter->ExtractSurface(&triangles, &inner);
  EXPECT_GT(std::count(inner.begin(), inner.end(), 1), 4);
  EXPECT_EQ(triangles.cols(), static_cast<Eigen::Index>(inner.size()));
  // Out of the tissue and the button released: the blade stops cutting, the tissue settles.
  session.SetToolCommand(s, Blade(cut.end + Eigen::Vector3d(0.0, 0.0, 0.03), false, ++seq));
  for (int i = 0; i < 50; ++i) {
    session.Step();
    for (const SessionEventRecord& e : session.TakeEvents()) {
      if (e.kind != SessionEventRecord::Kind::kCut) continue;
      ++cut_events;
      removed += e.detail;
      EXPECT_EQ(e.organ, 0);
      EXPECT_EQ(e.tool, s);
    }
  }
  EXPECT_EQ(cut_events, 1);
  EXPECT_EQ(removed, o.elements_cut);
  EXPECT_EQ(o.topology_version, version);
  EXPECT_EQ(session.rejected_steps(), 0u);
  EXPECT_TRUE(o.state->positions.allFinite());
  // A reset puts the tissue back, as a new topology.
  session.Reset();
  EXPECT_EQ(session.organ(0).elements_cut, 0);
  EXPECT_EQ(session.organ(0).cutter->num_alive(), session.organ(0).cutter->num_tets());
  EXPECT_EQ(session.organ(0).topology_version, version + 1);
}

// Seed 001's hybrid liver cut by the scalpel (issue 13: cutting in the meshless region by the
// visibility criterion, through the model interface): the stroke hides (node, point) pairs
// under the blade, counted as the organ's elements cut and reported by one event when the
// incision ends; no step is rejected, the field stays finite, and the topology (the meshless
// model keeps its nodes and surface) does not change.
TEST(SessionCut, AScalpelStrokeCutsTheEfgHybridLiver) {
  scene::SceneLines lines;
  const scene::Scene scene = scene::LoadSceneFile(
      std::string(SOMASIM_TEST_DATA_DIR) + "/scenes/liver288_efg_hybrid.scene.txtpb", &lines);
  Session session(scene, lines, ".");
  const int32_t s = session.ToolIndex("scalpel");
  const SessionOrgan& o = session.organ(0);
  ASSERT_NE(o.built.efg_hybrid, nullptr);
  ASSERT_TRUE(o.built.model->SupportsCutting());
  const Incision cut = AcrossTheTop(session);
  const uint32_t version = o.topology_version;
  uint64_t seq = 0;
  const int steps = 40;
  const auto start = std::chrono::steady_clock::now();
  for (int i = 0; i <= steps; ++i) {
    const double u = static_cast<double>(i) / steps;
    session.SetToolCommand(s, Blade((1.0 - u) * cut.start + u * cut.end, true, ++seq));
    session.Step();
    for (const SessionEventRecord& e : session.TakeEvents()) {
      EXPECT_NE(e.kind, SessionEventRecord::Kind::kCut) << "the event comes when it ends";
    }
  }
  const double took =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const models::meshless::EfgCutValues* values = o.built.efg_hybrid->CutOf(*o.state);
  ASSERT_NE(values, nullptr);
  EXPECT_GT(o.elements_cut, 0);
  EXPECT_EQ(values->hidden_pairs, o.elements_cut);
  EXPECT_EQ(session.rejected_steps(), 0u);
  EXPECT_TRUE(o.state->positions.allFinite());
  std::printf(
      "EFG hybrid liver288: a 2 cm stroke 4 mm deep in %d ticks hid %lld pairs (%lld Gauss "
      "points dropped, %lld node rows detached) in %.2f s, %lld partitions\n",
      steps + 1, static_cast<long long>(values->hidden_pairs),
      static_cast<long long>(values->dropped_points), static_cast<long long>(values->detached_rows),
      took, static_cast<long long>(o.built.efg_hybrid->Partitions(*o.state)));
  // Out of the tissue, the button released: one event with what the incision hid.
  session.SetToolCommand(s, Blade(cut.end + Eigen::Vector3d(0.0, 0.0, 0.03), false, ++seq));
  int32_t events = 0, removed = 0;
  for (int i = 0; i < 20; ++i) {
    session.Step();
    for (const SessionEventRecord& e : session.TakeEvents()) {
      if (e.kind != SessionEventRecord::Kind::kCut) continue;
      ++events;
      removed += e.detail;
    }
  }
  EXPECT_EQ(events, 1);
  EXPECT_EQ(removed, o.elements_cut);
  EXPECT_EQ(o.topology_version, version);
  EXPECT_EQ(session.rejected_steps(), 0u);
  EXPECT_TRUE(o.state->positions.allFinite());
}

TEST(SessionCut, WithoutTheCutButtonTheScalpelOnlyPresses) {
  Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  const int32_t s = session.ToolIndex("scalpel");
  const Incision cut = AcrossTheTop(session);
  uint64_t seq = 0;
  for (int i = 0; i <= 40; ++i) {
    const double u = static_cast<double>(i) / 40;
    session.SetToolCommand(s, Blade((1.0 - u) * cut.start + u * cut.end, false, ++seq));
    session.Step();
    for (const SessionEventRecord& e : session.TakeEvents()) {
      EXPECT_NE(e.kind, SessionEventRecord::Kind::kCut);
    }
  }
  EXPECT_EQ(session.organ(0).elements_cut, 0);
  EXPECT_EQ(session.organ(0).topology_version, 1u);
  EXPECT_TRUE(session.tool(s).force_model.in_contact);  // it presses like a probe
}

TEST(SessionCut, ABladeThatJumpsStartsANewIncisionInsteadOfCuttingThrough) {
  Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  const int32_t s = session.ToolIndex("scalpel");
  const Incision cut = AcrossTheTop(session);
  uint64_t seq = 0;
  // Engaged at one end, then the next command 3 cm away (a lost stretch of commands).
  session.SetToolCommand(s, Blade(cut.start - Eigen::Vector3d(0.01, 0.0, 0.0), true, ++seq));
  session.Step();
  session.SetToolCommand(s, Blade(cut.end + Eigen::Vector3d(0.01, 0.0, 0.0), true, ++seq));
  session.Step();
  EXPECT_EQ(session.organ(0).elements_cut, 0);
}

TEST(SessionCut, CuttingStepsAllocateNothing) {
  Session session(KidneyScene(), scene::SceneLines("kidney"), ".");
  const int32_t s = session.ToolIndex("scalpel");
  const Incision cut = AcrossTheTop(session);
  uint64_t seq = 0;
  const int steps = 80;
  for (int i = 0; i <= steps; ++i) {
    const double u = static_cast<double>(i) / steps;
    session.SetToolCommand(s, Blade((1.0 - u) * cut.start + u * cut.end, true, ++seq));
    if (i < 20) {
      session.Step();
      (void)session.TakeEvents();
      continue;
    }
    testing::AllocationCounter counter;
    session.Step();
    (void)session.TakeEvents();
    ASSERT_EQ(counter.count(), 0) << "tick " << i;
  }
  EXPECT_GT(session.organ(0).elements_cut, 0);
}

}  // namespace
}  // namespace somasim::server
