// The Gmsh reader's version 4.1 (ASCII and binary): $Entities, $Nodes and $Elements in blocks.
#include <array>
#include <cstdint>
#include <limits>
#include <string>
#include <string_view>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/gmsh_element_types.h"
#include "common/mesh_io/gmsh_internal.h"
#include "common/mesh_io/gmsh_reader.h"
#include "common/mesh_io/mesh_error.h"
#include "common/mesh_io/text_reader.h"

namespace somasim::mesh_io::gmsh_internal {

void GmshReader::ReadEntities41Ascii() {
  const std::string section = "$Entities";
  std::array<int64_t, 4> counts{};
  for (int64_t& c : counts) {
    c = SectionInt(section, "a number of entities");
    in_.CheckCount(c, 8, "entities");
  }
  for (size_t dim = 0; dim < 4; ++dim) {
    for (int64_t i = 0; i < counts[dim]; ++i) {
      SectionInt(section, "an entity tag");
      const int bounds = dim == 0 ? 3 : 6;  // a point, or a bounding box
      for (int k = 0; k < bounds; ++k) SectionDouble(section, "an entity coordinate");
      const int lists = dim == 0 ? 1 : 2;  // physical tags, then bounding entities
      for (int l = 0; l < lists; ++l) {
        const int64_t m = SectionInt(section, "a number of tags");
        in_.CheckCount(m, 2, "entity tags");
        for (int64_t k = 0; k < m; ++k) SectionInt(section, "an entity tag");
      }
    }
  }
  ExpectEndAfter("$EndEntities", section, counts[0] + counts[1] + counts[2] + counts[3], "entity",
                 "entities");
}

void GmshReader::ReadNodes41Ascii() {
  const std::string section = "$Nodes";
  const int64_t num_blocks = SectionInt(section, "the number of entity blocks");
  const int64_t n = SectionInt(section, "the number of nodes");
  SectionInt(section, "the smallest node tag");
  SectionInt(section, "the largest node tag");
  in_.EndOfLine("the $Nodes header");
  in_.CheckCount(num_blocks, 8, "node blocks");  // "0 1 0 0\n"
  in_.CheckCount(n, 8, "nodes");                 // "1\n0 0 0\n"
  builder_.Reserve(n, 0, 0);
  nodes_.Reserve(n);
  const std::string said = Plural(n, "node", "nodes");
  int64_t total = 0;
  for (int64_t b = 0; b < num_blocks; ++b) {
    const int64_t dim = SectionInt(section, "an entity dimension");
    const int64_t block_line = in_.token_location().line;
    SectionInt(section, "an entity tag");
    const int64_t parametric = SectionInt(section, "the parametric flag");
    const int64_t in_block = SectionInt(section, "the number of nodes in a block");
    in_.EndOfLine("a node block header");
    CheckBlockHeader(dim, parametric, block_line);
    if (in_block < 0 || in_block > n - total) {
      FailAt(MeshErrorKind::kCount, block_line,
             "node block " + std::to_string(b + 1) + " says " + std::to_string(in_block) +
                 " nodes, more than the " + std::to_string(n - total) + " left of the " + said +
                 " that $Nodes announces");
    }
    block_tags_.resize(static_cast<size_t>(in_block));
    for (int64_t& tag : block_tags_) {
      tag = SectionInt(section, "a node tag");
      AddNodeId(tag, in_.token_location().line);
    }
    if (in_block > 0) in_.EndOfLine("the node tags");
    const size_t values = 3 + static_cast<size_t>(parametric != 0 ? dim : 0);
    for (int64_t i = 0; i < in_block; ++i) {
      DataLine(section, said, total + i);
      if (tokens_.size() != values) {
        in_.Fail(MeshErrorKind::kSyntax, "a node of block " + std::to_string(b + 1) +
                                             " should have " + std::to_string(values) +
                                             " coordinates on its line (x y z" +
                                             (values > 3 ? " and parametric ones" : "") +
                                             "), found " + std::to_string(tokens_.size()));
      }
      const double x = TokenDouble(tokens_[0], "x");
      const double y = TokenDouble(tokens_[1], "y");
      const double z = TokenDouble(tokens_[2], "z");
      for (size_t k = 3; k < values; ++k) TokenDouble(tokens_[k], "a parametric coordinate");
      builder_.AddNode(x, y, z, in_.token_location(), block_tags_[static_cast<size_t>(i)]);
    }
    total += in_block;
  }
  if (total != n) {
    in_.FailAt(MeshErrorKind::kCount, SourceLocation::Line(in_.line()),
               "$Nodes says " + said + " but its " + Plural(num_blocks, "block", "blocks") +
                   " hold " + std::to_string(total));
  }
  ExpectEndAfter("$EndNodes", section, num_blocks, "entity block", "entity blocks");
}

void GmshReader::CheckBlockHeader(int64_t dim, int64_t parametric, int64_t where) const {
  if (dim < 0 || dim > 3) {
    FailAt(MeshErrorKind::kSyntax, where,
           "entity dimension " + std::to_string(dim) + " should be 0, 1, 2 or 3");
  }
  if (parametric != 0 && parametric != 1) {
    FailAt(MeshErrorKind::kSyntax, where,
           "the parametric flag should be 0 or 1, found " + std::to_string(parametric));
  }
}

void GmshReader::ReadElements41Ascii() {
  const std::string section = "$Elements";
  const int64_t num_blocks = SectionInt(section, "the number of entity blocks");
  const int64_t n = SectionInt(section, "the number of elements");
  SectionInt(section, "the smallest element tag");
  SectionInt(section, "the largest element tag");
  in_.EndOfLine("the $Elements header");
  in_.CheckCount(num_blocks, 8, "element blocks");  // "0 1 15 0\n"
  in_.CheckCount(n, 4, "elements");                 // "1 1\n"
  elements_.Reserve(n);
  const std::string said = Plural(n, "element", "elements");
  int64_t total = 0;
  for (int64_t b = 0; b < num_blocks; ++b) {
    const int64_t dim = SectionInt(section, "an entity dimension");
    const int64_t block_line = in_.token_location().line;
    SectionInt(section, "an entity tag");
    const int64_t type_number = SectionInt(section, "an element type");
    const int64_t in_block = SectionInt(section, "the number of elements in a block");
    in_.EndOfLine("an element block header");
    CheckBlockHeader(dim, 0, block_line);
    const ElementTypeInfo& type = ElementType(type_number, block_line);
    if (in_block < 0 || in_block > n - total) {
      FailAt(MeshErrorKind::kCount, block_line,
             "element block " + std::to_string(b + 1) + " says " + std::to_string(in_block) +
                 " elements, more than the " + std::to_string(n - total) + " left of the " + said +
                 " that $Elements announces");
    }
    for (int64_t i = 0; i < in_block; ++i) {
      DataLine(section, said, total + i);
      const int64_t line = in_.token_location().line;
      const int64_t id = TokenInt(tokens_[0], "the element tag");
      const size_t listed = tokens_.size() - 1;
      if (listed != static_cast<size_t>(type.nodes)) {
        in_.Fail(MeshErrorKind::kCount, "element " + std::to_string(id) + " (" + type.name +
                                            ") should list " + std::to_string(type.nodes) +
                                            " node tags, its line lists " + std::to_string(listed));
      }
      ParseNodeIds(1, listed);
      AddElement(id, type, line);
    }
    total += in_block;
  }
  if (total != n) {
    in_.FailAt(MeshErrorKind::kCount, SourceLocation::Line(in_.line()),
               "$Elements says " + said + " but its " + Plural(num_blocks, "block", "blocks") +
                   " hold " + std::to_string(total));
  }
  ExpectEndAfter("$EndElements", section, num_blocks, "entity block", "entity blocks");
}

// A size_t count; values beyond int64 are absurd and left for CheckCount to refuse.
int64_t GmshReader::ReadSize(ByteReader& br, std::string_view what) const {
  const uint64_t v = br.Read<uint64_t>(endian_, what);
  return v > static_cast<uint64_t>(std::numeric_limits<int64_t>::max())
             ? std::numeric_limits<int64_t>::max()
             : static_cast<int64_t>(v);
}

// A size_t node or element tag.
int64_t GmshReader::ReadTag(ByteReader& br, std::string_view what) const {
  const uint64_t v = br.Read<uint64_t>(endian_, what);
  if (v > static_cast<uint64_t>(std::numeric_limits<int64_t>::max())) {
    br.Fail(MeshErrorKind::kIndex,
            std::string(what) + " " + std::to_string(v) + " is larger than 2^63-1");
  }
  return static_cast<int64_t>(v);
}

void GmshReader::ReadEntities41Binary() {
  ByteReader br = DataReader();
  std::array<int64_t, 4> counts{};
  for (int64_t& c : counts) c = ReadSize(br, "a number of entities");
  // Smallest entities: a point is int + 3 doubles + size_t; others int + 6 doubles + 2 size_t.
  br.CheckCount(counts[0], 4 + 3 * 8 + 8, "points");
  for (size_t dim = 1; dim < 4; ++dim) br.CheckCount(counts[dim], 4 + 6 * 8 + 2 * 8, "entities");
  for (size_t dim = 0; dim < 4; ++dim) {
    for (int64_t i = 0; i < counts[dim]; ++i) {
      br.Read<int32_t>(endian_, "an entity tag");
      const size_t bounds = dim == 0 ? 3 : 6;
      br.Bytes(bounds * 8, "an entity's coordinates");
      const int lists = dim == 0 ? 1 : 2;
      for (int l = 0; l < lists; ++l) {
        const int64_t m = ReadSize(br, "a number of tags");
        br.CheckCount(m, 4, "entity tags");
        br.Bytes(4 * static_cast<size_t>(m), "entity tags");
      }
    }
  }
  in_.Skip(br.offset());
  ExpectEndAfter("$EndEntities", "$Entities", counts[0] + counts[1] + counts[2] + counts[3],
                 "entity", "entities");
}

void GmshReader::ReadNodes41Binary() {
  ByteReader br = DataReader();
  const int64_t num_blocks = ReadSize(br, "the number of entity blocks");
  const int64_t n = ReadSize(br, "the number of nodes");
  ReadSize(br, "the smallest node tag");
  ReadSize(br, "the largest node tag");
  br.CheckCount(num_blocks, 3 * 4 + 8, "node blocks");
  br.CheckCount(n, 8 + 3 * 8, "nodes");
  builder_.Reserve(n, 0, 0);
  nodes_.Reserve(n);
  int64_t total = 0;
  for (int64_t b = 0; b < num_blocks; ++b) {
    const int64_t block_at = br.file_offset();
    const int32_t dim = br.Read<int32_t>(endian_, "an entity dimension");
    br.Read<int32_t>(endian_, "an entity tag");
    const int32_t parametric = br.Read<int32_t>(endian_, "the parametric flag");
    const int64_t in_block = ReadSize(br, "the number of nodes in a block");
    CheckBlockHeader(dim, parametric, block_at);
    if (in_block > n - total) {
      FailAt(MeshErrorKind::kCount, block_at,
             "node block " + std::to_string(b + 1) + " says " + std::to_string(in_block) +
                 " nodes, more than the " + std::to_string(n - total) + " left of the " +
                 std::to_string(n) + " that $Nodes announces");
    }
    const int64_t values = 3 + (parametric != 0 ? dim : 0);
    br.CheckCount(in_block, 8 + values * 8, "nodes");
    block_tags_.resize(static_cast<size_t>(in_block));
    for (int64_t& tag : block_tags_) {
      const int64_t where = br.file_offset();
      tag = ReadTag(br, "a node tag");
      AddNodeId(tag, where);
    }
    for (int64_t i = 0; i < in_block; ++i) {
      const int64_t where = br.file_offset();
      const double x = br.Read<double>(endian_, "a node coordinate");
      const double y = br.Read<double>(endian_, "a node coordinate");
      const double z = br.Read<double>(endian_, "a node coordinate");
      br.Bytes(static_cast<size_t>(values - 3) * 8, "parametric coordinates");
      builder_.AddNode(x, y, z, SourceLocation::Byte(where), block_tags_[static_cast<size_t>(i)]);
    }
    total += in_block;
  }
  if (total != n) {
    br.Fail(MeshErrorKind::kCount, "$Nodes says " + std::to_string(n) + " nodes but its " +
                                       Plural(num_blocks, "block", "blocks") + " hold " +
                                       std::to_string(total));
  }
  in_.Skip(br.offset());
  ExpectEndAfter("$EndNodes", "$Nodes", num_blocks, "entity block", "entity blocks");
}

void GmshReader::ReadElements41Binary() {
  ByteReader br = DataReader();
  const int64_t num_blocks = ReadSize(br, "the number of entity blocks");
  const int64_t n = ReadSize(br, "the number of elements");
  ReadSize(br, "the smallest element tag");
  ReadSize(br, "the largest element tag");
  br.CheckCount(num_blocks, 3 * 4 + 8, "element blocks");
  br.CheckCount(n, 2 * 8, "elements");
  elements_.Reserve(n);
  int64_t total = 0;
  for (int64_t b = 0; b < num_blocks; ++b) {
    const int64_t block_at = br.file_offset();
    const int32_t dim = br.Read<int32_t>(endian_, "an entity dimension");
    br.Read<int32_t>(endian_, "an entity tag");
    const int32_t type_number = br.Read<int32_t>(endian_, "an element type");
    const int64_t in_block = ReadSize(br, "the number of elements in a block");
    CheckBlockHeader(dim, 0, block_at);
    const ElementTypeInfo& type = ElementType(type_number, block_at);
    if (in_block > n - total) {
      FailAt(MeshErrorKind::kCount, block_at,
             "element block " + std::to_string(b + 1) + " says " + std::to_string(in_block) +
                 " elements, more than the " + std::to_string(n - total) + " left of the " +
                 std::to_string(n) + " that $Elements announces");
    }
    br.CheckCount(in_block, 8 * (1 + int64_t{type.nodes}), "elements");
    element_nodes_.resize(static_cast<size_t>(type.nodes));
    for (int64_t i = 0; i < in_block; ++i) {
      const int64_t where = br.file_offset();
      const int64_t id = ReadTag(br, "an element tag");
      for (int64_t& node : element_nodes_) node = ReadTag(br, "a node tag");
      AddElement(id, type, where);
    }
    total += in_block;
  }
  if (total != n) {
    br.Fail(MeshErrorKind::kCount, "$Elements says " + std::to_string(n) + " elements but its " +
                                       Plural(num_blocks, "block", "blocks") + " hold " +
                                       std::to_string(total));
  }
  in_.Skip(br.offset());
  ExpectEndAfter("$EndElements", "$Elements", num_blocks, "entity block", "entity blocks");
}

}  // namespace somasim::mesh_io::gmsh_internal
