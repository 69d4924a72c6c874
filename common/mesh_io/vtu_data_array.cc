// The VTU reader's data arrays: a <DataArray> inspected (its type, layout and how many values it
// holds, known without decoding), then decoded: ASCII tokens, or binary blocks (inline base64,
// appended raw or base64) behind a UInt32/UInt64 header, in either byte order, optionally in
// zlib-compressed blocks (VTK's vtkZLibDataCompressor layout).
#include <zlib.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <optional>
#include <pugixml.hpp>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/base64.h"
#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/text_reader.h"
#include "common/mesh_io/vtu_reader.h"

namespace somasim::mesh_io::vtu_internal {

std::optional<ScalarInfo> ParseScalar(std::string_view name) {
  struct Entry {
    const char* name;
    ScalarInfo info;
  };
  static constexpr Entry kTypes[] = {
      {"Int8", {Scalar::kInt8, 1}},
      {"UInt8", {Scalar::kUInt8, 1}},
      {"Int16", {Scalar::kInt16, 2}},
      {"UInt16", {Scalar::kUInt16, 2}},
      {"Int32", {Scalar::kInt32, 4}},
      {"UInt32", {Scalar::kUInt32, 4}},
      {"Int64", {Scalar::kInt64, 8}},
      {"UInt64", {Scalar::kUInt64, 8}},
      {"Float32", {Scalar::kFloat32, 4}},
      {"Float64", {Scalar::kFloat64, 8}},
      // Strings and bits have no fixed count per tuple; their bytes are checked, not counted.
      {"String", {Scalar::kOther, 1}},
      {"Bit", {Scalar::kOther, 1}},
      {"Char", {Scalar::kInt8, 1}},
      {"UChar", {Scalar::kUInt8, 1}},
  };
  for (const Entry& e : kTypes) {
    if (name == e.name) return e.info;
  }
  return std::nullopt;
}

void IntegralRange(Scalar s, int64_t* lo, int64_t* hi) {
  switch (s) {
    case Scalar::kInt8:
      *lo = INT8_MIN, *hi = INT8_MAX;
      return;
    case Scalar::kUInt8:
      *lo = 0, *hi = UINT8_MAX;
      return;
    case Scalar::kInt16:
      *lo = INT16_MIN, *hi = INT16_MAX;
      return;
    case Scalar::kUInt16:
      *lo = 0, *hi = UINT16_MAX;
      return;
    case Scalar::kInt32:
      *lo = INT32_MIN, *hi = INT32_MAX;
      return;
    case Scalar::kUInt32:
      *lo = 0, *hi = UINT32_MAX;
      return;
    case Scalar::kUInt64:
      *lo = 0, *hi = INT64_MAX;
      return;
    default:
      *lo = INT64_MIN, *hi = INT64_MAX;
      return;
  }
}

namespace {

// Reads one header word (UInt32 or UInt64, in the file's byte order) from decoded bytes.
uint64_t HeaderWord(std::string_view bytes, uint64_t size, Endian endian) {
  uint64_t v = 0;
  for (uint64_t k = 0; k < size; ++k) {
    const uint64_t i = endian == Endian::kLittle ? size - 1 - k : k;
    v = (v << 8) | static_cast<unsigned char>(bytes[i]);
  }
  return v;
}

// Pulls bytes from a binary array: base64 text or raw appended bytes.
class BinarySource {
 public:
  explicit BinarySource(const ArrayRef& a) : a_(a), decoder_(a.base64 ? a.data : "") {}

  bool Read(size_t n, std::string* out) {
    if (a_.base64) {
      if (!decoder_.Read(n, out)) {
        error_ = decoder_.error();
        return false;
      }
      return true;
    }
    if (n > a_.data.size() - raw_pos_) {
      error_ = "need " + std::to_string(n) + " bytes but only " +
               std::to_string(a_.data.size() - raw_pos_) + " remain";
      return false;
    }
    out->append(a_.data.substr(raw_pos_, n));
    raw_pos_ += n;
    return true;
  }
  // Upper bound of the bytes still available.
  uint64_t Available() const {
    if (a_.base64) return (a_.data.size() - decoder_.position()) / 4 * 3 + 3;
    return a_.data.size() - raw_pos_;
  }
  size_t file_offset() const {
    return a_.data_offset + (a_.base64 ? decoder_.position() : raw_pos_);
  }
  bool AtEnd() { return a_.base64 ? decoder_.AtEnd() : true; }
  const std::string& error() const { return error_; }

 private:
  const ArrayRef& a_;
  Base64Decoder decoder_;
  size_t raw_pos_ = 0;
  std::string error_;
};

}  // namespace

ArrayRef VtuReader::Inspect(const pugi::xml_node& node) {
  ArrayRef a;
  a.node = node;
  a.where = NodeLine(node);
  const std::string name = node.attribute("Name").as_string("");
  a.label = "DataArray " + (name.empty() ? std::string("(unnamed)") : QuoteToken(name)) +
            " (line " + std::to_string(a.where.line) + ")";
  const pugi::xml_attribute type = node.attribute("type");
  if (!type) Fail(MeshErrorKind::kSyntax, a.where, a.label + " has no type attribute");
  const std::optional<ScalarInfo> info = ParseScalar(type.value());
  if (!info) {
    Fail(MeshErrorKind::kSyntax, a.where,
         a.label + " has unknown type " + QuoteToken(type.value()));
  }
  a.type = *info;
  a.type_name = type.value();
  a.components = CountAttribute(node, "NumberOfComponents", false, 1);
  if (a.components < 1 || a.components > (int64_t{1} << 20)) {
    Fail(MeshErrorKind::kCount, a.where,
         a.label + " has " + std::to_string(a.components) + " components");
  }
  if (node.attribute("NumberOfTuples")) {
    a.tuples = CountAttribute(node, "NumberOfTuples", true, 0);
  }
  const std::string_view format = node.attribute("format").as_string("");
  if (format == "ascii") {
    a.format = Format::kAscii;
  } else if (format == "binary") {
    a.format = Format::kBinary;
  } else if (format == "appended") {
    a.format = Format::kAppended;
  } else {
    Fail(MeshErrorKind::kSyntax, a.where,
         a.label + " has format " + QuoteToken(format) + "; expected ascii, binary or appended");
  }
  // The text of the element; VTK may put <InformationKey> elements before it.
  for (const pugi::xml_node& child : node.children()) {
    if (child.type() == pugi::node_pcdata || child.type() == pugi::node_cdata) {
      const ptrdiff_t off = child.offset_debug();
      a.chunks.emplace_back(child.value(), off < 0 ? 0 : FileOffset(static_cast<size_t>(off)));
    } else if (child.type() == pugi::node_element &&
               std::strcmp(child.name(), "InformationKey") != 0) {
      Fail(MeshErrorKind::kSyntax, NodeLine(child),
           std::string("unknown element <") + child.name() + "> inside " + a.label);
    }
  }
  if (a.format == Format::kAscii) {
    int64_t count = 0;
    for (const auto& [text, offset] : a.chunks) {
      size_t i = 0;
      while (i < text.size()) {
        while (i < text.size() && IsSpace(text[i])) ++i;
        if (i >= text.size()) break;
        ++count;
        while (i < text.size() && !IsSpace(text[i])) ++i;
      }
    }
    a.value_count = count;
    return a;
  }
  if (a.format == Format::kBinary) {
    a.base64 = true;
    if (a.chunks.size() == 1) {
      a.data = a.chunks[0].first;
      a.data_offset = a.chunks[0].second;
    } else {
      std::string& joined = owned_text_.emplace_back();
      for (const auto& chunk : a.chunks) joined += chunk.first;
      a.data = joined;
      a.data_offset =
          a.chunks.empty()
              ? FileOffset(static_cast<size_t>(std::max<ptrdiff_t>(0, node.offset_debug())))
              : a.chunks[0].second;
    }
  } else {
    if (!have_appended_) {
      Fail(MeshErrorKind::kSyntax, a.where,
           a.label + " is in appended format but the file has no <AppendedData>");
    }
    if (!node.attribute("offset")) {
      Fail(MeshErrorKind::kSyntax, a.where, a.label + " is appended but has no offset attribute");
    }
    const int64_t offset = CountAttribute(node, "offset", true, 0);
    if (static_cast<uint64_t>(offset) > appended_.size()) {
      Fail(MeshErrorKind::kSyntax, a.where,
           a.label + " has offset " + std::to_string(offset) +
               ", past the end of the appended data (" + std::to_string(appended_.size()) +
               (appended_base64_ ? " characters)" : " bytes)"));
    }
    a.base64 = appended_base64_;
    a.data = appended_.substr(static_cast<size_t>(offset));
    a.data_offset = appended_offset_ + static_cast<size_t>(offset);
  }
  InspectBinary(&a);
  return a;
}

// Reads the block header of a binary array. Uncompressed: one word, the byte count.
// Compressed (VTK's vtkZLibDataCompressor layout): number of blocks, uncompressed block size,
// uncompressed size of the last block (0 = full), then the compressed size of each block.
void VtuReader::InspectBinary(ArrayRef* a) {
  BinarySource source(*a);
  std::string header;
  const auto read_header = [&](uint64_t words, const char* what) {
    header.clear();
    if (words > source.Available() / header_size_) {
      Fail(MeshErrorKind::kCount, ByteAt(source.file_offset()),
           a->label + ": the " + what + " claims " + std::to_string(words) +
               " header words but the data is shorter (truncated or corrupt)");
    }
    if (!source.Read(static_cast<size_t>(words * header_size_), &header)) {
      Fail(MeshErrorKind::kSyntax, ByteAt(source.file_offset()),
           a->label + ": cannot read its binary header: " + source.error());
    }
  };
  if (!zlib_) {
    read_header(1, "header");
    a->header_bytes = header_size_;
    a->data_bytes = HeaderWord(header, header_size_, endian_);
    if (a->data_bytes > source.Available()) {
      Fail(MeshErrorKind::kCount, ByteAt(a->data_offset),
           a->label + ": its header announces " + std::to_string(a->data_bytes) +
               " bytes of data but at most " + std::to_string(source.Available()) +
               " follow (truncated file or corrupt header)");
    }
  } else {
    a->compressed = true;
    read_header(3, "compression header");
    const uint64_t blocks = HeaderWord(header, header_size_, endian_);
    a->block_size =
        HeaderWord(std::string_view(header).substr(header_size_), header_size_, endian_);
    a->last_block_size =
        HeaderWord(std::string_view(header).substr(2 * header_size_), header_size_, endian_);
    read_header(blocks, "compression header");
    a->block_bytes.resize(static_cast<size_t>(blocks));
    uint64_t compressed_total = 0;
    for (size_t b = 0; b < a->block_bytes.size(); ++b) {
      a->block_bytes[b] =
          HeaderWord(std::string_view(header).substr(b * header_size_), header_size_, endian_);
      // Saturating sum: any total beyond the data present fails the check below.
      compressed_total = std::min<uint64_t>(
          compressed_total + std::min<uint64_t>(a->block_bytes[b], uint64_t{1} << 60),
          uint64_t{1} << 61);
    }
    a->header_bytes = (3 + blocks) * header_size_;
    if (blocks > 0 && (a->block_size == 0 || a->last_block_size > a->block_size)) {
      Fail(MeshErrorKind::kSyntax, ByteAt(a->data_offset),
           a->label + ": inconsistent compression header (block size " +
               std::to_string(a->block_size) + ", last block " +
               std::to_string(a->last_block_size) + ")");
    }
    if (compressed_total > source.Available()) {
      Fail(MeshErrorKind::kCount, ByteAt(a->data_offset),
           a->label + ": the compression header announces " + std::to_string(compressed_total) +
               " bytes of compressed data but at most " + std::to_string(source.Available()) +
               " follow (truncated file or corrupt header)");
    }
    for (size_t b = 0; b < a->block_bytes.size(); ++b) {
      const uint64_t raw = (b + 1 == a->block_bytes.size() && a->last_block_size != 0)
                               ? a->last_block_size
                               : a->block_size;
      if (raw > a->block_bytes[b] * kMaxInflateRatio) {
        Fail(MeshErrorKind::kCount, ByteAt(a->data_offset),
             a->label + ": block #" + std::to_string(b + 1) + " claims to inflate " +
                 std::to_string(a->block_bytes[b]) + " compressed bytes to " + std::to_string(raw) +
                 ", more than zlib can (corrupt header)");
      }
      a->data_bytes += raw;
    }
  }
  if (a->data_bytes % static_cast<uint64_t>(a->type.bytes) != 0) {
    Fail(MeshErrorKind::kCount, ByteAt(a->data_offset),
         a->label + ": " + std::to_string(a->data_bytes) +
             " bytes of data is not a whole number "
             "of " +
             a->type_name + " values");
  }
  a->value_count = static_cast<int64_t>(a->data_bytes / static_cast<uint64_t>(a->type.bytes));
}

std::string VtuReader::DecodeBinary(const ArrayRef& a) {
  BinarySource source(a);
  std::string skipped;
  if (!source.Read(static_cast<size_t>(a.header_bytes), &skipped)) {
    Fail(MeshErrorKind::kSyntax, ByteAt(source.file_offset()), a.label + ": " + source.error());
  }
  std::string out;
  if (!a.compressed) {
    out.reserve(static_cast<size_t>(a.data_bytes));
    if (!source.Read(static_cast<size_t>(a.data_bytes), &out)) {
      Fail(MeshErrorKind::kSyntax, ByteAt(source.file_offset()),
           a.label + ": " + source.error() + " (truncated data?)");
    }
  } else {
    out.resize(static_cast<size_t>(a.data_bytes));
    size_t at = 0;
    std::string block;
    for (size_t b = 0; b < a.block_bytes.size(); ++b) {
      const size_t block_offset = source.file_offset();
      block.clear();
      if (!source.Read(static_cast<size_t>(a.block_bytes[b]), &block)) {
        Fail(MeshErrorKind::kSyntax, ByteAt(block_offset),
             a.label + ": compressed block #" + std::to_string(b + 1) + ": " + source.error());
      }
      const uint64_t raw = (b + 1 == a.block_bytes.size() && a.last_block_size != 0)
                               ? a.last_block_size
                               : a.block_size;
      uLongf dest_len = static_cast<uLongf>(raw);
      uLong source_len = static_cast<uLong>(block.size());
      const int rc = uncompress2(reinterpret_cast<Bytef*>(out.data() + at), &dest_len,
                                 reinterpret_cast<const Bytef*>(block.data()), &source_len);
      if (rc != Z_OK || dest_len != raw || source_len != block.size()) {
        std::string why = rc == Z_DATA_ERROR  ? "it is not a valid zlib stream"
                          : rc == Z_BUF_ERROR ? "it inflates to more bytes than the header says, "
                                                "or is cut short"
                                              : "zlib error " + std::to_string(rc);
        if (rc == Z_OK && dest_len != raw) {
          why = "it inflates to " + std::to_string(dest_len) + " bytes, the header says " +
                std::to_string(raw);
        } else if (rc == Z_OK) {
          why = "bytes are left over after its zlib stream";
        }
        Fail(MeshErrorKind::kSyntax, ByteAt(block_offset),
             a.label + ": compressed block #" + std::to_string(b + 1) + " is corrupt: " + why);
      }
      at += static_cast<size_t>(raw);
    }
  }
  if (a.format == Format::kBinary && !source.AtEnd()) {
    Fail(MeshErrorKind::kCount, ByteAt(source.file_offset()),
         a.label + " holds more base64 data than its header accounts for");
  }
  return out;
}

void VtuReader::DecodeAscii(const ArrayRef& a, bool want_ints, Values* out,
                            std::vector<int64_t>* lines) {
  int64_t lo = 0, hi = 0;
  IntegralRange(a.type.scalar, &lo, &hi);
  const bool integral = IsIntegral(a.type.scalar);
  for (const auto& [text, offset] : a.chunks) {
    int64_t line = LineAt(offset);
    size_t i = 0;
    while (i < text.size()) {
      while (i < text.size() && IsSpace(text[i])) {
        if (text[i] == '\n') ++line;
        ++i;
      }
      if (i >= text.size()) break;
      const size_t start = i;
      while (i < text.size() && !IsSpace(text[i])) ++i;
      const std::string_view token = text.substr(start, i - start);
      if (integral) {
        int64_t v = 0;
        if (!ParseInt64(token, &v)) {
          Fail(MeshErrorKind::kSyntax, SourceLocation::Line(line),
               a.label + ": expected an integer (" + a.type_name + "), found " + QuoteToken(token));
        }
        if (v < lo || v > hi) {
          Fail(MeshErrorKind::kSyntax, SourceLocation::Line(line),
               a.label + ": " + std::string(token) + " does not fit in " + a.type_name);
        }
        if (want_ints) {
          out->ints.push_back(v);
        } else {
          out->reals.push_back(static_cast<double>(v));
        }
      } else {
        double v = 0;
        if (!ParseDouble(token, &v)) {
          Fail(MeshErrorKind::kSyntax, SourceLocation::Line(line),
               a.label + ": expected a number, found " + QuoteToken(token));
        }
        if (!want_ints) out->reals.push_back(v);
      }
      if (lines) lines->push_back(line);
    }
  }
}

Values VtuReader::Decode(const ArrayRef& a, bool want_ints) {
  Values values;
  if (want_ints && !IsIntegral(a.type.scalar)) {
    Fail(MeshErrorKind::kSyntax, a.where,
         a.label + " must have an integer type, not " + a.type_name);
  }
  if (a.format == Format::kAscii) {
    if (want_ints) {
      values.ints.reserve(static_cast<size_t>(a.value_count));
    } else {
      values.reals.reserve(static_cast<size_t>(a.value_count));
    }
    DecodeAscii(a, want_ints, &values, nullptr);
    return values;
  }
  const std::string bytes = DecodeBinary(a);
  if (a.type.scalar == Scalar::kOther) return values;
  ByteReader r(bytes, file_name_, static_cast<int64_t>(a.data_offset));
  const size_t n = static_cast<size_t>(a.value_count);
  if (want_ints) {
    values.ints.reserve(n);
  } else {
    values.reals.reserve(n);
  }
  const char* what = "array value";
  for (size_t i = 0; i < n; ++i) {
    int64_t iv = 0;
    double dv = 0;
    switch (a.type.scalar) {
      case Scalar::kInt8:
        iv = r.Read<int8_t>(endian_, what);  // NOLINT(bugprone-signed-char-misuse): Int8 is signed
        break;
      case Scalar::kUInt8:
        iv = r.Read<uint8_t>(endian_, what);
        break;
      case Scalar::kInt16:
        iv = r.Read<int16_t>(endian_, what);
        break;
      case Scalar::kUInt16:
        iv = r.Read<uint16_t>(endian_, what);
        break;
      case Scalar::kInt32:
        iv = r.Read<int32_t>(endian_, what);
        break;
      case Scalar::kUInt32:
        iv = r.Read<uint32_t>(endian_, what);
        break;
      case Scalar::kInt64:
        iv = r.Read<int64_t>(endian_, what);
        break;
      case Scalar::kUInt64: {
        const uint64_t u = r.Read<uint64_t>(endian_, what);
        if (u > static_cast<uint64_t>(INT64_MAX)) {
          Fail(MeshErrorKind::kIndex, ByteAt(a.data_offset),
               a.label + ": value #" + std::to_string(i + 1) + " (" + std::to_string(u) +
                   ") is too large");
        }
        iv = static_cast<int64_t>(u);
        break;
      }
      case Scalar::kFloat32:
        dv = static_cast<double>(r.Read<float>(endian_, what));
        break;
      case Scalar::kFloat64:
        dv = r.Read<double>(endian_, what);
        break;
      case Scalar::kOther:
        break;
    }
    if (want_ints) {
      values.ints.push_back(iv);
    } else {
      values.reals.push_back(IsIntegral(a.type.scalar) ? static_cast<double>(iv) : dv);
    }
  }
  return values;
}

}  // namespace somasim::mesh_io::vtu_internal
