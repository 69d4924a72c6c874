#include "common/mesh_io/vtu_io.h"

#include <zlib.h>

#include <algorithm>
#include <cctype>
#include <cstdint>
#include <cstring>
#include <deque>
#include <limits>
#include <optional>
#include <pugixml.hpp>
#include <stdexcept>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "common/mesh_io/base64.h"
#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/text_reader.h"
#include "common/mesh_io/vtk_legacy_io.h"  // VtkCellType

namespace somasim::mesh_io {
namespace {

// Deflate cannot expand data by more than about 1032:1, so a block header claiming more is
// a corrupt (or hostile) file; checked before anything is allocated.
constexpr uint64_t kMaxInflateRatio = 1032;
// Counts above this cannot describe a real mesh and would overflow byte arithmetic.
constexpr int64_t kMaxCount = int64_t{1} << 50;

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

bool IsIntegral(Scalar s) {
  return s != Scalar::kFloat32 && s != Scalar::kFloat64 && s != Scalar::kOther;
}

// Range of an integral scalar, to refuse ASCII values that do not fit the declared type.
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
  void ReadPiece(const pugi::xml_node& piece, int piece_index, MeshBuilder* builder);

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

// Raw appended data is arbitrary bytes, which no XML parser accepts, so it is cut out before
// parsing: it runs from the '_' after <AppendedData ...> to the last </AppendedData>.
void VtuReader::SplitAppendedData() {
  const size_t tag = bytes_.find("<AppendedData");
  if (tag == std::string_view::npos) {
    xml_.assign(bytes_);
    return;
  }
  const size_t gt = bytes_.find('>', tag);
  if (gt == std::string_view::npos) {
    Fail(MeshErrorKind::kSyntax, SourceLocation::Line(LineAt(tag)),
         "the <AppendedData> tag is not closed (truncated file?)");
  }
  if (bytes_[gt - 1] == '/') {  // <AppendedData .../>: no data
    xml_.assign(bytes_);
    return;
  }
  size_t underscore = gt + 1;
  while (underscore < bytes_.size() && IsSpace(bytes_[underscore])) ++underscore;
  if (underscore >= bytes_.size() || bytes_[underscore] != '_') {
    Fail(MeshErrorKind::kSyntax, SourceLocation::Line(LineAt(tag)),
         "the content of <AppendedData> must start with '_' (VTK's marker before the data)");
  }
  const size_t close = bytes_.rfind("</AppendedData>");
  if (close == std::string_view::npos || close < underscore) {
    Fail(MeshErrorKind::kSyntax, ByteAt(bytes_.size()),
         "</AppendedData> is missing: the appended data is not closed (truncated file?)");
  }
  have_appended_ = true;
  appended_offset_ = underscore + 1;
  appended_ = bytes_.substr(appended_offset_, close - appended_offset_);
  cut_at_ = underscore;
  cut_length_ = close - underscore;
  xml_.reserve(underscore + bytes_.size() - close);
  xml_.assign(bytes_.substr(0, underscore));
  xml_.append(bytes_.substr(close));
}

int64_t VtuReader::CountAttribute(const pugi::xml_node& node, const char* name, bool required,
                                  int64_t fallback) const {
  const pugi::xml_attribute attr = node.attribute(name);
  if (!attr) {
    if (required) {
      Fail(MeshErrorKind::kSyntax, NodeLine(node),
           std::string("<") + node.name() + "> has no " + name + " attribute");
    }
    return fallback;
  }
  int64_t value = 0;
  if (!ParseInt64(attr.value(), &value)) {
    Fail(MeshErrorKind::kSyntax, NodeLine(node),
         std::string(name) + " of <" + node.name() +
             "> is not an integer: " + QuoteToken(attr.value()));
  }
  if (value < 0 || value > kMaxCount) {
    Fail(MeshErrorKind::kCount, NodeLine(node),
         std::string(name) + " of <" + node.name() + "> is " + std::to_string(value) +
             (value < 0 ? " (negative)" : " (absurdly large)"));
  }
  return value;
}

void VtuReader::CheckChildren(const pugi::xml_node& node,
                              std::initializer_list<const char*> allowed) const {
  for (const pugi::xml_node& child : node.children()) {
    if (child.type() == pugi::node_pcdata || child.type() == pugi::node_cdata) {
      const std::string_view text = child.value();
      if (std::all_of(text.begin(), text.end(), IsSpace)) continue;
      Fail(MeshErrorKind::kSyntax, NodeLine(child),
           std::string("unexpected text ") + QuoteToken(text) + " inside <" + node.name() + ">");
    }
    if (child.type() != pugi::node_element) continue;
    bool ok = false;
    for (const char* name : allowed) ok = ok || std::strcmp(child.name(), name) == 0;
    if (!ok) {
      Fail(MeshErrorKind::kSyntax, NodeLine(child),
           std::string("unknown element <") + child.name() + "> inside <" + node.name() + ">");
    }
  }
}

void VtuReader::ParseHeaderAttributes(const pugi::xml_node& root) {
  const pugi::xml_attribute type = root.attribute("type");
  if (!type) Fail(MeshErrorKind::kSyntax, NodeLine(root), "<VTKFile> has no type attribute");
  if (std::strcmp(type.value(), "UnstructuredGrid") != 0) {
    Fail(MeshErrorKind::kUnsupported, NodeLine(root),
         std::string("VTK XML files of type ") + QuoteToken(type.value()) +
             " are not supported: only UnstructuredGrid (.vtu) holds tetrahedra");
  }
  const std::string_view order = root.attribute("byte_order").as_string("LittleEndian");
  if (order == "BigEndian") {
    endian_ = Endian::kBig;
  } else if (order != "LittleEndian") {
    Fail(MeshErrorKind::kSyntax, NodeLine(root),
         "byte_order must be LittleEndian or BigEndian, not " + QuoteToken(order));
  }
  const std::string_view header = root.attribute("header_type").as_string("UInt32");
  if (header == "UInt64") {
    header_size_ = 8;
  } else if (header != "UInt32") {
    Fail(MeshErrorKind::kSyntax, NodeLine(root),
         "header_type must be UInt32 or UInt64, not " + QuoteToken(header));
  }
  const std::string_view compressor = root.attribute("compressor").as_string("");
  if (compressor == "vtkZLibDataCompressor") {
    zlib_ = true;
  } else if (!compressor.empty()) {
    Fail(MeshErrorKind::kUnsupported, NodeLine(root),
         "compressor " + QuoteToken(compressor) +
             " is not supported (only vtkZLibDataCompressor); re-save the file uncompressed or "
             "with zlib");
  }
}

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

// Where value #index of an array is: its line for ASCII, its byte for uncompressed binary data,
// the start of the array's data for compressed data (whose bytes cannot be pointed at).
SourceLocation VtuReader::ValueLocation(const ArrayRef& a, const std::vector<int64_t>& lines,
                                        size_t index) const {
  if (a.format == Format::kAscii) {
    return index < lines.size() ? SourceLocation::Line(lines[index]) : a.where;
  }
  if (a.compressed) return ByteAt(a.data_offset);
  const uint64_t byte = a.header_bytes + index * static_cast<uint64_t>(a.type.bytes);
  return ByteAt(a.data_offset + static_cast<size_t>(a.base64 ? byte / 3 * 4 : byte));
}

// Point and cell data are not kept, but they must be well-formed and of the right length.
void VtuReader::CheckAttributeArrays(const pugi::xml_node& data, int64_t tuples, const char* what) {
  CheckChildren(data, {"DataArray", "Array"});
  for (const pugi::xml_node& node : data.children()) {
    if (node.type() != pugi::node_element) continue;
    const ArrayRef a = Inspect(node);
    const int64_t n = a.tuples.value_or(tuples);
    if (tuples >= 0 && a.tuples && *a.tuples != tuples) {
      Fail(MeshErrorKind::kCount, a.where,
           a.label + " in <" + what + "> has NumberOfTuples " + std::to_string(*a.tuples) +
               " but the piece has " + std::to_string(tuples));
    }
    if (n >= 0 && a.type.scalar != Scalar::kOther &&
        (a.value_count % a.components != 0 || a.value_count / a.components != n)) {
      Fail(MeshErrorKind::kCount, a.where,
           a.label + " in <" + what + "> holds " + std::to_string(a.value_count) +
               " values; expected " + std::to_string(n) + " tuples of " +
               std::to_string(a.components) + " components");
    }
    Decode(a, false);
  }
}

void VtuReader::ReadPiece(const pugi::xml_node& piece, int piece_index, MeshBuilder* builder) {
  const SourceLocation piece_where = NodeLine(piece);
  const int64_t num_points = CountAttribute(piece, "NumberOfPoints", true, 0);
  const int64_t num_cells = CountAttribute(piece, "NumberOfCells", true, 0);
  CheckChildren(piece, {"PointData", "CellData", "Points", "Cells"});
  const auto only_child = [&](const char* name) {
    pugi::xml_node found;
    for (const pugi::xml_node& child : piece.children(name)) {
      if (found) {
        Fail(MeshErrorKind::kSyntax, NodeLine(child),
             std::string("a second <") + name + "> in the same <Piece>");
      }
      found = child;
    }
    return found;
  };
  const pugi::xml_node points = only_child("Points");
  const pugi::xml_node cells = only_child("Cells");
  if (!points && num_points > 0) {
    Fail(MeshErrorKind::kSyntax, piece_where,
         "<Piece> has NumberOfPoints=" + std::to_string(num_points) + " but no <Points>");
  }
  if (!cells && num_cells > 0) {
    Fail(MeshErrorKind::kSyntax, piece_where,
         "<Piece> has NumberOfCells=" + std::to_string(num_cells) + " but no <Cells>");
  }

  // Inspect the arrays first: their lengths are known without decoding, so every count that
  // disagrees with the data can be reported at once, before anything large is allocated.
  std::optional<ArrayRef> pts, conn, offs, types;
  if (points) {
    CheckChildren(points, {"DataArray"});
    for (const pugi::xml_node& node : points.children("DataArray")) {
      if (pts) Fail(MeshErrorKind::kSyntax, NodeLine(node), "<Points> has more than one DataArray");
      pts = Inspect(node);
    }
    if (!pts) Fail(MeshErrorKind::kSyntax, NodeLine(points), "<Points> has no DataArray");
    if (pts->type.scalar == Scalar::kOther) {
      Fail(MeshErrorKind::kSyntax, pts->where,
           "the Points " + pts->label + " has type " + pts->type_name + "; points need numbers");
    }
    if (pts->components != 3) {
      Fail(MeshErrorKind::kCount, pts->where,
           "the Points " + pts->label +
               " has NumberOfComponents=" + std::to_string(pts->components) + "; points need 3");
    }
  }
  if (cells) {
    CheckChildren(cells, {"DataArray"});
    for (const pugi::xml_node& node : cells.children("DataArray")) {
      const std::string_view name = node.attribute("Name").as_string("");
      std::optional<ArrayRef>* slot = name == "connectivity" ? &conn
                                      : name == "offsets"    ? &offs
                                      : name == "types"      ? &types
                                                             : nullptr;
      if (slot == nullptr) {
        // Polyhedron faces (VTK_POLYHEDRON cells are skipped, but their arrays checked).
        if (name == "faces" || name == "faceoffsets" || name == "face_connectivity" ||
            name == "face_offsets" || name == "polyhedron_to_faces" ||
            name == "polyhedron_offsets") {
          Decode(Inspect(node), false);
          continue;
        }
        Fail(MeshErrorKind::kSyntax, NodeLine(node),
             "unknown DataArray " + QuoteToken(name) +
                 " in <Cells> (expected connectivity, offsets and types)");
      }
      if (*slot) {
        Fail(MeshErrorKind::kSyntax, NodeLine(node),
             "a second DataArray " + QuoteToken(name) + " in <Cells>");
      }
      *slot = Inspect(node);
    }
    for (const auto& [slot, name] : {std::pair{&conn, "connectivity"}, std::pair{&offs, "offsets"},
                                     std::pair{&types, "types"}}) {
      if (!*slot) {
        Fail(MeshErrorKind::kSyntax, NodeLine(cells),
             std::string("<Cells> has no DataArray named '") + name + "'");
      }
    }
  }
  std::vector<std::string> problems;
  if (pts && pts->value_count != 3 * num_points) {
    problems.push_back("NumberOfPoints is " + std::to_string(num_points) +
                       " but the Points array (line " + std::to_string(pts->where.line) +
                       ") holds " + std::to_string(pts->value_count) + " values (" +
                       (pts->value_count % 3 == 0
                            ? std::to_string(pts->value_count / 3) + " points)"
                            : "not a whole number of points)"));
  }
  if (offs && offs->value_count != num_cells) {
    problems.push_back("NumberOfCells is " + std::to_string(num_cells) +
                       " but the offsets array (line " + std::to_string(offs->where.line) +
                       ") has " + std::to_string(offs->value_count) + " entries");
  }
  if (types && types->value_count != num_cells) {
    problems.push_back("NumberOfCells is " + std::to_string(num_cells) +
                       " but the types array (line " + std::to_string(types->where.line) +
                       ") has " + std::to_string(types->value_count) + " entries");
  }
  Values offsets;
  std::vector<int64_t> offset_lines;
  if (offs) {
    if (offs->format == Format::kAscii) {
      if (!IsIntegral(offs->type.scalar)) Decode(*offs, true);  // fails naming the type
      DecodeAscii(*offs, true, &offsets, &offset_lines);
    } else {
      offsets = Decode(*offs, true);
    }
    const int64_t last = offsets.ints.empty() ? 0 : offsets.ints.back();
    if (conn && conn->value_count != last) {
      problems.push_back("the last offset is " + std::to_string(last) +
                         " but the connectivity array (line " + std::to_string(conn->where.line) +
                         ") has " + std::to_string(conn->value_count) + " entries");
    }
  }
  if (!problems.empty()) {
    std::string fault = "Piece #" + std::to_string(piece_index + 1) + " disagrees with its data: ";
    for (size_t i = 0; i < problems.size(); ++i) fault += (i > 0 ? "; " : "") + problems[i];
    Fail(MeshErrorKind::kCount, piece_where, fault);
  }

  for (const pugi::xml_node& node : piece.children("PointData")) {
    CheckAttributeArrays(node, num_points, "PointData");
  }
  for (const pugi::xml_node& node : piece.children("CellData")) {
    CheckAttributeArrays(node, num_cells, "CellData");
  }

  const int64_t base = builder->num_nodes();
  if (pts) {
    std::vector<int64_t> lines;
    Values p;
    if (pts->format == Format::kAscii) {
      p.reals.reserve(static_cast<size_t>(pts->value_count));
      DecodeAscii(*pts, false, &p, &lines);
    } else {
      p = Decode(*pts, false);
    }
    for (size_t i = 0; i < static_cast<size_t>(num_points); ++i) {
      builder->AddNode(p.reals[3 * i], p.reals[3 * i + 1], p.reals[3 * i + 2],
                       ValueLocation(*pts, lines, 3 * i));
    }
  }
  if (!cells) return;

  const std::vector<int64_t>& ends = offsets.ints;
  int64_t previous = 0;
  for (size_t c = 0; c < ends.size(); ++c) {
    if (ends[c] < previous) {
      Fail(MeshErrorKind::kCount, ValueLocation(*offs, offset_lines, c),
           "offsets must not decrease, but offset #" + std::to_string(c + 1) + " is " +
               std::to_string(ends[c]) + " after " + std::to_string(previous));
    }
    previous = ends[c];
  }
  Values type_values;
  std::vector<int64_t> type_lines;
  if (types->format == Format::kAscii) {
    if (!IsIntegral(types->type.scalar)) Decode(*types, true);
    DecodeAscii(*types, true, &type_values, &type_lines);
  } else {
    type_values = Decode(*types, true);
  }
  Values connectivity;
  std::vector<int64_t> conn_lines;
  if (conn->format == Format::kAscii) {
    if (!IsIntegral(conn->type.scalar)) Decode(*conn, true);
    DecodeAscii(*conn, true, &connectivity, &conn_lines);
  } else {
    connectivity = Decode(*conn, true);
  }
  const std::vector<int64_t>& ids = connectivity.ints;
  for (size_t c = 0; c < static_cast<size_t>(num_cells); ++c) {
    const int64_t start = c == 0 ? 0 : ends[c - 1];
    const int64_t count = ends[c] - start;
    const int64_t type = type_values.ints[c];
    const SourceLocation where = count > 0
                                     ? ValueLocation(*conn, conn_lines, static_cast<size_t>(start))
                                     : ValueLocation(*types, type_lines, c);
    const VtkCellTypeInfo info = VtkCellType(type);
    if (info.name == nullptr) {
      Fail(MeshErrorKind::kSyntax, ValueLocation(*types, type_lines, c),
           "cell #" + std::to_string(c + 1) + " has unknown VTK cell type " + std::to_string(type));
    }
    if (info.num_points >= 0 && count != info.num_points) {
      Fail(MeshErrorKind::kCount, where,
           "cell #" + std::to_string(c + 1) + " is a " + info.name + " but has " +
               std::to_string(count) + " points instead of " + std::to_string(info.num_points));
    }
    if (type != kVtkTriangle && type != kVtkTetra) {
      builder->Skip(info.name);
      continue;
    }
    int64_t v[4] = {0, 0, 0, 0};
    for (int64_t k = 0; k < count; ++k) {
      const int64_t id = ids[static_cast<size_t>(start + k)];
      if (id < 0 || id >= num_points) {
        Fail(MeshErrorKind::kIndex, where,
             "cell #" + std::to_string(c + 1) + " of piece #" + std::to_string(piece_index + 1) +
                 " refers to point " + std::to_string(id) + " but the piece has " +
                 std::to_string(num_points) + " points");
      }
      v[k] = id + base;
    }
    if (type == kVtkTriangle) {
      builder->AddTriangle(v[0], v[1], v[2], where);
    } else {
      builder->AddTetrahedron(v[0], v[1], v[2], v[3], where);
    }
  }
}

MeshData VtuReader::Read(const ReadOptions& options) {
  for (size_t i = bytes_.find('\n'); i != std::string_view::npos; i = bytes_.find('\n', i + 1)) {
    newlines_.push_back(i);
  }
  SplitAppendedData();
  pugi::xml_document doc;
  // No end-of-line normalisation, so that offsets in the parsed text are offsets in the file.
  const unsigned flags = pugi::parse_cdata | pugi::parse_escapes | pugi::parse_wconv_attribute;
  const pugi::xml_parse_result parsed =
      doc.load_buffer(xml_.data(), xml_.size(), flags, pugi::encoding_utf8);
  if (!parsed) {
    const size_t at = FileOffset(static_cast<size_t>(std::max<ptrdiff_t>(0, parsed.offset)));
    std::string fault = std::string("malformed XML: ") + parsed.description();
    if (parsed.status == pugi::status_end_element_mismatch ||
        parsed.status == pugi::status_bad_end_element || at >= bytes_.size()) {
      fault += " (truncated file?)";
    }
    Fail(MeshErrorKind::kSyntax, SourceLocation::Line(LineAt(at)), fault);
  }
  const pugi::xml_node root = doc.document_element();
  if (!root || std::strcmp(root.name(), "VTKFile") != 0) {
    Fail(MeshErrorKind::kSyntax, root ? NodeLine(root) : SourceLocation::Line(1),
         std::string("not a VTK XML file: the root element is <") + root.name() +
             ">, not <VTKFile>");
  }
  ParseHeaderAttributes(root);
  CheckChildren(root, {"UnstructuredGrid", "AppendedData"});
  if (have_appended_) {
    const pugi::xml_node appended = root.child("AppendedData");
    const std::string_view encoding = appended.attribute("encoding").as_string("");
    if (encoding == "base64") {
      appended_base64_ = true;
    } else if (encoding != "raw") {
      Fail(MeshErrorKind::kSyntax, appended ? NodeLine(appended) : NodeLine(root),
           "<AppendedData> must have encoding=\"raw\" or \"base64\", not " + QuoteToken(encoding));
    }
  }
  pugi::xml_node grid;
  for (const pugi::xml_node& node : root.children("UnstructuredGrid")) {
    if (grid) Fail(MeshErrorKind::kSyntax, NodeLine(node), "a second <UnstructuredGrid>");
    grid = node;
  }
  if (!grid) Fail(MeshErrorKind::kSyntax, NodeLine(root), "<VTKFile> has no <UnstructuredGrid>");
  CheckChildren(grid, {"Piece", "FieldData"});
  for (const pugi::xml_node& field : grid.children("FieldData")) {
    CheckAttributeArrays(field, -1, "FieldData");
  }
  std::string format = "VTK XML UnstructuredGrid";
  MeshBuilder builder(file_name_, format);
  int pieces = 0;
  for (const pugi::xml_node& piece : grid.children("Piece")) {
    ReadPiece(piece, pieces++, &builder);
  }
  if (pieces == 0) {
    Fail(MeshErrorKind::kSyntax, NodeLine(grid), "<UnstructuredGrid> has no <Piece>");
  }
  return builder.Finish(options);
}

// Appends one array's binary block: a UInt32/UInt64 byte count then the values.
template <typename T, typename Get>
void AppendBlock(std::string* out, size_t n, Get get, Endian endian, bool header64) {
  const uint64_t bytes = n * sizeof(T);
  if (header64) {
    AppendBinary(out, bytes, endian);
  } else {
    AppendBinary(out, static_cast<uint32_t>(bytes), endian);
  }
  for (size_t i = 0; i < n; ++i) AppendBinary(out, static_cast<T>(get(i)), endian);
}

}  // namespace

MeshData ReadVtu(std::string_view bytes, const std::string& file_name, const ReadOptions& options) {
  VtuReader reader(bytes, file_name);
  return reader.Read(options);
}

std::string WriteVtu(const MeshData& mesh, const VtuWriteOptions& options) {
  const Endian endian = options.big_endian ? Endian::kBig : Endian::kLittle;
  const size_t n = static_cast<size_t>(mesh.vertices.cols());
  const size_t ntri = static_cast<size_t>(mesh.triangles.cols());
  const size_t ntet = static_cast<size_t>(mesh.tetrahedra.cols());
  const size_t ncells = ntet + ntri;
  const size_t nconn = 4 * ntet + 3 * ntri;
  // A UInt32 header cannot count more than 4 GiB; larger arrays need UInt64 headers.
  const bool header64 = std::max(3 * n, nconn) * 8 > UINT32_MAX;
  const auto point = [&](size_t i) {
    return mesh.vertices(static_cast<Eigen::Index>(i % 3), static_cast<Eigen::Index>(i / 3));
  };
  const auto connectivity = [&](size_t i) -> int64_t {
    if (i < 4 * ntet) {
      return mesh.tetrahedra(static_cast<Eigen::Index>(i % 4), static_cast<Eigen::Index>(i / 4));
    }
    const size_t k = i - 4 * ntet;
    return mesh.triangles(static_cast<Eigen::Index>(k % 3), static_cast<Eigen::Index>(k / 3));
  };
  const auto offset = [&](size_t c) -> int64_t {
    return static_cast<int64_t>(c < ntet ? 4 * (c + 1) : 4 * ntet + 3 * (c + 1 - ntet));
  };
  const auto type = [&](size_t c) -> int64_t { return c < ntet ? kVtkTetra : kVtkTriangle; };

  std::string out = "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" ";
  out += options.big_endian ? "byte_order=\"BigEndian\"" : "byte_order=\"LittleEndian\"";
  out += header64 ? " header_type=\"UInt64\">\n" : " header_type=\"UInt32\">\n";
  out += "  <UnstructuredGrid>\n    <Piece NumberOfPoints=\"" + std::to_string(n) +
         "\" NumberOfCells=\"" + std::to_string(ncells) + "\">\n";
  std::string appended;
  const char* format = options.encoding == VtuEncoding::kAscii    ? "ascii"
                       : options.encoding == VtuEncoding::kBase64 ? "binary"
                                                                  : "appended";
  // Writes one DataArray; values are produced by get(i), i < count.
  const auto write_array = [&](const char* type_name, const char* name, int components,
                               size_t count, auto get, auto binary_tag) {
    using T = decltype(binary_tag);
    out += std::string("        <DataArray type=\"") + type_name + "\" Name=\"" + name + "\"";
    if (components != 1) out += " NumberOfComponents=\"" + std::to_string(components) + "\"";
    out += std::string(" format=\"") + format + "\"";
    if (options.encoding == VtuEncoding::kAppendedRaw) {
      out += " offset=\"" + std::to_string(appended.size()) + "\"/>\n";
      AppendBlock<T>(&appended, count, get, endian, header64);
      return;
    }
    out += ">\n          ";
    if (options.encoding == VtuEncoding::kBase64) {
      std::string block;
      AppendBlock<T>(&block, count, get, endian, header64);
      AppendBase64(&out, block);
      out += '\n';
    } else {
      for (size_t i = 0; i < count; ++i) {
        if constexpr (std::is_floating_point_v<T>) {
          AppendDouble(&out, static_cast<double>(get(i)));
        } else {
          out += std::to_string(static_cast<int64_t>(get(i)));
        }
        const bool end_of_row =
            (i + 1) % static_cast<size_t>(components == 1 ? 6 : components) == 0;
        out += end_of_row || i + 1 == count ? "\n          " : " ";
      }
      if (count > 0) out.resize(out.size() - 10);
      if (count == 0) out += '\n';
    }
    out += "        </DataArray>\n";
  };
  if (!mesh.point_data.empty()) {
    out += "      <PointData>\n";
    for (const PointArray& array : mesh.point_data) {
      for (const char c : array.name) {  // the name goes into an XML attribute as is
        if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-' || c == ' ')) {
          throw std::invalid_argument("WriteVtu: point data name \"" + array.name +
                                      "\" may hold only letters, digits, ' ', '_' and '-'");
        }
      }
      if (array.name.empty() || array.components <= 0 ||
          array.values.size() != static_cast<size_t>(array.components) * n) {
        throw std::invalid_argument("WriteVtu: point data \"" + array.name + "\" has " +
                                    std::to_string(array.values.size()) + " values, not " +
                                    std::to_string(array.components) + " per node for " +
                                    std::to_string(n) + " nodes");
      }
      write_array(
          "Float64", array.name.c_str(), array.components, array.values.size(),
          [&array](size_t i) { return array.values[i]; }, double{});
    }
    out += "      </PointData>\n";
  }
  out += "      <Points>\n";
  write_array("Float64", "Points", 3, 3 * n, point, double{});
  out += "      </Points>\n      <Cells>\n";
  write_array("Int64", "connectivity", 1, nconn, connectivity, int64_t{});
  write_array("Int64", "offsets", 1, ncells, offset, int64_t{});
  write_array("UInt8", "types", 1, ncells, type, uint8_t{});
  out += "      </Cells>\n    </Piece>\n  </UnstructuredGrid>\n";
  if (options.encoding == VtuEncoding::kAppendedRaw) {
    out += "  <AppendedData encoding=\"raw\">\n   _";
    out += appended;
    out += "\n  </AppendedData>\n";
  }
  out += "</VTKFile>\n";
  return out;
}

}  // namespace somasim::mesh_io
