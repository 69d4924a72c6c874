// The cut's geometry: which segments cross a blade's swept quad.
#include "server/models/cut_geometry.h"

#include <gtest/gtest.h>

#include <random>

namespace somasim::models {
namespace {

using Eigen::Vector3d;

// A blade from z = 0.01 down to z = -0.01 along x = 0, moved along y from 0 to 0.02: the sweep
// is the part of the plane x = 0 with y in [0, 0.02] and z in [-0.01, 0.01].
SweptQuad Blade() {
  SweptQuad sweep;
  sweep.p0 = Vector3d(0.0, 0.0, 0.01);
  sweep.q0 = Vector3d(0.0, 0.0, -0.01);
  sweep.p1 = Vector3d(0.0, 0.02, 0.01);
  sweep.q1 = Vector3d(0.0, 0.02, -0.01);
  return sweep;
}

TEST(CutGeometry, SegmentsCrossingThePlaneInsideTheQuadAreCut) {
  const SweptQuad sweep = Blade();
  EXPECT_TRUE(SegmentCrossesSweep(Vector3d(-0.001, 0.01, 0.0), Vector3d(0.001, 0.01, 0.0), sweep));
  EXPECT_TRUE(
      SegmentCrossesSweep(Vector3d(0.003, 0.005, 0.008), Vector3d(-0.001, 0.015, -0.009), sweep));
  // Beyond the blade's reach (z), before its start (y < 0), or not reaching the plane.
  EXPECT_FALSE(
      SegmentCrossesSweep(Vector3d(-0.001, 0.01, 0.02), Vector3d(0.001, 0.01, 0.02), sweep));
  EXPECT_FALSE(
      SegmentCrossesSweep(Vector3d(-0.001, -0.01, 0.0), Vector3d(0.001, -0.01, 0.0), sweep));
  EXPECT_FALSE(SegmentCrossesSweep(Vector3d(0.001, 0.01, 0.0), Vector3d(0.003, 0.01, 0.0), sweep));
  // In the plane of the sweep: separates nothing.
  EXPECT_FALSE(SegmentCrossesSweep(Vector3d(0.0, 0.005, 0.0), Vector3d(0.0, 0.015, 0.0), sweep));
}

TEST(CutGeometry, AgreesWithThePlaneCrossingOfRandomSegments) {
  // For the planar sweep, a segment crosses iff its ends are on opposite sides of x = 0 and the
  // crossing point lies in the rectangle.
  const SweptQuad sweep = Blade();
  std::mt19937 random(11);
  std::uniform_real_distribution<double> coordinate(-0.03, 0.03);
  int crossings = 0;
  for (int trial = 0; trial < 2000; ++trial) {
    const Vector3d a(coordinate(random), coordinate(random), coordinate(random));
    const Vector3d b(coordinate(random), coordinate(random), coordinate(random));
    bool expected = false;
    if (a.x() * b.x() < 0.0) {
      const double s = a.x() / (a.x() - b.x());
      const Vector3d c = a + s * (b - a);
      expected = c.y() >= 0.0 && c.y() <= 0.02 && c.z() >= -0.01 && c.z() <= 0.01;
    }
    crossings += expected ? 1 : 0;
    EXPECT_EQ(SegmentCrossesSweep(a, b, sweep), expected) << "trial " << trial;
  }
  EXPECT_GT(crossings, 50);
}

TEST(CutGeometry, ABladeThatDidNotMoveCutsNothing) {
  SweptQuad still = Blade();
  still.p1 = still.p0;
  still.q1 = still.q0;
  EXPECT_FALSE(SegmentCrossesSweep(Vector3d(-0.001, 0.0, 0.0), Vector3d(0.001, 0.0, 0.0), still));
}

}  // namespace
}  // namespace somasim::models
