#include "common/mesh_io/mesh_builder.h"

#include <gtest/gtest.h>

#include <limits>

#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

// Builds the unit corner tet (positively oriented) with the given corner order.
MeshBuilder CornerTet(int a, int b, int c, int d) {
  MeshBuilder builder("t.vtk", "test");
  builder.AddNode(0, 0, 0, SourceLocation::Line(2));
  builder.AddNode(1, 0, 0, SourceLocation::Line(3));
  builder.AddNode(0, 1, 0, SourceLocation::Line(4));
  builder.AddNode(0, 0, 1, SourceLocation::Line(5));
  builder.AddTetrahedron(a, b, c, d, SourceLocation::Line(7));
  return builder;
}

MeshErrorKind KindOf(MeshBuilder builder, const ReadOptions& options = {}) {
  return ::somasim::testing::ErrorFrom([&] { builder.Finish(options); }).kind();
}

TEST(MeshBuilder, PositiveTetIsKept) {
  const MeshData m = CornerTet(0, 1, 2, 3).Finish({});
  EXPECT_EQ(m.vertices.cols(), 4);
  EXPECT_EQ(m.tetrahedra.cols(), 1);
  EXPECT_EQ(m.num_flipped, 0);
}

TEST(MeshBuilder, InvertedTetIsRefusedNamingItsLine) {
  try {
    CornerTet(0, 2, 1, 3).Finish({});
    FAIL();
  } catch (const MeshError& e) {
    EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
    EXPECT_EQ(e.where().line, 7);
    EXPECT_NE(std::string(e.what()).find("inverted"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("t.vtk:7"), std::string::npos) << e.what();
  }
}

TEST(MeshBuilder, FixOrientationFlipsInvertedTets) {
  ReadOptions options;
  options.fix_orientation = true;
  const MeshData m = CornerTet(0, 2, 1, 3).Finish(options);
  EXPECT_EQ(m.num_flipped, 1);
  const Eigen::Vector3d a = m.vertices.col(m.tetrahedra(0, 0)),
                        b = m.vertices.col(m.tetrahedra(1, 0)),
                        c = m.vertices.col(m.tetrahedra(2, 0)),
                        d = m.vertices.col(m.tetrahedra(3, 0));
  EXPECT_GT((b - a).dot((c - a).cross(d - a)), 0);
}

TEST(MeshBuilder, OutOfRangeAndRepeatedIndicesAreRefused) {
  EXPECT_EQ(KindOf(CornerTet(0, 1, 2, 4)), MeshErrorKind::kIndex);
  EXPECT_EQ(KindOf(CornerTet(0, 1, 1, 3)), MeshErrorKind::kElement);
  MeshBuilder b("x", "test");
  EXPECT_THROW(b.AddTriangle(-1, 0, 1, {}), MeshError);
  EXPECT_THROW(b.AddTetrahedron(0, 1, 2, int64_t{1} << 40, {}), MeshError);
}

TEST(MeshBuilder, FlatTetAndCollinearTriangleAreDegenerate) {
  MeshBuilder flat("f", "test");
  flat.AddNode(0, 0, 0, {});
  flat.AddNode(1, 0, 0, {});
  flat.AddNode(0, 1, 0, {});
  flat.AddNode(1, 1, 0, {});
  flat.AddTetrahedron(0, 1, 2, 3, SourceLocation::Line(9));
  EXPECT_EQ(KindOf(flat), MeshErrorKind::kElement);

  MeshBuilder line("l", "test");
  line.AddNode(0, 0, 0, {});
  line.AddNode(1, 0, 0, {});
  line.AddNode(2, 0, 0, {});
  line.AddTriangle(0, 1, 2, {});
  EXPECT_EQ(KindOf(line), MeshErrorKind::kElement);
}

TEST(MeshBuilder, NonFiniteCoordinateIsRefusedAtOnce) {
  MeshBuilder b("n.obj", "test");
  try {
    b.AddNode(0, std::numeric_limits<double>::quiet_NaN(), 0, SourceLocation::Line(12));
    FAIL();
  } catch (const MeshError& e) {
    EXPECT_EQ(e.kind(), MeshErrorKind::kValue);
    EXPECT_EQ(e.where().line, 12);
  }
  EXPECT_THROW(b.AddNode(std::numeric_limits<double>::infinity(), 0, 0, {}), MeshError);
}

TEST(MeshBuilder, UnitsScaleToMetres) {
  ReadOptions options;
  options.unit = Unit::kMillimetre;
  const MeshData m = CornerTet(0, 1, 2, 3).Finish(options);
  EXPECT_DOUBLE_EQ(m.vertices(0, 1), 0.001);
  options.unit = Unit::kCentimetre;
  EXPECT_DOUBLE_EQ(CornerTet(0, 1, 2, 3).Finish(options).vertices(2, 3), 0.01);
  EXPECT_EQ(ParseUnit("cm"), Unit::kCentimetre);
  EXPECT_FALSE(ParseUnit("inch").has_value());
}

TEST(MeshBuilder, SkippedKindsAreCountedTogether) {
  MeshBuilder b("s", "test");
  b.AddNode(0, 0, 0, {});
  b.Skip("line", 2);
  b.Skip("quad");
  b.Skip("line");
  const MeshData m = b.Finish({});
  ASSERT_EQ(m.skipped.size(), 2u);
  EXPECT_EQ(m.skipped[0].type, "line");
  EXPECT_EQ(m.skipped[0].count, 3);
  EXPECT_EQ(m.skipped[1].count, 1);
}

}  // namespace
}  // namespace somasim::mesh_io
