#include "common/mesh/quality.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh {
namespace {

TEST(TetQuality, RegularTetHasAspectOneAndArccosThirdDihedrals) {
  const mesh_io::MeshData tet = testing::RegularTet(0.01);
  const auto x = [&](int k) { return Eigen::Vector3d(tet.vertices.col(tet.tetrahedra(k, 0))); };
  const TetQuality q = ComputeTetQuality(x(0), x(1), x(2), x(3));
  const double dihedral = std::acos(1.0 / 3.0) * 180.0 / std::numbers::pi;  // 70.5288°
  EXPECT_NEAR(q.aspect_ratio, 1.0, 1e-12);
  EXPECT_NEAR(q.min_dihedral_deg, dihedral, 1e-9);
  EXPECT_NEAR(q.max_dihedral_deg, dihedral, 1e-9);
  EXPECT_NEAR(q.signed_volume, std::pow(0.01, 3) / (6 * std::sqrt(2.0)), 1e-20);
  EXPECT_NEAR(TetNormalisedVolume(x(0), x(1), x(2), x(3)), 1 / std::sqrt(2.0), 1e-12);
}

TEST(TetQuality, CornerTetHasRightAndSixtyDegreeDihedrals) {
  // The corner tet of the unit cube: three right dihedral angles at the origin's edges and
  // three of arccos(1/√3) = 54.7356° along the slanted face.
  const TetQuality q = ComputeTetQuality({0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1});
  EXPECT_NEAR(q.max_dihedral_deg, 90.0, 1e-9);
  EXPECT_NEAR(q.min_dihedral_deg, std::acos(1 / std::sqrt(3.0)) * 180 / std::numbers::pi, 1e-9);
  EXPECT_GT(q.aspect_ratio, 1.0);
}

TEST(TetQuality, QualityIsScaleInvariant) {
  const Eigen::Vector3d a(0.1, 0.2, 0.3), b(1.1, 0.0, 0.4), c(0.3, 0.9, 0.1), d(0.2, 0.4, 1.5);
  const TetQuality q1 = ComputeTetQuality(a, b, c, d);
  const TetQuality q2 = ComputeTetQuality(a * 1e-3, b * 1e-3, c * 1e-3, d * 1e-3);
  EXPECT_NEAR(q1.aspect_ratio, q2.aspect_ratio, 1e-9);
  EXPECT_NEAR(q1.min_dihedral_deg, q2.min_dihedral_deg, 1e-9);
  EXPECT_NEAR(q1.max_dihedral_deg, q2.max_dihedral_deg, 1e-9);
  EXPECT_NEAR(q2.signed_volume, q1.signed_volume * 1e-9, 1e-15);
}

TEST(TetQuality, FlatTetIsDegenerateAndSwappedTetIsInverted) {
  mesh_io::MeshData box = testing::BoxTets(2, 2, 2);
  std::swap(box.tetrahedra(2, 3), box.tetrahedra(3, 3));            // invert one
  box.vertices.col(box.vertices.cols() - 1) = box.vertices.col(0);  // no effect on flatness
  QualitySummary s = SummariseQuality({box.vertices, box.tetrahedra});
  EXPECT_EQ(s.num_tets, 48);
  EXPECT_GE(s.num_inverted, 1);

  const mesh_io::MeshData ok = testing::BoxTets(2, 2, 2);
  s = SummariseQuality({ok.vertices, ok.tetrahedra});
  EXPECT_EQ(s.num_inverted, 0);
  EXPECT_EQ(s.num_degenerate, 0);
  EXPECT_NEAR(s.min_volume, 1.0 / 8 / 6, 1e-15);
  EXPECT_LT(TetNormalisedVolume({0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {1, 1, 1e-14}),
            kDegenerateTetNormalisedVolume);
}

}  // namespace
}  // namespace somasim::mesh
