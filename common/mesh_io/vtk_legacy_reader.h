// Internal to the legacy VTK reader: its data types, the reader class and the helpers its parts
// share. The members are defined by topic: vtk_legacy_reader.cc (file and geometry sections, the
// mesh built from them), vtk_legacy_values.cc (ASCII and big-endian binary values, counts
// checked) and vtk_legacy_attributes.cc (point and cell data, FIELD and METADATA, checked and
// skipped).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/mesh_error.h"
#include "common/mesh_io/text_reader.h"

namespace somasim::mesh_io::vtk_legacy_internal {

// Data types of legacy VTK arrays. BINARY files store them big-endian.
enum class Scalar {
  kBit,
  kUInt8,
  kInt8,
  kUInt16,
  kInt16,
  kUInt32,
  kInt32,
  kUInt64,
  kInt64,
  kFloat32,
  kFloat64,
  kString,
};

// Bytes of one value in a BINARY file (0 for bit and string, which have their own layout).
int64_t ScalarBytes(Scalar s);
bool IsIntegral(Scalar s);
// Type names as VTK writes them (lower case; the reader compares case-insensitively).
std::optional<Scalar> ParseScalar(std::string_view name);

inline char ToUpper(char c) {
  return (c >= 'a' && c <= 'z') ? static_cast<char>(c - 'a' + 'A') : c;
}

inline std::string Upper(std::string_view s) {
  std::string out(s);
  for (char& c : out) c = ToUpper(c);
  return out;
}

// Keywords that start a section; used to tell a section keyword from data and to find where a
// binary block really ends when its count is wrong.
inline constexpr const char* kSectionKeywords[] = {
    "POINTS",
    "VERTICES",
    "LINES",
    "POLYGONS",
    "TRIANGLE_STRIPS",
    "CELLS",
    "CELL_TYPES",
    "OFFSETS",
    "CONNECTIVITY",
    "POINT_DATA",
    "CELL_DATA",
    "SCALARS",
    "COLOR_SCALARS",
    "LOOKUP_TABLE",
    "VECTORS",
    "NORMALS",
    "TEXTURE_COORDINATES",
    "TENSORS",
    "TENSORS6",
    "FIELD",
    "GLOBAL_IDS",
    "PEDIGREE_IDS",
    "EDGE_FLAGS",
    "METADATA",
};

inline bool IsSectionKeyword(std::string_view upper) {
  for (const char* k : kSectionKeywords) {
    if (upper == k) return true;
  }
  return false;
}

// A cell array as read: cell i uses conn[start[i] .. start[i+1]).
struct Cells {
  std::vector<int64_t> start{0};
  std::vector<int64_t> conn;
  std::vector<SourceLocation> where;
  SourceLocation keyword_where;
  bool present = false;
  int64_t count() const { return static_cast<int64_t>(where.size()); }
  int64_t points(size_t i) const { return start[i + 1] - start[i]; }
};

struct KeywordLine {
  std::string keyword;  // upper case
  std::vector<std::string_view> args;
  SourceLocation where;
  size_t offset = 0;  // byte offset of the keyword
};

// The last block of binary data read, to explain a count that does not match the data.
struct BinaryBlock {
  bool valid = false;
  std::string section;  // e.g. "POINTS"
  std::string detail;   // e.g. "508 points of float"
  size_t keyword_offset = 0;
  size_t begin = 0;
  size_t bytes = 0;
};

class LegacyReader {
 public:
  LegacyReader(std::string_view bytes, const std::string& file_name)
      : in_(bytes, file_name), file_name_(file_name) {}

  MeshData Read(const ReadOptions& options);

 private:
  [[noreturn]] void Fail(MeshErrorKind kind, SourceLocation where, const std::string& fault) const {
    in_.FailAt(kind, where, fault);
  }
  SourceLocation At(size_t offset) const {
    return binary_ ? SourceLocation::Byte(static_cast<int64_t>(offset)) : in_.token_location();
  }

  // Keyword lines (vtk_legacy_reader.cc).
  KeywordLine NextKeyword(std::string_view what);
  void ExpectArgs(const KeywordLine& kw, size_t min, size_t max, std::string_view usage) const;
  int64_t ArgInt(const KeywordLine& kw, size_t i, std::string_view what) const;
  Scalar ArgType(const KeywordLine& kw, size_t i) const;
  [[noreturn]] void UnknownKeyword(const KeywordLine& kw, std::string_view expected) const;
  [[noreturn]] void ExplainBinaryMismatch(const KeywordLine& kw) const;
  bool PeekKeyword(std::string_view upper);

  // Values (vtk_legacy_values.cc).
  void CheckCount(int64_t count, int64_t ascii_bytes_each, int64_t binary_bytes_each,
                  std::string_view what, SourceLocation where) const;
  // Reads count numbers of the given type, as V = int64_t (`type` must be an integral type) or
  // V = double (any numeric type).
  template <typename V>
  std::vector<V> ReadValues(Scalar type, int64_t count, const std::string& what,
                            const KeywordLine& kw, std::vector<SourceLocation>* where);
  // One value each, forced inline into the loops of ReadValues and SkipValues, their only
  // callers: gcc leaves a call per value to a member with external linkage.
  template <typename V>
  __attribute__((always_inline)) inline V AsciiValue(int64_t i, int64_t count,
                                                     const std::string& what,
                                                     const KeywordLine& kw);
  template <typename V>
  __attribute__((always_inline)) inline V BinaryValue(Scalar type, int64_t at, ByteReader* r,
                                                      const std::string& what) const;
  void SkipValues(Scalar type, int64_t count, const std::string& what, const KeywordLine& kw);
  ByteReader BeginBinary(int64_t bytes, const std::string& what, const KeywordLine& kw);
  void EndBinary(size_t bytes);

  // Sections (vtk_legacy_reader.cc; METADATA, FIELD and the attributes in
  // vtk_legacy_attributes.cc) and the mesh built from them.
  void ReadPoints(const KeywordLine& kw);
  Cells ReadCells(const KeywordLine& kw);
  Cells ReadClassicCells(const KeywordLine& kw, int64_t n, int64_t size);
  Cells ReadOffsetCells(const KeywordLine& kw, int64_t n_offsets, int64_t n_conn);
  void ReadCellTypes(const KeywordLine& kw);
  void SkipMetadata(const KeywordLine& kw);
  void SkipField(const KeywordLine& kw, int64_t tuples);
  void ReadAttributes(KeywordLine kw);
  void Build(MeshBuilder* builder);

  TextReader in_;
  std::string file_name_;
  bool binary_ = false;
  bool polydata_ = false;
  BinaryBlock last_block_;

  bool have_points_ = false;
  std::vector<double> coords_;  // 3 per point, file unit
  std::vector<SourceLocation> point_where_;
  Cells verts_, lines_, polys_, strips_;  // POLYDATA
  Cells cells_;                           // UNSTRUCTURED_GRID
  bool have_types_ = false;
  std::vector<int64_t> types_;
  std::vector<SourceLocation> type_where_;
  SourceLocation types_keyword_where_;
};

}  // namespace somasim::mesh_io::vtk_legacy_internal
