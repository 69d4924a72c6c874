#include "common/mesh_io/obj_io.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <optional>
#include <random>
#include <string>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_io/mesh_error.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

using ::somasim::testing::BoxSurface;
using ::somasim::testing::BoxTets;
using ::somasim::testing::ErrorFrom;
using ::somasim::testing::SameMesh;
using ::somasim::testing::SharedMesh;
using ::somasim::testing::Slurp;
using ::somasim::testing::SquarePatch;
using ::somasim::testing::TestData;

MeshData Read(std::string_view text, const ReadOptions& options = {}) {
  return ReadObj(text, "test.obj", options);
}

// The error reading `text` raises (fails the test when there is none).
MeshError ErrorOf(std::string_view text, const ReadOptions& options = {}) {
  return ErrorFrom([&] { Read(text, options); }, text);
}

MeshData WithoutTets(MeshData mesh) {
  mesh.tetrahedra.resize(4, 0);
  return mesh;
}

TEST(ObjWriter, WritesVerticesAndOneBasedFaces) {
  const MeshData patch = SquarePatch(1);
  const std::string text = WriteObj(patch);
  EXPECT_NE(text.find("\nv 0.01 0 0\n"), std::string::npos) << text;
  EXPECT_NE(text.find("\nf 1 2 4\nf 1 4 3\n"), std::string::npos) << text;
}

TEST(ObjWriter, RoundTripIsBitExact) {
  // Box sides that are not binary fractions exercise the shortest round-trip formatting.
  MeshData awkward = BoxTets(3, 2, 2, 0.3, 0.7, 1.0 / 3.0);
  for (double& x : awkward.vertices.col(5)) x = std::nextafter(x, 2.0);
  for (const MeshData& mesh : {BoxSurface(3, 2, 2), SquarePatch(4), BoxTets(3, 2, 2), awkward}) {
    const MeshData read = Read(WriteObj(mesh));
    EXPECT_TRUE(SameMesh(WithoutTets(mesh), read, 0.0));
    EXPECT_EQ(read.tetrahedra.cols(), 0);
    EXPECT_TRUE(read.skipped.empty());
    EXPECT_EQ(read.format, "Wavefront OBJ");
    // And once more: what was read writes back to the same text.
    EXPECT_EQ(WriteObj(read), WriteObj(mesh));
  }
}

TEST(ObjReader, ScalesToMetres) {
  const MeshData mesh = Read("v 1 2 3\nv 4 5 6\nv 7 8 10\nf 1 2 3\n", {Unit::kCentimetre, false});
  EXPECT_DOUBLE_EQ(mesh.vertices(2, 2), 0.1);
}

// OBJ has no counts and no end marker: a file cut at a line boundary is a valid, shorter file,
// and a cut inside a number is a different number. So truncation cannot be detected; what is
// required is that every prefix either fails with MeshError or reads as a mesh whose nodes and
// triangles are those of the full file, except that the last node or the last triangle may
// differ (its final number was cut).
TEST(ObjReader, TruncationNeverCrashesAndYieldsAPrefix) {
  const MeshData full = Read(WriteObj(BoxSurface(1, 1, 1)));
  const std::string text = WriteObj(full);
  int refused = 0;
  for (size_t n = 0; n < text.size(); ++n) {
    MeshData part;
    try {
      part = Read(text.substr(0, n));
    } catch (const MeshError&) {
      ++refused;
      continue;
    }
    const Eigen::Index nodes = part.vertices.cols(), tris = part.triangles.cols();
    ASSERT_LE(nodes, full.vertices.cols()) << "prefix " << n;
    ASSERT_LE(tris, full.triangles.cols()) << "prefix " << n;
    const bool in_faces = tris > 0;  // the writer puts every v line before the f lines
    for (Eigen::Index i = 0; i < nodes - (in_faces ? 0 : 1); ++i) {
      ASSERT_EQ(part.vertices.col(i), full.vertices.col(i)) << "prefix " << n << " node " << i;
    }
    for (Eigen::Index t = 0; t + 1 < tris; ++t) {
      ASSERT_EQ(part.triangles.col(t), full.triangles.col(t)) << "prefix " << n;
    }
  }
  EXPECT_GT(refused, 0);  // e.g. "f 1 2" and "v 0 0"
}

TEST(ObjReader, RandomByteDamageOnlyRaisesMeshError) {
  const std::string text = WriteObj(BoxSurface(2, 1, 1));
  std::mt19937 rng(42);
  for (int trial = 0; trial < 3000; ++trial) {
    try {
      Read(testing::DamageBytes(text, 1 + trial % 4, &rng));
    } catch (const MeshError&) {
    }
  }
}

TEST(ObjReader, ReadsExporterStyleQuadsByFanTriangulation) {
  const MeshData mesh = ReadObj(Slurp(TestData("obj/cube_quads.obj")), "cube_quads.obj", {});
  EXPECT_EQ(mesh.vertices.cols(), 8);
  ASSERT_EQ(mesh.triangles.cols(), 12);
  EXPECT_EQ(mesh.triangles.col(0), Eigen::Vector3i(0, 3, 2));
  EXPECT_EQ(mesh.triangles.col(1), Eigen::Vector3i(0, 2, 1));
  // Fan-triangulated faces are kept, not dropped, so they are not in `skipped`.
  EXPECT_TRUE(mesh.skipped.empty());
  EXPECT_EQ(mesh.format,
            "Wavefront OBJ (6 polygon faces with more than 3 corners fan-triangulated into 12 "
            "triangles)");
  const mesh::SurfaceMesh surface{mesh.vertices, mesh.triangles};
  EXPECT_DOUBLE_EQ(mesh::SurfaceEnclosedVolume(surface), 1.0);
  EXPECT_TRUE(mesh::AnalyseSurfaceTopology(surface).watertight);
}

TEST(ObjReader, ReadsCrlfColoursRelativeIndicesContinuationsLinesAndPoints) {
  const MeshData mesh = ReadObj(Slurp(TestData("obj/dialects_crlf.obj")), "dialects.obj", {});
  ASSERT_EQ(mesh.vertices.cols(), 5);
  EXPECT_EQ(mesh.vertices.col(4), Eigen::Vector3d(-0.5, -0.5, -1.0));
  Eigen::Matrix<int32_t, 3, 5> expected;
  expected << 0, 0, 0, 1, 2,  //
      2, 1, 3, 2, 0,          //
      1, 3, 2, 3, 4;
  EXPECT_EQ(mesh.triangles, expected);
  ASSERT_EQ(mesh.skipped.size(), 2u);
  EXPECT_EQ(mesh.skipped[0].type, "polyline (OBJ l)");
  EXPECT_EQ(mesh.skipped[0].count, 1);
  EXPECT_EQ(mesh.skipped[1].type, "point (OBJ p)");
  EXPECT_EQ(mesh.skipped[1].count, 1);
}

TEST(ObjReader, IgnoresNonGeometryStatements) {
  const MeshData mesh = Read(
      "mtllib a.mtl\no thing\ng group\ns 1\nmg 1 2\nusemtl m\nusemap off\nmaplib x\nlod 1\n"
      "shadow_obj s.obj\ntrace_obj t.obj\nbevel off\nc_interp off\nd_interp off\n"
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nvp 0.5\ncstype bezier\ndeg 3\nstep 1\n"
      "f 1/1/1 2/1/1 3/1/1\n");
  EXPECT_EQ(mesh.triangles.cols(), 1);
}

TEST(ObjReader, RefusesFreeFormGeometry) {
  const MeshError e = ErrorOf(Slurp(TestData("obj/freeform_curve.obj")));
  EXPECT_EQ(e.kind(), MeshErrorKind::kUnsupported);
  EXPECT_EQ(e.where().line, 8);
  EXPECT_NE(e.fault().find("curv"), std::string::npos) << e.what();
  EXPECT_EQ(ErrorOf("v 0 0 0\nsurf 0 1 0 1 1 2 3 4\n").kind(), MeshErrorKind::kUnsupported);
}

TEST(ObjReader, RefusesUnknownStatementNamingIt) {
  const MeshError e = ErrorOf("v 0 0 0\nv 1 0 0\nv 0 1 0\nfoo 1 2\nf 1 2 3\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().line, 4);
  EXPECT_NE(e.fault().find("'foo'"), std::string::npos) << e.what();
  // Keywords are lower case.
  EXPECT_EQ(ErrorOf("V 0 0 0\n").kind(), MeshErrorKind::kSyntax);
}

TEST(ObjReader, RefusesIndexZero) {
  const MeshError e = ErrorOf("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.where().line, 4);
  EXPECT_NE(e.fault().find("index 0"), std::string::npos) << e.what();
  EXPECT_EQ(ErrorOf("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/0 2 3\n").kind(), MeshErrorKind::kIndex);
}

TEST(ObjReader, RefusesIndicesOutOfRange) {
  MeshError e = ErrorOf("v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 4\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.where().line, 5);
  e = ErrorOf("v 0 0 0\nv 1 0 0\nf -1 -2 -3\nv 0 1 0\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.where().line, 3);
  EXPECT_NE(e.fault().find("only 2"), std::string::npos) << e.what();
  EXPECT_EQ(ErrorOf("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999\n").kind(),
            MeshErrorKind::kIndex);
  EXPECT_EQ(ErrorOf("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -99999999999999\n").kind(),
            MeshErrorKind::kIndex);
  // Too large for int64 is not an index at all.
  EXPECT_EQ(ErrorOf("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n").kind(),
            MeshErrorKind::kSyntax);
}

TEST(ObjReader, RefusesNonFiniteCoordinates) {
  for (const char* bad : {"nan", "inf", "-inf", "1e999"}) {
    const MeshError e = ErrorOf(std::string("v 0 0 0\nv 1 0 ") + bad + "\nv 0 1 0\nf 1 2 3\n");
    EXPECT_EQ(e.kind(), MeshErrorKind::kValue) << bad;
    EXPECT_EQ(e.where().line, 2) << bad;
  }
}

TEST(ObjReader, RefusesMalformedStatements) {
  const char* cases[] = {
      "v 0 0\n",                                     // too few numbers
      "v 0 0 0 1 1\n",                               // 5 numbers
      "v 0 0 x\n",                                   // not a number
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n",          // two corners
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/2/3/4 2 3\n",  // too many slashes
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/ 2 3\n",       // empty texture index
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1// 2 3\n",      // empty normal index
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nf a 2 3\n",        // not an index
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1.5 2 3\n",      // not an integer
      "\x01\x02\xff garbage\n",
  };
  for (const char* text : cases) {
    EXPECT_EQ(ErrorOf(text).kind(), MeshErrorKind::kSyntax) << text;
  }
}

TEST(ObjReader, RefusesDegenerateTriangles) {
  MeshError e = ErrorOf("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
  EXPECT_EQ(e.where().line, 4);
  e = ErrorOf("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 2\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
}

TEST(ObjReader, FanTriangulatesConvexPolygonsOnly) {
  const std::string pentagon = "v 0 0 0\nv 2 0 0\nv 3 1 0\nv 1 2 0\nv -1 1 0\n";
  const MeshData mesh = Read(pentagon + "f 1 2 3 4 5\n");
  ASSERT_EQ(mesh.triangles.cols(), 3);
  EXPECT_EQ(mesh.triangles.col(2), Eigen::Vector3i(0, 3, 4));
  EXPECT_EQ(mesh.format,
            "Wavefront OBJ (1 polygon face with more than 3 corners fan-triangulated into 3 "
            "triangles)");
  // Clockwise is as convex as counter-clockwise.
  EXPECT_EQ(Read(pentagon + "f 5 4 3 2 1\n").triangles.cols(), 3);
  // A warped (non-planar) quad is split like a flat one.
  EXPECT_EQ(Read("v 0 0 0\nv 1 0 0.1\nv 1 1 0\nv 0 1 0.1\nf 1 2 3 4\n").triangles.cols(), 2);

  // A reflex corner: a fan from the first corner would fold over itself.
  MeshError e = ErrorOf("v 0 0 0\nv 2 0 0\nv 1 0.5 0\nv 2 2 0\nv 0 2 0\n\nf 1 2 3 4 5\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kUnsupported);
  EXPECT_EQ(e.where().line, 7);
  EXPECT_NE(e.fault().find("not convex"), std::string::npos) << e.what();
  // A pentagram turns the same way at every corner but winds around twice.
  e = ErrorOf(pentagon + "f 1 3 5 2 4\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kUnsupported) << e.what();
  // All corners on one line.
  e = ErrorOf("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3 4\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement) << e.what();
}

TEST(ObjReader, AcceptsCommentsBlankLinesAndTrailingContinuation) {
  const MeshData mesh =
      Read("# header\n\n   \nv 0 0 0 # origin\nv 1 0 0\nv 0 1 0\n#f 9 9 9\nf 1 2 3 \\");
  EXPECT_EQ(mesh.triangles.cols(), 1);
  EXPECT_THROW(Read(""), MeshError);  // no nodes: never what a user meant to load
}

TEST(ObjReader, ReadsSofaLiver) {
  const MeshData mesh = ReadObj(Slurp(SharedMesh("liver.obj")), "liver.obj", {});
  EXPECT_EQ(mesh.vertices.cols(), 181);
  // The last 42 vertices are referenced by no face (interior nodes of its twin liver.msh).
  EXPECT_EQ(mesh.triangles.cols(), 274);
  EXPECT_TRUE(mesh.skipped.empty());
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(mesh.vertices);
  EXPECT_NEAR(box.min.x(), -4.68, 0.01);
  EXPECT_NEAR(box.max.x(), 1.80, 0.01);
  EXPECT_NEAR(box.min.y(), 0.22, 0.01);
  EXPECT_NEAR(box.max.y(), 5.16, 0.01);
  EXPECT_NEAR(box.min.z(), -1.69, 0.01);
  EXPECT_NEAR(box.max.z(), 2.73, 0.01);
  const mesh::SurfaceTopology topology =
      mesh::AnalyseSurfaceTopology({mesh.vertices, mesh.triangles});
  EXPECT_TRUE(topology.watertight);
}

TEST(ObjReader, ReadsSofaSmoothLiver) {
  const MeshData mesh =
      ReadObj(Slurp(SharedMesh("liver-smooth.obj")), "liver-smooth.obj", {Unit::kCentimetre});
  EXPECT_EQ(mesh.vertices.cols(), 2194);
  EXPECT_EQ(mesh.triangles.cols(), 4384);
  EXPECT_TRUE(mesh.skipped.empty());
  // Read in centimetres, as the file's comment says: bounding box in metres.
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(mesh.vertices);
  EXPECT_NEAR(box.min.x(), -0.04658325, 1e-12);
  EXPECT_NEAR(box.max.x(), 0.0172803, 1e-12);
  EXPECT_NEAR(box.min.y(), 0.00264401, 1e-12);
  EXPECT_NEAR(box.max.y(), 0.05171952, 1e-12);
  EXPECT_NEAR(box.min.z(), -0.01673848, 1e-12);
  EXPECT_NEAR(box.max.z(), 0.02738287, 1e-12);
  EXPECT_TRUE(mesh::AnalyseSurfaceTopology({mesh.vertices, mesh.triangles}).watertight);
}

}  // namespace
}  // namespace somasim::mesh_io
