// The VTU reader's document structure: raw appended data cut out before parsing, the XML
// parsed, <VTKFile>'s attributes (byte order, header type, compressor), <AppendedData>'s
// encoding, <UnstructuredGrid> and its pieces.
#include "common/mesh_io/vtu_reader.h"

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <initializer_list>
#include <pugixml.hpp>
#include <string>
#include <string_view>

#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/text_reader.h"
#include "common/mesh_io/vtu_io.h"

namespace somasim::mesh_io {
namespace vtu_internal {

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

}  // namespace vtu_internal

MeshData ReadVtu(std::string_view bytes, const std::string& file_name, const ReadOptions& options) {
  vtu_internal::VtuReader reader(bytes, file_name);
  return reader.Read(options);
}

}  // namespace somasim::mesh_io
