#include "common/mesh_io/vtk_legacy_io.h"

#include <algorithm>
#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/text_reader.h"

namespace somasim::mesh_io {
namespace {

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
int64_t ScalarBytes(Scalar s) {
  switch (s) {
    case Scalar::kUInt8:
    case Scalar::kInt8:
      return 1;
    case Scalar::kUInt16:
    case Scalar::kInt16:
      return 2;
    case Scalar::kUInt32:
    case Scalar::kInt32:
    // NOLINTNEXTLINE(bugprone-branch-clone): for V = int64_t both float cases give 0
    case Scalar::kFloat32:
      return 4;
    case Scalar::kUInt64:
    case Scalar::kInt64:
    case Scalar::kFloat64:
      return 8;
    case Scalar::kBit:
    case Scalar::kString:
      return 0;
  }
  return 0;
}

bool IsIntegral(Scalar s) {
  return s != Scalar::kFloat32 && s != Scalar::kFloat64 && s != Scalar::kString;
}

char ToUpper(char c) { return (c >= 'a' && c <= 'z') ? static_cast<char>(c - 'a' + 'A') : c; }

std::string Upper(std::string_view s) {
  std::string out(s);
  for (char& c : out) c = ToUpper(c);
  return out;
}

// Type names as VTK writes them (lower case; the reader compares case-insensitively). "long" is
// taken as 8 bytes, as on the LP64 systems that write such files.
std::optional<Scalar> ParseScalar(std::string_view name) {
  struct Entry {
    const char* name;
    Scalar scalar;
  };
  static constexpr Entry kTypes[] = {
      {"BIT", Scalar::kBit},
      {"UNSIGNED_CHAR", Scalar::kUInt8},
      {"CHAR", Scalar::kInt8},
      {"SIGNED_CHAR", Scalar::kInt8},
      {"VTKTYPEUINT8", Scalar::kUInt8},
      {"VTKTYPEINT8", Scalar::kInt8},
      {"UNSIGNED_SHORT", Scalar::kUInt16},
      {"SHORT", Scalar::kInt16},
      {"VTKTYPEUINT16", Scalar::kUInt16},
      {"VTKTYPEINT16", Scalar::kInt16},
      {"UNSIGNED_INT", Scalar::kUInt32},
      {"INT", Scalar::kInt32},
      {"VTKIDTYPE", Scalar::kInt32},  // VTK writes vtkIdType arrays as 32-bit int
      {"VTKTYPEUINT32", Scalar::kUInt32},
      {"VTKTYPEINT32", Scalar::kInt32},
      {"UNSIGNED_LONG", Scalar::kUInt64},
      {"LONG", Scalar::kInt64},
      {"UNSIGNED_LONG_LONG", Scalar::kUInt64},
      {"LONG_LONG", Scalar::kInt64},
      {"VTKTYPEUINT64", Scalar::kUInt64},
      {"VTKTYPEINT64", Scalar::kInt64},
      {"FLOAT", Scalar::kFloat32},
      {"VTKTYPEFLOAT32", Scalar::kFloat32},
      {"DOUBLE", Scalar::kFloat64},
      {"VTKTYPEFLOAT64", Scalar::kFloat64},
      {"STRING", Scalar::kString},
      {"UTF8_STRING", Scalar::kString},
  };
  const std::string upper = Upper(name);
  for (const Entry& e : kTypes) {
    if (upper == e.name) return e.scalar;
  }
  return std::nullopt;
}

// Keywords that start a section; used to tell a section keyword from data and to find where a
// binary block really ends when its count is wrong.
constexpr const char* kSectionKeywords[] = {
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

bool IsSectionKeyword(std::string_view upper) {
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

  KeywordLine NextKeyword(std::string_view what);
  void ExpectArgs(const KeywordLine& kw, size_t min, size_t max, std::string_view usage) const;
  int64_t ArgInt(const KeywordLine& kw, size_t i, std::string_view what) const;
  Scalar ArgType(const KeywordLine& kw, size_t i) const;
  [[noreturn]] void UnknownKeyword(const KeywordLine& kw, std::string_view expected) const;
  [[noreturn]] void ExplainBinaryMismatch(const KeywordLine& kw) const;
  bool PeekKeyword(std::string_view upper);

  void CheckCount(int64_t count, int64_t ascii_bytes_each, int64_t binary_bytes_each,
                  std::string_view what, SourceLocation where) const;
  // Reads count numbers of the given type, as V = int64_t (`type` must be an integral type) or
  // V = double (any numeric type).
  template <typename V>
  std::vector<V> ReadValues(Scalar type, int64_t count, const std::string& what,
                            const KeywordLine& kw, std::vector<SourceLocation>* where);
  template <typename V>
  V AsciiValue(int64_t i, int64_t count, const std::string& what, const KeywordLine& kw);
  template <typename V>
  V BinaryValue(Scalar type, int64_t at, ByteReader* r, const std::string& what) const;
  void SkipValues(Scalar type, int64_t count, const std::string& what, const KeywordLine& kw);
  ByteReader BeginBinary(int64_t bytes, const std::string& what, const KeywordLine& kw);
  void EndBinary(size_t bytes);

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

KeywordLine LegacyReader::NextKeyword(std::string_view what) {
  KeywordLine kw;
  const std::string_view token = in_.Token(what);
  kw.offset = in_.offset() - token.size();
  kw.where = At(kw.offset);
  kw.keyword = Upper(token);
  const std::optional<std::string_view> rest = in_.TryLine();
  if (rest) SplitTokens(*rest, &kw.args);
  return kw;
}

void LegacyReader::ExpectArgs(const KeywordLine& kw, size_t min, size_t max,
                              std::string_view usage) const {
  if (kw.args.size() < min || kw.args.size() > max) {
    Fail(MeshErrorKind::kSyntax, kw.where,
         kw.keyword + " line has " + std::to_string(kw.args.size()) + " arguments; expected '" +
             std::string(usage) + "'");
  }
}

int64_t LegacyReader::ArgInt(const KeywordLine& kw, size_t i, std::string_view what) const {
  int64_t value = 0;
  if (!ParseInt64(kw.args[i], &value)) {
    Fail(MeshErrorKind::kSyntax, kw.where,
         "expected an integer for " + std::string(what) + " on the " + kw.keyword +
             " line, found " + QuoteToken(kw.args[i]));
  }
  if (value < 0) {
    Fail(MeshErrorKind::kCount, kw.where,
         kw.keyword + " gives a negative " + std::string(what) + ": " + std::to_string(value));
  }
  return value;
}

Scalar LegacyReader::ArgType(const KeywordLine& kw, size_t i) const {
  const std::optional<Scalar> type = ParseScalar(kw.args[i]);
  if (!type) {
    if (Upper(kw.args[i]) == "VARIANT") {
      Fail(MeshErrorKind::kUnsupported, kw.where,
           "arrays of type 'variant' are not supported (" + kw.keyword + ")");
    }
    Fail(MeshErrorKind::kSyntax, kw.where,
         "unknown data type " + QuoteToken(kw.args[i]) + " on the " + kw.keyword + " line");
  }
  return *type;
}

bool LegacyReader::PeekKeyword(std::string_view upper) {
  const std::string_view rest = in_.rest();
  size_t i = 0;
  // In BINARY files the bytes right after a keyword line are data: do not skip them as spaces.
  if (!binary_) {
    while (i < rest.size() && IsSpace(rest[i])) ++i;
  }
  if (rest.size() - i < upper.size()) return false;
  for (size_t k = 0; k < upper.size(); ++k) {
    if (ToUpper(rest[i + k]) != upper[k]) return false;
  }
  return i + upper.size() == rest.size() || IsSpace(rest[i + upper.size()]);
}

void LegacyReader::UnknownKeyword(const KeywordLine& kw, std::string_view expected) const {
  if (binary_ && last_block_.valid) {
    const size_t end = last_block_.begin + last_block_.bytes;
    bool right_after = kw.offset >= end;
    for (size_t i = end; right_after && i < kw.offset; ++i) {
      right_after = IsSpace(in_.text()[i]);
    }
    if (right_after) ExplainBinaryMismatch(kw);
  }
  Fail(MeshErrorKind::kSyntax, kw.where,
       "unknown keyword " + QuoteToken(kw.keyword) + " (expected " + std::string(expected) + ")");
}

// A keyword was expected right after a block of binary data but something else is there: the
// count before the block does not match the data. Finds where the next section really starts,
// and whether the data was mangled into text (backslash escapes of bytes), to say exactly what
// is wrong.
void LegacyReader::ExplainBinaryMismatch(const KeywordLine& kw) const {
  const std::string_view text = in_.text();
  const BinaryBlock& block = last_block_;
  size_t next = std::string_view::npos;
  std::string next_keyword;
  for (const char* k : kSectionKeywords) {
    for (const char* sep : {" ", "\n", "\r\n"}) {
      const std::string needle = "\n" + std::string(k) + sep;
      const size_t pos = text.find(needle, block.begin);
      if (pos != std::string_view::npos && pos < next) {
        next = pos;
        next_keyword = k;
      }
    }
  }
  const size_t scan_end = next == std::string_view::npos ? text.size() : next;
  int64_t escapes = 0;
  std::string example;
  const auto is_hex = [](char c) {
    return (c >= '0' && c <= '9') || (c >= 'A' && c <= 'F') || (c >= 'a' && c <= 'f');
  };
  for (size_t i = block.begin; i + 2 < scan_end; ++i) {
    if (text[i] == '\\' && is_hex(text[i + 1]) && is_hex(text[i + 2])) {
      if (example.empty()) example = std::string(text.substr(i, 3));
      ++escapes;
      i += 2;
    }
  }
  std::string fault = block.section + " declares " + block.detail + ", i.e. " +
                      std::to_string(block.bytes) + " bytes of binary data, but ";
  if (next != std::string_view::npos) {
    fault += "the next section (" + next_keyword + " at byte " + std::to_string(next + 1) +
             ") begins " + std::to_string(next - block.begin) +
             " bytes after the data starts: the count in " + block.section +
             " does not match the data";
  } else {
    fault += "what follows those bytes is " + QuoteToken(kw.keyword) +
             ", not a section keyword: the count in " + block.section + " does not match the data";
  }
  if (escapes > 0) {
    fault += "; the binary data is also corrupt: it contains " + std::to_string(escapes) +
             " backslash escapes such as '" + example +
             "' (binary bytes rewritten as text, e.g. by an editor or a text-mode copy)";
  }
  Fail(MeshErrorKind::kCount, SourceLocation::Byte(static_cast<int64_t>(block.keyword_offset)),
       fault);
}

void LegacyReader::CheckCount(int64_t count, int64_t ascii_bytes_each, int64_t binary_bytes_each,
                              std::string_view what, SourceLocation where) const {
  if (count < 0) {
    Fail(MeshErrorKind::kCount, where,
         "negative count of " + std::string(what) + ": " + std::to_string(count));
  }
  const int64_t left = static_cast<int64_t>(in_.remaining());
  // ASCII values are separated by whitespace: n values take at least n*each - 1 bytes.
  const bool fits = binary_ ? (binary_bytes_each <= 0 || count <= left / binary_bytes_each)
                            : (ascii_bytes_each <= 0 || count <= (left + 1) / ascii_bytes_each);
  if (!fits) {
    Fail(MeshErrorKind::kCount, where,
         "the file claims " + std::to_string(count) + " " + std::string(what) + " but only " +
             std::to_string(left) + " bytes remain (truncated file or wrong count)");
  }
}

ByteReader LegacyReader::BeginBinary(int64_t bytes, const std::string& what,
                                     const KeywordLine& kw) {
  if (bytes < 0 || static_cast<uint64_t>(bytes) > in_.remaining()) {
    Fail(MeshErrorKind::kCount, kw.where,
         what + " need " + std::to_string(bytes) + " bytes of binary data but only " +
             std::to_string(in_.remaining()) + " remain (truncated file or wrong count)");
  }
  last_block_.valid = true;
  last_block_.keyword_offset = kw.offset;
  last_block_.begin = in_.offset();
  last_block_.bytes = static_cast<size_t>(bytes);
  return ByteReader(in_.rest().substr(0, static_cast<size_t>(bytes)), file_name_,
                    static_cast<int64_t>(in_.offset()));
}

void LegacyReader::EndBinary(size_t bytes) { in_.Skip(bytes); }

// Reads one binary value as T from the big-endian data.
template <typename T>
T ReadBig(ByteReader* reader, std::string_view what) {
  return reader->Read<T>(Endian::kBig, what);
}

template <typename V>
std::vector<V> LegacyReader::ReadValues(Scalar type, int64_t count, const std::string& what,
                                        const KeywordLine& kw, std::vector<SourceLocation>* where) {
  constexpr bool kInts = std::is_same_v<V, int64_t>;
  static_assert(kInts || std::is_same_v<V, double>);
  if (kInts ? (!IsIntegral(type) || type == Scalar::kBit)
            : (type == Scalar::kBit || type == Scalar::kString)) {
    Fail(MeshErrorKind::kSyntax, kw.where,
         what +
             (kInts ? " must have an integer data type, not "
                    : " must have a numeric data type, not ") +
             QuoteToken(kw.args.back()));
  }
  CheckCount(count, 2, ScalarBytes(type), what, kw.where);
  std::vector<V> values;
  values.reserve(static_cast<size_t>(count));
  if (where) where->reserve(static_cast<size_t>(count));
  if (!binary_) {
    for (int64_t i = 0; i < count; ++i) {
      values.push_back(AsciiValue<V>(i, count, what, kw));
      if (where) where->push_back(in_.token_location());
    }
    return values;
  }
  const int64_t bytes = count * ScalarBytes(type);
  ByteReader r = BeginBinary(bytes, what, kw);
  for (int64_t i = 0; i < count; ++i) {
    const int64_t at = r.file_offset();
    values.push_back(BinaryValue<V>(type, at, &r, what));
    if (where) where->push_back(SourceLocation::Byte(at));
  }
  EndBinary(static_cast<size_t>(bytes));
  return values;
}

// The next ASCII token as the i-th of `count` values (int64_t or double). A section keyword in
// its place means the count is wrong.
template <typename V>
V LegacyReader::AsciiValue(int64_t i, int64_t count, const std::string& what,
                           const KeywordLine& kw) {
  constexpr bool kInts = std::is_same_v<V, int64_t>;
  const std::string_view token = in_.Token(what);
  V v = 0;
  bool parsed = false;
  if constexpr (kInts) {
    parsed = ParseInt64(token, &v);
  } else {
    parsed = ParseDouble(token, &v);
  }
  if (!parsed) {
    if (IsSectionKeyword(Upper(token))) {
      Fail(MeshErrorKind::kCount, in_.token_location(),
           kw.keyword + " announces " + std::to_string(count) + " " + what + " but only " +
               std::to_string(i) + " come before " + Upper(token));
    }
    Fail(MeshErrorKind::kSyntax, in_.token_location(),
         (kInts ? "expected an integer for " : "expected a number for ") + what + ", found " +
             QuoteToken(token));
  }
  return v;
}

// One big-endian value at byte `at` as an int64_t or a double. As int64_t, an unsigned 64-bit
// value beyond its range is refused, and floating types (refused by ReadValues) give 0.
template <typename V>
V LegacyReader::BinaryValue(Scalar type, int64_t at, ByteReader* r, const std::string& what) const {
  switch (type) {
    case Scalar::kUInt8:
      return static_cast<V>(ReadBig<uint8_t>(r, what));
    case Scalar::kInt8:
      return static_cast<V>(ReadBig<int8_t>(r, what));
    case Scalar::kUInt16:
      return static_cast<V>(ReadBig<uint16_t>(r, what));
    case Scalar::kInt16:
      return static_cast<V>(ReadBig<int16_t>(r, what));
    case Scalar::kUInt32:
      return static_cast<V>(ReadBig<uint32_t>(r, what));
    case Scalar::kInt32:
      return static_cast<V>(ReadBig<int32_t>(r, what));
    case Scalar::kUInt64: {
      const uint64_t u = ReadBig<uint64_t>(r, what);
      if constexpr (std::is_same_v<V, int64_t>) {
        if (u > static_cast<uint64_t>(std::numeric_limits<int64_t>::max())) {
          Fail(MeshErrorKind::kIndex, SourceLocation::Byte(at),
               what + " holds the value " + std::to_string(u) + ", too large for an index");
        }
      }
      return static_cast<V>(u);
    }
    case Scalar::kInt64:
      return static_cast<V>(ReadBig<int64_t>(r, what));
    case Scalar::kFloat32:
    case Scalar::kFloat64:
      if constexpr (std::is_same_v<V, double>) {
        return type == Scalar::kFloat32 ? static_cast<double>(ReadBig<float>(r, what))
                                        : ReadBig<double>(r, what);
      }
      break;
    default:
      break;
  }
  return 0;
}

// Attribute data is not kept, but its size is checked so that a truncated or miscounted
// section is refused rather than misread.
void LegacyReader::SkipValues(Scalar type, int64_t count, const std::string& what,
                              const KeywordLine& kw) {
  if (type == Scalar::kString) {
    // One string per line in ASCII; in BINARY each string is preceded by its length, whose
    // two top bits say how many bytes the length takes (VTK's vtkDataWriter convention).
    CheckCount(count, 1, 1, what, kw.where);
    if (!binary_) {
      for (int64_t i = 0; i < count; ++i) in_.Line(what);
      return;
    }
    ByteReader r(in_.rest(), file_name_, static_cast<int64_t>(in_.offset()));
    for (int64_t i = 0; i < count; ++i) {
      const uint8_t first = r.Read<uint8_t>(Endian::kBig, what);
      uint64_t length = 0;
      switch (first >> 6) {
        case 3:
          length = first & 0x3fu;
          break;
        case 2:
          length =
              ((static_cast<uint64_t>(first) & 0x3fu) << 8) | r.Read<uint8_t>(Endian::kBig, what);
          break;
        case 1: {
          length = static_cast<uint64_t>(first) & 0x3fu;
          for (int k = 0; k < 3; ++k) length = (length << 8) | r.Read<uint8_t>(Endian::kBig, what);
          break;
        }
        default: {
          length = first;
          for (int k = 0; k < 7; ++k) length = (length << 8) | r.Read<uint8_t>(Endian::kBig, what);
          break;
        }
      }
      if (length > r.remaining()) {
        r.Fail(MeshErrorKind::kSyntax, "a string of " + what + " claims " + std::to_string(length) +
                                           " bytes but only " + std::to_string(r.remaining()) +
                                           " remain");
      }
      r.Bytes(static_cast<size_t>(length), what);
    }
    in_.Skip(r.offset());
    return;
  }
  if (!binary_) {
    CheckCount(count, 2, 0, what, kw.where);
    for (int64_t i = 0; i < count; ++i) AsciiValue<double>(i, count, what, kw);
    return;
  }
  int64_t bytes = 0;
  if (type == Scalar::kBit) {
    bytes = count / 8 + (count % 8 != 0 ? 1 : 0);
  } else {
    CheckCount(count, 0, ScalarBytes(type), what, kw.where);
    bytes = count * ScalarBytes(type);
  }
  BeginBinary(bytes, what, kw);
  EndBinary(static_cast<size_t>(bytes));
}

void LegacyReader::ReadPoints(const KeywordLine& kw) {
  ExpectArgs(kw, 2, 2, "POINTS <count> <data type>");
  if (have_points_) Fail(MeshErrorKind::kSyntax, kw.where, "a second POINTS section");
  have_points_ = true;
  const int64_t n = ArgInt(kw, 0, "point count");
  const Scalar type = ArgType(kw, 1);
  if (type == Scalar::kBit || type == Scalar::kString) {
    Fail(MeshErrorKind::kSyntax, kw.where,
         "POINTS must have a numeric data type, not " + QuoteToken(kw.args[1]));
  }
  CheckCount(n, 6, 3 * ScalarBytes(type), "points", kw.where);
  last_block_.section = "POINTS";
  last_block_.detail = std::to_string(n) + " points of " + std::string(kw.args[1]);
  std::vector<SourceLocation> where;
  coords_ = ReadValues<double>(type, 3 * n, "point coordinates", kw, &where);
  point_where_.reserve(static_cast<size_t>(n));
  for (size_t i = 0; i < where.size(); i += 3) point_where_.push_back(where[i]);
}

Cells LegacyReader::ReadCells(const KeywordLine& kw) {
  ExpectArgs(kw, 2, 2, kw.keyword + " <cell count> <entry count>");
  const int64_t a = ArgInt(kw, 0, "cell count");
  const int64_t b = ArgInt(kw, 1, "entry count");
  // VTK 5.1 files follow the line with OFFSETS and CONNECTIVITY arrays; older ones with the
  // entries "n id1 .. idn" of each cell.
  Cells cells = PeekKeyword("OFFSETS") ? ReadOffsetCells(kw, a, b) : ReadClassicCells(kw, a, b);
  cells.keyword_where = kw.where;
  return cells;
}

Cells LegacyReader::ReadClassicCells(const KeywordLine& kw, int64_t n, int64_t size) {
  CheckCount(size, 2, 4, kw.keyword + " entries", kw.where);
  if (n > size) {
    Fail(MeshErrorKind::kCount, kw.where,
         kw.keyword + " says " + std::to_string(n) + " cells in " + std::to_string(size) +
             " entries, but every cell takes at least one entry (its point count)");
  }
  last_block_.section = kw.keyword;
  last_block_.detail = std::to_string(size) + " entries of int";
  std::vector<SourceLocation> where;
  const std::vector<int64_t> entries =
      ReadValues<int64_t>(Scalar::kInt32, size, kw.keyword + " entries", kw, &where);
  Cells cells;
  cells.present = true;
  cells.start.reserve(static_cast<size_t>(n) + 1);
  cells.where.reserve(static_cast<size_t>(n));
  cells.conn.reserve(static_cast<size_t>(size - n));
  size_t used = 0;
  for (int64_t i = 0; i < n; ++i) {
    if (used >= entries.size()) {
      Fail(MeshErrorKind::kCount, kw.where,
           kw.keyword + " says " + std::to_string(n) + " cells in " + std::to_string(size) +
               " entries, but the entries run out after " + std::to_string(i) + " cells");
    }
    const int64_t npts = entries[used];
    const SourceLocation at = where[used];
    if (npts < 0) {
      Fail(MeshErrorKind::kCount, at,
           kw.keyword + " cell #" + std::to_string(i + 1) + " has a negative point count (" +
               std::to_string(npts) + ")");
    }
    if (npts > static_cast<int64_t>(entries.size() - used - 1)) {
      Fail(MeshErrorKind::kCount, at,
           kw.keyword + " says " + std::to_string(size) + " entries, but cell #" +
               std::to_string(i + 1) + " (" + std::to_string(npts) +
               " points) runs past them: the entry count or a point count is wrong");
    }
    cells.conn.insert(cells.conn.end(), entries.begin() + static_cast<std::ptrdiff_t>(used) + 1,
                      entries.begin() + static_cast<std::ptrdiff_t>(used) + 1 +
                          static_cast<std::ptrdiff_t>(npts));
    cells.start.push_back(static_cast<int64_t>(cells.conn.size()));
    cells.where.push_back(at);
    used += 1 + static_cast<size_t>(npts);
  }
  if (used != entries.size()) {
    Fail(MeshErrorKind::kCount, kw.where,
         kw.keyword + " says " + std::to_string(size) + " entries but its " + std::to_string(n) +
             " cells use " + std::to_string(used));
  }
  return cells;
}

Cells LegacyReader::ReadOffsetCells(const KeywordLine& kw, int64_t n_offsets, int64_t n_conn) {
  const KeywordLine off = NextKeyword("OFFSETS");
  ExpectArgs(off, 1, 1, "OFFSETS <data type>");
  const Scalar off_type = ArgType(off, 0);
  last_block_.section = "OFFSETS";
  last_block_.detail = std::to_string(n_offsets) + " offsets of " + std::string(off.args[0]);
  std::vector<SourceLocation> where;
  const std::vector<int64_t> offsets =
      ReadValues<int64_t>(off_type, n_offsets, kw.keyword + " offsets", off, &where);
  KeywordLine con = NextKeyword("CONNECTIVITY");
  while (con.keyword == "METADATA") {
    SkipMetadata(con);
    con = NextKeyword("CONNECTIVITY");
  }
  if (con.keyword != "CONNECTIVITY") {
    UnknownKeyword(con, "CONNECTIVITY after the OFFSETS of " + kw.keyword);
  }
  ExpectArgs(con, 1, 1, "CONNECTIVITY <data type>");
  const Scalar con_type = ArgType(con, 0);
  last_block_.section = "CONNECTIVITY";
  last_block_.detail = std::to_string(n_conn) + " indices of " + std::string(con.args[0]);
  Cells cells;
  cells.present = true;
  cells.conn = ReadValues<int64_t>(con_type, n_conn, kw.keyword + " connectivity", con, nullptr);
  if (offsets.empty()) {
    if (n_conn != 0) {
      Fail(MeshErrorKind::kCount, kw.where,
           kw.keyword + " has no offsets but " + std::to_string(n_conn) + " connectivity entries");
    }
    return cells;
  }
  if (offsets[0] != 0) {
    Fail(MeshErrorKind::kCount, where[0],
         kw.keyword + " offsets must start at 0, not " + std::to_string(offsets[0]));
  }
  cells.start.reserve(offsets.size());
  cells.where.reserve(offsets.size() - 1);
  for (size_t i = 1; i < offsets.size(); ++i) {
    if (offsets[i] < offsets[i - 1]) {
      Fail(MeshErrorKind::kCount, where[i],
           kw.keyword + " offset #" + std::to_string(i + 1) + " (" + std::to_string(offsets[i]) +
               ") is smaller than the one before (" + std::to_string(offsets[i - 1]) + ")");
    }
    if (offsets[i] > n_conn) {
      Fail(MeshErrorKind::kCount, where[i],
           kw.keyword + " offset #" + std::to_string(i + 1) + " (" + std::to_string(offsets[i]) +
               ") is past the end of the " + std::to_string(n_conn) + " connectivity entries");
    }
    cells.start.push_back(offsets[i]);
    cells.where.push_back(where[i - 1]);
  }
  if (offsets.back() != n_conn) {
    Fail(MeshErrorKind::kCount, where.back(),
         kw.keyword + " offsets end at " + std::to_string(offsets.back()) + " but " +
             std::to_string(n_conn) + " connectivity entries were given");
  }
  return cells;
}

void LegacyReader::ReadCellTypes(const KeywordLine& kw) {
  ExpectArgs(kw, 1, 1, "CELL_TYPES <count>");
  if (have_types_) Fail(MeshErrorKind::kSyntax, kw.where, "a second CELL_TYPES section");
  have_types_ = true;
  types_keyword_where_ = kw.where;
  const int64_t n = ArgInt(kw, 0, "cell count");
  last_block_.section = "CELL_TYPES";
  last_block_.detail = std::to_string(n) + " cell types of int";
  types_ = ReadValues<int64_t>(Scalar::kInt32, n, "cell types", kw, &type_where_);
}

// METADATA (VTK 8+) follows an array: COMPONENT_NAMES and INFORMATION lines, ended by an empty
// line. Nothing in it matters for the mesh; a missing end means a truncated file.
void LegacyReader::SkipMetadata(const KeywordLine& kw) {
  ExpectArgs(kw, 0, 0, "METADATA");
  for (;;) {
    const std::string_view line = in_.Line("a METADATA block (it ends with an empty line)");
    if (std::all_of(line.begin(), line.end(), IsSpace)) return;
  }
}

void LegacyReader::SkipField(const KeywordLine& kw, int64_t tuples) {
  ExpectArgs(kw, 2, 2, "FIELD <name> <array count>");
  const int64_t arrays = ArgInt(kw, 1, "array count");
  CheckCount(arrays, 8, 8, "FIELD arrays", kw.where);
  for (int64_t a = 0; a < arrays; ++a) {
    KeywordLine array = NextKeyword("FIELD array");
    if (array.keyword == "METADATA") {
      SkipMetadata(array);
      --a;
      continue;
    }
    if (array.keyword == "NULL_ARRAY") continue;
    const std::string name(in_.text().substr(array.offset, array.keyword.size()));
    array.keyword = "FIELD array " + QuoteToken(name);
    ExpectArgs(array, 3, 3, "<name> <components> <tuples> <data type>");
    const int64_t components = ArgInt(array, 0, "number of components");
    const int64_t n = ArgInt(array, 1, "number of tuples");
    const Scalar type = ArgType(array, 2);
    if (components < 1 || components > (int64_t{1} << 20)) {
      Fail(MeshErrorKind::kCount, array.where,
           array.keyword + " has " + std::to_string(components) + " components");
    }
    if (tuples >= 0 && n != tuples) {
      Fail(MeshErrorKind::kCount, array.where,
           array.keyword + " has " + std::to_string(n) + " tuples but its section has " +
               std::to_string(tuples));
    }
    CheckCount(n, components, components, "tuples of " + array.keyword, array.where);
    last_block_.section = array.keyword;
    last_block_.detail = std::to_string(n) + " tuples of " + std::string(array.args[2]);
    SkipValues(type, n * components, "values of " + array.keyword, array);
  }
}

void LegacyReader::ReadAttributes(KeywordLine kw) {
  const int64_t num_points = static_cast<int64_t>(coords_.size() / 3);
  const int64_t num_cells = polydata_
                                ? verts_.count() + lines_.count() + polys_.count() + strips_.count()
                                : cells_.count();
  bool seen_point_data = false, seen_cell_data = false;
  int64_t n = 0;
  for (;;) {
    const std::string& k = kw.keyword;
    const auto type_at = [&](size_t i) {
      last_block_.section = k;
      last_block_.detail = std::to_string(n) + " values of " + std::string(kw.args[i]);
      return ArgType(kw, i);
    };
    if (k == "POINT_DATA" || k == "CELL_DATA") {
      ExpectArgs(kw, 1, 1, k + " <count>");
      const bool points = k == "POINT_DATA";
      bool& seen = points ? seen_point_data : seen_cell_data;
      if (seen) Fail(MeshErrorKind::kSyntax, kw.where, "a second " + k + " section");
      seen = true;
      n = ArgInt(kw, 0, "count");
      const int64_t expected = points ? num_points : num_cells;
      if (n != expected) {
        Fail(MeshErrorKind::kCount, kw.where,
             k + " says " + std::to_string(n) + " but the dataset has " + std::to_string(expected) +
                 (points ? " points" : " cells"));
      }
    } else if (k == "SCALARS") {
      ExpectArgs(kw, 2, 3, "SCALARS <name> <data type> [<components>]");
      const Scalar type = type_at(1);
      const int64_t components = kw.args.size() == 3 ? ArgInt(kw, 2, "number of components") : 1;
      if (components < 1 || components > 4) {
        Fail(MeshErrorKind::kCount, kw.where,
             "SCALARS must have 1 to 4 components, not " + std::to_string(components));
      }
      if (PeekKeyword("LOOKUP_TABLE")) {
        const KeywordLine table = NextKeyword("LOOKUP_TABLE");
        ExpectArgs(table, 1, 1, "LOOKUP_TABLE <name>");
      }
      SkipValues(type, n * components, "SCALARS values", kw);
    } else if (k == "COLOR_SCALARS") {
      ExpectArgs(kw, 2, 2, "COLOR_SCALARS <name> <components>");
      const int64_t components = ArgInt(kw, 1, "number of components");
      if (components < 1 || components > 4) {
        Fail(MeshErrorKind::kCount, kw.where,
             "COLOR_SCALARS must have 1 to 4 components, not " + std::to_string(components));
      }
      last_block_.section = k;
      last_block_.detail = std::to_string(n) + " colours";
      SkipValues(binary_ ? Scalar::kUInt8 : Scalar::kFloat32, n * components,
                 "COLOR_SCALARS values", kw);
    } else if (k == "LOOKUP_TABLE") {
      ExpectArgs(kw, 2, 2, "LOOKUP_TABLE <name> <size>");
      const int64_t size = ArgInt(kw, 1, "table size");
      CheckCount(size, 8, 4, "LOOKUP_TABLE colours", kw.where);
      last_block_.section = k;
      last_block_.detail = std::to_string(size) + " colours";
      SkipValues(binary_ ? Scalar::kUInt8 : Scalar::kFloat32, 4 * size, "LOOKUP_TABLE values", kw);
    } else if (k == "VECTORS" || k == "NORMALS") {
      ExpectArgs(kw, 2, 2, k + " <name> <data type>");
      SkipValues(type_at(1), 3 * n, k + " values", kw);
    } else if (k == "TEXTURE_COORDINATES") {
      ExpectArgs(kw, 3, 3, "TEXTURE_COORDINATES <name> <dimension> <data type>");
      const int64_t dim = ArgInt(kw, 1, "dimension");
      if (dim < 1 || dim > 3) {
        Fail(MeshErrorKind::kCount, kw.where,
             "TEXTURE_COORDINATES must have dimension 1 to 3, not " + std::to_string(dim));
      }
      SkipValues(type_at(2), dim * n, "TEXTURE_COORDINATES values", kw);
    } else if (k == "TENSORS" || k == "TENSORS6") {
      ExpectArgs(kw, 2, 2, k + " <name> <data type>");
      SkipValues(type_at(1), (k == "TENSORS" ? 9 : 6) * n, k + " values", kw);
    } else if (k == "GLOBAL_IDS" || k == "PEDIGREE_IDS" || k == "EDGE_FLAGS") {
      ExpectArgs(kw, 2, 2, k + " <name> <data type>");
      SkipValues(type_at(1), n, k + " values", kw);
    } else if (k == "FIELD") {
      SkipField(kw, n);
    } else if (k == "METADATA") {
      SkipMetadata(kw);
    } else {
      UnknownKeyword(kw,
                     "an attribute: SCALARS, COLOR_SCALARS, LOOKUP_TABLE, VECTORS, NORMALS, "
                     "TEXTURE_COORDINATES, TENSORS, FIELD, POINT_DATA or CELL_DATA; geometry "
                     "sections must come before POINT_DATA and CELL_DATA");
    }
    if (in_.AtEnd()) return;
    kw = NextKeyword("attribute keyword");
  }
}

// Turns what was read into nodes and elements; done once the whole file has been parsed so
// that structural faults (miscounted binary blocks) are reported before value faults that
// misread data would cause.
void LegacyReader::Build(MeshBuilder* builder) {
  const int64_t n = static_cast<int64_t>(coords_.size() / 3);
  for (int64_t i = 0; i < n; ++i) {
    const size_t k = 3 * static_cast<size_t>(i);
    builder->AddNode(coords_[k], coords_[k + 1], coords_[k + 2],
                     point_where_[static_cast<size_t>(i)]);
  }
  if (polydata_) {
    if (verts_.count() > 0) builder->Skip("vertex", verts_.count());
    if (lines_.count() > 0) builder->Skip("line", lines_.count());
    for (size_t c = 0; c < static_cast<size_t>(polys_.count()); ++c) {
      const int64_t* v = polys_.conn.data() + polys_.start[c];
      if (polys_.points(c) == 3) {
        builder->AddTriangle(v[0], v[1], v[2], polys_.where[c]);
      } else {
        builder->Skip("polygon");
      }
    }
    int64_t degenerate = 0;
    for (size_t c = 0; c < static_cast<size_t>(strips_.count()); ++c) {
      const int64_t* v = strips_.conn.data() + strips_.start[c];
      const int64_t m = strips_.points(c);
      if (m < 3) {
        Fail(MeshErrorKind::kCount, strips_.where[c],
             "triangle strip #" + std::to_string(c + 1) + " has " + std::to_string(m) +
                 " points; a strip needs at least 3");
      }
      // VTK's strip convention: triangle i is (i, i+1, i+2) for even i and (i+1, i, i+2) for
      // odd i, so that all triangles have the orientation of the first.
      for (int64_t i = 0; i + 2 < m; ++i) {
        const int64_t a = (i % 2 == 0) ? v[i] : v[i + 1];
        const int64_t b = (i % 2 == 0) ? v[i + 1] : v[i];
        const int64_t c3 = v[i + 2];
        // Strips join and turn with repeated points; those zero-area triangles are not part of
        // the surface.
        if (a == b || b == c3 || a == c3) {
          ++degenerate;
          continue;
        }
        builder->AddTriangle(a, b, c3, strips_.where[c]);
      }
    }
    if (degenerate > 0) builder->Skip("degenerate triangle of a strip", degenerate);
    return;
  }
  if (cells_.present != have_types_) {
    Fail(MeshErrorKind::kSyntax, have_types_ ? types_keyword_where_ : cells_.keyword_where,
         cells_.present ? "UNSTRUCTURED_GRID has CELLS but no CELL_TYPES section"
                        : "UNSTRUCTURED_GRID has CELL_TYPES but no CELLS section");
  }
  if (cells_.count() != static_cast<int64_t>(types_.size())) {
    Fail(MeshErrorKind::kCount, types_keyword_where_,
         "CELL_TYPES lists " + std::to_string(types_.size()) + " types but CELLS has " +
             std::to_string(cells_.count()) + " cells");
  }
  for (size_t c = 0; c < types_.size(); ++c) {
    const int64_t type = types_[c];
    const VtkCellTypeInfo info = VtkCellType(type);
    if (info.name == nullptr) {
      Fail(MeshErrorKind::kSyntax, type_where_[c],
           "cell #" + std::to_string(c + 1) + " has unknown VTK cell type " + std::to_string(type));
    }
    const int64_t m = cells_.points(c);
    if (info.num_points >= 0 && m != info.num_points) {
      Fail(MeshErrorKind::kCount, cells_.where[c],
           "cell #" + std::to_string(c + 1) + " is a " + info.name + " but has " +
               std::to_string(m) + " points instead of " + std::to_string(info.num_points));
    }
    const int64_t* v = cells_.conn.data() + cells_.start[c];
    if (type == kVtkTriangle) {
      builder->AddTriangle(v[0], v[1], v[2], cells_.where[c]);
    } else if (type == kVtkTetra) {
      builder->AddTetrahedron(v[0], v[1], v[2], v[3], cells_.where[c]);
    } else {
      builder->Skip(info.name);
    }
  }
}

MeshData LegacyReader::Read(const ReadOptions& options) {
  const std::string_view header = in_.Line("the header line");
  constexpr std::string_view kMagic = "# VTK DATAFILE VERSION";
  if (header.size() < kMagic.size() || Upper(header.substr(0, kMagic.size())) != kMagic) {
    Fail(MeshErrorKind::kSyntax, SourceLocation::Line(1),
         "not a legacy VTK file: the first line must be '# vtk DataFile Version x.y', found " +
             QuoteToken(header));
  }
  std::vector<std::string_view> version;
  SplitTokens(header.substr(kMagic.size()), &version);
  in_.Line("the title line");
  const KeywordLine encoding = NextKeyword("ASCII or BINARY");
  if (encoding.keyword == "BINARY") {
    binary_ = true;
  } else if (encoding.keyword != "ASCII") {
    Fail(MeshErrorKind::kSyntax, encoding.where,
         "the third line must say ASCII or BINARY, found " + QuoteToken(encoding.keyword));
  }
  ExpectArgs(encoding, 0, 0, encoding.keyword);
  const KeywordLine dataset = NextKeyword("DATASET");
  if (dataset.keyword != "DATASET") {
    Fail(MeshErrorKind::kSyntax, dataset.where,
         "expected 'DATASET <type>' after the " + encoding.keyword + " line, found " +
             QuoteToken(dataset.keyword));
  }
  ExpectArgs(dataset, 1, 1, "DATASET <type>");
  const std::string type = Upper(dataset.args[0]);
  if (type == "POLYDATA") {
    polydata_ = true;
  } else if (type != "UNSTRUCTURED_GRID") {
    if (type == "STRUCTURED_POINTS" || type == "STRUCTURED_GRID" || type == "RECTILINEAR_GRID" ||
        type == "FIELD") {
      Fail(MeshErrorKind::kUnsupported, dataset.where,
           "DATASET " + type +
               " is not supported: only POLYDATA and UNSTRUCTURED_GRID hold "
               "triangles or tetrahedra");
    }
    Fail(MeshErrorKind::kSyntax, dataset.where,
         "unknown DATASET type " + QuoteToken(dataset.args[0]));
  }
  const char* geometry_keywords =
      polydata_ ? "POINTS, VERTICES, LINES, POLYGONS, TRIANGLE_STRIPS, FIELD, POINT_DATA or "
                  "CELL_DATA"
                : "POINTS, CELLS, CELL_TYPES, FIELD, POINT_DATA or CELL_DATA";
  SourceLocation end_of_geometry = dataset.where;
  while (!in_.AtEnd()) {
    const KeywordLine kw = NextKeyword("section keyword");
    const std::string& k = kw.keyword;
    if (k == "POINTS") {
      ReadPoints(kw);
    } else if (k == "METADATA") {
      SkipMetadata(kw);
    } else if (k == "FIELD") {
      SkipField(kw, -1);
    } else if (k == "POINT_DATA" || k == "CELL_DATA") {
      ReadAttributes(kw);
      break;
    } else if (polydata_ &&
               (k == "VERTICES" || k == "LINES" || k == "POLYGONS" || k == "TRIANGLE_STRIPS")) {
      Cells& cells = k == "VERTICES"   ? verts_
                     : k == "LINES"    ? lines_
                     : k == "POLYGONS" ? polys_
                                       : strips_;
      if (cells.present) Fail(MeshErrorKind::kSyntax, kw.where, "a second " + k + " section");
      cells = ReadCells(kw);
    } else if (!polydata_ && k == "CELLS") {
      if (cells_.present) Fail(MeshErrorKind::kSyntax, kw.where, "a second CELLS section");
      cells_ = ReadCells(kw);
    } else if (!polydata_ && k == "CELL_TYPES") {
      ReadCellTypes(kw);
    } else {
      UnknownKeyword(kw, geometry_keywords);
    }
    end_of_geometry = kw.where;
  }
  if (!have_points_) {
    Fail(MeshErrorKind::kSyntax, end_of_geometry,
         "the file has no POINTS section (truncated file?)");
  }
  std::string format = "VTK legacy";
  if (!version.empty()) format += " " + std::string(version[0]);
  format += binary_ ? " BINARY " : " ASCII ";
  format += polydata_ ? "POLYDATA" : "UNSTRUCTURED_GRID";
  MeshBuilder builder(file_name_, format);
  Build(&builder);
  return builder.Finish(options);
}

void AppendInt(std::string* out, int64_t value) { *out += std::to_string(value); }

}  // namespace

MeshData ReadVtkLegacy(std::string_view bytes, const std::string& file_name,
                       const ReadOptions& options) {
  LegacyReader reader(bytes, file_name);
  return reader.Read(options);
}

std::string WriteVtkLegacy(const MeshData& mesh, Encoding encoding) {
  const bool binary = encoding == Encoding::kBinary;
  const int64_t n = mesh.vertices.cols();
  const int64_t ntri = mesh.triangles.cols();
  const int64_t ntet = mesh.tetrahedra.cols();
  std::string out = "# vtk DataFile Version 3.0\nsomasim mesh\n";
  out += binary ? "BINARY\n" : "ASCII\n";
  out += ntet > 0 ? "DATASET UNSTRUCTURED_GRID\n" : "DATASET POLYDATA\n";
  out += "POINTS " + std::to_string(n) + " double\n";
  for (int64_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      const double x = mesh.vertices(k, i);
      if (binary) {
        AppendBinary(&out, x, Endian::kBig);
      } else {
        AppendDouble(&out, x);
        out += k < 2 ? ' ' : '\n';
      }
    }
  }
  if (binary) out += '\n';
  // One cell: its point count then its indices (32-bit in BINARY files, as VTK writes them).
  const auto append_cell = [&](const int32_t* v, int m) {
    if (binary) {
      AppendBinary(&out, static_cast<int32_t>(m), Endian::kBig);
      for (int k = 0; k < m; ++k) AppendBinary(&out, v[k], Endian::kBig);
      return;
    }
    AppendInt(&out, m);
    for (int k = 0; k < m; ++k) {
      out += ' ';
      AppendInt(&out, v[k]);
    }
    out += '\n';
  };
  if (ntet == 0) {
    if (ntri > 0) {
      out += "POLYGONS " + std::to_string(ntri) + " " + std::to_string(4 * ntri) + "\n";
      for (int64_t t = 0; t < ntri; ++t) append_cell(mesh.triangles.col(t).data(), 3);
      if (binary) out += '\n';
    }
    return out;
  }
  const int64_t cells = ntet + ntri;
  out += "CELLS " + std::to_string(cells) + " " + std::to_string(5 * ntet + 4 * ntri) + "\n";
  for (int64_t t = 0; t < ntet; ++t) append_cell(mesh.tetrahedra.col(t).data(), 4);
  for (int64_t t = 0; t < ntri; ++t) append_cell(mesh.triangles.col(t).data(), 3);
  if (binary) out += '\n';
  out += "CELL_TYPES " + std::to_string(cells) + "\n";
  for (int64_t c = 0; c < cells; ++c) {
    const int32_t type = static_cast<int32_t>(c < ntet ? kVtkTetra : kVtkTriangle);
    if (binary) {
      AppendBinary(&out, type, Endian::kBig);
    } else {
      AppendInt(&out, type);
      out += '\n';
    }
  }
  if (binary) out += '\n';
  return out;
}

}  // namespace somasim::mesh_io
