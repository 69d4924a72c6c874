// A haptic arm's kinematics (haptic_node/kinematics.h): forward kinematics of a planar two-link
// arm against the closed form (with homing offsets), the Jacobian of a six-joint arm with a
// prismatic joint against central differences, torques J^T F by virtual work, the workspace
// mapping, the shipped seed-002 arm at home, and bad files refused naming the line or field.
#include "haptic_node/kinematics.h"

#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "tests/support/allocation_counter.h"

namespace somasim::haptic {
namespace {

using Eigen::Vector3d;

const std::string kPlanar = R"(
format_version: 1
name: "planar"
joint { type: REVOLUTE axis { z: 1 } min: -3 max: 3 max_torque: 2 home_offset: 0.5 }
joint { type: REVOLUTE origin { x: 0.3 } axis { z: 1 } min: -3 max: 3 max_torque: 2 }
tip { x: 0.25 }
scale: 1
force_scale: 1
max_force: 5
)";

TEST(ArmKinematics, PlanarTwoLinkForwardKinematicsIsTheClosedForm) {
  const ArmKinematics k = ArmKinematics::FromText(kPlanar, "planar");
  ASSERT_EQ(k.num_joints(), 2);
  for (const double a : {-1.0, 0.0, 0.4, 2.0}) {
    for (const double b : {-2.5, 0.0, 1.1}) {
      const double encoders[2] = {a + 0.5, b};  // joint 0's encoder reads 0.5 at q = 0
      const JointVector q = k.JointsFromEncoders(encoders);
      EXPECT_NEAR(q[0], a, 1e-15);
      const ArmPose p = k.Forward(q);
      EXPECT_NEAR(p.position.x(), 0.3 * std::cos(a) + 0.25 * std::cos(a + b), 1e-14);
      EXPECT_NEAR(p.position.y(), 0.3 * std::sin(a) + 0.25 * std::sin(a + b), 1e-14);
      EXPECT_NEAR(p.position.z(), 0.0, 1e-15);
      EXPECT_NEAR(std::atan2(p.rotation(1, 0), p.rotation(0, 0)), std::remainder(a + b, 2 * M_PI),
                  1e-12);
    }
  }
}

const std::string kSixJoints = R"(
format_version: 1
joint { type: REVOLUTE origin { z: 0.1 } rpy { x: 0.1 } axis { z: 1 } min: -3 max: 3 max_torque: 3 }
joint { type: REVOLUTE origin { x: 0.05 } rpy { y: 0.3 z: -0.2 } axis { y: 1 } min: -3 max: 3 max_torque: 3 }
joint { type: PRISMATIC origin { x: 0.2 } axis { x: 1 y: 0.2 } min: -0.1 max: 0.1 max_torque: 30 }
joint { type: REVOLUTE origin { x: 0.1 } rpy { x: -0.4 } axis { x: 1 y: 1 z: 0 } min: -3 max: 3 max_torque: 0.5 }
joint { type: REVOLUTE axis { y: 1 } min: -3 max: 3 max_torque: 0.5 }
joint { type: REVOLUTE origin { z: 0.02 } axis { z: 1 } min: -3 max: 3 max_torque: 0.5 }
tip { x: 0.04 y: 0.01 }
scale: 0.5
scene_origin { x: 0.1 y: -0.2 z: 0.3 }
scene_rpy { z: 0.7 }
force_scale: 2
max_force: 8
)";

TEST(ArmKinematics, JacobianMatchesCentralDifferences) {
  const ArmKinematics k = ArmKinematics::FromText(kSixJoints, "six");
  JointVector q = JointVector::Zero();
  q.head<6>() << 0.3, -0.7, 0.04, 1.1, -0.5, 2.0;
  Jacobian j;
  const ArmPose p = k.Forward(q, &j);
  const double h = 1e-6;
  for (int i = 0; i < 6; ++i) {
    JointVector plus = q, minus = q;
    plus[i] += h;
    minus[i] -= h;
    const Vector3d fd = (k.Forward(plus).position - k.Forward(minus).position) / (2 * h);
    EXPECT_LT((j.col(i) - fd).norm(), 1e-8 * std::max(1.0, fd.norm())) << "joint " << i;
  }
  EXPECT_EQ(j.rightCols(kMaxJoints - 6).norm(), 0.0);
  EXPECT_NEAR((p.rotation.transpose() * p.rotation - Eigen::Matrix3d::Identity()).norm(), 0.0,
              1e-14);
}

// τ·δq equals F·δx for a small joint motion (virtual work): the torques render F at the handle.
TEST(ArmKinematics, TorquesAreJTransposeFByVirtualWork) {
  const ArmKinematics k = ArmKinematics::FromText(kSixJoints, "six");
  JointVector q = JointVector::Zero();
  q.head<6>() << -0.2, 0.4, -0.03, 0.3, 0.9, -1.0;
  Jacobian j;
  const ArmPose p = k.Forward(q, &j);
  const Vector3d scene_force(0.3, -0.4, 0.5);  // small: no motor saturates
  const Vector3d arm_force = k.ForceToArm(scene_force);
  EXPECT_NEAR(arm_force.norm(), 2.0 * scene_force.norm(), 1e-14);  // force_scale 2
  JointVector tau;
  EXPECT_FALSE(k.Torques(j, arm_force, &tau));
  JointVector dq = JointVector::Zero();
  dq.head<6>() << 1e-7, -2e-7, 1e-7, 3e-7, -1e-7, 2e-7;
  const Vector3d dx = k.Forward(q + dq).position - p.position;
  EXPECT_NEAR(tau.dot(dq), arm_force.dot(dx), 1e-12);
  // A force beyond a motor's limit: that joint saturates with its sign, the others do not.
  JointVector big;
  EXPECT_TRUE(k.Torques(j, 1e4 * arm_force, &big));
  for (int i = 0; i < 6; ++i) {
    EXPECT_LE(std::abs(big[i]), k.max_torque(i) + 1e-12);
    if (tau[i] != 0.0) {
      EXPECT_EQ(std::signbit(big[i]), std::signbit(tau[i]));
    }
  }
}

TEST(ArmKinematics, MapsTheWorkspaceIntoTheScene) {
  const ArmKinematics k = ArmKinematics::FromText(kSixJoints, "six");
  ArmPose arm;
  arm.position = Vector3d(0.2, 0.0, 0.0);
  const ArmPose scene = k.ToScene(arm);
  // 0.5 × (0.2, 0, 0) turned 0.7 rad about z, then moved to (0.1, -0.2, 0.3).
  EXPECT_NEAR(scene.position.x(), 0.1 + 0.1 * std::cos(0.7), 1e-15);
  EXPECT_NEAR(scene.position.y(), -0.2 + 0.1 * std::sin(0.7), 1e-15);
  EXPECT_NEAR(scene.position.z(), 0.3, 1e-15);
  EXPECT_NEAR(k.VelocityToScene(Vector3d(0, 0, 1)).z(), 0.5, 1e-15);
  // A scene force comes back into the arm's frame turned the other way, scaled.
  const Vector3d f = k.ForceToArm(Vector3d(std::cos(0.7), std::sin(0.7), 0));
  EXPECT_NEAR(f.x(), 2.0, 1e-14);
  EXPECT_NEAR(f.y(), 0.0, 1e-14);
}

TEST(ArmKinematics, TheShippedSeed002ArmHangsItsHandleAboveTheOrgansAtHome) {
  const ArmKinematics k = ArmKinematics::Load(std::string(SOMASIM_ARMS_DIR) + "/seed002.arm.txtpb");
  ASSERT_EQ(k.num_joints(), 6);
  const double home[6] = {0, 0, 0, 0, 0, 0};
  const JointVector q = k.JointsFromEncoders(home);
  EXPECT_TRUE(k.InRange(q));
  const ArmPose arm = k.Forward(q);
  EXPECT_NEAR((arm.position - Vector3d(0.2, 0.0, -0.15)).norm(), 0.0, 1e-12);
  const ArmPose scene = k.ToScene(arm);
  EXPECT_NEAR((scene.position - Vector3d(-0.03, 0.0, 0.10)).norm(), 0.0, 1e-12);
  // The shaft (+z of the tool frame) points up, from the tip towards the handle.
  EXPECT_NEAR(scene.rotation.col(2).z(), 1.0, 1e-12);
  JointVector far = q;
  far[2] = 3.0;
  EXPECT_FALSE(k.InRange(far));
}

TEST(ArmKinematics, TicksAllocateNothing) {
  const ArmKinematics k = ArmKinematics::FromText(kSixJoints, "six");
  JointVector q = JointVector::Zero();
  Jacobian j;
  JointVector tau;
  double sum = 0.0;
  const somasim::testing::AllocationCounter count;
  for (int i = 0; i < 1000; ++i) {
    q[0] = 1e-3 * i;
    const ArmPose p = k.ToScene(k.Forward(q, &j));
    k.Torques(j, k.ForceToArm(Vector3d(0, 0, 1)), &tau);
    sum += p.position.x() + tau[0];
  }
  EXPECT_EQ(count.count(), 0);
  EXPECT_TRUE(std::isfinite(sum));
}

TEST(ArmKinematics, RefusesBadConfigurationsNamingTheLineOrField) {
  struct Case {
    std::string text;
    std::string expected;
  };
  const std::string j = "joint { axis { z: 1 } min: -1 max: 1 max_torque: 1 }\n";
  const std::string tail = "scale: 1 force_scale: 1 max_force: 5\n";
  const Case cases[] = {
      {"format_version: 1\n" + j + "scale: 1 force_scale: 1 max_force: 5 bogus: 3\n",
       "arm:3: Message type \"somasim.arm.Arm\" has no field named \"bogus\""},
      {"format_version: 1\njoint { axis { z: 1 }", "arm:2:"},  // truncated
      {"format_version: 2\n" + j + tail, "arm: format_version: 2 is not supported"},
      {"format_version: 1\n" + tail, "arm: joint: an arm has 1..8 joints, not 0"},
      {"format_version: 1\n" + j + j + j + j + j + j + j + j + j + tail, "not 9"},
      {"format_version: 1\njoint { min: -1 max: 1 max_torque: 1 }\n" + tail,
       "joint[0].axis: zero length"},
      {"format_version: 1\njoint { origin { x: nan } axis { z: 1 } min: -1 max: 1 max_torque: 1 "
       "}\n" +
           tail,
       "joint[0].origin: not finite"},
      {"format_version: 1\njoint { axis { z: 1 } min: 1 max: 1 max_torque: 1 }\n" + tail,
       "joint[0].min: 1.000000 is not below max 1.000000"},
      {"format_version: 1\njoint { axis { z: 1 } min: -1 max: 1 max_torque: -1 }\n" + tail,
       "joint[0].max_torque: must be > 0"},
      {"format_version: 1\njoint { axis { z: 1 } min: -1 max: 1 max_torque: inf }\n" + tail,
       "joint[0].max_torque: not finite"},
      {"format_version: 1\n" + j + "scale: 0 force_scale: 1 max_force: 5\n", "scale: must be"},
      {"format_version: 1\n" + j + "scale: 1 force_scale: nan max_force: 5\n", "force_scale"},
      {"format_version: 1\n" + j + "scale: 1 force_scale: 1 max_force: 500\n",
       "max_force: must be in (0, 100] N"},
      {"format_version: 1\n" + j + tail + "tool_rpy { y: inf }\n", "tool_rpy: not finite"},
  };
  for (const Case& c : cases) {
    try {
      ArmKinematics::FromText(c.text, "arm");
      ADD_FAILURE() << "accepted:\n" << c.text;
    } catch (const ArmConfigError& e) {
      EXPECT_NE(std::string(e.what()).find(c.expected), std::string::npos)
          << "text:\n"
          << c.text << "\nsaid: " << e.what();
    }
  }
  EXPECT_THROW(ArmKinematics::Load("/nonexistent.arm.txtpb"), ArmConfigError);
}

}  // namespace
}  // namespace somasim::haptic
