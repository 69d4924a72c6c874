#include "server/contact/grasp.h"

#include <gtest/gtest.h>

#include "server/contact/contact_pipeline.h"
#include "tests/server/contact/contact_fixtures.h"
#include "tests/server/contact/contact_test_meshes.h"
#include "tests/support/sanitizer.h"

namespace somasim::contact {
namespace {

ToolShape Grasper() {
  ToolShape shape;
  shape.kind = ToolKind::kGrasper;
  return shape;
}

TEST(Grasp, ClosingOnTissueHoldsTheNodesNearTheJawsAndOpeningLetsGo) {
  const mesh::SurfaceMesh patch = testing::FlatPatch(20, 0.05);  // 5 mm spacing
  const AabbTree tree(patch.vertices, patch.triangles);
  GraspSettings settings;
  Grasp grasp(settings);
  ToolPose pose;
  pose.tip = Eigen::Vector3d(0.0, 0.0, 0.001);  // shaft up from 1 mm above the patch
  pose.jaw_opening = 1.0;
  grasp.Update(Grasper(), pose, tree, patch.vertices);
  EXPECT_FALSE(grasp.holding());
  pose.jaw_opening = 0.1;
  grasp.Update(Grasper(), pose, tree, patch.vertices);
  ASSERT_TRUE(grasp.holding());
  // Within 3 mm of the jaws' segment: only the node under the tip (the next is 5 mm away).
  ASSERT_EQ(grasp.num_held(), 1);
  EXPECT_EQ(grasp.attachments()[0].node, 10 * 21 + 10);
  EXPECT_DOUBLE_EQ(grasp.attachments()[0].stiffness, settings.stiffness);
  // The jaws carry the held point: lifting the tool lifts the target.
  pose.tip.z() += 0.004;
  pose.jaw_opening = 0.3;  // between the thresholds: still closed
  grasp.Update(Grasper(), pose, tree, patch.vertices);
  ASSERT_TRUE(grasp.holding());
  EXPECT_NEAR(grasp.attachments()[0].target.z(), 0.004, 1e-15);
  EXPECT_NEAR(grasp.ToolForce(patch.vertices).z(), -settings.stiffness * 0.004, 1e-12);
  pose.jaw_opening = 0.5;
  grasp.Update(Grasper(), pose, tree, patch.vertices);
  EXPECT_FALSE(grasp.holding());
  EXPECT_EQ(grasp.ToolForce(patch.vertices), Eigen::Vector3d::Zero());
}

TEST(Grasp, ClosingInTheAirHoldsNothingUntilReopened) {
  const mesh::SurfaceMesh patch = testing::FlatPatch(20, 0.05);
  const AabbTree tree(patch.vertices, patch.triangles);
  Grasp grasp(GraspSettings{});
  ToolPose pose;
  pose.tip = Eigen::Vector3d(0.0, 0.0, 0.02);
  pose.jaw_opening = 0.0;
  grasp.Update(Grasper(), pose, tree, patch.vertices);
  EXPECT_TRUE(grasp.jaws_closed());
  EXPECT_FALSE(grasp.holding());
  pose.tip.z() = 0.0;  // closed jaws pushed onto tissue do not pick it up
  grasp.Update(Grasper(), pose, tree, patch.vertices);
  EXPECT_FALSE(grasp.holding());
  // A probe never grasps.
  ToolShape probe;
  pose.jaw_opening = 1.0;
  grasp.Update(probe, pose, tree, patch.vertices);
  pose.jaw_opening = 0.0;
  grasp.Update(probe, pose, tree, patch.vertices);
  EXPECT_FALSE(grasp.holding());
}

TEST(Grasp, KeepsTheNodesNearestTheJawsWhenMoreAreInReach) {
  const mesh::SurfaceMesh patch = testing::FlatPatch(40, 0.05);  // 2.5 mm spacing
  const AabbTree tree(patch.vertices, patch.triangles);
  GraspSettings settings;
  settings.max_nodes = 3;
  Grasp grasp(settings);
  ToolShape shape = Grasper();
  shape.grasp_radius = 0.006;
  ToolPose pose;
  pose.tip = Eigen::Vector3d(0.0001, 0.0002, 0.0);
  pose.orientation = Eigen::AngleAxisd(0.5 * M_PI, Eigen::Vector3d::UnitY());  // jaws along x
  pose.jaw_opening = 1.0;
  grasp.Update(shape, pose, tree, patch.vertices);
  pose.jaw_opening = 0.0;
  grasp.Update(shape, pose, tree, patch.vertices);
  ASSERT_EQ(grasp.num_held(), 3);
  // Nodes on the jaws' line (y = 0) are at 0.2 mm; the next row is 2.3 mm away.
  for (const models::Attachment& a : grasp.attachments()) {
    EXPECT_NEAR(patch.vertices(1, a.node), 0.0, 1e-12);
  }
}

TEST(Grasp, BadSettingsAreRefused) {
  GraspSettings s;
  s.close_below = 0.5;
  s.open_above = 0.4;
  EXPECT_THROW(Grasp{s}, std::invalid_argument);
  s = GraspSettings{};
  s.stiffness = std::nan("");
  EXPECT_THROW(Grasp{s}, std::invalid_argument);
  s = GraspSettings{};
  s.max_nodes = 0;
  EXPECT_THROW(Grasp{s}, std::invalid_argument);
}

TEST(Grasp, GraspPullAndReleaseReturnsElasticTissueToRest) {
  // Seconds of FEM dynamics: the Release build runs it (ASan makes it 40 s).
  if (testing::kUnderSanitizer) GTEST_SKIP() << "FEM dynamics: Release only";
  testing::HeldOrgan organ = testing::HeldKidney();
  const mesh::Points rest = organ.state->positions;
  OrganSurface surface(rest, organ.mesh.surface);
  ToolPose pose;
  pose.tip = rest.col(organ.top);
  pose.jaw_opening = 1.0;
  ContactSettings settings;
  ToolContact tool(Grasper(), settings, pose);
  const double dt = 0.005;
  auto step = [&](const ToolPose& p) {
    surface.Refit(organ.state->positions);
    tool.Update(p, surface, organ.state->positions);
    ASSERT_EQ(testing::StepWithTool(organ, tool, dt, organ.state.get()), models::StepStatus::kOk);
  };
  step(pose);
  pose.jaw_opening = 0.0;
  step(pose);
  ASSERT_TRUE(tool.grasp().holding());
  // Pull 6 mm up over 0.3 s, hold 0.5 s.
  const Eigen::Vector3d start = pose.tip;
  for (int i = 1; i <= 60; ++i) {
    pose.tip = start + Eigen::Vector3d(0.0, 0.0, 0.006 * i / 60.0);
    step(pose);
  }
  for (int i = 0; i < 100; ++i) step(pose);
  const double lifted = organ.state->positions(2, organ.top) - rest(2, organ.top);
  EXPECT_GT(lifted, 0.003);  // the tissue followed (the grasp spring stretches the rest)
  EXPECT_LT(lifted, 0.006);
  const Eigen::Vector3d pull = tool.ToolForce(organ.state->positions);
  EXPECT_LT(pull.z(), -0.01);  // the tissue pulls the tool back down
  // Release and let it settle: back to rest.
  pose.jaw_opening = 1.0;
  for (int i = 0; i < 600; ++i) step(pose);
  EXPECT_FALSE(tool.grasp().holding());
  EXPECT_LT((organ.state->positions - rest).colwise().norm().maxCoeff(), 0.02 * lifted);
}

}  // namespace
}  // namespace somasim::contact
