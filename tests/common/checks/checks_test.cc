// common/checks: the finite-and-positive checks and the tool-pose check refuse NaN, infinities
// and out-of-range values, and accept the boundaries they name.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <stdexcept>

#include "common/checks/finite.h"
#include "common/checks/tool_pose.h"

namespace somasim::checks {
namespace {

constexpr double kNan = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

TEST(Checks, FinitePositiveAndNonNegativeRefuseNanAndInfinities) {
  EXPECT_TRUE(FinitePositive(1e-300));
  EXPECT_FALSE(FinitePositive(0.0));
  EXPECT_FALSE(FinitePositive(-1.0));
  EXPECT_FALSE(FinitePositive(kNan));
  EXPECT_FALSE(FinitePositive(kInf));
  EXPECT_TRUE(FiniteNonNegative(0.0));
  EXPECT_FALSE(FiniteNonNegative(-0.5));
  EXPECT_FALSE(FiniteNonNegative(kNan));
  EXPECT_FALSE(FiniteNonNegative(kInf));
}

TEST(Checks, RequireNamesTheParameterAndItsUnit) {
  EXPECT_NO_THROW(RequireFinitePositive("spring", "stiffness", 2.0, "[N/m]"));
  try {
    RequireFinitePositive("spring", "stiffness", kNan, "[N/m]");
    FAIL() << "NaN accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_STREQ(e.what(), "spring: stiffness must be finite and > 0 [N/m]");
  }
  EXPECT_THROW(RequireFiniteNonNegative("tool", "radius", -kInf), std::invalid_argument);
}

TEST(Checks, ToolPoseAcceptsAPoseAndNamesWhatIsWrongWithABadOne) {
  const double p[3] = {0.1, -0.2, 0.3};
  const double q[4] = {1.0, 0.0, 0.0, 0.0};
  EXPECT_EQ(CheckToolPose(p, q, 0.0), ToolPoseProblem::kNone);
  EXPECT_EQ(CheckToolPose(p, q, 1.0), ToolPoseProblem::kNone);

  const double at_limit[3] = {10.0, 0.0, 0.0};
  const double beyond[3] = {6.0, 6.0, 6.0};  // 10.4 m
  const double nan_p[3] = {0.0, kNan, 0.0};
  const double inf_p[3] = {0.0, 0.0, -kInf};
  const double huge_p[3] = {1e200, 0.0, 0.0};  // its square overflows
  EXPECT_EQ(CheckToolPose(at_limit, q, 0.5), ToolPoseProblem::kNone);
  EXPECT_EQ(CheckToolPose(beyond, q, 0.5), ToolPoseProblem::kPosition);
  EXPECT_EQ(CheckToolPose(nan_p, q, 0.5), ToolPoseProblem::kPosition);
  EXPECT_EQ(CheckToolPose(inf_p, q, 0.5), ToolPoseProblem::kPosition);
  EXPECT_EQ(CheckToolPose(huge_p, q, 0.5), ToolPoseProblem::kPosition);

  const double near_unit[4] = {1.0005, 0.0, 0.0, 0.0};
  const double not_unit[4] = {0.5, 0.5, 0.5, 0.0};  // |q| = 0.87
  const double zero_q[4] = {0.0, 0.0, 0.0, 0.0};
  const double nan_q[4] = {kNan, 0.0, 0.0, 1.0};
  EXPECT_EQ(CheckToolPose(p, near_unit, 0.5), ToolPoseProblem::kNone);
  EXPECT_EQ(CheckToolPose(p, not_unit, 0.5), ToolPoseProblem::kOrientation);
  EXPECT_EQ(CheckToolPose(p, zero_q, 0.5), ToolPoseProblem::kOrientation);
  EXPECT_EQ(CheckToolPose(p, nan_q, 0.5), ToolPoseProblem::kOrientation);

  EXPECT_EQ(CheckToolPose(p, q, -1e-9), ToolPoseProblem::kGrip);
  EXPECT_EQ(CheckToolPose(p, q, 1.0 + 1e-9), ToolPoseProblem::kGrip);
  EXPECT_EQ(CheckToolPose(p, q, kNan), ToolPoseProblem::kGrip);
  // The first problem is the one named.
  EXPECT_EQ(CheckToolPose(nan_p, nan_q, kNan), ToolPoseProblem::kPosition);
}

}  // namespace
}  // namespace somasim::checks
