#include "server/contact/tool.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

namespace somasim::contact {
namespace {

TEST(ToolShape, DefaultsAreUsableAndBadDimensionsAreNamed) {
  EXPECT_EQ(ToolShapeError(ToolShape{}), "");
  ToolShape shape;
  shape.shaft_length = -0.1;
  EXPECT_NE(ToolShapeError(shape).find("shaft_length"), std::string::npos);
  shape = ToolShape{};
  shape.grasp_radius = std::nan("");
  EXPECT_NE(ToolShapeError(shape).find("grasp_radius"), std::string::npos);
  shape = ToolShape{};
  shape.blade_length = 1.0;  // longer than the shaft
  EXPECT_NE(ToolShapeError(shape).find("blade_length"), std::string::npos);
  shape = ToolShape{};
  shape.jaw_length = std::numeric_limits<double>::infinity();
  EXPECT_NE(ToolShapeError(shape).find("jaw_length"), std::string::npos);
  shape = ToolShape{};
  shape.shaft_radius = 0.0;
  EXPECT_NE(ToolShapeError(shape).find("shaft_radius"), std::string::npos);
  EXPECT_STREQ(ToolKindName(ToolKind::kScalpel), "scalpel");
  EXPECT_STREQ(ToolKindName(ToolKind::kCamera), "camera");
}

TEST(ToolPose, NonFiniteOrNonUnitPosesAndBadJawsAreNamed) {
  EXPECT_EQ(ToolPoseError(ToolPose{}), "");
  ToolPose pose;
  pose.tip.x() = std::nan("");
  EXPECT_NE(ToolPoseError(pose).find("tip"), std::string::npos);
  pose = ToolPose{};
  pose.orientation.coeffs() << 0.0, 0.0, 0.0, 0.0;
  EXPECT_NE(ToolPoseError(pose).find("unit"), std::string::npos);
  pose.orientation.coeffs() << 0.0, std::numeric_limits<double>::infinity(), 0.0, 1.0;
  EXPECT_NE(ToolPoseError(pose).find("orientation"), std::string::npos);
  pose = ToolPose{};
  pose.jaw_opening = 1.5;
  EXPECT_NE(ToolPoseError(pose).find("jaw"), std::string::npos);
}

TEST(ToolPose, TheShaftRunsAlongTheToolsZAxisFromTheTip) {
  ToolPose pose;
  pose.tip = Eigen::Vector3d(0.1, 0.2, 0.3);
  pose.orientation = Eigen::AngleAxisd(0.5 * M_PI, Eigen::Vector3d::UnitX());
  EXPECT_NEAR((ShaftAxis(pose) - Eigen::Vector3d(0.0, -1.0, 0.0)).norm(), 0.0, 1e-15);
  EXPECT_NEAR((PointOnShaft(pose, 0.02) - Eigen::Vector3d(0.1, 0.18, 0.3)).norm(), 0.0, 1e-15);
}

}  // namespace
}  // namespace somasim::contact
