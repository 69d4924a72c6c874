#include "common/mesh_io/vtu_io.h"

#include <gtest/gtest.h>
#include <zlib.h>

#include <chrono>
#include <cstdint>
#include <limits>
#include <random>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/base64.h"
#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_error.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

using ::somasim::testing::BoxSurface;
using ::somasim::testing::BoxTets;
using ::somasim::testing::Contains;
using ::somasim::testing::ErrorFrom;
using ::somasim::testing::Replace;
using ::somasim::testing::SameMesh;
using ::somasim::testing::SharedMesh;
using ::somasim::testing::SkippedCount;
using ::somasim::testing::Slurp;
using ::somasim::testing::SquarePatch;
using ::somasim::testing::TestData;

MeshData Read(std::string_view bytes, const ReadOptions& options = {}) {
  return ReadVtu(bytes, "test.vtu", options);
}

MeshError ErrorOf(std::string_view bytes, const ReadOptions& options = {}) {
  return ErrorFrom([&] { Read(bytes, options); }, bytes);
}

// ---------------------------------------------------------------------------------------------
// Files in the dialects ParaView and VTK write, made here with zlib and the base64 encoder.

struct Dialect {
  std::string name;
  std::string format = "binary";  // ascii | binary | appended
  bool appended_base64 = false;
  bool compressed = false;
  bool header64 = false;
  bool big_endian = false;
  size_t block_size = 32768;
  // Uncompressed inline binary with the header and the data base64-encoded separately (as some
  // non-VTK writers do) instead of as one stream (as VTK does).
  bool separate_header = false;
  bool no_header_type = false;  // version 0.1 files: UInt32 headers, no header_type attribute
};

class VtuMaker {
 public:
  explicit VtuMaker(Dialect d) : d_(std::move(d)) {}

  template <typename T>
  std::string Array(const char* type, const char* name, int components,
                    const std::vector<T>& values, const char* extra = "") {
    std::string xml = std::string("<DataArray type=\"") + type + "\" Name=\"" + name +
                      "\" NumberOfComponents=\"" + std::to_string(components) + "\"" + extra +
                      " format=\"" + d_.format + "\"";
    if (d_.format == "ascii") {
      xml += ">\n";
      for (T v : values) {
        if constexpr (std::is_floating_point_v<T>) {
          xml += FormatDouble(static_cast<double>(v)) + " ";
        } else {
          xml += std::to_string(static_cast<int64_t>(v)) + " ";
        }
      }
      return xml + "\n</DataArray>\n";
    }
    std::string raw;
    for (T v : values) AppendBinary(&raw, v, endian());
    if (d_.format == "appended") {
      xml += " offset=\"" + std::to_string(appended_.size()) + "\"/>\n";
      appended_ += Encode(raw, d_.appended_base64);
      return xml;
    }
    return xml + ">\n" + Encode(raw, true) + "\n</DataArray>\n";
  }

  std::string File(const std::string& piece_content, int64_t points, int64_t cells,
                   const std::string& type = "UnstructuredGrid") {
    std::string xml = "<?xml version=\"1.0\"?>\n<!-- written by a test -->\n<VTKFile type=\"" +
                      type + "\" version=\"" + (d_.no_header_type ? "0.1" : "1.0") + "\"";
    xml += d_.big_endian ? " byte_order=\"BigEndian\"" : " byte_order=\"LittleEndian\"";
    if (!d_.no_header_type) {
      xml += d_.header64 ? " header_type=\"UInt64\"" : " header_type=\"UInt32\"";
    }
    if (d_.compressed) xml += " compressor=\"vtkZLibDataCompressor\"";
    xml += ">\n<UnstructuredGrid>\n<Piece NumberOfPoints=\"" + std::to_string(points) +
           "\" NumberOfCells=\"" + std::to_string(cells) + "\">\n" + piece_content +
           "</Piece>\n</UnstructuredGrid>\n";
    if (d_.format == "appended") {
      xml += std::string("<AppendedData encoding=\"") + (d_.appended_base64 ? "base64" : "raw") +
             "\">\n   _" + appended_ + "\n</AppendedData>\n";
    }
    return xml + "</VTKFile>\n";
  }

  // A mesh written with Float32 points, Int32 connectivity and offsets, UInt8 types, plus point
  // and cell data that the reader must check and ignore.
  std::string Mesh(const MeshData& m) {
    const int64_t ntet = m.tetrahedra.cols(), ntri = m.triangles.cols();
    std::vector<float> points;
    for (Eigen::Index i = 0; i < m.vertices.size(); ++i) {
      points.push_back(static_cast<float>(m.vertices.data()[i]));
    }
    std::vector<int32_t> conn, offsets;
    std::vector<uint8_t> types;
    for (int64_t t = 0; t < ntet; ++t) {
      for (int k = 0; k < 4; ++k) conn.push_back(m.tetrahedra(k, t));
      offsets.push_back(static_cast<int32_t>(conn.size()));
      types.push_back(10);
    }
    for (int64_t t = 0; t < ntri; ++t) {
      for (int k = 0; k < 3; ++k) conn.push_back(m.triangles(k, t));
      offsets.push_back(static_cast<int32_t>(conn.size()));
      types.push_back(5);
    }
    const size_t n = static_cast<size_t>(m.vertices.cols());
    std::string piece = "<PointData Scalars=\"temperature\">\n" +
                        Array("Float64", "temperature", 1, std::vector<double>(n, 37.5)) +
                        "</PointData>\n<CellData>\n" +
                        Array("Int32", "material", 1, std::vector<int32_t>(types.size(), 3)) +
                        "</CellData>\n<Points>\n" + Array("Float32", "Points", 3, points) +
                        "</Points>\n<Cells>\n" + Array("Int32", "connectivity", 1, conn) +
                        Array("Int32", "offsets", 1, offsets) + Array("UInt8", "types", 1, types) +
                        "</Cells>\n";
    return File(piece, static_cast<int64_t>(n), ntet + ntri);
  }

 private:
  Endian endian() const { return d_.big_endian ? Endian::kBig : Endian::kLittle; }

  std::string Word(uint64_t v) const {
    std::string out;
    if (d_.header64) {
      AppendBinary(&out, v, endian());
    } else {
      AppendBinary(&out, static_cast<uint32_t>(v), endian());
    }
    return out;
  }

  // One array's bytes in VTK's layout, base64-encoded or raw.
  std::string Encode(const std::string& raw, bool base64) const {
    if (!d_.compressed) {
      const std::string header = Word(raw.size());
      if (!base64) return header + raw;
      if (d_.separate_header) return Base64Encode(header) + Base64Encode(raw);
      return Base64Encode(header + raw);  // one stream, as vtkXMLWriter does
    }
    std::string header, data;
    const size_t blocks = (raw.size() + d_.block_size - 1) / d_.block_size;
    header = Word(blocks) + Word(d_.block_size) + Word(raw.size() % d_.block_size);
    for (size_t b = 0; b < blocks; ++b) {
      const std::string block = raw.substr(b * d_.block_size, d_.block_size);
      uLongf size = compressBound(static_cast<uLong>(block.size()));
      std::string packed(size, '\0');
      EXPECT_EQ(compress2(reinterpret_cast<Bytef*>(packed.data()), &size,
                          reinterpret_cast<const Bytef*>(block.data()),
                          static_cast<uLong>(block.size()), 6),
                Z_OK);
      packed.resize(size);
      header += Word(size);
      data += packed;
    }
    // VTK encodes the compression header and the blocks as two separate base64 streams.
    return base64 ? Base64Encode(header) + Base64Encode(data) : header + data;
  }

  Dialect d_;
  std::string appended_;
};

std::vector<Dialect> ParaViewDialects() {
  std::vector<Dialect> out;
  out.push_back({.name = "ascii", .format = "ascii"});
  out.push_back({.name = "inline binary UInt32", .format = "binary"});
  out.push_back({.name = "inline binary UInt64", .format = "binary", .header64 = true});
  out.push_back({.name = "inline binary, version 0.1", .format = "binary", .no_header_type = true});
  out.push_back(
      {.name = "inline binary, separate header", .format = "binary", .separate_header = true});
  out.push_back({.name = "inline binary BigEndian", .format = "binary", .big_endian = true});
  out.push_back({.name = "inline zlib", .format = "binary", .compressed = true});
  out.push_back({.name = "inline zlib, small blocks UInt64 BigEndian",
                 .format = "binary",
                 .compressed = true,
                 .header64 = true,
                 .big_endian = true,
                 .block_size = 64});
  out.push_back({.name = "appended raw", .format = "appended"});
  out.push_back({.name = "appended raw UInt64 BigEndian",
                 .format = "appended",
                 .header64 = true,
                 .big_endian = true});
  out.push_back({.name = "appended base64", .format = "appended", .appended_base64 = true});
  out.push_back(
      {.name = "appended raw zlib", .format = "appended", .compressed = true, .block_size = 100});
  out.push_back({.name = "appended base64 zlib",
                 .format = "appended",
                 .appended_base64 = true,
                 .compressed = true,
                 .block_size = 100});
  return out;
}

// A box whose coordinates are exact in float32: the dialects write Float32 points.
MeshData FloatExactBox() { return BoxTets(2, 1, 1); }

// ---------------------------------------------------------------------------------------------
// Round trips

TEST(VtuWriter, RoundTripIsBitExactInEveryEncoding) {
  const std::vector<MeshData> meshes = {BoxTets(3, 2, 2, 0.3, 0.7, 1.0 / 3.0), BoxSurface(2, 1, 3),
                                        SquarePatch(3)};
  for (const MeshData& mesh : meshes) {
    for (VtuEncoding encoding :
         {VtuEncoding::kAscii, VtuEncoding::kBase64, VtuEncoding::kAppendedRaw}) {
      for (bool big : {false, true}) {
        const std::string text = WriteVtu(mesh, {encoding, big});
        const MeshData read = Read(text);
        EXPECT_TRUE(SameMesh(mesh, read, 0.0));
        EXPECT_EQ(read.tetrahedra.cols(), mesh.tetrahedra.cols());
        EXPECT_EQ(read.triangles.cols(), mesh.triangles.cols());
        EXPECT_TRUE(read.skipped.empty());
        EXPECT_EQ(WriteVtu(read, {encoding, big}), text);
      }
    }
  }
}

TEST(VtuWriter, WritesTheAnnouncedLayout) {
  const MeshData box = BoxTets(1, 1, 1);
  const std::string ascii = WriteVtu(box, {VtuEncoding::kAscii, false});
  EXPECT_TRUE(Contains(ascii, "<Piece NumberOfPoints=\"8\" NumberOfCells=\"18\">"));
  EXPECT_TRUE(Contains(ascii, "type=\"Float64\" Name=\"Points\" NumberOfComponents=\"3\""));
  EXPECT_TRUE(Contains(ascii, "type=\"Int64\" Name=\"connectivity\""));
  EXPECT_TRUE(Contains(ascii, "type=\"UInt8\" Name=\"types\""));
  EXPECT_TRUE(Contains(ascii, "\n          10 10 10 10 10 10\n          5 5"));
  const std::string big = WriteVtu(box, {VtuEncoding::kAppendedRaw, true});
  EXPECT_TRUE(Contains(big, "byte_order=\"BigEndian\" header_type=\"UInt32\""));
  EXPECT_TRUE(Contains(big, "<AppendedData encoding=\"raw\">\n   _"));
  // The Points block starts with its UInt32 byte count, big-endian: 8 points × 24 bytes.
  const size_t data = big.find('_', big.find("<AppendedData")) + 1;
  EXPECT_EQ(big.substr(data, 4), std::string("\0\0\0\xc0", 4));
}

// Point data (e.g. somasim-solve's displacement) goes into <PointData> in every encoding; our own
// reader checks its size against the points and still reads the mesh.
TEST(VtuWriter, WritesPointData) {
  MeshData box = BoxTets(1, 1, 1);
  PointArray displacement{"displacement", 3, {}};
  for (int k = 0; k < 24; ++k) displacement.values.push_back(0.25 * k - 1.0);
  box.point_data.push_back(displacement);
  box.point_data.push_back({"pressure", 1, std::vector<double>(8, 3.5)});
  for (VtuEncoding encoding :
       {VtuEncoding::kAscii, VtuEncoding::kBase64, VtuEncoding::kAppendedRaw}) {
    const std::string text = WriteVtu(box, {encoding, false});
    EXPECT_TRUE(Contains(text, "<PointData>")) << static_cast<int>(encoding);
    EXPECT_TRUE(Contains(text, "Name=\"displacement\" NumberOfComponents=\"3\""));
    EXPECT_TRUE(SameMesh(box, Read(text), 0.0));
  }
  const std::string ascii = WriteVtu(box, {VtuEncoding::kAscii, false});
  EXPECT_TRUE(Contains(ascii, "\n          -1 -0.75 -0.5\n          -0.25 0 0.25\n"));
  MeshData bad = box;
  bad.point_data[0].values.pop_back();
  EXPECT_THROW(WriteVtu(bad, {}), std::invalid_argument);
  bad = box;
  bad.point_data[0].name = "a\"b";
  EXPECT_THROW(WriteVtu(bad, {}), std::invalid_argument);
}

// A well-formed file with no points is written, but reading refuses it (MeshBuilder's rule).
TEST(VtuWriter, EmptyMeshIsWrittenButRefusedOnRead) {
  for (VtuEncoding encoding :
       {VtuEncoding::kAscii, VtuEncoding::kBase64, VtuEncoding::kAppendedRaw}) {
    try {
      Read(WriteVtu(MeshData{}, {encoding, false}));
      ADD_FAILURE() << "accepted";
    } catch (const MeshError& e) {
      EXPECT_NE(e.fault().find("holds no nodes"), std::string::npos) << e.what();
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Dialects

TEST(VtuReader, ReadsEveryParaViewDialect) {
  const MeshData box = FloatExactBox();
  for (const Dialect& d : ParaViewDialects()) {
    SCOPED_TRACE(d.name);
    const std::string file = VtuMaker(d).Mesh(box);
    MeshData read;
    ASSERT_NO_THROW(read = Read(file)) << ErrorOf(file).what();
    EXPECT_TRUE(SameMesh(box, read, 0.0));
  }
}

TEST(VtuReader, ReadsSmallHandWrittenFiles) {
  const MeshData two = Read(Slurp(TestData("vtk/two_pieces.vtu")));
  EXPECT_EQ(two.vertices.cols(), 9);
  ASSERT_EQ(two.tetrahedra.cols(), 2);
  EXPECT_EQ(two.tetrahedra.col(1), Eigen::Vector4i(4, 5, 6, 7));  // second piece, offset by 4
  EXPECT_EQ(two.triangles.cols(), 1);
  EXPECT_EQ(SkippedCount(two, "VTK_QUAD"), 1);
  EXPECT_EQ(SkippedCount(two, "VTK_QUADRATIC_TETRA"), 0);
  EXPECT_EQ(SkippedCount(two, "VTK_VERTEX"), 1);
  const MeshData zlib = Read(Slurp(TestData("vtk/zlib_appended.vtu")));
  EXPECT_EQ(zlib.vertices.cols(), 4);
  EXPECT_EQ(zlib.tetrahedra.cols(), 1);
}

TEST(VtuReader, RefusesEveryTruncation) {
  std::vector<std::string> files;
  const MeshData box = BoxTets(1, 1, 1);
  for (VtuEncoding encoding :
       {VtuEncoding::kAscii, VtuEncoding::kBase64, VtuEncoding::kAppendedRaw}) {
    files.push_back(WriteVtu(box, {encoding, encoding == VtuEncoding::kAppendedRaw}));
  }
  Dialect zlib{.name = "zlib", .format = "appended", .compressed = true, .block_size = 64};
  files.push_back(VtuMaker(zlib).Mesh(FloatExactBox()));
  for (const std::string& full : files) {
    for (size_t len = 0; len < full.size(); ++len) {
      const std::string_view rest = std::string_view(full).substr(len);
      if (rest.find_first_not_of(" \n") == std::string_view::npos) continue;
      try {
        Read(full.substr(0, len));
        ADD_FAILURE() << "a cut after " << len << " bytes was accepted";
      } catch (const MeshError&) {
      }
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Bad input

// The corner tetrahedron, ASCII; the parts can be replaced to make faulty files.
std::string CornerTet(const std::string& points = "0 0 0 1 0 0 0 1 0 0 0 1",
                      const std::string& conn = "0 1 2 3", const std::string& offsets = "4",
                      const std::string& types = "10",
                      const std::string& piece = "NumberOfPoints=\"4\" NumberOfCells=\"1\"") {
  return "<VTKFile type=\"UnstructuredGrid\" version=\"0.1\" byte_order=\"LittleEndian\">\n"
         "  <UnstructuredGrid>\n"
         "    <Piece " +
         piece +
         ">\n"
         "      <Points>\n"
         "        <DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"ascii\">\n"
         "          " +
         points +
         "\n"
         "        </DataArray>\n"
         "      </Points>\n"
         "      <Cells>\n"
         "        <DataArray type=\"Int32\" Name=\"connectivity\" format=\"ascii\">\n"
         "          " +
         conn +
         "\n"
         "        </DataArray>\n"
         "        <DataArray type=\"Int32\" Name=\"offsets\" format=\"ascii\">\n"
         "          " +
         offsets +
         "\n"
         "        </DataArray>\n"
         "        <DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">\n"
         "          " +
         types +
         "\n"
         "        </DataArray>\n"
         "      </Cells>\n"
         "    </Piece>\n"
         "  </UnstructuredGrid>\n"
         "</VTKFile>\n";
}

TEST(VtuReader, ReadsTheCornerTet) {
  const MeshData m = Read(CornerTet());
  EXPECT_EQ(m.tetrahedra.cols(), 1);
  EXPECT_EQ(m.format, "VTK XML UnstructuredGrid");
}

TEST(VtuReader, RefusesNonFiniteCoordinateNamingTheLine) {
  const MeshError e = ErrorOf(CornerTet("0 0 0 1 0 0\n          0 nan 0 0 0 1"));
  EXPECT_EQ(e.kind(), MeshErrorKind::kValue);
  EXPECT_EQ(e.where().line, 7);
  EXPECT_EQ(ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 -inf")).kind(), MeshErrorKind::kValue);
}

TEST(VtuReader, RefusesNonFiniteBinaryCoordinateNamingTheByte) {
  MeshData tet = ::somasim::testing::RegularTet();
  std::string file = WriteVtu(tet, {VtuEncoding::kAppendedRaw, false});
  const size_t data = file.find('_', file.find("<AppendedData")) + 1;
  const double inf = std::numeric_limits<double>::infinity();
  std::string bytes;
  AppendBinary(&bytes, inf, Endian::kLittle);
  file.replace(data + 4 + 3 * 8 + 8, 8, bytes);  // y of the second point
  const MeshError e = ErrorOf(file);
  EXPECT_EQ(e.kind(), MeshErrorKind::kValue);
  EXPECT_EQ(e.where().byte, static_cast<int64_t>(data + 4 + 3 * 8));
}

TEST(VtuReader, RefusesIndexOutOfRange) {
  const MeshError e = ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2 4"));
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.where().line, 11);
  EXPECT_TRUE(Contains(e.what(), "refers to point 4 but the piece has 4 points")) << e.what();
  EXPECT_EQ(ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 -2 3")).kind(),
            MeshErrorKind::kIndex);
}

TEST(VtuReader, RefusesCountsThatDisagreeWithTheData) {
  const MeshError points = ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1 5"));
  EXPECT_EQ(points.kind(), MeshErrorKind::kCount);
  EXPECT_EQ(points.where().line, 3);
  EXPECT_TRUE(Contains(points.what(),
                       "NumberOfPoints is 4 but the Points array (line 5) holds "
                       "13 values (not a whole number of points)"))
      << points.what();
  const MeshError cells = ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2 3", "4", "10 10"));
  EXPECT_EQ(cells.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(cells.what(), "NumberOfCells is 1 but the types array (line 16) has 2"))
      << cells.what();
  const MeshError conn = ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2 3 0"));
  EXPECT_EQ(conn.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(conn.what(),
                       "the last offset is 4 but the connectivity array (line 10) "
                       "has 5 entries"))
      << conn.what();
  // Point data of the wrong length.
  const std::string with_data =
      Replace(CornerTet(), "      <Points>",
              "      <PointData><DataArray type=\"Float64\" Name=\"t\" format=\"ascii\">1 2 3"
              "</DataArray></PointData>\n      <Points>");
  EXPECT_EQ(ErrorOf(with_data).kind(), MeshErrorKind::kCount);
}

TEST(VtuReader, RefusesOffsetsThatDecrease) {
  const MeshError e = ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2 3", "4 3 4", "10 10 10",
                                        "NumberOfPoints=\"4\" NumberOfCells=\"3\""));
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(e.what(), "offsets must not decrease")) << e.what();
}

TEST(VtuReader, RefusesAbsurdCountsFast) {
  const auto start = std::chrono::steady_clock::now();
  EXPECT_EQ(ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2 3", "4", "10",
                              "NumberOfPoints=\"1000000000000\" NumberOfCells=\"1\""))
                .kind(),
            MeshErrorKind::kCount);
  EXPECT_EQ(ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2 3", "4", "10",
                              "NumberOfPoints=\"4\" NumberOfCells=\"99999999999999999999\""))
                .kind(),
            MeshErrorKind::kSyntax);
  // A binary header announcing 2^40 bytes.
  std::string header;
  AppendBinary(&header, uint64_t{1} << 40, Endian::kLittle);
  std::string file = WriteVtu(BoxTets(1, 1, 1), {VtuEncoding::kAppendedRaw, false});
  file = Replace(file, "header_type=\"UInt32\"", "header_type=\"UInt64\"");
  const size_t data = file.find('_', file.find("<AppendedData")) + 1;
  file.replace(data, 4, header);
  EXPECT_EQ(ErrorOf(file).kind(), MeshErrorKind::kCount);
  // A compression header announcing 2^31 blocks, or blocks that inflate 10^6-fold.
  VtuMaker zlib({.name = "zlib", .format = "binary", .compressed = true});
  std::string words;
  for (uint32_t w : {0x80000000u, 32768u, 0u}) AppendBinary(&words, w, Endian::kLittle);
  const std::string bomb_header = Base64Encode(words);
  const std::string good = zlib.Mesh(FloatExactBox());
  const size_t points = good.find("Name=\"Points\"");
  const size_t text = good.find('>', points) + 2;
  std::string many_blocks = good;
  many_blocks.replace(text, bomb_header.size(), bomb_header);
  const MeshError blocks = ErrorOf(many_blocks);
  EXPECT_EQ(blocks.kind(), MeshErrorKind::kCount) << blocks.what();
  words.clear();
  for (uint32_t w : {1u, 1000000000u, 0u, 12u}) AppendBinary(&words, w, Endian::kLittle);
  std::string bomb = good;
  const std::string bomb_words = Base64Encode(words);
  bomb.replace(text, bomb_words.size(), bomb_words);
  const MeshError inflate = ErrorOf(bomb);
  EXPECT_EQ(inflate.kind(), MeshErrorKind::kCount) << inflate.what();
  EXPECT_TRUE(Contains(inflate.what(), "more than zlib can")) << inflate.what();
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(2));
}

TEST(VtuReader, RefusesCorruptCompressedData) {
  Dialect d{.name = "zlib", .format = "appended", .compressed = true};
  std::string file = VtuMaker(d).Mesh(FloatExactBox());
  const size_t data = file.find('_', file.find("<AppendedData")) + 1;
  // The first array (temperature) has one block: 4 header words, then its zlib stream.
  file[data + 16 + 5] = static_cast<char>(file[data + 16 + 5] ^ 0x55);
  const MeshError e = ErrorOf(file);
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().byte, static_cast<int64_t>(data + 16));
  EXPECT_TRUE(Contains(e.what(), "compressed block #1 is corrupt")) << e.what();
}

TEST(VtuReader, RefusesUnknownElementsNamingTheLine) {
  const MeshError e =
      ErrorOf(Replace(CornerTet(), "      <Cells>", "      <Verts/>\n      <Cells>"));
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().line, 9);
  EXPECT_TRUE(Contains(e.what(), "unknown element <Verts> inside <Piece>")) << e.what();
  const MeshError array = ErrorOf(Replace(CornerTet(), "Name=\"offsets\"", "Name=\"offset\""));
  EXPECT_EQ(array.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf(Replace(CornerTet(), "format=\"ascii\"", "format=\"hex\"")).kind(),
            MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf(Replace(CornerTet(), "type=\"UInt8\"", "type=\"UInt7\"")).kind(),
            MeshErrorKind::kSyntax);
}

TEST(VtuReader, RefusesMalformedXmlNamingTheLine) {
  const MeshError e = ErrorOf(Replace(CornerTet(), "      </Points>", "      </Pointz>"));
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(e.where().line, 8);
  EXPECT_TRUE(Contains(e.what(), "malformed XML")) << e.what();
}

TEST(VtuReader, RefusesWrongElementSizes) {
  const MeshError e = ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2", "3"));
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_TRUE(Contains(e.what(), "cell #1 is a VTK_TETRA but has 3 points instead of 4"))
      << e.what();
  EXPECT_EQ(e.where().line, 11);
  const MeshError unknown = ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2 3", "4", "99"));
  EXPECT_EQ(unknown.kind(), MeshErrorKind::kSyntax);
  EXPECT_TRUE(Contains(unknown.what(), "unknown VTK cell type 99")) << unknown.what();
  EXPECT_EQ(ErrorOf(CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 1 2 3", "4", "300")).kind(),
            MeshErrorKind::kSyntax);  // 300 does not fit in UInt8
}

TEST(VtuReader, InvertedTetrahedronIsRefusedOrFlipped) {
  const std::string file = CornerTet("0 0 0 1 0 0 0 1 0 0 0 1", "0 2 1 3");
  const MeshError e = ErrorOf(file);
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
  EXPECT_EQ(e.where().line, 11);
  ReadOptions fix;
  fix.fix_orientation = true;
  const MeshData m = Read(file, fix);
  EXPECT_EQ(m.num_flipped, 1);
}

TEST(VtuReader, RefusesOtherFileTypesAndCompressors) {
  const MeshError poly =
      ErrorOf(Replace(CornerTet(), "UnstructuredGrid\" version", "PolyData\" version"));
  EXPECT_EQ(poly.kind(), MeshErrorKind::kUnsupported);
  EXPECT_TRUE(Contains(poly.what(), "'PolyData'")) << poly.what();
  const MeshError lz4 = ErrorOf(Replace(CornerTet(), "byte_order=\"LittleEndian\"",
                                        "byte_order=\"LittleEndian\" "
                                        "compressor=\"vtkLZ4DataCompressor\""));
  EXPECT_EQ(lz4.kind(), MeshErrorKind::kUnsupported);
  EXPECT_TRUE(Contains(lz4.what(), "vtkLZ4DataCompressor")) << lz4.what();
  EXPECT_EQ(ErrorOf(Replace(CornerTet(), "LittleEndian", "MiddleEndian")).kind(),
            MeshErrorKind::kSyntax);
}

TEST(VtuReader, RefusesBadBinaryData) {
  std::string base64 = WriteVtu(BoxTets(1, 1, 1), {VtuEncoding::kBase64, false});
  const size_t text = base64.find('>', base64.find("Name=\"Points\"")) + 12;
  std::string bad_char = base64;
  bad_char[text + 5] = '*';
  const MeshError e = ErrorOf(bad_char);
  EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
  EXPECT_TRUE(Contains(e.what(), "'*' is not a base64 character")) << e.what();
  EXPECT_GE(e.where().byte, static_cast<int64_t>(text));
  // Extra base64 data after what the header announces.
  std::string extra = Replace(base64, "\n        </DataArray>\n      </Points>",
                              "AAAA\n        </DataArray>\n      </Points>");
  EXPECT_EQ(ErrorOf(extra).kind(), MeshErrorKind::kCount);
  // Appended data: missing '_', offset past the end, unknown encoding.
  std::string raw = WriteVtu(BoxTets(1, 1, 1), {VtuEncoding::kAppendedRaw, false});
  EXPECT_EQ(ErrorOf(Replace(raw, "   _", "   ")).kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf(Replace(raw, "offset=\"0\"", "offset=\"999999\"")).kind(),
            MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf(Replace(raw, "encoding=\"raw\"", "encoding=\"hex\"")).kind(),
            MeshErrorKind::kSyntax);
}

TEST(VtuReader, RefusesGarbage) {
  EXPECT_EQ(ErrorOf("").kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf("<html><body/></html>").kind(), MeshErrorKind::kSyntax);
  EXPECT_EQ(ErrorOf("# vtk DataFile Version 3.0\n").kind(), MeshErrorKind::kSyntax);
  std::mt19937 rng(11);
  std::vector<std::string> seeds;
  for (const Dialect& d : ParaViewDialects()) seeds.push_back(VtuMaker(d).Mesh(FloatExactBox()));
  for (int round = 0; round < 400; ++round) {
    try {
      Read(testing::DamageBytes(seeds[static_cast<size_t>(round) % seeds.size()], 3, &rng));
    } catch (const MeshError&) {
    }
  }
  std::string noise(3000, '\0');
  for (char& c : noise) c = static_cast<char>(rng() & 0xff);
  EXPECT_THROW(Read(noise), MeshError);
}

// ---------------------------------------------------------------------------------------------
// Base64

TEST(Base64, RoundTripsEveryLength) {
  std::string bytes;
  for (int n = 0; n < 40; ++n) {
    const std::string text = Base64Encode(bytes);
    EXPECT_EQ(text.size() % 4, 0u);
    std::string back, error;
    ASSERT_TRUE(Base64Decode(text, &back, &error)) << error;
    EXPECT_EQ(back, bytes);
    bytes += static_cast<char>(n * 37 + 200);
  }
  EXPECT_EQ(Base64Encode("Man"), "TWFu");
  EXPECT_EQ(Base64Encode("Ma"), "TWE=");
  EXPECT_EQ(Base64Encode("M"), "TQ==");
}

TEST(Base64, DecodesConcatenatedPaddedStreamsAndSkipsWhitespace) {
  std::string out, error;
  ASSERT_TRUE(Base64Decode("TQ==\n TWE=\tTWFu", &out, &error)) << error;
  EXPECT_EQ(out, "MMaMan");
  EXPECT_FALSE(Base64Decode("TW=u", &out, &error));
  EXPECT_FALSE(Base64Decode("T===", &out, &error));
  EXPECT_FALSE(Base64Decode("TWF", &out, &error));
  EXPECT_FALSE(Base64Decode("TW-u", &out, &error));
}

// ---------------------------------------------------------------------------------------------
// Real files

::testing::AssertionResult BoxIs(const MeshData& m, const Eigen::Vector3d& lo,
                                 const Eigen::Vector3d& hi) {
  const Eigen::Vector3d a = m.vertices.rowwise().minCoeff(), b = m.vertices.rowwise().maxCoeff();
  if ((a - lo).cwiseAbs().maxCoeff() > 1e-5 || (b - hi).cwiseAbs().maxCoeff() > 1e-5) {
    return ::testing::AssertionFailure()
           << "bounding box " << a.transpose() << " .. " << b.transpose();
  }
  return ::testing::AssertionSuccess();
}

TEST(VtuReader, ReadsSofaArmadillo) {
  const MeshData m = Read(Slurp(SharedMesh("Armadillo_Tetra_4406.vtu")));
  EXPECT_EQ(m.vertices.cols(), 1446);
  EXPECT_EQ(m.tetrahedra.cols(), 4406);
  EXPECT_EQ(m.triangles.cols(), 0);
  EXPECT_TRUE(m.skipped.empty());
  EXPECT_TRUE(BoxIs(m, {-6.33702, -5.40248, -5.76189}, {6.33169, 9.69253, 5.76059}));
  for (VtuEncoding encoding :
       {VtuEncoding::kAscii, VtuEncoding::kBase64, VtuEncoding::kAppendedRaw}) {
    EXPECT_TRUE(SameMesh(m, Read(WriteVtu(m, {encoding, false})), 0.0));
  }
}

TEST(VtuReader, ReadsSofaRaptor) {
  const MeshData m = Read(Slurp(SharedMesh("raptorTetra_8418.vtu")));
  EXPECT_EQ(m.vertices.cols(), 2996);
  EXPECT_EQ(m.tetrahedra.cols(), 8418);
  EXPECT_EQ(m.triangles.cols(), 0);
  EXPECT_TRUE(BoxIs(m, {-2.11393, -0.247808, -9.13365}, {2.10897, 6.97908, 6.88252}));
}

// The broken Armadillo says 1445 points and 4407 cells for 1446 points and 4406 types, lacks
// one offset and one connectivity index.
TEST(VtuReader, RefusesBrokenSofaArmadilloNamingTheFault) {
  const MeshError e = ErrorOf(Slurp(SharedMesh("Armadillo_Tetra_4406_for_test_broken.vtu")));
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_EQ(e.where().line, 3);
  for (const char* part :
       {"NumberOfPoints is 1445 but the Points array (line 5) holds 4338 values (1446 points)",
        "NumberOfCells is 4407 but the offsets array (line 5863) has 4405 entries",
        "NumberOfCells is 4407 but the types array (line 5866) has 4406 entries",
        "the last offset is 17624 but the connectivity array (line 1455) has 17623 entries"}) {
    EXPECT_TRUE(Contains(e.what(), part)) << e.what();
  }
}

}  // namespace
}  // namespace somasim::mesh_io
