#include "common/mesh_gen/implicit.h"

#include <gtest/gtest.h>

namespace somasim::mesh_gen {
namespace {

using Eigen::Vector3d;

TEST(Implicit, SphereValueIsSignedDistance) {
  const Ellipsoid sphere(Vector3d(1, 2, 3), Vector3d::Constant(0.5));
  EXPECT_NEAR(sphere.Value(Vector3d(1, 2, 3)), -0.5, 1e-15);
  EXPECT_NEAR(sphere.Value(Vector3d(2, 2, 3)), 0.5, 1e-15);
  EXPECT_NEAR(ImplicitGradient(sphere, Vector3d(1, 2.7, 3)).y(), 1.0, 1e-8);
}

TEST(Implicit, ProjectionLandsOnTheSurface) {
  const Ellipsoid ellipsoid(Vector3d::Zero(), Vector3d(0.06, 0.03, 0.02));
  for (const Vector3d& p :
       {Vector3d(0.1, 0.01, 0.0), Vector3d(0.0, 0.001, 0.001), Vector3d(-0.02, -0.05, 0.04)}) {
    EXPECT_LT(std::abs(ellipsoid.Value(ProjectToSurface(ellipsoid, p))), 1e-9);
  }
}

TEST(Implicit, SegmentRootIsOnTheSurfaceAndTheSegment) {
  const Ellipsoid ellipsoid(Vector3d::Zero(), Vector3d(0.06, 0.03, 0.02));
  const Vector3d a(0.001, 0.002, -0.001);
  const Vector3d b(0.09, 0.05, 0.03);
  const Vector3d root = FindSegmentRoot(ellipsoid, a, b);
  EXPECT_LT(std::abs(ellipsoid.Value(root)), 1e-11);
  EXPECT_LT(((root - a).cross(b - a)).norm(), 1e-15);
  EXPECT_EQ(root, FindSegmentRoot(ellipsoid, a, b));
}

}  // namespace
}  // namespace somasim::mesh_gen
