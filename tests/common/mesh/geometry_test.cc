#include "common/mesh/geometry.h"

#include <gtest/gtest.h>

#include <cmath>

#include "common/mesh/topology.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh {
namespace {

TEST(Geometry, UnitTetHasVolumeOneSixth) {
  const Eigen::Vector3d a(0, 0, 0), b(1, 0, 0), c(0, 1, 0), d(0, 0, 1);
  EXPECT_DOUBLE_EQ(TetSignedVolume(a, b, c, d), 1.0 / 6.0);
  EXPECT_DOUBLE_EQ(TetSignedVolume(a, c, b, d), -1.0 / 6.0);  // odd permutation flips the sign
}

TEST(Geometry, BoxTetVolumeEqualsBoxVolume) {
  const mesh_io::MeshData box = testing::BoxTets(3, 2, 4, 0.3, 0.2, 0.1);
  EXPECT_NEAR(TetMeshVolume({box.vertices, box.tetrahedra}), 0.3 * 0.2 * 0.1, 1e-15);
}

TEST(Geometry, BoundarySurfaceEnclosesTheVolumeOfItsTets) {
  const mesh_io::MeshData box = testing::BoxTets(4, 3, 2, 0.04, 0.03, 0.02);
  const SurfaceMesh surface = ExtractBoundarySurface({box.vertices, box.tetrahedra});
  EXPECT_NEAR(SurfaceEnclosedVolume(surface), 0.04 * 0.03 * 0.02, 1e-17);
  EXPECT_NEAR(SurfaceArea(surface), 2 * (0.04 * 0.03 + 0.04 * 0.02 + 0.03 * 0.02), 1e-15);
}

TEST(Geometry, EnclosedVolumeIsTranslationInvariant) {
  mesh_io::MeshData box = testing::BoxSurface(2, 2, 2);
  const double before = SurfaceEnclosedVolume({box.vertices, box.triangles});
  box.vertices.colwise() += Eigen::Vector3d(10.0, -5.0, 3.0);
  EXPECT_NEAR(SurfaceEnclosedVolume({box.vertices, box.triangles}), before, 1e-12);
}

TEST(Geometry, BoundingBoxCoversAllPoints) {
  Points p(3, 3);
  p << 0, -1, 2,  //
      5, 4, 3,    //
      -7, 8, 0;
  const BoundingBox box = ComputeBoundingBox(p);
  EXPECT_FALSE(box.empty);
  EXPECT_EQ(box.min, Eigen::Vector3d(-1, 3, -7));
  EXPECT_EQ(box.max, Eigen::Vector3d(2, 5, 8));
  EXPECT_TRUE(ComputeBoundingBox(Points(3, 0)).empty);
}

}  // namespace
}  // namespace somasim::mesh
