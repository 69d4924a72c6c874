#include "server/contact/rigid_body.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <vector>

#include "common/mesh/topology.h"
#include "server/contact/contact_pipeline.h"
#include "server/models/fem/fem_model.h"
#include "tests/server/contact/contact_test_meshes.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::contact {
namespace {

const Eigen::Vector3d kGravity(0.0, 0.0, -9.81);

// kidney424 with a pocket in its top: the tetrahedra with a corner within `pocket` of `centre`
// are removed (and the nodes left in none), so a stone can rest in the hollow.
struct PocketedKidney {
  mesh::TetMesh volume;
  mesh::Triangles surface;
  Eigen::Vector3d centre;
  double top_z = 0.0;
  std::vector<int32_t> held;
};

PocketedKidney MakePocketedKidney(double pocket) {
  const testing::OrganWithSurface kidney = testing::VolumeOrgan("kidney424");
  const mesh::Points& x = kidney.volume.vertices;
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  PocketedKidney out;
  out.top_z = x(2, top);
  out.centre = x.col(top) - Eigen::Vector3d(0.0, 0.0, 0.3 * pocket);
  std::vector<int32_t> kept;
  for (Eigen::Index t = 0; t < kidney.volume.tetrahedra.cols(); ++t) {
    bool near = false;
    for (int c = 0; c < 4; ++c) {
      near = near || (x.col(kidney.volume.tetrahedra(c, t)) - out.centre).norm() < pocket;
    }
    if (!near) kept.push_back(static_cast<int32_t>(t));
  }
  std::vector<int32_t> renumber(static_cast<size_t>(x.cols()), -1);
  int32_t nodes = 0;
  for (const int32_t t : kept) {
    for (int c = 0; c < 4; ++c) {
      int32_t& n = renumber[static_cast<size_t>(kidney.volume.tetrahedra(c, t))];
      if (n < 0) n = nodes++;
    }
  }
  out.volume.vertices.resize(3, nodes);
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (renumber[static_cast<size_t>(i)] >= 0) {
      out.volume.vertices.col(renumber[static_cast<size_t>(i)]) = x.col(i);
    }
  }
  out.volume.tetrahedra.resize(4, static_cast<Eigen::Index>(kept.size()));
  for (size_t k = 0; k < kept.size(); ++k) {
    for (int c = 0; c < 4; ++c) {
      out.volume.tetrahedra(c, static_cast<Eigen::Index>(k)) =
          renumber[static_cast<size_t>(kidney.volume.tetrahedra(c, kept[k]))];
    }
  }
  out.surface = mesh::ExtractBoundarySurface(out.volume).triangles;
  const double z_lo = out.volume.vertices.row(2).minCoeff();
  for (int32_t i = 0; i < nodes; ++i) {
    if (out.volume.vertices(2, i) < z_lo + 0.1 * (out.top_z - z_lo)) out.held.push_back(i);
  }
  return out;
}

TEST(RigidSphere, AGrasperLiftsTheStoneOutOfTheKidney) {
  // Long under the sanitizer (10-35 s): the Release build runs it (CI tiers).
  if (testing::kUnderSanitizer) GTEST_SKIP() << "long: Release only";
  const double radius = 0.006;
  const PocketedKidney kidney = MakePocketedKidney(0.011);
  models::fem::FemParameters p;
  p.youngs_modulus = 20e3;
  p.poisson_ratio = 0.45;
  p.rayleigh_mass = 30.0;
  p.rayleigh_stiffness = 0.002;
  const auto model = models::fem::FemModel::FromTetMesh(kidney.volume, p);
  const auto state = model->MakeState();
  const mesh::Points rest = state->positions;
  OrganSurface surface(rest, kidney.surface);
  RigidSphereSettings settings;
  settings.radius = radius;
  RigidSphere stone(settings, kidney.centre);

  ToolShape grasper;
  grasper.kind = ToolKind::kGrasper;
  ToolPose pose;
  pose.tip = kidney.centre + Eigen::Vector3d(0.0, 0.0, 0.05);  // well above, jaws open
  ContactSettings contact;
  ToolContact tool(grasper, contact, pose);
  std::vector<models::Attachment> springs;
  const double dt = 0.005;
  auto step = [&]() {
    surface.Refit(state->positions);
    stone.CollectTissueContacts(surface.tree(), state->positions);
    tool.Update(pose, surface, state->positions);
    springs.assign(stone.attachments().begin(), stone.attachments().end());
    springs.insert(springs.end(), tool.attachments().begin(), tool.attachments().end());
    models::StepInputs inputs;
    inputs.dt = dt;
    inputs.gravity = kGravity;
    inputs.fixed_nodes = kidney.held;
    inputs.attachments = springs;
    ASSERT_EQ(model->Step(inputs, state.get()), models::StepStatus::kOk);
    stone.UpdateTool(grasper, pose);
    ASSERT_TRUE(stone.Step(dt, kGravity, state->positions));
  };
  // The stone settles into its pocket: held by the tissue, not falling through.
  for (int i = 0; i < 200; ++i) step();
  EXPECT_LT(stone.velocity().norm(), 1e-3);
  EXPECT_GT(stone.attachments().size(), 0u);
  EXPECT_LT(stone.position().z() + radius, kidney.top_z + 0.002);  // in the kidney
  EXPECT_GT(stone.position().z(), kidney.centre.z() - 0.011);      // resting on the pocket
  const Eigen::Vector3d settled = stone.position();
  // The grasper comes down onto the stone and closes.
  const Eigen::Vector3d above = settled + Eigen::Vector3d(0.0, 0.0, radius + 0.001);
  const Eigen::Vector3d from = pose.tip;
  for (int i = 1; i <= 20; ++i) {
    pose.tip = from + (above - from) * (i / 20.0);
    step();
  }
  pose.jaw_opening = 0.0;
  step();
  ASSERT_TRUE(stone.grasped());
  // Lift 4 cm in 0.5 s, hold 0.25 s.
  const Eigen::Vector3d start = pose.tip;
  for (int i = 1; i <= 100; ++i) {
    pose.tip = start + Eigen::Vector3d(0.0, 0.0, 0.04 * i / 100.0);
    step();
  }
  for (int i = 0; i < 50; ++i) step();
  EXPECT_TRUE(stone.grasped());
  EXPECT_GT(stone.position().z() - radius, kidney.top_z + 0.01);  // out, clear of the kidney
  EXPECT_TRUE(stone.attachments().empty());                       // touching no tissue
  // The hand carries the stone's weight.
  EXPECT_NEAR(stone.tool_force().z(), -stone.mass() * 9.81, 0.05 * stone.mass() * 9.81);
  // The tissue, relieved of the stone, settles back towards rest (under its own weight).
  EXPECT_LT(stone.velocity().norm(), 1e-3);
}

TEST(RigidSphere, AProbePushesTheStoneWithoutPassingThroughIt) {
  RigidSphereSettings settings;
  settings.radius = 0.005;
  RigidSphere stone(settings, Eigen::Vector3d::Zero());
  const mesh::Points none(3, 0);
  ToolShape probe;
  ToolPose pose;
  pose.tip = Eigen::Vector3d(-0.02, 0.0, 0.0);
  stone.UpdateTool(probe, pose);
  ASSERT_TRUE(stone.Step(0.001, Eigen::Vector3d::Zero(), none));
  EXPECT_EQ(stone.velocity(), Eigen::Vector3d::Zero());
  // One update jumps the tip from one side to the other: the sweep still pushes the stone.
  pose.tip = Eigen::Vector3d(0.02, 0.0, 0.001);
  stone.UpdateTool(probe, pose);
  ASSERT_TRUE(stone.Step(0.001, Eigen::Vector3d::Zero(), none));
  // It passed just above the centre: the stone goes down, the tool is pushed up.
  EXPECT_LT(stone.velocity().z(), 0.0);
  EXPECT_GT(stone.tool_force().z(), 0.0);
  // A camera never touches it.
  RigidSphere other(settings, Eigen::Vector3d::Zero());
  ToolShape camera;
  camera.kind = ToolKind::kCamera;
  pose.tip = Eigen::Vector3d::Zero();
  other.UpdateTool(camera, pose);
  ASSERT_TRUE(other.Step(0.001, Eigen::Vector3d::Zero(), none));
  EXPECT_EQ(other.velocity(), Eigen::Vector3d::Zero());
}

TEST(RigidSphere, FallsFreelyUnderGravityAndRefusesBadInput) {
  RigidSphere stone(RigidSphereSettings{}, Eigen::Vector3d::Zero());
  const mesh::Points none(3, 0);
  for (int i = 0; i < 100; ++i) ASSERT_TRUE(stone.Step(0.001, kGravity, none));
  // Implicit Euler with water's drag only: v ≈ g t.
  EXPECT_NEAR(stone.velocity().z(), -9.81 * 0.1, 0.01);
  EXPECT_FALSE(stone.Step(std::nan(""), kGravity, none));
  EXPECT_FALSE(stone.Step(0.001, Eigen::Vector3d(0.0, std::nan(""), 0.0), none));
  RigidSphereSettings bad;
  bad.radius = 0.0;
  EXPECT_THROW(RigidSphere(bad, Eigen::Vector3d::Zero()), std::invalid_argument);
  bad = RigidSphereSettings{};
  bad.density = std::numeric_limits<double>::infinity();
  EXPECT_THROW(RigidSphere(bad, Eigen::Vector3d::Zero()), std::invalid_argument);
  bad = RigidSphereSettings{};
  bad.damping = -1.0;
  EXPECT_THROW(RigidSphere(bad, Eigen::Vector3d::Zero()), std::invalid_argument);
  EXPECT_THROW(RigidSphere(RigidSphereSettings{}, Eigen::Vector3d(std::nan(""), 0.0, 0.0)),
               std::invalid_argument);
}

TEST(RigidSphere, TissueContactsAndStepsAllocateNothing) {
  const testing::OrganWithSurface kidney = testing::VolumeOrgan("kidney424");
  const mesh::Points& x = kidney.volume.vertices;
  const AabbTree tree(x, kidney.surface);
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  RigidSphere stone(RigidSphereSettings{}, x.col(top) + Eigen::Vector3d(0.0, 0.0, 0.002));
  ToolShape probe;
  ToolPose pose;
  pose.tip = x.col(top) + Eigen::Vector3d(0.0, 0.0, 0.01);
  const testing::AllocationCounter counter;
  for (int i = 0; i < 50; ++i) {
    stone.CollectTissueContacts(tree, x);
    stone.UpdateTool(probe, pose);
    stone.Step(0.001, kGravity, x);
  }
  EXPECT_EQ(counter.count(), 0);
  EXPECT_GT(stone.attachments().size(), 0u);
}

}  // namespace
}  // namespace somasim::contact
