#include "common/mesh_io/stl_io.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_error.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

using ::somasim::testing::BoxSurface;
using ::somasim::testing::BoxTets;
using ::somasim::testing::ErrorFrom;
using ::somasim::testing::SameMesh;
using ::somasim::testing::SameMeshUpToVertexOrder;
using ::somasim::testing::Slurp;
using ::somasim::testing::SquarePatch;
using ::somasim::testing::TestData;

MeshData Read(std::string_view bytes, const ReadOptions& options = {}) {
  return ReadStl(bytes, "test.stl", options);
}

MeshError ErrorOf(std::string_view bytes) {
  return ErrorFrom([&] { Read(bytes); }, bytes);
}

// The boundary surface of a box whose sides are not binary fractions, without unused vertices.
MeshData AwkwardSurface() {
  MeshData box = BoxTets(3, 2, 2, 0.3, 0.7, 1.0 / 3.0);
  std::vector<int32_t> map;
  const mesh::SurfaceMesh s = mesh::CompactSurface({box.vertices, box.triangles}, &map);
  box.vertices = s.vertices;
  box.triangles = s.triangles;
  box.tetrahedra.resize(4, 0);
  return box;
}

MeshData RoundedToFloat(MeshData mesh) {
  for (double& x : mesh.vertices.reshaped()) x = static_cast<double>(static_cast<float>(x));
  return mesh;
}

// The vertices of both meshes are the same set of points, bit for bit.
::testing::AssertionResult SameVertexSet(const MeshData& a, const MeshData& b) {
  const auto sorted = [](const MeshData& m) {
    std::vector<std::array<double, 3>> v;
    for (Eigen::Index i = 0; i < m.vertices.cols(); ++i) {
      v.push_back({m.vertices(0, i), m.vertices(1, i), m.vertices(2, i)});
    }
    std::sort(v.begin(), v.end());
    return v;
  };
  if (sorted(a) != sorted(b)) return ::testing::AssertionFailure() << "vertex sets differ";
  return ::testing::AssertionSuccess();
}

// A binary STL with the given header and facets (each 9 corner coordinates).
std::string BinaryStl(const std::string& header, const std::vector<std::array<float, 9>>& facets,
                      uint32_t count) {
  std::string out = header;
  out.resize(80, ' ');
  AppendBinary(&out, count, Endian::kLittle);
  for (const auto& f : facets) {
    for (int k = 0; k < 3; ++k) AppendBinary(&out, 0.0f, Endian::kLittle);
    for (float x : f) AppendBinary(&out, x, Endian::kLittle);
    AppendBinary(&out, uint16_t{0}, Endian::kLittle);
  }
  return out;
}

const std::string kTriangleAscii =
    "solid t\n"
    "facet normal 0 0 1\n"
    " outer loop\n"
    "  vertex 0 0 0\n"
    "  vertex 1 0 0\n"
    "  vertex 0 1 0\n"
    " endloop\n"
    "endfacet\n"
    "endsolid t\n";

TEST(StlWriter, AsciiComputesFacetNormals) {
  const std::string text = WriteStl(SquarePatch(1), Encoding::kAscii);
  EXPECT_EQ(
      text.rfind("solid somasim\n  facet normal 0 0 1\n    outer loop\n      vertex 0 0 0\n", 0),
      0u)
      << text;
  EXPECT_EQ(text.substr(text.size() - 17), "endsolid somasim\n");
}

TEST(StlWriter, BinaryLayout) {
  const MeshData box = BoxSurface(1, 1, 1);
  const std::string bytes = WriteStl(box, Encoding::kBinary);
  ASSERT_EQ(bytes.size(), 84 + 50 * 12u);
  EXPECT_EQ(bytes.substr(0, 8), std::string("somasim\0", 8));
  uint32_t count = 0;
  std::memcpy(&count, bytes.data() + 80, 4);  // little-endian host assumed by the test
  EXPECT_EQ(count, 12u);
  // The first facet's normal is the outward unit normal of the box face.
  float normal[3];
  std::memcpy(normal, bytes.data() + 84, sizeof normal);
  EXPECT_EQ(std::abs(normal[0]) + std::abs(normal[1]) + std::abs(normal[2]), 1.0f);
}

TEST(StlWriter, RefusesCoordinatesBeyondFloat32) {
  MeshData mesh = SquarePatch(1);
  mesh.vertices(0, 3) = 1e39;
  try {
    WriteStl(mesh, Encoding::kBinary);
    ADD_FAILURE() << "no error";
  } catch (const MeshError& e) {
    EXPECT_EQ(e.kind(), MeshErrorKind::kValue);
  }
  EXPECT_NO_THROW(WriteStl(mesh, Encoding::kAscii));
}

TEST(StlRoundTrip, AsciiIsExactUpToVertexOrder) {
  for (const MeshData& mesh : {BoxSurface(3, 2, 2), AwkwardSurface(), SquarePatch(3)}) {
    const MeshData read = Read(WriteStl(mesh, Encoding::kAscii));
    EXPECT_EQ(read.format, "STL ASCII");
    EXPECT_TRUE(SameMeshUpToVertexOrder(mesh, read, 1e-12));
    EXPECT_TRUE(SameVertexSet(mesh, read));
    // Vertices are now in order of first appearance: from here on nothing changes at all.
    EXPECT_TRUE(SameMesh(read, Read(WriteStl(read, Encoding::kAscii)), 0.0));
    EXPECT_EQ(WriteStl(read, Encoding::kAscii), WriteStl(mesh, Encoding::kAscii));
  }
}

TEST(StlRoundTrip, BinaryIsExactToFloat32) {
  for (const MeshData& mesh : {BoxSurface(3, 2, 2), AwkwardSurface(), SquarePatch(3)}) {
    const MeshData read = Read(WriteStl(mesh, Encoding::kBinary));
    EXPECT_EQ(read.format, "STL binary");
    const MeshData expected = RoundedToFloat(mesh);
    EXPECT_TRUE(SameMeshUpToVertexOrder(expected, read, 1e-12));
    EXPECT_TRUE(SameVertexSet(expected, read));
    EXPECT_TRUE(SameMesh(read, Read(WriteStl(read, Encoding::kBinary)), 0.0));
  }
}

TEST(StlRoundTrip, VolumeMeshTetrahedraAreNotWritten) {
  // The writer writes triangles only; WriteMeshFile passes the boundary of a volume mesh.
  const MeshData box = BoxTets(3, 2, 2);
  const MeshData read = Read(WriteStl(box, Encoding::kAscii));
  EXPECT_EQ(read.tetrahedra.cols(), 0);
  EXPECT_EQ(read.triangles.cols(), box.triangles.cols());
}

TEST(StlReader, EveryAsciiTruncationIsRefused) {
  const std::string text = WriteStl(BoxSurface(1, 1, 1), Encoding::kAscii);
  const MeshData full = Read(text);
  // Cutting into the name after the final 'endsolid' still leaves a complete file.
  const size_t complete = text.rfind("endsolid") + 8;
  for (size_t n = 0; n < text.size(); ++n) {
    if (n < complete) {
      EXPECT_THROW(Read(text.substr(0, n)), MeshError) << "prefix " << n;
    } else {
      EXPECT_TRUE(SameMesh(full, Read(text.substr(0, n)), 0.0)) << "prefix " << n;
    }
  }
}

TEST(StlReader, EveryBinaryTruncationIsRefused) {
  const std::string bytes = WriteStl(BoxSurface(1, 1, 1), Encoding::kBinary);
  for (size_t n = 0; n < bytes.size(); ++n) {
    EXPECT_THROW(Read(bytes.substr(0, n)), MeshError) << "prefix " << n;
  }
}

TEST(StlReader, RandomByteDamageOnlyRaisesMeshError) {
  for (Encoding encoding : {Encoding::kAscii, Encoding::kBinary}) {
    const std::string bytes = WriteStl(BoxSurface(2, 1, 1), encoding);
    std::mt19937 rng(7);
    for (int trial = 0; trial < 3000; ++trial) {
      try {
        Read(testing::DamageBytes(bytes, 1 + trial % 4, &rng));
      } catch (const MeshError&) {
      }
    }
  }
}

TEST(StlReader, BinaryWhoseHeaderStartsWithSolid) {
  const MeshData mesh = ReadStl(Slurp(TestData("stl/tetra_binary_solid_header.stl")), "t.stl", {});
  EXPECT_EQ(mesh.format, "STL binary");
  EXPECT_EQ(mesh.vertices.cols(), 4);
  EXPECT_EQ(mesh.triangles.cols(), 4);
  EXPECT_DOUBLE_EQ(mesh::SurfaceEnclosedVolume({mesh.vertices, mesh.triangles}), 1.0 / 6.0);
}

TEST(StlReader, AsciiWithSeveralSolidsMixedCaseAndCrlf) {
  const MeshData mesh = ReadStl(Slurp(TestData("stl/tetra_two_solids.stl")), "t.stl", {});
  EXPECT_EQ(mesh.format, "STL ASCII");
  // Corners are merged across the solids, numbered in order of first appearance.
  ASSERT_EQ(mesh.vertices.cols(), 4);
  Eigen::Matrix<int32_t, 3, 4> expected;
  expected << 0, 0, 0, 2,  //
      1, 2, 3, 1,          //
      2, 3, 1, 3;
  EXPECT_EQ(mesh.triangles, expected);
  EXPECT_EQ(mesh.vertices.col(1), Eigen::Vector3d(0, 1, 0));
  const mesh::SurfaceMesh surface{mesh.vertices, mesh.triangles};
  EXPECT_TRUE(mesh::AnalyseSurfaceTopology(surface).watertight);
  EXPECT_DOUBLE_EQ(mesh::SurfaceEnclosedVolume(surface), 1.0 / 6.0);
}

TEST(StlReader, MergesOnlyExactlyEqualCorners) {
  // -0 equals +0; a corner one ulp away is another node.
  const MeshData mesh = Read(
      "solid\n"
      "facet normal 0 0 0 outer loop vertex 0 0 0 vertex 1 0 0 vertex 0 1 0 endloop endfacet\n"
      "facet normal 0 0 0 outer loop vertex -0 0 -0 vertex 0 1 0 vertex 0 0 1 endloop endfacet\n"
      "facet normal 0 0 0 outer loop vertex 1.0000000000000002 0 0 vertex 0 1 0 vertex 0 0 1 "
      "endloop endfacet\n"
      "endsolid\n");
  EXPECT_EQ(mesh.vertices.cols(), 5);
  EXPECT_EQ(mesh.triangles.col(1), Eigen::Vector3i(0, 2, 3));
  EXPECT_EQ(mesh.triangles.col(2), Eigen::Vector3i(4, 2, 3));
}

// Well-formed but empty solids are refused: a mesh with no nodes is never what a user meant.
TEST(StlReader, EmptySolidsAreRefused) {
  EXPECT_NE(ErrorOf("solid empty\nendsolid empty\n").fault().find("holds no nodes"),
            std::string::npos);
  EXPECT_NE(ErrorOf(BinaryStl("empty", {}, 0)).fault().find("holds no nodes"), std::string::npos);
}

TEST(StlReader, RefusesFilesThatAreNeitherBinaryNorAscii) {
  std::string bytes = BinaryStl("some header", {}, 12);
  bytes.resize(600, '\x01');
  MeshError e = ErrorOf(bytes);
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().byte, 0);
  EXPECT_NE(e.fault().find("does not start with 'solid'"), std::string::npos) << e.what();
  EXPECT_NE(e.fault().find("12 triangles (the count in its header) needs 684 bytes, but the "
                           "file has 600"),
            std::string::npos)
      << e.what();

  e = ErrorOf("hello");
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_NE(e.fault().find("shorter than the 84-byte header"), std::string::npos) << e.what();
  EXPECT_EQ(ErrorOf("").kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf("solidity is a virtue").kind(), MeshErrorKind::kSyntax);
}

TEST(StlReader, ExplainsABrokenBinaryFileWhoseHeaderSaysSolid) {
  std::string bytes = BinaryStl("solid by some CAD tool", {{0, 0, 0, 1, 0, 0, 0, 1, 0}}, 1);
  bytes.pop_back();
  const MeshError e = ErrorOf(bytes);
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_NE(e.fault().find("needs 134 bytes, but the file has 133"), std::string::npos) << e.what();
}

TEST(StlReader, AbsurdTriangleCountFailsFast) {
  // 2^32 - 1 triangles claimed in a 134-byte file: not binary (size), not ASCII.
  std::string bytes = BinaryStl("x", {{0, 0, 0, 1, 0, 0, 0, 1, 0}}, 0xFFFFFFFFu);
  const MeshError e = ErrorOf(bytes);
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_NE(e.fault().find("needs 214748364834 bytes"), std::string::npos) << e.what();
}

TEST(StlReader, RefusesFacetsThatAreNotTriangles) {
  MeshError e = ErrorOf(
      "solid\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nendloop\nendfacet\n"
      "endsolid\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().line, 2);
  EXPECT_NE(e.fault().find("2 vertices"), std::string::npos) << e.what();
  e = ErrorOf(
      "solid\n\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 1 1 0\n"
      "vertex 0 1 0\nendloop\nendfacet\nendsolid\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().line, 3);
}

TEST(StlReader, RefusesUnknownKeywordsNamingThem) {
  std::string text = kTriangleAscii;
  text.replace(text.find("outer loop"), 10, "outer lop");
  MeshError e = ErrorOf(text);
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().line, 3);
  EXPECT_NE(e.fault().find("'lop'"), std::string::npos) << e.what();
  e = ErrorOf(kTriangleAscii + "trailing words\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().line, 10);
  text = kTriangleAscii;
  text.replace(text.find("vertex 1 0 0"), 12, "vertex 1 zero 0");
  EXPECT_EQ(ErrorOf(text).kind(), MeshErrorKind::kSyntax);
}

TEST(StlReader, RefusesNonFiniteCoordinates) {
  std::string text = kTriangleAscii;
  text.replace(text.find("vertex 1 0 0"), 12, "vertex 1 nan 0");
  MeshError e = ErrorOf(text);
  EXPECT_EQ(e.kind(), MeshErrorKind::kValue);
  EXPECT_EQ(e.where().line, 5);

  const float inf = std::numeric_limits<float>::infinity();
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (float bad : {inf, -inf, nan}) {
    const std::string bytes =
        BinaryStl("x", {{0, 0, 0, 1, 0, 0, 0, 1, 0}, {0, 0, 0, 1, 0, 0, 0, bad, 1}}, 2);
    e = ErrorOf(bytes);
    EXPECT_EQ(e.kind(), MeshErrorKind::kValue);
    EXPECT_EQ(e.where().byte, 84 + 50);  // the second facet
  }
}

TEST(StlReader, RefusesDegenerateFacets) {
  const std::string bytes =
      BinaryStl("x", {{0, 0, 0, 1, 0, 0, 0, 1, 0}, {0, 0, 0, 1, 0, 0, 2, 0, 0}}, 2);
  const MeshError e = ErrorOf(bytes);
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
  EXPECT_EQ(e.where().byte, 84 + 50);
  std::string text = kTriangleAscii;
  text.replace(text.find("vertex 0 1 0"), 12, "vertex 0 0 0");
  EXPECT_EQ(ErrorOf(text).kind(), MeshErrorKind::kElement);
}

TEST(StlReader, ScalesToMetres) {
  const MeshData mesh = Read(kTriangleAscii, {Unit::kMillimetre, false});
  EXPECT_DOUBLE_EQ(mesh.vertices(0, 1), 0.001);
}

}  // namespace
}  // namespace somasim::mesh_io
