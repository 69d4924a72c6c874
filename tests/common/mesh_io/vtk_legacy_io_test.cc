#include "common/mesh_io/vtk_legacy_io.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <limits>
#include <random>
#include <string>
#include <string_view>
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
using ::somasim::testing::SameMesh;
using ::somasim::testing::SharedMesh;
using ::somasim::testing::SkippedCount;
using ::somasim::testing::Slurp;
using ::somasim::testing::SquarePatch;
using ::somasim::testing::TestData;

MeshData Read(std::string_view bytes, const ReadOptions& options = {}) {
  return ReadVtkLegacy(bytes, "test.vtk", options);
}

MeshError ErrorOf(std::string_view bytes, const ReadOptions& options = {}) {
  return ErrorFrom([&] { Read(bytes, options); }, bytes);
}

constexpr const char* kHeader = "# vtk DataFile Version 3.0\ntest\nASCII\n";

// The corner tetrahedron (positively oriented), as an ASCII unstructured grid.
std::string CornerTet(const std::string& cells = "CELLS 1 5\n4 0 1 2 3\n",
                      const std::string& types = "CELL_TYPES 1\n10\n",
                      const std::string& points = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n") {
  return std::string(kHeader) + "DATASET UNSTRUCTURED_GRID\nPOINTS 4 double\n" + points + cells +
         types;
}

// Big-endian helpers for hand-made BINARY files.
template <typename T>
std::string Big(std::initializer_list<T> values) {
  std::string out;
  for (T v : values) AppendBinary(&out, v, Endian::kBig);
  return out;
}

// ---------------------------------------------------------------------------------------------
// Round trips

TEST(VtkLegacyWriter, RoundTripIsBitExactForTetsAndTriangles) {
  const MeshData box = BoxTets(3, 2, 2, 0.3, 0.7, 1.0 / 3.0);
  for (Encoding encoding : {Encoding::kAscii, Encoding::kBinary}) {
    const std::string text = WriteVtkLegacy(box, encoding);
    const MeshData read = Read(text);
    EXPECT_TRUE(SameMesh(box, read, 0.0));
    EXPECT_EQ(read.tetrahedra.cols(), box.tetrahedra.cols());
    EXPECT_EQ(read.triangles.cols(), box.triangles.cols());
    EXPECT_TRUE(read.skipped.empty());
    EXPECT_EQ(WriteVtkLegacy(read, encoding), text);  // read → write reproduces the file
  }
}

TEST(VtkLegacyWriter, RoundTripIsBitExactForSurfaces) {
  for (const MeshData& surface : {BoxSurface(2, 3, 1), SquarePatch(4)}) {
    for (Encoding encoding : {Encoding::kAscii, Encoding::kBinary}) {
      const std::string text = WriteVtkLegacy(surface, encoding);
      EXPECT_TRUE(Contains(text, "DATASET POLYDATA\n"));
      const MeshData read = Read(text);
      EXPECT_TRUE(SameMesh(surface, read, 0.0));
      EXPECT_EQ(read.tetrahedra.cols(), 0);
    }
  }
}

TEST(VtkLegacyWriter, WritesUnstructuredGridWithTetrahedraFirst) {
  const std::string text = WriteVtkLegacy(BoxTets(1, 1, 1), Encoding::kAscii);
  EXPECT_TRUE(Contains(text, "DATASET UNSTRUCTURED_GRID\nPOINTS 8 double\n"));
  EXPECT_TRUE(Contains(text, "CELLS 18 78\n4 "));
  EXPECT_TRUE(Contains(text, "CELL_TYPES 18\n10\n"));
  EXPECT_EQ(text.substr(text.size() - 2), "5\n");
}

// A well-formed file with no points is written, but reading refuses it: a mesh with no nodes is
// never what a user meant to load (MeshBuilder's rule).
TEST(VtkLegacyWriter, EmptyMeshIsWrittenButRefusedOnRead) {
  MeshData empty;
  for (Encoding encoding : {Encoding::kAscii, Encoding::kBinary}) {
    try {
      Read(WriteVtkLegacy(empty, encoding));
      ADD_FAILURE() << "accepted";
    } catch (const MeshError& e) {
      EXPECT_NE(e.fault().find("holds no nodes"), std::string::npos) << e.what();
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Truncation

bool OnlyWhitespace(std::string_view s) {
  for (char c : s) {
    if (c != ' ' && c != '\n' && c != '\r' && c != '\t') return false;
  }
  return true;
}

// Legacy VTK has no end marker and no overall count of sections: a cut exactly between two
// sections leaves a valid, shorter file, and in ASCII a cut inside the very last number leaves
// a valid (different) number. Those cuts cannot be detected; every other one must be refused.
void ExpectTruncationsRefused(const std::string& full, bool ascii) {
  int accepted = 0;
  for (size_t len = 0; len < full.size(); ++len) {
    const std::string_view rest = std::string_view(full).substr(len);
    if (OnlyWhitespace(rest)) continue;
    try {
      Read(full.substr(0, len));
    } catch (const MeshError&) {
      continue;
    } catch (...) {
      ADD_FAILURE() << "a cut after " << len << " bytes threw something else than MeshError";
      continue;
    }
    ++accepted;
    size_t k = 0;
    while (k < rest.size() && OnlyWhitespace(rest.substr(k, 1))) ++k;
    const std::string_view next = rest.substr(k);
    const bool at_section =
        next.starts_with("POLYGONS ") || next.starts_with("CELLS ") || next.starts_with("POINTS ");
    bool in_last_number = ascii;
    for (size_t i = 0; i < rest.size(); ++i) {
      if (OnlyWhitespace(rest.substr(i, 1)) && !OnlyWhitespace(rest.substr(i))) {
        in_last_number = false;
      }
    }
    EXPECT_TRUE(at_section || in_last_number)
        << "a cut after " << len << " bytes was accepted; the rest was '" << rest << "'";
  }
  EXPECT_LE(accepted, 3);
}

TEST(VtkLegacyReader, RefusesEveryDetectableTruncation) {
  for (Encoding encoding : {Encoding::kAscii, Encoding::kBinary}) {
    SCOPED_TRACE(encoding == Encoding::kAscii ? "ASCII" : "BINARY");
    ExpectTruncationsRefused(WriteVtkLegacy(BoxTets(1, 1, 1), encoding),
                             encoding == Encoding::kAscii);
    ExpectTruncationsRefused(WriteVtkLegacy(BoxSurface(1, 1, 1), encoding),
                             encoding == Encoding::kAscii);
  }
}

TEST(VtkLegacyReader, RefusesTruncatedAttributeSection) {
  const std::string file =
      CornerTet() + "POINT_DATA 4\nSCALARS t float\nLOOKUP_TABLE default\n1 2 3";
  const MeshError e = ErrorOf(file);
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount) << e.what();
  const std::string binary = WriteVtkLegacy(BoxTets(1, 1, 1), Encoding::kBinary) +
                             "POINT_DATA 8\nVECTORS v float\n" + std::string(95, '\0');
  EXPECT_EQ(ErrorOf(binary).kind(), MeshErrorKind::kCount) << ErrorOf(binary).what();
  EXPECT_NO_THROW(Read(binary + '\0'));
}

TEST(VtkLegacyReader, RefusesUnterminatedMetadata) {
  const std::string file =
      CornerTet() +
      "POINT_DATA 4\nSCALARS t float\nLOOKUP_TABLE default\n1 2 3 4\nMETADATA\n"
      "INFORMATION 1\nNAME L2_NORM_RANGE LOCATION vtkDataArray\n";
  EXPECT_EQ(ErrorOf(file).kind(), MeshErrorKind::kSyntax);
  EXPECT_NO_THROW(Read(file + "DATA 2 0 1\n\n"));
}

// ---------------------------------------------------------------------------------------------
// Bad input

TEST(VtkLegacyReader, RefusesNonFiniteCoordinateNamingTheLine) {
  const MeshError e = ErrorOf(
      CornerTet("CELLS 1 5\n4 0 1 2 3\n", "CELL_TYPES 1\n10\n", "0 0 0\n1 0 0\n0 nan 0\n0 0 1\n"));
  EXPECT_EQ(e.kind(), MeshErrorKind::kValue);
  EXPECT_EQ(e.where().line, 8);
  const MeshError inf = ErrorOf(CornerTet("CELLS 1 5\n4 0 1 2 3\n", "CELL_TYPES 1\n10\n",
                                          "0 0 0\n1 0 0\n0 1 0\n0 0 1e999\n"));
  EXPECT_EQ(inf.kind(), MeshErrorKind::kValue);
  EXPECT_EQ(inf.where().line, 9);
}

TEST(VtkLegacyReader, RefusesNonFiniteBinaryCoordinateNamingTheByte) {
  std::string file = "# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\nPOINTS 3 float\n";
  const size_t data = file.size();
  file += Big<float>({0, 0, 0, 1, 0, 0, 0, std::numeric_limits<float>::infinity(), 0});
  file += "\nPOLYGONS 1 4\n" + Big<int32_t>({3, 0, 1, 2}) + "\n";
  const MeshError e = ErrorOf(file);
  EXPECT_EQ(e.kind(), MeshErrorKind::kValue);
  EXPECT_EQ(e.where().byte, static_cast<int64_t>(data + 24));
}

TEST(VtkLegacyReader, RefusesIndexOutOfRange) {
  const MeshError e = ErrorOf(CornerTet("CELLS 1 5\n4 0 1 2 4\n"));
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.where().line, 11);
  EXPECT_EQ(ErrorOf(CornerTet("CELLS 1 5\n4 0 1 2 -1\n")).kind(), MeshErrorKind::kIndex);
}

TEST(VtkLegacyReader, RefusesCellsSizeThatDisagreesWithTheCells) {
  const MeshError more = ErrorOf(CornerTet("CELLS 1 6\n4 0 1 2 3\n"));
  EXPECT_EQ(more.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(more.what(), "CELLS announces 6")) << more.what();
  const MeshError fewer = ErrorOf(CornerTet("CELLS 1 4\n4 0 1 2 3\n"));
  EXPECT_EQ(fewer.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(fewer.what(), "runs past")) << fewer.what();
  const MeshError unused = ErrorOf(CornerTet("CELLS 1 6\n4 0 1 2 3 0\n"));
  EXPECT_EQ(unused.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(unused.what(), "CELLS says 6 entries but its 1 cells use 5"))
      << unused.what();
}

TEST(VtkLegacyReader, RefusesCellTypesCountThatDisagreesWithCells) {
  const MeshError e = ErrorOf(CornerTet("CELLS 1 5\n4 0 1 2 3\n", "CELL_TYPES 2\n10\n10\n"));
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(e.what(), "CELL_TYPES lists 2 types but CELLS has 1 cells")) << e.what();
  EXPECT_EQ(ErrorOf(CornerTet("CELLS 1 5\n4 0 1 2 3\n", "")).kind(), MeshErrorKind::kSyntax);
}

TEST(VtkLegacyReader, RefusesPointDataCountThatDisagreesWithPoints) {
  const MeshError e = ErrorOf(CornerTet() + "POINT_DATA 5\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(e.what(), "POINT_DATA says 5 but the dataset has 4 points")) << e.what();
  EXPECT_EQ(ErrorOf(CornerTet() + "CELL_DATA 2\n").kind(), MeshErrorKind::kCount);
}

TEST(VtkLegacyReader, RefusesAbsurdCountsFast) {
  const auto start = std::chrono::steady_clock::now();
  for (const std::string& file :
       {std::string(kHeader) + "DATASET POLYDATA\nPOINTS 1000000000000 float\n0 0 0\n",
        CornerTet("CELLS 1000000000000 1000000000000\n4 0 1 2 3\n"),
        CornerTet("CELLS 1 5\n4 0 1 2 3\n", "CELL_TYPES 1000000000000\n10\n"),
        CornerTet() + "POINT_DATA 4\nFIELD f 1000000000000\n",
        CornerTet() + "POINT_DATA 4\nFIELD f 1\na 1000000000000 4 float\n",
        CornerTet() + "POINT_DATA 4\nLOOKUP_TABLE t 1000000000000\n",
        std::string("# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\nPOINTS "
                    "4611686018427387904 double\n")}) {
    const MeshError e = ErrorOf(file);
    EXPECT_EQ(e.kind(), MeshErrorKind::kCount) << e.what();
  }
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(2));
}

TEST(VtkLegacyReader, RefusesUnknownKeyword) {
  const MeshError e = ErrorOf(CornerTet() + "SPHERES 3\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().line, 14);
  EXPECT_TRUE(Contains(e.what(), "unknown keyword 'SPHERES'")) << e.what();
  // Geometry after the attributes, and sections of the other dataset type, are refused too.
  EXPECT_EQ(ErrorOf(CornerTet() + "POINT_DATA 4\nCELLS 1 5\n4 0 1 2 3\n").kind(),
            MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf(std::string(kHeader) + "DATASET POLYDATA\nPOINTS 0 float\nCELLS 0 0\n").kind(),
            MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf(CornerTet() + "POINT_DATA 4\nSCALARS t bogus_type\n").kind(),
            MeshErrorKind::kSyntax);
}

TEST(VtkLegacyReader, RefusesOtherDatasetTypesNamingThem) {
  const MeshError e =
      ErrorOf(std::string(kHeader) + "DATASET STRUCTURED_POINTS\nDIMENSIONS 2 2 2\n");
  EXPECT_EQ(e.kind(), MeshErrorKind::kUnsupported);
  EXPECT_TRUE(Contains(e.what(), "STRUCTURED_POINTS")) << e.what();
  EXPECT_EQ(ErrorOf(std::string(kHeader) + "DATASET RECTILINEAR_GRID\n").kind(),
            MeshErrorKind::kUnsupported);
  EXPECT_EQ(ErrorOf(std::string(kHeader) + "DATASET TRIANGLES\n").kind(), MeshErrorKind::kSyntax);
}

TEST(VtkLegacyReader, RefusesWrongElementSizes) {
  const MeshError tet = ErrorOf(CornerTet("CELLS 1 4\n3 0 1 2\n"));
  EXPECT_EQ(tet.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(tet.what(), "cell #1 is a VTK_TETRA but has 3 points instead of 4"))
      << tet.what();
  EXPECT_EQ(tet.where().line, 11);
  const MeshError hex = ErrorOf(CornerTet("CELLS 1 5\n4 0 1 2 3\n", "CELL_TYPES 1\n12\n"));
  EXPECT_EQ(hex.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(hex.what(), "VTK_HEXAHEDRON")) << hex.what();
  const MeshError unknown = ErrorOf(CornerTet("CELLS 1 5\n4 0 1 2 3\n", "CELL_TYPES 1\n99\n"));
  EXPECT_EQ(unknown.kind(), MeshErrorKind::kSyntax);
  EXPECT_TRUE(Contains(unknown.what(), "unknown VTK cell type 99")) << unknown.what();
}

TEST(VtkLegacyReader, InvertedTetrahedronIsRefusedOrFlipped) {
  const std::string file = CornerTet("CELLS 1 5\n4 0 2 1 3\n");
  const MeshError e = ErrorOf(file);
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
  EXPECT_EQ(e.where().line, 11);
  ReadOptions fix;
  fix.fix_orientation = true;
  const MeshData m = Read(file, fix);
  EXPECT_EQ(m.num_flipped, 1);
  EXPECT_EQ(m.tetrahedra.cols(), 1);
}

TEST(VtkLegacyReader, RefusesGarbage) {
  EXPECT_EQ(ErrorOf("").kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf("solid cube\nfacet normal 0 0 1\n").kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf("# vtk DataFile Version 3.0\ntitle\nUTF8\n").kind(), MeshErrorKind::kSyntax);
  std::mt19937 rng(7);
  const std::string good = WriteVtkLegacy(BoxTets(1, 1, 1), Encoding::kBinary);
  for (int round = 0; round < 300; ++round) {
    try {
      Read(testing::DamageBytes(good, 4, &rng));
    } catch (const MeshError&) {
    }
  }
  std::string noise(2000, '\0');
  for (char& c : noise) c = static_cast<char>(rng() & 0xff);
  EXPECT_THROW(Read(noise), MeshError);
  EXPECT_THROW(Read("# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\n" + noise),
               MeshError);
}

TEST(VtkLegacyReader, ExplainsBinaryBlockWhoseCountIsWrong) {
  std::string file = "# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\nPOINTS 2 float\n";
  file += Big<float>({0, 0, 0, 1, 0, 0, 0, 1, 0});
  file += "\nPOLYGONS 1 4\n" + Big<int32_t>({3, 0, 1, 2}) + "\n";
  const MeshError e = ErrorOf(file);
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_EQ(e.where().byte, 53);
  EXPECT_TRUE(Contains(e.what(),
                       "POINTS declares 2 points of float, i.e. 24 bytes of binary "
                       "data, but the next section (POLYGONS at byte 105) begins 36 "
                       "bytes after the data starts"))
      << e.what();
}

// ---------------------------------------------------------------------------------------------
// Dialects

TEST(VtkLegacyReader, ReadsPolydataWithStripsAndAttributes) {
  const MeshData m = Read(Slurp(TestData("vtk/polydata_strips_attributes.vtk")));
  EXPECT_EQ(m.vertices.cols(), 6);
  // One triangle from POLYGONS, then the strip 0 1 2 3 4 5 with alternating orientation.
  Eigen::Matrix<int32_t, 3, 5> expected;
  expected << 0, 0, 2, 2, 4,  //
      1, 1, 1, 3, 3,          //
      2, 2, 3, 4, 5;
  ASSERT_EQ(m.triangles.cols(), 5);
  EXPECT_EQ(m.triangles, expected);
  EXPECT_EQ(SkippedCount(m, "vertex"), 1);
  EXPECT_EQ(SkippedCount(m, "line"), 1);
  EXPECT_EQ(SkippedCount(m, "polygon"), 1);
  EXPECT_EQ(m.format, "VTK legacy 3.0 ASCII POLYDATA");
}

TEST(VtkLegacyReader, DropsDegenerateStripTriangles) {
  const std::string file = std::string(kHeader) +
                           "DATASET POLYDATA\nPOINTS 5 float\n0 0 0 1 0 0 0 1 0 1 1 0 2 1 0\n"
                           "TRIANGLE_STRIPS 1 7\n6 0 1 2 3 3 4\n";
  const MeshData m = Read(file);
  EXPECT_EQ(m.triangles.cols(), 2);  // (0 1 2), (2 1 3); then (2 3 3), (3 3 4) are turns
  EXPECT_EQ(SkippedCount(m, "degenerate triangle of a strip"), 2);
}

TEST(VtkLegacyReader, ReadsVtk51OffsetsAndConnectivity) {
  const MeshData m = Read(Slurp(TestData("vtk/ug_v51_mixed.vtk")));
  EXPECT_EQ(m.vertices.cols(), 11);
  ASSERT_EQ(m.tetrahedra.cols(), 1);
  EXPECT_EQ(m.tetrahedra.col(0), Eigen::Vector4i(0, 1, 2, 3));
  ASSERT_EQ(m.triangles.cols(), 1);
  EXPECT_EQ(m.triangles.col(0), Eigen::Vector3i(0, 2, 1));
  EXPECT_EQ(SkippedCount(m, "VTK_QUADRATIC_TETRA"), 1);
  EXPECT_EQ(SkippedCount(m, "VTK_VERTEX"), 1);
}

TEST(VtkLegacyReader, ReadsClassicCellsSkippingOtherCellTypes) {
  const MeshData m = Read(Slurp(TestData("vtk/ug_classic_mixed.vtk")));
  EXPECT_EQ(m.vertices.cols(), 9);
  EXPECT_EQ(m.tetrahedra.cols(), 1);
  EXPECT_EQ(m.triangles.cols(), 1);
  EXPECT_EQ(SkippedCount(m, "VTK_HEXAHEDRON"), 1);
  EXPECT_EQ(SkippedCount(m, "VTK_QUAD"), 1);
  EXPECT_EQ(SkippedCount(m, "VTK_WEDGE"), 1);
}

TEST(VtkLegacyReader, RefusesBadVtk51Offsets) {
  const std::string points = "POINTS 4 double\n0 0 0 1 0 0 0 1 0 0 0 1\n";
  const std::string head = std::string(kHeader) + "DATASET UNSTRUCTURED_GRID\n" + points;
  const auto file = [&](const std::string& offsets, const std::string& conn) {
    return head + "CELLS 2 4\nOFFSETS vtktypeint64\n" + offsets + "\nCONNECTIVITY vtktypeint64\n" +
           conn + "\nCELL_TYPES 1\n10\n";
  };
  EXPECT_NO_THROW(Read(file("0 4", "0 1 2 3")));
  EXPECT_EQ(ErrorOf(file("1 4", "0 1 2 3")).kind(), MeshErrorKind::kCount);
  EXPECT_EQ(ErrorOf(file("0 3", "0 1 2 3")).kind(), MeshErrorKind::kCount);
  EXPECT_EQ(ErrorOf(file("0 5", "0 1 2 3")).kind(), MeshErrorKind::kCount);
  EXPECT_EQ(ErrorOf(file("0 4", "0 1 2")).kind(), MeshErrorKind::kCount);
  EXPECT_EQ(ErrorOf(head + "CELLS 2 4\nOFFSETS float\n0 4\n").kind(), MeshErrorKind::kSyntax);
}

TEST(VtkLegacyReader, ReadsBinaryVtk51WithAttributes) {
  std::string file = "# vtk DataFile Version 5.1\nvtk output\nBINARY\nDATASET UNSTRUCTURED_GRID\n";
  file += "POINTS 5 double\n" + Big<double>({0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 1, 1});
  file += "\nMETADATA\nINFORMATION 0\n\n";
  file += "CELLS 4 9\nOFFSETS vtktypeint64\n" + Big<int64_t>({0, 4, 7, 9});
  file += "\nCONNECTIVITY vtktypeint64\n" + Big<int64_t>({0, 1, 2, 3, 1, 2, 4, 3, 4});
  file += "\nCELL_TYPES 3\n" + Big<int32_t>({10, 5, 3});
  file += "\nCELL_DATA 3\nSCALARS id bit 1\nLOOKUP_TABLE default\n" + std::string(1, '\x05');
  file += "\nPOINT_DATA 5\nSCALARS t float 2\nLOOKUP_TABLE default\n" +
          Big<float>({1, 2, 3, 4, 5, 6, 7, 8, 9, 10});
  file += "\nCOLOR_SCALARS c 4\n" + std::string(20, '\x7f');
  file += "\nTENSORS stress double\n" + std::string(5 * 9 * 8, '\0');
  file += "\nFIELD FieldData 2\nnames 1 5 string\n";
  for (const char* s : {"a", "bb", "", "dddd", "e"}) {
    file += static_cast<char>(0xC0 | std::string(s).size());
    file += s;
  }
  file += "\nids 1 5 vtkIdType\n" + Big<int32_t>({1, 2, 3, 4, 5});
  file += "\nMETADATA\nCOMPONENT_NAMES\nid\n\n";
  const MeshData m = Read(file);
  EXPECT_EQ(m.vertices.cols(), 5);
  EXPECT_EQ(m.tetrahedra.cols(), 1);
  ASSERT_EQ(m.triangles.cols(), 1);
  EXPECT_EQ(m.triangles.col(0), Eigen::Vector3i(1, 2, 4));
  EXPECT_EQ(SkippedCount(m, "VTK_LINE"), 1);
  EXPECT_EQ(m.format, "VTK legacy 5.1 BINARY UNSTRUCTURED_GRID");
  // One byte less of the last array is a truncated file.
  EXPECT_THROW(Read(file.substr(0, file.rfind("\nMETADATA") - 1)), MeshError);
}

TEST(VtkLegacyReader, AcceptsKeywordsInAnyCaseAndWindowsLineEnds) {
  std::string file = CornerTet();
  std::string crlf;
  for (char c : file) {
    if (c == '\n') crlf += '\r';
    crlf += c;
  }
  EXPECT_EQ(Read(crlf).tetrahedra.cols(), 1);
  const std::string lower =
      "# vtk DataFile Version 2.0\nt\nascii\ndataset unstructured_grid\npoints 4 float\n"
      "0 0 0 1 0 0 0 1 0 0 0 1\ncells 1 5\n4 0 1 2 3\ncell_types 1\n10\n";
  EXPECT_EQ(Read(lower).tetrahedra.cols(), 1);
}

// ---------------------------------------------------------------------------------------------
// Real files

TEST(VtkLegacyReader, ReadsSofaLiver) {
  const MeshData m = Read(Slurp(SharedMesh("liver.vtk")));
  EXPECT_EQ(m.format, "VTK legacy 3.0 BINARY POLYDATA");
  EXPECT_EQ(m.vertices.cols(), 5008);
  EXPECT_EQ(m.triangles.cols(), 10000);
  EXPECT_EQ(m.tetrahedra.cols(), 0);
  EXPECT_TRUE(m.skipped.empty());
  const Eigen::Vector3d lo = m.vertices.rowwise().minCoeff();
  const Eigen::Vector3d hi = m.vertices.rowwise().maxCoeff();
  EXPECT_NEAR(lo.x(), 25.7094, 1e-3);
  EXPECT_NEAR(lo.y(), 60.8448, 1e-3);
  EXPECT_NEAR(lo.z(), 43.5186, 1e-3);
  EXPECT_NEAR(hi.x(), 219.984, 1e-3);
  EXPECT_NEAR(hi.y(), 214.55, 1e-3);
  EXPECT_NEAR(hi.z(), 200.0, 1e-3);
  // Binary write → read keeps it exactly (float data is exact in double).
  EXPECT_TRUE(SameMesh(m, Read(WriteVtkLegacy(m, Encoding::kBinary)), 0.0));
  EXPECT_TRUE(SameMesh(m, Read(WriteVtkLegacy(m, Encoding::kAscii)), 0.0));
}

// The broken SOFA liver has POINTS 508 instead of 5008, and its binary data was rewritten as
// text: bytes turned into backslash escapes such as \E3 (and carriage returns lost).
TEST(VtkLegacyReader, RefusesBrokenSofaLiverNamingTheFault) {
  const MeshError e = ErrorOf(Slurp(SharedMesh("liver_for_test_broken.vtk")));
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_EQ(e.where().byte, 62);
  EXPECT_TRUE(Contains(e.what(), "POINTS declares 508 points of float, i.e. 6096 bytes"))
      << e.what();
  EXPECT_TRUE(Contains(e.what(), "the next section (POLYGONS at byte 100451)")) << e.what();
  EXPECT_TRUE(Contains(e.what(), "backslash escapes such as '\\E3'")) << e.what();
}

}  // namespace
}  // namespace somasim::mesh_io
