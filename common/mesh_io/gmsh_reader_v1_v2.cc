// The Gmsh reader's versions 1 and 2 (ASCII and binary): $NOD/$ELM and $Nodes/$Elements.
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/gmsh_element_types.h"
#include "common/mesh_io/gmsh_internal.h"
#include "common/mesh_io/gmsh_reader.h"
#include "common/mesh_io/mesh_error.h"
#include "common/mesh_io/text_reader.h"

namespace somasim::mesh_io::gmsh_internal {

void GmshReader::ReadVersion1() {
  version_ = Version::kV1;
  format_ = "Gmsh 1";
  nodes_section_ = "$NOD";
  in_.EndOfLine("$NOD");
  ReadNodesAscii("$NOD", "$ENDNOD");
  const std::optional<std::string_view> elm = in_.TryToken();
  if (!elm) {
    in_.FailAt(MeshErrorKind::kSyntax, SourceLocation::Line(in_.line()),
               "missing $ELM section after $ENDNOD (truncated file?)");
  }
  if (*elm != "$ELM") {
    in_.Fail(MeshErrorKind::kSyntax,
             "expected $ELM after $ENDNOD (a version 1 file holds $NOD then $ELM), found " +
                 QuoteToken(*elm));
  }
  in_.EndOfLine("$ELM");
  ReadElements1();
  if (const std::optional<std::string_view> extra = in_.TryToken()) {
    in_.Fail(MeshErrorKind::kSyntax,
             "unexpected " + QuoteToken(*extra) +
                 " after $ENDELM (a version 1 file holds only $NOD and $ELM)");
  }
}

// "id x y z" lines (versions 1 and 2 ASCII).
void GmshReader::ReadNodesAscii(const std::string& section, const std::string& end) {
  const int64_t n = CountLine("the number of nodes");
  in_.CheckCount(n, 8, "nodes");  // "1 0 0 0\n"
  builder_.Reserve(n, 0, 0);
  nodes_.Reserve(n);
  const std::string said = Plural(n, "node", "nodes");
  for (int64_t i = 0; i < n; ++i) {
    DataLine(section, said, i);
    const int64_t line = in_.token_location().line;
    if (tokens_.size() != 4) {
      in_.Fail(MeshErrorKind::kSyntax,
               "a node line should hold 'id x y z', found " +
                   Plural(static_cast<int64_t>(tokens_.size()), "value", "values"));
    }
    const int64_t id = TokenInt(tokens_[0], "the node id");
    const double x = TokenDouble(tokens_[1], "x");
    const double y = TokenDouble(tokens_[2], "y");
    const double z = TokenDouble(tokens_[3], "z");
    AddNodeId(id, line);
    builder_.AddNode(x, y, z, SourceLocation::Line(line), id);
  }
  ExpectEndAfter(end, section, n, "node", "nodes");
}

// "id type reg-phys reg-elem num-nodes node-ids..." lines.
void GmshReader::ReadElements1() {
  const int64_t n = CountLine("the number of elements");
  in_.CheckCount(n, 12, "elements");  // "1 15 0 0 1 1\n"
  elements_.Reserve(n);
  const std::string said = Plural(n, "element", "elements");
  for (int64_t i = 0; i < n; ++i) {
    DataLine("$ELM", said, i);
    const int64_t line = in_.token_location().line;
    if (tokens_.size() < 5) {
      in_.Fail(MeshErrorKind::kSyntax,
               "an element line should hold 'id type reg-phys reg-elem number-of-nodes "
               "node-ids...', found " +
                   Plural(static_cast<int64_t>(tokens_.size()), "value", "values"));
    }
    const int64_t id = TokenInt(tokens_[0], "the element id");
    const int64_t type_number = TokenInt(tokens_[1], "the element type");
    TokenInt(tokens_[2], "the physical region");
    TokenInt(tokens_[3], "the elementary region");
    const int64_t said_nodes = TokenInt(tokens_[4], "the number of nodes");
    const ElementTypeInfo& type = ElementType(type_number, line);
    if (said_nodes != type.nodes) {
      in_.Fail(MeshErrorKind::kCount, "element " + std::to_string(id) + " says " +
                                          std::to_string(said_nodes) + " nodes but its type " +
                                          std::to_string(type.type) + " (" + type.name + ") has " +
                                          std::to_string(type.nodes));
    }
    const size_t listed = tokens_.size() - 5;
    if (listed != static_cast<size_t>(type.nodes)) {
      in_.Fail(MeshErrorKind::kCount, "element " + std::to_string(id) + " (" + type.name +
                                          ") should list " + std::to_string(type.nodes) +
                                          " node ids, its line lists " + std::to_string(listed));
    }
    ParseNodeIds(5, listed);
    AddElement(id, type, line);
  }
  ExpectEndAfter("$ENDELM", "$ELM", n, "element", "elements");
}

// "id type number-of-tags tags... node-ids..." lines.
void GmshReader::ReadElements2Ascii() {
  const int64_t n = CountLine("the number of elements");
  in_.CheckCount(n, 8, "elements");  // "1 15 0 1\n"
  elements_.Reserve(n);
  const std::string said = Plural(n, "element", "elements");
  for (int64_t i = 0; i < n; ++i) {
    DataLine("$Elements", said, i);
    const int64_t line = in_.token_location().line;
    if (tokens_.size() < 3) {
      in_.Fail(MeshErrorKind::kSyntax,
               "an element line should hold 'id type number-of-tags tags... node-ids...', "
               "found " +
                   Plural(static_cast<int64_t>(tokens_.size()), "value", "values"));
    }
    const int64_t id = TokenInt(tokens_[0], "the element id");
    const int64_t type_number = TokenInt(tokens_[1], "the element type");
    const int64_t num_tags = TokenInt(tokens_[2], "the number of tags");
    const ElementTypeInfo& type = ElementType(type_number, line);
    const int64_t after_count = static_cast<int64_t>(tokens_.size()) - 3;
    if (num_tags < 0 || num_tags > after_count) {
      in_.Fail(MeshErrorKind::kCount, "element " + std::to_string(id) + " says " +
                                          std::to_string(num_tags) + " tags but its line holds " +
                                          std::to_string(after_count) +
                                          " values after the tag count");
    }
    const int64_t listed = after_count - num_tags;
    if (listed != type.nodes) {
      in_.Fail(MeshErrorKind::kCount, "element " + std::to_string(id) + " (" + type.name +
                                          ") should list " + std::to_string(type.nodes) +
                                          " node ids after its " + Plural(num_tags, "tag", "tags") +
                                          ", its line lists " + std::to_string(listed));
    }
    for (int64_t k = 0; k < num_tags; ++k) {
      TokenInt(tokens_[static_cast<size_t>(3 + k)], "a tag");
    }
    ParseNodeIds(static_cast<size_t>(3 + num_tags), static_cast<size_t>(listed));
    AddElement(id, type, line);
  }
  ExpectEndAfter("$EndElements", "$Elements", n, "element", "elements");
}

void GmshReader::ReadNodes2Binary() {
  const int64_t n = CountLine("the number of nodes");
  ByteReader br = DataReader();
  br.CheckCount(n, 4 + 3 * 8, "binary nodes");
  builder_.Reserve(n, 0, 0);
  nodes_.Reserve(n);
  for (int64_t i = 0; i < n; ++i) {
    const int64_t where = br.file_offset();
    const int32_t id = br.Read<int32_t>(endian_, "a node id");
    const double x = br.Read<double>(endian_, "a node coordinate");
    const double y = br.Read<double>(endian_, "a node coordinate");
    const double z = br.Read<double>(endian_, "a node coordinate");
    AddNodeId(id, where);
    builder_.AddNode(x, y, z, SourceLocation::Byte(where), id);
  }
  in_.Skip(br.offset());
  ExpectEndAfter("$EndNodes", "$Nodes", n, "node", "nodes");
}

// Blocks of (type, number of elements, number of tags), each followed by its elements as
// id, tags..., node ids..., all int32.
void GmshReader::ReadElements2Binary() {
  const int64_t n = CountLine("the number of elements");
  ByteReader br = DataReader();
  br.CheckCount(n, 2 * 4, "binary elements");
  elements_.Reserve(n);
  int64_t read = 0;
  while (read < n) {
    const int64_t block_at = br.file_offset();
    const int32_t type_number = br.Read<int32_t>(endian_, "an element block's type");
    const int32_t count = br.Read<int32_t>(endian_, "an element block's element count");
    const int32_t num_tags = br.Read<int32_t>(endian_, "an element block's tag count");
    const ElementTypeInfo& type = ElementType(type_number, block_at);
    if (count < 0 || count > n - read) {
      FailAt(MeshErrorKind::kCount, block_at,
             "an element block says " + std::to_string(count) + " elements but only " +
                 std::to_string(n - read) + " of the " + std::to_string(n) +
                 " that $Elements announces remain");
    }
    if (num_tags < 0) {
      FailAt(MeshErrorKind::kCount, block_at,
             "an element block says " + std::to_string(num_tags) + " tags per element");
    }
    const int64_t ints_each = 1 + int64_t{num_tags} + type.nodes;
    br.CheckCount(count, 4 * ints_each, "binary elements");
    element_nodes_.resize(static_cast<size_t>(type.nodes));
    for (int32_t e = 0; e < count; ++e) {
      const int64_t where = br.file_offset();
      const int32_t id = br.Read<int32_t>(endian_, "an element id");
      br.Bytes(4 * static_cast<size_t>(num_tags), "element tags");
      for (int64_t& node : element_nodes_) node = br.Read<int32_t>(endian_, "a node id");
      AddElement(id, type, where);
    }
    read += count;
  }
  in_.Skip(br.offset());
  ExpectEndAfter("$EndElements", "$Elements", n, "element", "elements");
}

}  // namespace somasim::mesh_io::gmsh_internal
