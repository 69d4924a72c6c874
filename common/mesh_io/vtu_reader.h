// Internal to the VTU reader: its data types, the reader class and the helpers its parts share.
// The members are defined by topic: vtu_reader.cc (the XML document: appended data cut out,
// <VTKFile> and <UnstructuredGrid>), vtu_piece.cc (one <Piece>: its arrays checked against its
// counts, its points and cells) and vtu_data_array.cc (one <DataArray>: inspected, then decoded
// from ascii, base64 or raw bytes, zlib-compressed or not).
#pragma once

#include <algorithm>
#include <cstdint>
#include <deque>
#include <initializer_list>
#include <limits>
#include <optional>
#include <pugixml.hpp>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/mesh_error.h"

namespace somasim::mesh_io::vtu_internal {

// Deflate cannot expand data by more than about 1032:1, so a block header claiming more is
// a corrupt (or hostile) file; checked before anything is allocated.
inline constexpr uint64_t kMaxInflateRatio = 1032;
// Counts above this cannot describe a real mesh and would overflow byte arithmetic.
inline constexpr int64_t kMaxCount = int64_t{1} << 50;

enum class Scalar {
  kInt8,
  kUInt8,
  kInt16,
  kUInt16,
  kInt32,
  kUInt32,
  kInt64,
  kUInt64,
  kFloat32,
  kFloat64,
  kOther
};

struct ScalarInfo {
  Scalar scalar;
  int64_t bytes;
};

std::optional<ScalarInfo> ParseScalar(std::string_view name);

inline bool IsIntegral(Scalar s) {
  return s != Scalar::kFloat32 && s != Scalar::kFloat64 && s != Scalar::kOther;
}

// Range of an integral scalar, to refuse ASCII values that do not fit the declared type.
void IntegralRange(Scalar s, int64_t* lo, int64_t* hi);

enum class Format { kAscii, kBinary, kAppended };

// A DataArray element, inspected: its declared type and layout and how many values it holds
// (known from the text or the binary header without decoding the data).
struct ArrayRef {
  pugi::xml_node node;
  std::string label;  // e.g. "DataArray 'connectivity' (line 12)"
  SourceLocation where;
  ScalarInfo type{Scalar::kOther, 1};
  std::string type_name;
  int64_t components = 1;
  std::optional<int64_t> tuples;  // NumberOfTuples, when given
  Format format = Format::kAscii;
  // ASCII: the text pieces and the file offsets where they start.
  std::vector<std::pair<std::string_view, size_t>> chunks;
  // Binary: base64 text (inline, or appended from the offset) or raw appended bytes.
  bool base64 = false;
  std::string_view data;   // from the array's first byte/character to the end of what is there
  size_t data_offset = 0;  // file offset of data[0]
  bool compressed = false;
  uint64_t header_bytes = 0;  // bytes of the header before the (compressed) data
  uint64_t data_bytes = 0;    // uncompressed bytes of the values
  uint64_t block_size = 0, last_block_size = 0;
  std::vector<uint64_t> block_bytes;  // compressed size of each block
  int64_t value_count = 0;
};

// Values of a decoded array: integers for index arrays, doubles otherwise.
struct Values {
  std::vector<int64_t> ints;
  std::vector<double> reals;
};

// The arrays of one <Piece>, inspected: its points and the three arrays of its cells.
struct PieceArrays {
  std::optional<ArrayRef> pts, conn, offs, types;
};

// What a <Piece> says it holds, and where it is (for messages).
struct PieceCounts {
  int piece_index = 0;  // 0-based
  SourceLocation where;
  int64_t num_points = 0;
  int64_t num_cells = 0;
};

class VtuReader {
 public:
  VtuReader(std::string_view bytes, const std::string& file_name)
      : bytes_(bytes), file_name_(file_name) {}

  MeshData Read(const ReadOptions& options);

 private:
  [[noreturn]] void Fail(MeshErrorKind kind, SourceLocation where, const std::string& fault) const {
    throw MeshError(kind, file_name_, where, fault);
  }
  size_t FileOffset(size_t xml_offset) const {
    return xml_offset < cut_at_ ? xml_offset : xml_offset + cut_length_;
  }
  int64_t LineAt(size_t file_offset) const {
    return 1 +
           static_cast<int64_t>(std::lower_bound(newlines_.begin(), newlines_.end(), file_offset) -
                                newlines_.begin());
  }
  SourceLocation NodeLine(const pugi::xml_node& node) const {
    const ptrdiff_t off = node.offset_debug();
    return SourceLocation::Line(off < 0 ? 0 : LineAt(FileOffset(static_cast<size_t>(off))));
  }
  SourceLocation ByteAt(size_t file_offset) const {
    return SourceLocation::Byte(static_cast<int64_t>(file_offset));
  }

  void SplitAppendedData();
  void ParseHeaderAttributes(const pugi::xml_node& root);
  int64_t CountAttribute(const pugi::xml_node& node, const char* name, bool required,
                         int64_t fallback) const;
  void CheckChildren(const pugi::xml_node& node, std::initializer_list<const char*> allowed) const;

  ArrayRef Inspect(const pugi::xml_node& node);
  void InspectBinary(ArrayRef* a);
  Values Decode(const ArrayRef& a, bool want_ints);
  void DecodeAscii(const ArrayRef& a, bool want_ints, Values* out, std::vector<int64_t>* lines);
  std::string DecodeBinary(const ArrayRef& a);
  SourceLocation ValueLocation(const ArrayRef& a, const std::vector<int64_t>& lines,
                               size_t index) const;
  void CheckAttributeArrays(const pugi::xml_node& data, int64_t tuples, const char* what);

  // One <Piece>, in stages (vtu_piece.cc): its arrays inspected, their counts checked against
  // the piece's, its attribute data checked, then its points and cells added to the builder.
  void ReadPiece(const pugi::xml_node& piece, int piece_index, MeshBuilder* builder);
  pugi::xml_node OnlyChild(const pugi::xml_node& piece, const char* name) const;
  ArrayRef InspectPoints(const pugi::xml_node& points);
  void InspectCells(const pugi::xml_node& cells, PieceArrays* arrays);
  void CheckPieceCounts(const PieceArrays& arrays, const PieceCounts& counts, Values* offsets,
                        std::vector<int64_t>* offset_lines);
  Values DecodeIndices(const ArrayRef& a, std::vector<int64_t>* lines);
  void AddPoints(const ArrayRef& pts, int64_t num_points, MeshBuilder* builder);
  void AddCells(const PieceArrays& arrays, const PieceCounts& counts,
                const std::vector<int64_t>& ends, const std::vector<int64_t>& offset_lines,
                int64_t base, MeshBuilder* builder);

  std::string_view bytes_;
  std::string file_name_;
  std::vector<size_t> newlines_;  // file offsets of '\n' (for line numbers)
  std::string xml_;               // the XML to parse: the file without its raw appended data
  size_t cut_at_ = std::numeric_limits<size_t>::max();
  size_t cut_length_ = 0;
  bool have_appended_ = false;
  std::string_view appended_;  // after the '_' up to </AppendedData>
  size_t appended_offset_ = 0;
  bool appended_base64_ = false;
  Endian endian_ = Endian::kLittle;
  uint64_t header_size_ = 4;
  bool zlib_ = false;
  std::deque<std::string> owned_text_;  // base64 text joined from several XML text nodes
};

}  // namespace somasim::mesh_io::vtu_internal
