#include "common/mesh_io/stl_io.h"

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <string_view>
#include <unordered_map>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/text_reader.h"

namespace somasim::mesh_io {
namespace {

constexpr size_t kBinaryHeaderBytes = 84;  // 80-byte free text, then the uint32 triangle count
constexpr size_t kBinaryFacetBytes = 50;   // normal + 3 corners (12 float32) + uint16 attribute

bool EqualsNoCase(std::string_view a, std::string_view b) {
  if (a.size() != b.size()) return false;
  for (size_t i = 0; i < a.size(); ++i) {
    if (std::tolower(static_cast<unsigned char>(a[i])) !=
        std::tolower(static_cast<unsigned char>(b[i]))) {
      return false;
    }
  }
  return true;
}

std::string_view SkipBom(std::string_view bytes) {
  if (bytes.substr(0, 3) == "\xEF\xBB\xBF") bytes.remove_prefix(3);
  return bytes;
}

// ASCII STL starts with the keyword "solid" (any case), possibly after white space.
bool StartsWithSolid(std::string_view bytes) {
  bytes = SkipBom(bytes);
  size_t i = 0;
  while (i < bytes.size() && std::isspace(static_cast<unsigned char>(bytes[i]))) ++i;
  if (!EqualsNoCase(bytes.substr(i, 5), "solid")) return false;
  return i + 5 == bytes.size() || std::isspace(static_cast<unsigned char>(bytes[i + 5]));
}

// True when the bytes contain control characters that never occur in a text file.
bool LooksBinary(std::string_view bytes) {
  for (char ch : bytes) {
    const auto c = static_cast<unsigned char>(ch);
    if ((c < 0x20 && !std::isspace(c)) || c == 0x7f) return true;
  }
  return false;
}

// Why the file is not a binary STL, in words.
std::string NotBinaryReason(std::string_view bytes) {
  if (bytes.size() < kBinaryHeaderBytes) {
    return "at " + std::to_string(bytes.size()) + " bytes it is shorter than the " +
           std::to_string(kBinaryHeaderBytes) + "-byte header of a binary STL";
  }
  ByteReader header(bytes.substr(80, 4), "");
  const uint32_t count = header.Read<uint32_t>(Endian::kLittle, "triangle count");
  const uint64_t need = kBinaryHeaderBytes + kBinaryFacetBytes * uint64_t{count};
  return "a binary STL with " + std::to_string(count) + " triangle" + (count == 1 ? "" : "s") +
         " (the count in its header) needs " + std::to_string(need) + " bytes, but the file has " +
         std::to_string(bytes.size());
}

// Coordinates equal as numbers (bit patterns after turning -0 into +0) share a node; nodes are
// numbered in order of first appearance, so the result does not depend on hashing.
template <typename Bits>
struct CornerKeyHash {
  size_t operator()(const std::array<Bits, 3>& k) const {
    uint64_t h = 0x9E3779B97F4A7C15ull;
    for (Bits b : k) {
      h ^= static_cast<uint64_t>(b) + 0x9E3779B97F4A7C15ull + (h << 6) + (h >> 2);
    }
    return static_cast<size_t>(h);
  }
};

template <typename Real, typename Bits>
class CornerMerger {
 public:
  explicit CornerMerger(MeshBuilder* builder) : builder_(builder) {}
  void Reserve(size_t n) { index_.reserve(n); }

  int64_t Node(Real x, Real y, Real z, SourceLocation where) {
    const std::array<Bits, 3> key = {BitsOf(x), BitsOf(y), BitsOf(z)};
    auto [it, inserted] = index_.try_emplace(key, builder_->num_nodes());
    if (inserted) {
      builder_->AddNode(static_cast<double>(x), static_cast<double>(y), static_cast<double>(z),
                        where);
    }
    return it->second;
  }

 private:
  static Bits BitsOf(Real v) {
    const Real positive_zero = v + Real(0);  // -0 + 0 = +0; everything else unchanged
    Bits b;
    std::memcpy(&b, &positive_zero, sizeof b);
    return b;
  }

  MeshBuilder* builder_;
  std::unordered_map<std::array<Bits, 3>, int64_t, CornerKeyHash<Bits>> index_;
};

MeshData ReadBinaryStl(std::string_view bytes, const std::string& file_name,
                       const ReadOptions& options) {
  ByteReader reader(bytes, file_name);
  reader.Bytes(80, "header");
  const uint32_t count = reader.Read<uint32_t>(Endian::kLittle, "triangle count");
  reader.CheckCount(count, kBinaryFacetBytes, "triangles");
  MeshBuilder builder(file_name, "STL binary");
  // A closed surface has about half as many nodes as triangles.
  builder.Reserve(count / 2 + 3, count, 0);
  CornerMerger<float, uint32_t> merger(&builder);
  merger.Reserve(count / 2 + 3);
  for (uint32_t t = 0; t < count; ++t) {
    const SourceLocation where = SourceLocation::Byte(reader.file_offset());
    for (int k = 0; k < 3; ++k) reader.Read<float>(Endian::kLittle, "facet normal");
    int64_t corner[3];
    for (int64_t& c : corner) {
      const float x = reader.Read<float>(Endian::kLittle, "facet corner");
      const float y = reader.Read<float>(Endian::kLittle, "facet corner");
      const float z = reader.Read<float>(Endian::kLittle, "facet corner");
      c = merger.Node(x, y, z, where);
    }
    reader.Read<uint16_t>(Endian::kLittle, "facet attribute");
    builder.AddTriangle(corner[0], corner[1], corner[2], where);
  }
  return builder.Finish(options);
}

void Expect(TextReader* reader, std::string_view keyword, std::string_view context) {
  const std::string_view token = reader->Token("'" + std::string(keyword) + "'");
  if (!EqualsNoCase(token, keyword)) {
    reader->Fail(MeshErrorKind::kSyntax, "expected '" + std::string(keyword) + "' " +
                                             std::string(context) + ", found " + QuoteToken(token));
  }
}

MeshData ReadAsciiStl(std::string_view bytes, const std::string& file_name,
                      const ReadOptions& options) {
  TextReader reader(bytes, file_name);
  reader.Skip(bytes.size() - SkipBom(bytes).size());
  MeshBuilder builder(file_name, "STL ASCII");
  CornerMerger<double, uint64_t> merger(&builder);
  bool first_solid = true;
  // Several solids may follow one another; each is "solid [name] facet... endsolid [name]".
  while (!reader.AtEnd()) {
    const std::string_view solid = reader.Token("'solid'");
    if (!EqualsNoCase(solid, "solid")) {
      reader.Fail(MeshErrorKind::kSyntax,
                  std::string(first_solid ? "expected 'solid'"
                                          : "expected 'solid' or the end of "
                                            "the file after 'endsolid'") +
                      ", found " + QuoteToken(solid));
    }
    first_solid = false;
    reader.TryLine();  // the solid's name, free text
    for (;;) {
      const std::string_view token = reader.Token("'facet' or 'endsolid'");
      if (EqualsNoCase(token, "endsolid")) {
        reader.TryLine();  // the name again, free text
        break;
      }
      if (!EqualsNoCase(token, "facet")) {
        reader.Fail(MeshErrorKind::kSyntax,
                    "expected 'facet' or 'endsolid', found " + QuoteToken(token));
      }
      const SourceLocation facet = reader.token_location();
      Expect(&reader, "normal", "after 'facet'");
      // The normal is not used (it is redundant with the corner order, and often zero).
      for (int k = 0; k < 3; ++k) reader.Double("a component of the facet normal");
      Expect(&reader, "outer", "after the facet normal");
      Expect(&reader, "loop", "after 'outer'");
      int64_t corner[3] = {};
      int num_corners = 0;
      for (;;) {
        const std::string_view v = reader.Token("'vertex' or 'endloop'");
        if (EqualsNoCase(v, "endloop")) break;
        if (!EqualsNoCase(v, "vertex")) {
          reader.Fail(MeshErrorKind::kSyntax,
                      "expected 'vertex' or 'endloop', found " + QuoteToken(v));
        }
        const SourceLocation where = reader.token_location();
        const double x = reader.Double("the x coordinate of a vertex");
        const double y = reader.Double("the y coordinate of a vertex");
        const double z = reader.Double("the z coordinate of a vertex");
        if (num_corners == 3) {
          reader.FailAt(MeshErrorKind::kSyntax, facet,
                        "facet has more than 3 vertices; STL facets are triangles");
        }
        corner[num_corners++] = merger.Node(x, y, z, where);
      }
      if (num_corners != 3) {
        reader.FailAt(MeshErrorKind::kSyntax, facet,
                      "facet has " + std::to_string(num_corners) +
                          " vertices; STL facets are triangles (3 vertices)");
      }
      Expect(&reader, "endfacet", "after 'endloop'");
      builder.AddTriangle(corner[0], corner[1], corner[2], facet);
    }
  }
  return builder.Finish(options);
}

Eigen::Vector3d UnitNormal(const MeshData& mesh, Eigen::Index t) {
  const Eigen::Vector3d a = mesh.vertices.col(mesh.triangles(0, t));
  const Eigen::Vector3d b = mesh.vertices.col(mesh.triangles(1, t));
  const Eigen::Vector3d c = mesh.vertices.col(mesh.triangles(2, t));
  const Eigen::Vector3d n = (b - a).cross(c - a);
  const double length = n.norm();
  return length > 0 && std::isfinite(length) ? Eigen::Vector3d(n / length)
                                             : Eigen::Vector3d::Zero();
}

void CheckIndices(const MeshData& mesh) {
  for (Eigen::Index i = 0; i < mesh.triangles.size(); ++i) {
    const int32_t v = mesh.triangles.data()[i];
    if (v < 0 || v >= mesh.vertices.cols()) {
      throw MeshError(MeshErrorKind::kIndex, "", {},
                      "cannot write STL: triangle #" + std::to_string(i / 3 + 1) +
                          " refers to node " + std::to_string(v) + " of " +
                          std::to_string(mesh.vertices.cols()));
    }
  }
}

std::string WriteAsciiStl(const MeshData& mesh) {
  std::string out = "solid somasim\n";
  out.reserve(static_cast<size_t>(mesh.triangles.cols()) * 256 + 32);
  for (Eigen::Index t = 0; t < mesh.triangles.cols(); ++t) {
    const Eigen::Vector3d n = UnitNormal(mesh, t);
    out += "  facet normal";
    for (int k = 0; k < 3; ++k) {
      out += ' ';
      AppendDouble(&out, n[k]);
    }
    out += "\n    outer loop\n";
    for (int c = 0; c < 3; ++c) {
      out += "      vertex";
      for (int k = 0; k < 3; ++k) {
        out += ' ';
        AppendDouble(&out, mesh.vertices(k, mesh.triangles(c, t)));
      }
      out += '\n';
    }
    out += "    endloop\n  endfacet\n";
  }
  out += "endsolid somasim\n";
  return out;
}

float ToFloat(double value, Eigen::Index node) {
  if (std::isfinite(value) &&
      std::abs(value) > static_cast<double>(std::numeric_limits<float>::max())) {
    throw MeshError(MeshErrorKind::kValue, "", {},
                    "cannot write binary STL: node " + std::to_string(node) + " has coordinate " +
                        FormatDouble(value) + ", beyond the range of float32");
  }
  return static_cast<float>(value);
}

std::string WriteBinaryStl(const MeshData& mesh) {
  const Eigen::Index count = mesh.triangles.cols();
  if (count > std::numeric_limits<uint32_t>::max()) {
    throw MeshError(
        MeshErrorKind::kCount, "", {},
        "cannot write binary STL: " + std::to_string(count) + " triangles exceed its 32-bit count");
  }
  std::string out(80, '\0');
  const std::string_view name = "somasim";  // never "solid...", which readers take for ASCII
  out.replace(0, name.size(), name);
  out.reserve(kBinaryHeaderBytes + kBinaryFacetBytes * static_cast<size_t>(count));
  AppendBinary(&out, static_cast<uint32_t>(count), Endian::kLittle);
  for (Eigen::Index t = 0; t < count; ++t) {
    const Eigen::Vector3d n = UnitNormal(mesh, t);
    for (int k = 0; k < 3; ++k) AppendBinary(&out, static_cast<float>(n[k]), Endian::kLittle);
    for (int c = 0; c < 3; ++c) {
      const Eigen::Index node = mesh.triangles(c, t);
      for (int k = 0; k < 3; ++k) {
        AppendBinary(&out, ToFloat(mesh.vertices(k, node), node), Endian::kLittle);
      }
    }
    AppendBinary(&out, uint16_t{0}, Endian::kLittle);
  }
  return out;
}

}  // namespace

MeshData ReadStl(std::string_view bytes, const std::string& file_name, const ReadOptions& options) {
  // Binary when the size is exactly what the count in the header implies, whatever the header
  // text says: some exporters start binary headers with "solid". A text file cannot match by
  // chance below 7 GB: four text bytes (tab or above) at offset 80 count at least 0x09090909.
  if (bytes.size() >= kBinaryHeaderBytes) {
    ByteReader header(bytes.substr(80, 4), file_name, 80);
    const uint64_t count = header.Read<uint32_t>(Endian::kLittle, "triangle count");
    if (kBinaryHeaderBytes + kBinaryFacetBytes * count == bytes.size()) {
      return ReadBinaryStl(bytes, file_name, options);
    }
  }
  if (StartsWithSolid(bytes)) {
    try {
      return ReadAsciiStl(bytes, file_name, options);
    } catch (const MeshError& e) {
      // A truncated or padded binary STL whose header starts with "solid" lands here: say so.
      if (!LooksBinary(bytes)) throw;
      throw MeshError(e.kind(), e.file(), e.where(),
                      e.fault() +
                          " (the file starts with 'solid' but holds binary data; it is "
                          "not a valid binary STL either: " +
                          NotBinaryReason(bytes) + ")");
    }
  }
  throw MeshError(
      MeshErrorKind::kSyntax, file_name, SourceLocation::Byte(0),
      "not an STL file: it does not start with 'solid' (ASCII STL), and " + NotBinaryReason(bytes));
}

std::string WriteStl(const MeshData& mesh, Encoding encoding) {
  CheckIndices(mesh);
  return encoding == Encoding::kBinary ? WriteBinaryStl(mesh) : WriteAsciiStl(mesh);
}

}  // namespace somasim::mesh_io
