// Tests of the Gmsh .msh reader and writer: versions 1, 2.2 and 4.1, ASCII and binary.
#include "common/mesh_io/gmsh_io.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_error.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

using ::somasim::testing::BoxSurface;
using ::somasim::testing::BoxTets;
using ::somasim::testing::Contains;
using ::somasim::testing::ErrorFrom;
using ::somasim::testing::RegularTet;
using ::somasim::testing::Replace;
using ::somasim::testing::SameMesh;
using ::somasim::testing::SharedMesh;
using ::somasim::testing::Slurp;
using ::somasim::testing::SquarePatch;
using ::somasim::testing::TestData;

struct Variant {
  GmshVersion version;
  Encoding encoding;
  const char* format;  // MeshData::format of the file read back
};

constexpr Variant kVariants[] = {
    {GmshVersion::kV1, Encoding::kAscii, "Gmsh 1"},
    {GmshVersion::kV22, Encoding::kAscii, "Gmsh 2.2 ASCII"},
    {GmshVersion::kV22, Encoding::kBinary, "Gmsh 2.2 binary"},
    {GmshVersion::kV41, Encoding::kAscii, "Gmsh 4.1 ASCII"},
    {GmshVersion::kV41, Encoding::kBinary, "Gmsh 4.1 binary"},
};

MeshData Read(std::string_view bytes, const ReadOptions& options = {}) {
  return ReadGmsh(bytes, "test.msh", options);
}

// The MeshError that reading `bytes` throws; fails the test when it reads.
MeshError ReadError(std::string_view bytes, const ReadOptions& options = {}) {
  return ErrorFrom([&] { Read(bytes, options); }, bytes);
}

#define EXPECT_FAULT(error, expected_kind, part)                          \
  do {                                                                    \
    const MeshError& e_ = (error);                                        \
    EXPECT_EQ(e_.kind(), (expected_kind)) << e_.what();                   \
    EXPECT_TRUE(Contains(e_.fault(), (part))) << "fault: " << e_.fault(); \
  } while (false)

// A small version 2.2 ASCII file: a positively oriented tetrahedron and one of its faces.
constexpr std::string_view kSmall22 =
    "$MeshFormat\n"
    "2.2 0 8\n"
    "$EndMeshFormat\n"
    "$Nodes\n"
    "4\n"
    "1 0 0 0\n"
    "2 1 0 0\n"
    "3 0 1 0\n"
    "4 0 0 1\n"
    "$EndNodes\n"
    "$Elements\n"
    "2\n"
    "1 4 2 1 1 1 2 3 4\n"
    "2 2 2 1 1 1 3 2\n"
    "$EndElements\n";

// The same mesh as version 1 and 4.1 ASCII.
constexpr std::string_view kSmall1 =
    "$NOD\n"
    "4\n"
    "1 0 0 0\n"
    "2 1 0 0\n"
    "3 0 1 0\n"
    "4 0 0 1\n"
    "$ENDNOD\n"
    "$ELM\n"
    "2\n"
    "1 4 1 1 4 1 2 3 4\n"
    "2 2 1 1 3 1 3 2\n"
    "$ENDELM\n";

constexpr std::string_view kSmall41 =
    "$MeshFormat\n"
    "4.1 0 8\n"
    "$EndMeshFormat\n"
    "$Entities\n"
    "0 0 1 1\n"
    "1 0 0 0 1 1 1 0 0\n"
    "1 0 0 0 1 1 1 0 1 1\n"
    "$EndEntities\n"
    "$Nodes\n"
    "1 4 1 4\n"
    "3 1 0 4\n"
    "1\n"
    "2\n"
    "3\n"
    "4\n"
    "0 0 0\n"
    "1 0 0\n"
    "0 1 0\n"
    "0 0 1\n"
    "$EndNodes\n"
    "$Elements\n"
    "2 2 1 2\n"
    "3 1 4 1\n"
    "1 1 2 3 4\n"
    "2 1 2 1\n"
    "2 1 3 2\n"
    "$EndElements\n";

void ExpectSmallMesh(const MeshData& m) {
  ASSERT_EQ(m.vertices.cols(), 4);
  ASSERT_EQ(m.tetrahedra.cols(), 1);
  ASSERT_EQ(m.triangles.cols(), 1);
  EXPECT_EQ(m.tetrahedra.col(0), Eigen::Vector4i(0, 1, 2, 3));
  EXPECT_EQ(m.triangles.col(0), Eigen::Vector3i(0, 2, 1));
  EXPECT_EQ(m.vertices.col(1), Eigen::Vector3d(1, 0, 0));
  EXPECT_TRUE(m.skipped.empty());
}

// ---------------------------------------------------------------------------------------------
// Round trips

TEST(GmshWriter, RoundTripIsBitExactInEveryVersionAndEncoding) {
  // Coordinates that need all 17 digits, to catch any rounding.
  MeshData box = BoxTets(3, 2, 2, 0.1, 1.0 / 3.0, std::sqrt(2.0));
  box.vertices(0, 5) += 1e-17 * 0.3;
  for (const MeshData& mesh : {box, BoxSurface(2, 2, 1), SquarePatch(3), RegularTet(0.07)}) {
    for (const Variant& v : kVariants) {
      SCOPED_TRACE(v.format);
      const std::string bytes = WriteGmsh(mesh, v.version, v.encoding);
      const MeshData back = Read(bytes);
      EXPECT_EQ(back.format, v.format);
      EXPECT_TRUE(SameMesh(mesh, back, 0.0));
      EXPECT_TRUE(back.skipped.empty());
      EXPECT_EQ(WriteGmsh(back, v.version, v.encoding), bytes) << "second write differs";
    }
  }
}

// A well-formed file with no nodes is written, but reading refuses it (MeshBuilder's rule).
TEST(GmshWriter, EmptyMeshIsWrittenButRefusedOnRead) {
  const MeshData empty;
  for (const Variant& v : kVariants) {
    SCOPED_TRACE(v.format);
    try {
      Read(WriteGmsh(empty, v.version, v.encoding));
      ADD_FAILURE() << "accepted";
    } catch (const MeshError& e) {
      EXPECT_NE(e.fault().find("holds no nodes"), std::string::npos) << e.what();
    }
  }
}

TEST(GmshWriter, BinaryVersion1IsUnsupported) {
  try {
    WriteGmsh(RegularTet(), GmshVersion::kV1, Encoding::kBinary);
    FAIL() << "no error";
  } catch (const MeshError& e) {
    EXPECT_EQ(e.kind(), MeshErrorKind::kUnsupported);
  }
}

TEST(GmshWriter, RefusesIndexOutOfRange) {
  MeshData mesh = RegularTet();
  mesh.tetrahedra(3, 0) = 4;
  try {
    WriteGmsh(mesh, GmshVersion::kV41, Encoding::kAscii);
    FAIL() << "no error";
  } catch (const MeshError& e) {
    EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  }
}

TEST(GmshWriter, Version41HasEntitiesForEveryBlock) {
  const std::string text = WriteGmsh(BoxTets(1, 1, 1), GmshVersion::kV41, Encoding::kAscii);
  // No points or curves, one surface and one volume, each with its bounding box.
  EXPECT_TRUE(Contains(text, "$Entities\n0 0 1 1\n1 0 0 0 1 1 1 0 0\n1 0 0 0 1 1 1 0 0\n")) << text;
  EXPECT_TRUE(Contains(text, "$Nodes\n1 8 1 8\n3 1 0 8\n1\n2\n")) << text;
  // Tetrahedra first (volume 1), then triangles (surface 1), tagged 1.. in that order.
  EXPECT_TRUE(Contains(text, "$Elements\n2 18 1 18\n3 1 4 6\n1 ")) << text;
  EXPECT_TRUE(Contains(text, "2 1 2 12\n7 ")) << text;
}

TEST(GmshWriter, SurfaceOnlyVersion41PutsNodesOnTheSurface) {
  const std::string text = WriteGmsh(SquarePatch(1), GmshVersion::kV41, Encoding::kAscii);
  EXPECT_TRUE(Contains(text, "$Entities\n0 0 1 0\n")) << text;
  EXPECT_TRUE(Contains(text, "$Nodes\n1 4 1 4\n2 1 0 4\n")) << text;
}

// ---------------------------------------------------------------------------------------------
// Truncation

// Every prefix of a written file is refused, except those that only drop trailing whitespace:
// every section has an end marker and binary data sits between counts and markers.
TEST(GmshReader, RefusesEveryTruncation) {
  MeshData mesh = BoxTets(1, 1, 1);
  for (const Variant& v : kVariants) {
    SCOPED_TRACE(v.format);
    const std::string bytes = WriteGmsh(mesh, v.version, v.encoding);
    for (size_t length = 0; length < bytes.size(); ++length) {
      const std::string_view rest = std::string_view(bytes).substr(length);
      if (rest.find_first_not_of(" \t\r\n") == std::string_view::npos) continue;
      try {
        Read(std::string_view(bytes).substr(0, length));
        ADD_FAILURE() << "prefix of " << length << " of " << bytes.size() << " bytes was read";
      } catch (const MeshError&) {
      }
    }
  }
}

// ---------------------------------------------------------------------------------------------
// The three versions' ASCII forms

TEST(GmshReader, ReadsSmallFilesOfEveryVersion) {
  for (const std::string_view text : {kSmall1, kSmall22, kSmall41}) {
    SCOPED_TRACE(text.substr(0, 20));
    ExpectSmallMesh(Read(text));
  }
  EXPECT_EQ(Read(kSmall1).format, "Gmsh 1");
  EXPECT_EQ(Read(kSmall22).format, "Gmsh 2.2 ASCII");
  EXPECT_EQ(Read(kSmall41).format, "Gmsh 4.1 ASCII");
}

TEST(GmshReader, ReadsVersions20And21AsVersion2) {
  EXPECT_EQ(Read(Replace(std::string(kSmall22), "2.2 0 8", "2.1 0 8")).format, "Gmsh 2.1 ASCII");
  EXPECT_EQ(Read(Replace(std::string(kSmall22), "2.2 0 8", "2 0 8")).format, "Gmsh 2.0 ASCII");
}

TEST(GmshReader, AppliesTheUnit) {
  ReadOptions options;
  options.unit = Unit::kMillimetre;
  const MeshData m = Read(kSmall22, options);
  EXPECT_DOUBLE_EQ(m.vertices(0, 1), 0.001);
}

TEST(GmshReader, MapsSparseUnorderedNodeIds) {
  const std::string text =
      "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n4\n"
      "40 0 0 0\n7 1 0 0\n1000000000000 0 1 0\n3 0 0 1\n$EndNodes\n"
      "$Elements\n1\n9 4 0 40 7 1000000000000 3\n$EndElements\n";
  const MeshData m = Read(text);
  ASSERT_EQ(m.tetrahedra.cols(), 1);
  EXPECT_EQ(m.tetrahedra.col(0), Eigen::Vector4i(0, 1, 2, 3));
  EXPECT_EQ(m.vertices.col(2), Eigen::Vector3d(0, 1, 0));
}

TEST(GmshReader, SkipsAndCountsOtherElementTypes) {
  const std::string text =
      "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n8\n"
      "1 0 0 0\n2 1 0 0\n3 1 1 0\n4 0 1 0\n5 0 0 1\n6 1 0 1\n7 1 1 1\n"
      "8 0 1 1\n$EndNodes\n$Elements\n7\n"
      "1 15 2 0 1 1\n"
      "2 1 2 0 1 1 2\n"
      "3 1 2 0 1 2 3\n"
      "4 3 2 0 1 1 2 3 4\n"
      "5 5 2 0 1 1 2 3 4 5 6 7 8\n"
      "6 2 2 0 1 1 2 3\n"
      "7 9 2 0 1 1 2 3 4 5 6\n"
      "$EndElements\n";
  const MeshData m = Read(text);
  EXPECT_EQ(m.triangles.cols(), 1);
  EXPECT_EQ(m.tetrahedra.cols(), 0);
  ASSERT_EQ(m.skipped.size(), 5u);
  EXPECT_EQ(m.skipped[0].type, "point");
  EXPECT_EQ(m.skipped[0].count, 1);
  EXPECT_EQ(m.skipped[1].type, "line");
  EXPECT_EQ(m.skipped[1].count, 2);
  EXPECT_EQ(m.skipped[2].type, "quadrangle");
  EXPECT_EQ(m.skipped[3].type, "hexahedron");
  EXPECT_EQ(m.skipped[4].type, "triangle (6 nodes)");
}

TEST(GmshReader, SkipsNonMeshSections) {
  std::string text(kSmall22);
  text +=
      "$NodeData\n1\n\"u\"\n1\n0\n3\n0\n1\n4\n1 0\n2 0\n3 0\n4 0\n$EndNodeData\n"
      "$Periodic\n0\n$EndPeriodic\n";
  text = Replace(text, "$Nodes",
                 "$PhysicalNames\n1\n3 1 \"a $EndPhysical name\"\n$EndPhysicalNames\n$Nodes");
  ExpectSmallMesh(Read(text));
}

TEST(GmshReader, ReadsVersion41ParametricNodesAndSparseTags) {
  const std::string text =
      "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n"
      "$Nodes\n3 4 2 90\n"
      "0 1 1 1\n90\n0 0 0\n"
      "1 1 1 1\n2\n1 0 0 0.5\n"
      "2 1 1 2\n50\n3\n0 1 0 0.1 0.2\n0 0 1 0.3 0.4\n"
      "$EndNodes\n"
      "$Elements\n1 1 1 1\n3 1 4 1\n1 90 2 50 3\n$EndElements\n";
  const MeshData m = Read(text);
  ASSERT_EQ(m.vertices.cols(), 4);
  EXPECT_EQ(m.vertices.col(3), Eigen::Vector3d(0, 0, 1));
  ASSERT_EQ(m.tetrahedra.cols(), 1);
  EXPECT_EQ(m.tetrahedra.col(0), Eigen::Vector4i(0, 1, 2, 3));
}

// ---------------------------------------------------------------------------------------------
// Binary

// A version 2.2 binary file of the small mesh in the given byte order, built by hand.
std::string Binary22(Endian endian) {
  std::string out = "$MeshFormat\n2.2 1 8\n";
  AppendBinary(&out, int32_t{1}, endian);
  out += "\n$EndMeshFormat\n$Nodes\n4\n";
  const double xyz[4][3] = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
  for (int32_t i = 0; i < 4; ++i) {
    AppendBinary(&out, i + 1, endian);
    for (const double c : xyz[i]) AppendBinary(&out, c, endian);
  }
  out += "\n$EndNodes\n$Elements\n2\n";
  for (const int32_t v : {4, 1, 1, /* element */ 1, 7, 1, 2, 3, 4}) AppendBinary(&out, v, endian);
  for (const int32_t v : {2, 1, 0, /* element */ 2, 1, 3, 2}) AppendBinary(&out, v, endian);
  out += "\n$EndElements\n";
  return out;
}

TEST(GmshReader, ReadsBinaryInBothByteOrders) {
  ExpectSmallMesh(Read(Binary22(Endian::kLittle)));
  ExpectSmallMesh(Read(Binary22(Endian::kBig)));
}

TEST(GmshReader, RefusesBinaryWithWrongDataSizeOrByteOrderMark) {
  std::string bytes = Binary22(Endian::kLittle);
  EXPECT_FAULT(ReadError(Replace(bytes, "2.2 1 8", "2.2 1 4")), MeshErrorKind::kUnsupported,
               "data size 4");
  bytes[20] = 2;  // the byte-order mark
  EXPECT_FAULT(ReadError(bytes), MeshErrorKind::kSyntax, "byte-order mark");
}

TEST(GmshReader, RefusesBinaryElementBlockLongerThanAnnounced) {
  std::string bytes = Binary22(Endian::kLittle);
  // The tetrahedron block claims both elements; the triangle block header then has no room.
  const size_t block = bytes.find("$Elements\n2\n") + std::string("$Elements\n2\n").size();
  bytes[block + 4] = 3;
  EXPECT_FAULT(ReadError(bytes), MeshErrorKind::kCount, "3 elements but only 2");
}

// ---------------------------------------------------------------------------------------------
// Faults

TEST(GmshReader, RefusesNonFiniteCoordinates) {
  for (const char* bad : {"nan", "inf", "-inf", "1e999"}) {
    const MeshError e =
        ReadError(Replace(std::string(kSmall22), "3 0 1 0", std::string("3 0 ") + bad + " 0"));
    EXPECT_FAULT(e, MeshErrorKind::kValue, "node 3");
    EXPECT_EQ(e.where().line, 8) << bad;
  }
}

TEST(GmshReader, RefusesUnknownNodeIdNamingElementAndNode) {
  const MeshError e =
      ReadError(Replace(std::string(kSmall22), "1 4 2 1 1 1 2 3 4", "1 4 2 1 1 1 2 3 99"));
  EXPECT_FAULT(e, MeshErrorKind::kIndex, "element 1 refers to node id 99");
  EXPECT_EQ(e.where().line, 13);
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall1), "2 2 1 1 3 1 3 2", "2 2 1 1 3 1 3 0")),
               MeshErrorKind::kIndex, "element 2 refers to node id 0, which $NOD does not define");
}

TEST(GmshReader, RefusesDuplicatedIds) {
  MeshError e = ReadError(Replace(std::string(kSmall22), "3 0 1 0", "2 0 1 0"));
  EXPECT_FAULT(e, MeshErrorKind::kIndex, "node id 2 is duplicated (first on line 7)");
  EXPECT_EQ(e.where().line, 8);
  e = ReadError(Replace(std::string(kSmall22), "2 2 2 1 1", "1 2 2 1 1"));
  EXPECT_FAULT(e, MeshErrorKind::kIndex, "element id 1 is duplicated (first on line 13)");
  EXPECT_EQ(e.where().line, 14);
  e = ReadError(Replace(std::string(kSmall41), "1\n2\n3\n4\n", "1\n2\n3\n1\n"));
  EXPECT_FAULT(e, MeshErrorKind::kIndex, "node id 1 is duplicated");
  e = ReadError(Replace(std::string(kSmall41), "2 1 3 2\n", "1 1 3 2\n"));
  EXPECT_FAULT(e, MeshErrorKind::kIndex, "element id 1 is duplicated");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "4 0 0 1", "-4 0 0 1")),
               MeshErrorKind::kIndex, "negative");
}

TEST(GmshReader, RefusesCountsThatDisagreeWithTheData) {
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "$Nodes\n4\n", "$Nodes\n5\n")),
               MeshErrorKind::kCount, "$Nodes says 5 nodes but the section ends after 4");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "$Nodes\n4\n", "$Nodes\n3\n")),
               MeshErrorKind::kCount, "$Nodes says 3 nodes but more data follows");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "$Elements\n2\n", "$Elements\n3\n")),
               MeshErrorKind::kCount, "$Elements says 3 elements but the section ends after 2");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall1), "$ELM\n2\n", "$ELM\n1\n")),
               MeshErrorKind::kCount, "$ELM says 1 element but more data follows");
  // Version 4.1: totals against blocks, blocks against data.
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "1 4 1 4\n", "1 5 1 4\n")),
               MeshErrorKind::kCount, "$Nodes says 5 nodes but its 1 block hold 4");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "3 1 0 4\n", "3 1 0 5\n")),
               MeshErrorKind::kCount, "more than the 4 left");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "2 2 1 2\n", "3 2 1 2\n")),
               MeshErrorKind::kCount, "");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "2 1 2 1\n", "2 1 2 2\n")),
               MeshErrorKind::kCount, "more than the 1 left");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "0 0 1 1\n", "0 0 1 2\n")),
               MeshErrorKind::kCount, "$Entities ends early");
}

TEST(GmshReader, RefusesAbsurdCountsAtOnce) {
  const auto start = std::chrono::steady_clock::now();
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "$Nodes\n4\n", "$Nodes\n1000000000000\n")),
               MeshErrorKind::kCount, "1000000000000 nodes");
  EXPECT_FAULT(
      ReadError(Replace(std::string(kSmall22), "$Elements\n2\n", "$Elements\n1000000000000\n")),
      MeshErrorKind::kCount, "1000000000000 elements");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "1 4 1 4\n", "1 1000000000000 1 4\n")),
               MeshErrorKind::kCount, "1000000000000 nodes");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "0 0 1 1\n", "0 0 1 1000000000000\n")),
               MeshErrorKind::kCount, "1000000000000 entities");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "1 4 2 1 1", "1 4 1000000000000 1 1")),
               MeshErrorKind::kCount, "1000000000000 tags");
  EXPECT_FAULT(
      ReadError(Replace(Binary22(Endian::kLittle), "$Nodes\n4\n", "$Nodes\n1000000000000\n")),
      MeshErrorKind::kCount, "1000000000000 binary nodes");
  // Binary 4.1: a size_t count of 2^64-1 in the $Nodes header.
  std::string bytes = WriteGmsh(RegularTet(), GmshVersion::kV41, Encoding::kBinary);
  const size_t nodes = bytes.find("$Nodes\n") + 7;
  for (size_t k = 8; k < 16; ++k) bytes[nodes + k] = '\xff';
  EXPECT_EQ(ReadError(bytes).kind(), MeshErrorKind::kCount);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  EXPECT_LT(seconds, 2.0);
}

TEST(GmshReader, RefusesWrongElementSizes) {
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "1 4 2 1 1 1 2 3 4", "1 4 2 1 1 1 2 3")),
               MeshErrorKind::kCount, "element 1 (tetrahedron) should list 4 node ids");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "2 2 2 1 1 1 3 2", "2 2 2 1 1 1 3 2 4")),
               MeshErrorKind::kCount, "element 2 (triangle) should list 3 node ids");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall1), "1 4 1 1 4 1 2 3 4", "1 4 1 1 3 1 2 3")),
               MeshErrorKind::kCount, "element 1 says 3 nodes but its type 4 (tetrahedron) has 4");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall1), "1 4 1 1 4 1 2 3 4", "1 4 1 1 4 1 2 3")),
               MeshErrorKind::kCount, "should list 4 node ids, its line lists 3");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "1 1 2 3 4\n", "1 1 2 3\n")),
               MeshErrorKind::kCount, "should list 4 node tags, its line lists 3");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "\n1 0 0\n0 1 0\n", "\n1 0\n0 1 0\n")),
               MeshErrorKind::kSyntax, "should have 3 coordinates");
}

TEST(GmshReader, RefusesUnknownElementTypes) {
  MeshError e = ReadError(Replace(std::string(kSmall22), "2 2 2 1 1 1 3 2", "2 999 2 1 1 1 3 2"));
  EXPECT_FAULT(e, MeshErrorKind::kUnsupported, "element type 999");
  EXPECT_EQ(e.where().line, 14);
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "2 2 2 1 1 1 3 2", "2 34 2 1 1 1 3 2")),
               MeshErrorKind::kUnsupported, "element type 34 (polygon)");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall41), "2 1 2 1\n", "2 1 200 1\n")),
               MeshErrorKind::kUnsupported, "element type 200");
}

TEST(GmshReader, RefusesUnknownSectionsAndStrayText) {
  EXPECT_FAULT(ReadError(std::string(kSmall22) + "$Foo\n1\n$EndFoo\n"), MeshErrorKind::kSyntax,
               "unknown section '$Foo'");
  EXPECT_FAULT(ReadError(std::string(kSmall22) + "hello\n"), MeshErrorKind::kSyntax,
               "outside any section");
  EXPECT_FAULT(ReadError(std::string(kSmall22) + "$EndNodes\n"), MeshErrorKind::kSyntax,
               "no open section");
  EXPECT_FAULT(ReadError(std::string(kSmall1) + "$Foo\n"), MeshErrorKind::kSyntax,
               "only $NOD and $ELM");
  EXPECT_FAULT(ReadError(std::string(kSmall22) + "$NodeData\n1\n"), MeshErrorKind::kSyntax,
               "has no $EndNodeData");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "$EndNodes\n", "$EndNode\n")),
               MeshErrorKind::kSyntax, "expected $EndNodes");
  EXPECT_FAULT(ReadError(Replace(std::string(kSmall22), "$MeshFormat", "MeshFormat")),
               MeshErrorKind::kSyntax, "not a Gmsh .msh file");
  EXPECT_FAULT(ReadError(std::string(kSmall22) + "$Nodes\n0\n$EndNodes\n"), MeshErrorKind::kSyntax,
               "a second $Nodes");
  EXPECT_FAULT(ReadError(std::string(kSmall22) + "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n"),
               MeshErrorKind::kSyntax, "a second $MeshFormat");
}

TEST(GmshReader, RefusesMissingSections) {
  const std::string header = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n";
  EXPECT_FAULT(ReadError(header), MeshErrorKind::kSyntax, "no $Nodes section");
  EXPECT_FAULT(ReadError(header + "$Nodes\n0\n$EndNodes\n"), MeshErrorKind::kSyntax,
               "no $Elements section");
  EXPECT_FAULT(ReadError(header + "$Elements\n0\n$EndElements\n$Nodes\n0\n$EndNodes\n"),
               MeshErrorKind::kSyntax, "$Elements comes before $Nodes");
  EXPECT_FAULT(ReadError("$NOD\n0\n$ENDNOD\n"), MeshErrorKind::kSyntax, "missing $ELM");
  EXPECT_FAULT(ReadError(""), MeshErrorKind::kSyntax, "empty file");
}

TEST(GmshReader, RefusesUnsupportedVersionsNamingThem) {
  const std::string small(kSmall22);
  EXPECT_FAULT(ReadError(Replace(small, "2.2 0 8", "4 0 8")), MeshErrorKind::kUnsupported,
               "version 4.0");
  EXPECT_FAULT(ReadError(Replace(small, "2.2 0 8", "3.0 0 8")), MeshErrorKind::kUnsupported, "3.0");
  EXPECT_FAULT(ReadError(Replace(small, "2.2 0 8", "5.7 0 8")), MeshErrorKind::kUnsupported,
               "'5.7'");
  EXPECT_FAULT(ReadError(Replace(small, "2.2 0 8", "1.0 0 8")), MeshErrorKind::kUnsupported,
               "'1.0'");
  EXPECT_FAULT(ReadError(Replace(small, "2.2 0 8", "abc 0 8")), MeshErrorKind::kSyntax, "'abc'");
  EXPECT_FAULT(ReadError(Replace(small, "2.2 0 8", "2.2 2 8")), MeshErrorKind::kSyntax,
               "file type");
}

TEST(GmshReader, RefusesInvertedTetrahedronUnlessFixingOrientation) {
  const std::string inverted =
      Replace(std::string(kSmall22), "1 4 2 1 1 1 2 3 4", "1 4 2 1 1 1 3 2 4");
  const MeshError e = ReadError(inverted);
  EXPECT_FAULT(e, MeshErrorKind::kElement, "inverted");
  EXPECT_EQ(e.where().line, 13);
  ReadOptions fix;
  fix.fix_orientation = true;
  const MeshData m = Read(inverted, fix);
  EXPECT_EQ(m.num_flipped, 1);
  EXPECT_EQ(m.tetrahedra.col(0), Eigen::Vector4i(0, 2, 3, 1));
}

TEST(GmshReader, BinaryFaultsNameTheByteOffset) {
  std::string bytes = Binary22(Endian::kLittle);
  const size_t second_node = bytes.find("$Nodes\n4\n") + 9 + 28;
  bytes[second_node] = 1;  // node id 2 becomes 1
  const MeshError e = ReadError(bytes);
  EXPECT_FAULT(e, MeshErrorKind::kIndex, "node id 1 is duplicated (first at byte");
  EXPECT_EQ(e.where().byte, static_cast<int64_t>(second_node));
}

// Random byte changes in real and written files: only MeshError may come out (ASan/UBSan watch
// the rest).
TEST(GmshReader, SurvivesCorruptedBytes) {
  std::vector<std::string> seeds = {std::string(kSmall1), std::string(kSmall22),
                                    std::string(kSmall41), Binary22(Endian::kBig)};
  for (const Variant& v : kVariants)
    seeds.push_back(WriteGmsh(BoxTets(1, 1, 1), v.version, v.encoding));
  std::mt19937 random(12345);
  const std::string alphabet = "0123456789 \n-+.e$\xff";
  int refused = 0, total = 0;
  for (const std::string& seed : seeds) {
    for (int trial = 0; trial < 300; ++trial) {
      std::string bytes = seed;
      const int changes = 1 + static_cast<int>(random() % 4);
      for (int c = 0; c < changes; ++c) {
        const size_t at = random() % bytes.size();
        bytes[at] =
            random() % 2 ? alphabet[random() % alphabet.size()] : static_cast<char>(random() % 256);
      }
      ++total;
      try {
        Read(bytes);
      } catch (const MeshError&) {
        ++refused;
      }
    }
  }
  EXPECT_GT(refused, total / 2);
  // Pure garbage.
  EXPECT_THROW(Read(std::string("\x00\x01\x02garbage\xff\xfe", 12)), MeshError);
  EXPECT_THROW(Read("$MeshFormat\n\xff\xff\xff"), MeshError);
}

// ---------------------------------------------------------------------------------------------
// Hand-written and Gmsh-written samples (tests/data/gmsh)

TEST(GmshSamples, Version1MixedTypesSparseIds) {
  const MeshData m = Read(Slurp(TestData("gmsh/v1_mixed_sparse.msh")));
  ASSERT_EQ(m.vertices.cols(), 6);
  ASSERT_EQ(m.tetrahedra.cols(), 1);
  ASSERT_EQ(m.triangles.cols(), 1);
  EXPECT_EQ(m.tetrahedra.col(0), Eigen::Vector4i(0, 1, 2, 3));
  EXPECT_EQ(m.triangles.col(0), Eigen::Vector3i(0, 2, 1));
  ASSERT_EQ(m.skipped.size(), 3u);
  EXPECT_EQ(m.skipped[0].type, "point");
  EXPECT_EQ(m.skipped[0].count, 2);
  EXPECT_EQ(m.skipped[1].type, "line");
  EXPECT_EQ(m.skipped[2].type, "quadrangle");
}

TEST(GmshSamples, Version22CrlfPhysicalNamesThreeTagsAndData) {
  const MeshData m = Read(Slurp(TestData("gmsh/v22_dialect_crlf.msh")));
  ASSERT_EQ(m.vertices.cols(), 5);
  EXPECT_EQ(m.vertices.col(4), Eigen::Vector3d(0.15, 0.25, 0.0));
  ASSERT_EQ(m.tetrahedra.cols(), 1);
  EXPECT_EQ(m.tetrahedra.col(0), Eigen::Vector4i(0, 1, 2, 3));
  ASSERT_EQ(m.triangles.cols(), 1);
  EXPECT_EQ(m.triangles.col(0), Eigen::Vector3i(0, 2, 1));
  ASSERT_EQ(m.skipped.size(), 2u);
  EXPECT_EQ(m.skipped[0].type, "line (3 nodes)");
  EXPECT_EQ(m.skipped[1].type, "point");
}

// Files written by Gmsh 4.8.4 (Debian) from a unit cube meshed with size 1: 14 nodes, 24
// tetrahedra, 24 boundary triangles, 12 lines, 8 points. The .geo was
//   SetFactory("OpenCASCADE"); Box(1) = {0, 0, 0, 1, 1, 1};
//   Mesh.MeshSizeMin = 1; Mesh.MeshSizeMax = 1;
// saved with `gmsh -3 cube.geo -format msh41 -bin` (cube_41_binary), `-format msh22 -bin`
// (cube_22_binary), `-format msh41 -parametric` (cube_41_parametric), `-order 2 -format msh41`
// (cube_41_order2); cube_22_physical adds Physical Volume("tissue") = {1} and
// Physical Surface("skin") = {1:6}, so that only those elements are saved, with $PhysicalNames.
void ExpectGmshCube(const MeshData& m, bool with_lower_dimensions) {
  EXPECT_EQ(m.vertices.cols(), 14);
  EXPECT_EQ(m.tetrahedra.cols(), 24);
  EXPECT_EQ(m.triangles.cols(), 24);
  EXPECT_EQ(m.vertices.rowwise().minCoeff(), Eigen::Vector3d(0, 0, 0));
  EXPECT_EQ(m.vertices.rowwise().maxCoeff(), Eigen::Vector3d(1, 1, 1));
  if (with_lower_dimensions) {
    ASSERT_EQ(m.skipped.size(), 2u);
    EXPECT_EQ(m.skipped[0].type, "point");
    EXPECT_EQ(m.skipped[0].count, 8);
    EXPECT_EQ(m.skipped[1].type, "line");
    EXPECT_EQ(m.skipped[1].count, 12);
  } else {
    EXPECT_TRUE(m.skipped.empty());
  }
}

TEST(GmshSamples, WrittenByGmsh) {
  {
    const MeshData m = Read(Slurp(TestData("gmsh/cube_41_binary.msh")));
    EXPECT_EQ(m.format, "Gmsh 4.1 binary");
    ExpectGmshCube(m, true);
    // The same mesh as the 2.2 binary file Gmsh wrote in the same run.
    EXPECT_TRUE(SameMesh(Read(Slurp(TestData("gmsh/cube_22_binary.msh"))), m, 0.0));
  }
  {
    const MeshData m = Read(Slurp(TestData("gmsh/cube_22_binary.msh")));
    EXPECT_EQ(m.format, "Gmsh 2.2 binary");
    ExpectGmshCube(m, true);
  }
  {
    // Physical groups: only the volume and its surface are saved, with $PhysicalNames.
    const MeshData m = Read(Slurp(TestData("gmsh/cube_22_physical.msh")));
    EXPECT_EQ(m.format, "Gmsh 2.2 ASCII");
    ExpectGmshCube(m, false);
  }
  {
    const MeshData m = Read(Slurp(TestData("gmsh/cube_41_parametric.msh")));
    ExpectGmshCube(m, true);
  }
  {
    // Second order: 10-node tetrahedra and 6-node triangles are skipped, not truncated.
    const MeshData m = Read(Slurp(TestData("gmsh/cube_41_order2.msh")));
    EXPECT_EQ(m.tetrahedra.cols(), 0);
    EXPECT_EQ(m.triangles.cols(), 0);
    ASSERT_EQ(m.skipped.size(), 4u);
    EXPECT_EQ(m.skipped[1].type, "line (3 nodes)");
    EXPECT_EQ(m.skipped[2].type, "triangle (6 nodes)");
    EXPECT_EQ(m.skipped[2].count, 24);
    EXPECT_EQ(m.skipped[3].type, "tetrahedron (10 nodes)");
    EXPECT_EQ(m.skipped[3].count, 24);
  }
}

// meshio 7.0 writes version 4.1 without $Entities (Gmsh accepts that), ASCII coordinates in
// %.16e, and element tags per block from 1. These files hold BoxTets(1, 1, 1)'s tetrahedra.
TEST(GmshSamples, WrittenByMeshioWithoutEntities) {
  const MeshData box = BoxTets(1, 1, 1);
  for (const char* name : {"gmsh/meshio_41_ascii.msh", "gmsh/meshio_41_binary.msh"}) {
    SCOPED_TRACE(name);
    const MeshData m = Read(Slurp(TestData(name)));
    EXPECT_EQ(m.vertices, box.vertices);
    EXPECT_EQ(m.tetrahedra, box.tetrahedra);
    EXPECT_EQ(m.triangles.cols(), 0);
  }
}

// ---------------------------------------------------------------------------------------------
// SOFA's real files (shared/data/meshes)

void ExpectBox(const MeshData& m, const Eigen::Vector3d& lo, const Eigen::Vector3d& hi) {
  const Eigen::Vector3d min = m.vertices.rowwise().minCoeff();
  const Eigen::Vector3d max = m.vertices.rowwise().maxCoeff();
  // The README gives the box to two decimals.
  EXPECT_LT((min - lo).cwiseAbs().maxCoeff(), 0.005) << min.transpose();
  EXPECT_LT((max - hi).cwiseAbs().maxCoeff(), 0.005) << max.transpose();
}

TEST(GmshRealFiles, Liver) {
  const MeshData m = Read(Slurp(SharedMesh("liver.msh")));
  EXPECT_EQ(m.format, "Gmsh 1");
  EXPECT_EQ(m.vertices.cols(), 181);
  EXPECT_EQ(m.tetrahedra.cols(), 596);
  EXPECT_EQ(m.triangles.cols(), 0);
  EXPECT_TRUE(m.skipped.empty());
  EXPECT_EQ(m.num_flipped, 0);
  ExpectBox(m, {-4.68, 0.22, -1.69}, {1.80, 5.16, 2.73});
}

TEST(GmshRealFiles, Liver2) {
  const MeshData m = Read(Slurp(SharedMesh("liver2.msh")));
  EXPECT_EQ(m.format, "Gmsh 1");
  EXPECT_EQ(m.vertices.cols(), 507);
  EXPECT_EQ(m.tetrahedra.cols(), 1493);
  EXPECT_EQ(m.triangles.cols(), 860);
  ASSERT_EQ(m.skipped.size(), 1u);
  EXPECT_EQ(m.skipped[0].type, "line");
  EXPECT_EQ(m.skipped[0].count, 71);
  EXPECT_EQ(m.tetrahedra.cols() + m.triangles.cols() + m.skipped[0].count, 2424);
}

TEST(GmshRealFiles, Msh4Cube) {
  const MeshData m = Read(Slurp(SharedMesh("msh4_cube.msh")));
  EXPECT_EQ(m.format, "Gmsh 4.1 ASCII");
  ExpectGmshCube(m, true);
}

TEST(GmshRealFiles, SixTetraBadIsRefusedForItsDuplicatedElementId) {
  const std::string bytes = Slurp(SharedMesh("6_tetra_bad.msh"));
  const MeshError e = ReadError(bytes);
  EXPECT_FAULT(e, MeshErrorKind::kIndex, "element id 44 is duplicated (first on line 26)");
  EXPECT_EQ(e.where().line, 27);
  // Also with fix_orientation: the id fault is in the file's structure.
  ReadOptions fix;
  fix.fix_orientation = true;
  EXPECT_EQ(ReadError(bytes, fix).kind(), MeshErrorKind::kIndex);
}

TEST(GmshRealFiles, SixTetraBadWithFixedIdsHasOneInvertedTetrahedron) {
  std::string bytes = Slurp(SharedMesh("6_tetra_bad.msh"));
  // Number the six elements 1..6.
  for (int id = 1; id <= 6; ++id) {
    bytes = Replace(bytes, "\n44 4 ", "\n" + std::to_string(id) + " 4 ");
  }
  const MeshError e = ReadError(bytes);
  EXPECT_FAULT(e, MeshErrorKind::kElement, "tetrahedron #6");
  EXPECT_FAULT(e, MeshErrorKind::kElement, "inverted");
  EXPECT_EQ(e.where().line, 31);
  ReadOptions fix;
  fix.fix_orientation = true;
  const MeshData m = Read(bytes, fix);
  EXPECT_EQ(m.num_flipped, 1);
  EXPECT_EQ(m.vertices.cols(), 17);
  EXPECT_EQ(m.tetrahedra.cols(), 6);
}

}  // namespace
}  // namespace somasim::mesh_io
