// The legacy VTK reader's values: the data types, counts checked against what the file still
// holds, ASCII tokens and big-endian binary blocks read as integers or doubles, and attribute
// values checked and skipped.
#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/text_reader.h"
#include "common/mesh_io/vtk_legacy_reader.h"

namespace somasim::mesh_io::vtk_legacy_internal {

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

template std::vector<int64_t> LegacyReader::ReadValues<int64_t>(Scalar, int64_t, const std::string&,
                                                                const KeywordLine&,
                                                                std::vector<SourceLocation>*);
template std::vector<double> LegacyReader::ReadValues<double>(Scalar, int64_t, const std::string&,
                                                              const KeywordLine&,
                                                              std::vector<SourceLocation>*);

}  // namespace somasim::mesh_io::vtk_legacy_internal
