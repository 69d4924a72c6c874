#include "server/contact/contact_pipeline.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <limits>

#include "common/mesh_gen/builtin_organs.h"
#include "server/contact/force_model_maker.h"
#include "server/contact/tissue_compliance.h"
#include "server/models/mass_spring_model.h"
#include "tests/server/contact/contact_fixtures.h"
#include "tests/server/contact/contact_test_meshes.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::contact {
namespace {

using force_model::EvaluateLocalForceModel;
using force_model::ForceSample;
using force_model::LocalForceModelError;

// A probe above the organ's top node, pushed `depth` [m] below where the surface was.
struct Pressing {
  testing::HeldOrgan organ = testing::HeldKidney();
  mesh::Points rest = organ.state->positions;
  OrganSurface surface{rest, organ.mesh.surface};
  ToolPose pose;
  ContactSettings settings;
  ToolContact tool{ToolShape{}, settings, AboveTop()};

  ToolPose AboveTop() const {
    ToolPose p;
    p.tip = rest.col(organ.top) + Eigen::Vector3d(0.0003, 0.0002, 0.01);
    return p;
  }
  void Step(double dt = 0.005) {
    surface.Refit(organ.state->positions);
    tool.Update(pose, surface, organ.state->positions);
    ASSERT_EQ(testing::StepWithTool(organ, tool, dt, organ.state.get()), models::StepStatus::kOk);
  }
  void PressTo(double depth, int settle_steps) {
    pose = AboveTop();
    const Eigen::Vector3d start = pose.tip;
    const double travel = 0.01 + depth;
    for (int i = 1; i <= 40; ++i) {
      pose.tip = start - Eigen::Vector3d(0.0, 0.0, travel * i / 40.0);
      Step();
    }
    for (int i = 0; i < settle_steps; ++i) Step();
  }
};

TEST(ToolContact, AProbePressingIntoAnOrganSettlesWhereTheSpringBalancesTheTissue) {
  // Long under the sanitizer (10-35 s): the Release build runs it (CI tiers).
  if (testing::kUnderSanitizer) GTEST_SKIP() << "long: Release only";
  Pressing press;
  press.PressTo(0.004, 300);
  const auto& x = press.organ.state->positions;
  ASSERT_TRUE(press.tool.proxy().in_contact());
  // The surface gave way, but less than the device went in: the spring holds the rest.
  const double indentation = press.rest(2, press.organ.top) - x(2, press.organ.top);
  EXPECT_GT(indentation, 0.0005);
  EXPECT_LT(indentation, 0.004);
  // The hand is pushed out along the surface normal, with seed 002 eq. 12's spring: after the
  // step the springs' force equals K_t (x_surface - x_device) at the step's end.
  const Eigen::Vector3d f = press.tool.ToolForce(x);
  EXPECT_GT(f.z(), 0.1);
  EXPECT_GT(f.normalized().dot(press.tool.proxy().normal()), 0.9);
  // Settled: one more update finds the same force from the proxy.
  press.surface.Refit(x);
  press.tool.Update(press.pose, press.surface, x);
  const Eigen::Vector3d g = press.tool.proxy().DeviceForce(press.settings.tool_stiffness);
  EXPECT_NEAR((f - g).norm(), 0.0, 0.02 * g.norm());
  // The proxy is outside the organ.
  EXPECT_LT(testing::WindingNumber(x, press.organ.mesh.surface, press.tool.proxy().proxy()), 0.5);
}

TEST(ToolContact, AProbeCannotPushThroughAMassSpringSheet) {
  // seed 002's simple tissue (an open, gently domed patch), an implicit mass-spring sheet held
  // around its rim like a drum skin, pressed far further than it can give: the proxy stays on
  // top.
  const mesh::SurfaceMesh sheet = mesh_gen::GenerateBuiltinOrgan("tissue45").surface;
  models::MassSpringParameters p;
  p.youngs_modulus = 100e3;
  p.integrator = models::MassSpringIntegrator::kImplicitEuler;
  p.damping_ratio = 0.5;
  const auto model = models::MassSpringModel::FromSurface(sheet, p);
  const auto state = model->MakeState();
  const mesh::Points& x = state->positions;
  const Eigen::Vector3d centre = 0.5 * (x.rowwise().minCoeff() + x.rowwise().maxCoeff());
  const double rim =
      0.8 * (x.topRows<2>().colwise() - centre.head<2>()).colwise().norm().maxCoeff();
  std::vector<int32_t> held;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if ((x.col(i).head<2>() - centre.head<2>()).norm() > rim)
      held.push_back(static_cast<int32_t>(i));
  }
  OrganSurface surface(x, sheet.triangles);
  ToolPose pose;
  pose.tip = Eigen::Vector3d(centre.x(), centre.y(), x.row(2).maxCoeff() + 0.01);
  ToolContact tool(ToolShape{}, ContactSettings{}, pose);
  const Eigen::Vector3d start = pose.tip;
  bool touched = false;
  for (int i = 1; i <= 300; ++i) {
    pose.tip = start - Eigen::Vector3d(0.0, 0.0, 0.04 * std::min(i, 100) / 100.0);
    surface.Refit(x);
    tool.Update(pose, surface, x);
    // Nothing of the sheet above the proxy: it is still on the side it came from. (Checked
    // after the update, against the surface it was updated on; the step then moves the sheet.)
    SegmentHit hit;
    ASSERT_FALSE(surface.tree().FirstHit(
        tool.proxy().proxy(), tool.proxy().proxy() + Eigen::Vector3d(0.0, 0.0, 1.0), &hit))
        << "step " << i;
    models::StepInputs inputs;
    inputs.dt = 0.002;
    inputs.fixed_nodes = held;
    inputs.attachments = tool.attachments();
    ASSERT_EQ(model->Step(inputs, state.get()), models::StepStatus::kOk);
    touched = touched || tool.proxy().in_contact();
  }
  EXPECT_TRUE(touched);
  EXPECT_GT(tool.ToolForce(x).z(), 0.0);
}

TEST(ToolContact, TheLocalForceModelGivesTheToolsForceAtTheDeviceAndPredictsTheNext) {
  // Seconds of FEM dynamics: the Release build runs it (ASan makes it 40 s).
  if (testing::kUnderSanitizer) GTEST_SKIP() << "FEM dynamics: Release only";
  Pressing press;
  // A shallow press: the rest state's compliance describes it (3 mm into this coarse 20 kPa
  // kidney, the full model has softened by 40 %: docs/contact.md).
  press.PressTo(0.0005, 300);
  const mesh::Points& x = press.organ.state->positions;
  FemCompliance fem(*press.organ.model, press.organ.held);
  const ContactForModel contact =
      press.tool.ForLocalModel(*press.organ.model, *press.organ.state, &fem);
  ASSERT_TRUE(contact.in_contact);
  const LocalForceModel model = MakeLocalForceModel(contact, 1, 0.0);
  ASSERT_EQ(LocalForceModelError(model), nullptr);
  // At the device: the force the tool feels now (its normal part: all of it, nearly).
  const Eigen::Vector3d f = press.tool.ToolForce(x);
  const ForceSample here = EvaluateLocalForceModel(model, press.pose.tip, Eigen::Vector3d::Zero());
  EXPECT_NEAR((here.force - contact.normal * contact.normal.dot(f)).norm(), 0.0, 1e-9 * f.norm());
  EXPECT_GT(here.force.normalized().dot(f.normalized()), 0.95);  // the springs drag a little
  // 0.5 mm further in: what the local model predicts against where the full model settles.
  const Eigen::Vector3d further = press.pose.tip - 0.0005 * contact.normal;
  const ForceSample predicted = EvaluateLocalForceModel(model, further, Eigen::Vector3d::Zero());
  press.pose.tip = further;
  for (int i = 0; i < 300; ++i) press.Step();
  const Eigen::Vector3d settled = press.tool.ToolForce(press.organ.state->positions);
  const double increase = contact.normal.dot(settled - f);
  const double predicted_increase = contact.normal.dot(predicted.force - here.force);
  EXPECT_GT(increase, 0.0);
  EXPECT_NEAR(predicted_increase, increase, 0.1 * increase);
}

TEST(ToolContact, LiftingTheProbeReleasesTheTissue) {
  Pressing press;
  press.PressTo(0.003, 50);
  ASSERT_FALSE(press.tool.attachments().empty());
  press.pose.tip.z() += 0.02;
  press.Step();
  EXPECT_FALSE(press.tool.proxy().in_contact());
  EXPECT_TRUE(press.tool.attachments().empty());
  EXPECT_EQ(press.tool.ToolForce(press.organ.state->positions), Eigen::Vector3d::Zero());
}

TEST(ToolContact, UpdatesAndStepsAllocateNothingInSteadyState) {
  Pressing press;
  press.PressTo(0.003, 5);
  const testing::AllocationCounter counter;
  for (int i = 0; i < 20; ++i) {
    press.pose.tip.x() += 0.0001;
    press.Step();
  }
  EXPECT_EQ(counter.count(), 0);
}

TEST(ToolContact, BadPosesAreIgnoredAndACameraTouchesNothing) {
  Pressing press;
  press.PressTo(0.003, 5);
  const ToolPose good = press.tool.pose();
  ToolPose bad = good;
  bad.tip.y() = std::nan("");
  press.surface.Refit(press.organ.state->positions);
  press.tool.Update(bad, press.surface, press.organ.state->positions);
  EXPECT_EQ(press.tool.pose().tip, good.tip);
  EXPECT_TRUE(press.tool.proxy().in_contact());
  EXPECT_TRUE(press.tool.ToolForce(press.organ.state->positions).allFinite());

  ToolShape camera;
  camera.kind = ToolKind::kCamera;
  ToolContact laparoscope(camera, ContactSettings{}, good);
  laparoscope.Update(good, press.surface, press.organ.state->positions);
  EXPECT_FALSE(laparoscope.proxy().in_contact());
  EXPECT_TRUE(laparoscope.attachments().empty());
}

TEST(ToolContact, BadShapesSettingsAndStartPosesAreRefused) {
  ToolShape shape;
  shape.shaft_length = 0.0;
  EXPECT_THROW(ToolContact(shape, ContactSettings{}, ToolPose{}), std::invalid_argument);
  ContactSettings settings;
  settings.tool_stiffness = -1.0;
  EXPECT_THROW(ToolContact(ToolShape{}, settings, ToolPose{}), std::invalid_argument);
  settings = ContactSettings{};
  settings.force_limit = std::nan("");
  EXPECT_THROW(ToolContact(ToolShape{}, settings, ToolPose{}), std::invalid_argument);
  ToolPose pose;
  pose.tip.z() = std::numeric_limits<double>::infinity();
  EXPECT_THROW(ToolContact(ToolShape{}, ContactSettings{}, pose), std::invalid_argument);
  const mesh::SurfaceMesh patch = testing::FlatPatch(2, 1.0);
  mesh::Triangles bad = patch.triangles;
  bad(1, 0) = 99;
  EXPECT_THROW(OrganSurface(patch.vertices, bad), std::invalid_argument);
}

}  // namespace
}  // namespace somasim::contact
