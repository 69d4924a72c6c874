// The Gmsh reader's file and section structure, and what all versions share.
#include "common/mesh_io/gmsh_reader.h"

#include <algorithm>
#include <array>
#include <cstdint>
#include <iterator>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/gmsh_io.h"

namespace somasim::mesh_io {
namespace gmsh_internal {
namespace {

// Sections a mesh file may hold that carry no mesh: skipped up to their end marker.
constexpr std::string_view kSkippedSections[] = {
    "$PhysicalNames",
    "$PartitionedEntities",
    "$Periodic",
    "$GhostElements",
    "$Parametrizations",
    "$NodeData",
    "$ElementData",
    "$ElementNodeData",
    "$InterpolationScheme",
    "$Comments",
    "$Entities",
};

bool IsSkippedSection(std::string_view name) {
  return std::find(std::begin(kSkippedSections), std::end(kSkippedSections), name) !=
         std::end(kSkippedSections);
}

std::string EndMarker(std::string_view section) { return "$End" + std::string(section.substr(1)); }

}  // namespace

MeshData GmshReader::Read(const ReadOptions& options) {
  const std::optional<std::string_view> first = in_.TryToken();
  if (!first) in_.Fail(MeshErrorKind::kSyntax, "empty file: not a Gmsh mesh");
  if (*first == "$MeshFormat") {
    ReadMeshFormat();
    ReadSections();
  } else if (*first == "$NOD") {
    ReadVersion1();
  } else {
    in_.Fail(MeshErrorKind::kSyntax,
             "not a Gmsh .msh file: it should start with $MeshFormat (versions 2 and 4) or "
             "$NOD (version 1), found " +
                 QuoteToken(*first));
  }
  FlushSkipped();
  MeshData out = builder_.Finish(options);
  out.format = format_;
  return out;
}

void GmshReader::ReadMeshFormat() {
  in_.EndOfLine("$MeshFormat");
  const std::string_view version = in_.Token("the format version");
  double number = 0.0;
  if (!ParseDouble(version, &number)) {
    in_.Fail(MeshErrorKind::kSyntax,
             "$MeshFormat: the version should be a number such as 4.1 "
             "or 2.2, found " +
                 QuoteToken(version));
  }
  if (number == 4.1) {
    version_ = Version::kV41;
    version_name_ = "4.1";
  } else if (number == 2.2 || number == 2.1 || number == 2.0) {
    // 2.0 and 2.1 differ from 2.2 only in optional sections ($PhysicalNames).
    version_ = Version::kV2;
    version_name_ = number == 2.2 ? "2.2" : number == 2.1 ? "2.1" : "2.0";
  } else if (number == 4.0) {
    in_.Fail(MeshErrorKind::kUnsupported,
             "Gmsh format version 4.0 is not supported (its layout differs from 4.1); save the "
             "mesh again from Gmsh 4.1 or later, as version 4.1 or 2.2");
  } else if (number >= 3.0 && number < 4.0) {
    in_.Fail(MeshErrorKind::kUnsupported,
             "Gmsh format version " + std::string(version) +
                 " is not supported (3.x was never a released MSH version); save the mesh as "
                 "version 4.1 or 2.2");
  } else {
    in_.Fail(MeshErrorKind::kUnsupported, "Gmsh format version " + QuoteToken(version) +
                                              " is not supported (somasim reads versions 1, "
                                              "2.0-2.2 and 4.1)");
  }
  const int64_t file_type = in_.Int("the file type");
  if (file_type != 0 && file_type != 1) {
    in_.Fail(MeshErrorKind::kSyntax,
             "$MeshFormat: the file type should be 0 (ASCII) or 1 "
             "(binary), found " +
                 std::to_string(file_type));
  }
  const int64_t data_size = in_.Int("the data size");
  binary_ = file_type == 1;
  if (binary_ && data_size != 8) {
    in_.Fail(MeshErrorKind::kUnsupported, "$MeshFormat: binary data size " +
                                              std::to_string(data_size) +
                                              " is not supported (only 8-byte size_t and double)");
  }
  if (!binary_ && data_size <= 0) {
    in_.Fail(MeshErrorKind::kSyntax,
             "$MeshFormat: the data size should be positive, found " + std::to_string(data_size));
  }
  in_.EndOfLine("the $MeshFormat line");
  if (binary_) {
    // The integer 1, written in the writer's byte order, tells the byte order.
    ByteReader br(bytes_.substr(in_.offset()), file_name_, static_cast<int64_t>(in_.offset()));
    const uint32_t one = br.Read<uint32_t>(Endian::kLittle, "the binary byte-order mark");
    if (one == 1) {
      endian_ = Endian::kLittle;
    } else if (one == 0x01000000u) {
      endian_ = Endian::kBig;
    } else {
      in_.FailAt(MeshErrorKind::kSyntax, SourceLocation::Byte(static_cast<int64_t>(in_.offset())),
                 "$MeshFormat: the binary byte-order mark should be the integer 1, found " +
                     std::to_string(one));
    }
    in_.Skip(br.offset());
  }
  ExpectEndMarker("$EndMeshFormat", "$MeshFormat");
  format_ = "Gmsh " + version_name_ + (binary_ ? " binary" : " ASCII");
}

void GmshReader::ReadSections() {
  bool seen_nodes = false, seen_elements = false, seen_entities = false;
  while (const std::optional<std::string_view> token = in_.TryToken()) {
    const std::string_view name = *token;
    if (name.empty() || name.front() != '$') {
      in_.Fail(MeshErrorKind::kSyntax, "unexpected " + QuoteToken(name) +
                                           " outside any section (sections start with $Name "
                                           "and end with $EndName)");
    }
    const std::string section(name);
    if (section == "$Nodes") {
      if (seen_nodes) in_.Fail(MeshErrorKind::kSyntax, "a second $Nodes section");
      seen_nodes = true;
      in_.EndOfLine("$Nodes");
      if (version_ == Version::kV41) {
        binary_ ? ReadNodes41Binary() : ReadNodes41Ascii();
      } else {
        binary_ ? ReadNodes2Binary() : ReadNodesAscii("$Nodes", "$EndNodes");
      }
    } else if (section == "$Elements") {
      if (seen_elements) in_.Fail(MeshErrorKind::kSyntax, "a second $Elements section");
      if (!seen_nodes) {
        in_.Fail(MeshErrorKind::kSyntax,
                 "$Elements comes before $Nodes (elements refer to "
                 "nodes, which must be defined first)");
      }
      seen_elements = true;
      in_.EndOfLine("$Elements");
      if (version_ == Version::kV41) {
        binary_ ? ReadElements41Binary() : ReadElements41Ascii();
      } else {
        binary_ ? ReadElements2Binary() : ReadElements2Ascii();
      }
    } else if (section == "$Entities" && version_ == Version::kV41) {
      if (seen_entities) in_.Fail(MeshErrorKind::kSyntax, "a second $Entities section");
      if (seen_nodes) in_.Fail(MeshErrorKind::kSyntax, "$Entities comes after $Nodes");
      seen_entities = true;
      in_.EndOfLine("$Entities");
      binary_ ? ReadEntities41Binary() : ReadEntities41Ascii();
    } else if (IsSkippedSection(section)) {
      SkipSection(section);
    } else if (section == "$MeshFormat") {
      in_.Fail(MeshErrorKind::kSyntax, "a second $MeshFormat section");
    } else if (section == "$ParametricNodes") {
      in_.Fail(MeshErrorKind::kUnsupported,
               "$ParametricNodes (Gmsh 2 nodes with parametric coordinates) is not supported; "
               "save the mesh without parametric coordinates");
    } else if (section.rfind("$End", 0) == 0) {
      in_.Fail(MeshErrorKind::kSyntax,
               "unexpected " + QuoteToken(section) + " with no open section");
    } else {
      in_.Fail(MeshErrorKind::kSyntax, "unknown section " + QuoteToken(section));
    }
  }
  if (!seen_nodes) {
    in_.FailAt(MeshErrorKind::kSyntax, SourceLocation::Line(in_.line()),
               "the file has no $Nodes section");
  }
  if (!seen_elements) {
    in_.FailAt(MeshErrorKind::kSyntax, SourceLocation::Line(in_.line()),
               "the file has no $Elements section");
  }
}

// Skips a section that holds no mesh, up to its end marker. The marker is searched as a
// whole token so that binary or free-text content cannot end the section by accident except
// by containing that exact token.
void GmshReader::SkipSection(const std::string& section) {
  const std::string end = EndMarker(section);
  size_t pos = in_.offset();
  while (true) {
    pos = bytes_.find(end, pos);
    if (pos == std::string_view::npos) {
      in_.Fail(MeshErrorKind::kSyntax,
               "section " + section + " has no " + end + " (truncated file?)");
    }
    const size_t after = pos + end.size();
    const bool starts_token = pos == 0 || IsSpace(bytes_[pos - 1]);
    const bool ends_token = after == bytes_.size() || IsSpace(bytes_[after]);
    if (starts_token && ends_token) break;
    pos = after;
  }
  in_.Skip(pos - in_.offset());
  ExpectEndMarker(end, section);
}

// The end marker of a section whose content was fully read.
void GmshReader::ExpectEndMarker(const std::string& end, const std::string& section) {
  const std::optional<std::string_view> token = in_.TryToken();
  if (!token) {
    in_.FailAt(MeshErrorKind::kSyntax, SourceLocation::Line(in_.line()),
               "missing " + end + " to close " + section + " (truncated file?)");
  }
  if (*token != end) {
    in_.Fail(MeshErrorKind::kSyntax,
             "expected " + end + " to close " + section + ", found " + QuoteToken(*token));
  }
  in_.EndOfLine(end);
}

// The end marker after `count` items of a section, telling "more data than announced" apart
// from a missing marker.
void GmshReader::ExpectEndAfter(const std::string& end, const std::string& section, int64_t count,
                                const char* one, const char* many) {
  const std::optional<std::string_view> token = in_.TryToken();
  if (!token) {
    in_.FailAt(MeshErrorKind::kSyntax, SourceLocation::Line(in_.line()),
               "missing " + end + " to close " + section + " (truncated file?)");
  }
  if (*token == end) {
    in_.EndOfLine(end);
    return;
  }
  if (binary_) {
    in_.Fail(MeshErrorKind::kSyntax, "found " + QuoteToken(*token) + " where " + end +
                                         " should follow the binary data of " + section + " (" +
                                         Plural(count, one, many) +
                                         "): wrong count or corrupt binary data");
  }
  if (!token->empty() && token->front() == '$') {
    in_.Fail(MeshErrorKind::kSyntax,
             "expected " + end + " to close " + section + ", found " + QuoteToken(*token));
  }
  in_.Fail(MeshErrorKind::kCount,
           section + " says " + Plural(count, one, many) + " but more data follows before " + end);
}

// Next non-blank line of a section's data, split into tokens_. Fails at the end of the file
// and when the section's end (a $ marker) comes first.
void GmshReader::DataLine(const std::string& section, const std::string& items_said, int64_t read) {
  while (true) {
    const std::optional<std::string_view> line = in_.TryLine();
    if (!line) {
      in_.FailAt(MeshErrorKind::kSyntax, SourceLocation::Line(in_.line()),
                 "unexpected end of file in " + section + " after " + std::to_string(read) +
                     " of " + items_said + " (truncated file?)");
    }
    tokens_.clear();
    SplitTokens(*line, &tokens_);
    if (tokens_.empty()) continue;
    if (tokens_[0].front() == '$') {
      in_.Fail(MeshErrorKind::kCount, section + " says " + items_said +
                                          " but the section ends after " + std::to_string(read));
    }
    return;
  }
}

// Next token of a section read token by token; a $ marker there means a count was too large.
std::string_view GmshReader::SectionToken(const std::string& section, const char* what) {
  const std::string_view token = in_.Token(what);
  if (token.front() == '$') {
    in_.Fail(MeshErrorKind::kCount, section + " ends early: expected " + std::string(what) +
                                        ", found " + QuoteToken(token) +
                                        " (a count in the section exceeds its data)");
  }
  return token;
}

int64_t GmshReader::SectionInt(const std::string& section, const char* what) {
  return TokenInt(SectionToken(section, what), what);
}

double GmshReader::SectionDouble(const std::string& section, const char* what) {
  return TokenDouble(SectionToken(section, what), what);
}

int64_t GmshReader::TokenInt(std::string_view token, std::string_view what) const {
  return in_.IntOf(token, what);
}

double GmshReader::TokenDouble(std::string_view token, std::string_view what) const {
  return in_.DoubleOf(token, what);
}

// A count on its own line (versions 1 and 2).
int64_t GmshReader::CountLine(const char* what) {
  const int64_t count = in_.Int(what);
  in_.EndOfLine(what);
  return count;
}

void GmshReader::AddId(IdMap* ids, const char* what, int64_t id, int64_t where) {
  if (id < 0) {
    FailAt(MeshErrorKind::kIndex, where,
           std::string(what) + " id " + std::to_string(id) + " is negative");
  }
  const int64_t first = ids->Add(id, where);
  if (first >= 0) {
    FailAt(MeshErrorKind::kIndex, where,
           std::string(what) + " id " + std::to_string(id) + " is duplicated (first " +
               Describe(ids->where(first)) + ")");
  }
}

void GmshReader::AddNodeId(int64_t id, int64_t where) { AddId(&nodes_, "node", id, where); }

const ElementTypeInfo& GmshReader::ElementType(int64_t type, int64_t where) const {
  const ElementTypeInfo* info = FindElementType(type);
  if (info != nullptr) return *info;
  if (const char* name = UnreadableTypeName(type)) {
    FailAt(MeshErrorKind::kUnsupported, where,
           "element type " + std::to_string(type) + " (" + name +
               ") is not supported: its node count is not fixed by its type");
  }
  FailAt(MeshErrorKind::kUnsupported, where,
         "element type " + std::to_string(type) +
             " is not a Gmsh element type somasim knows, so its node count and the rest of "
             "the file cannot be read");
}

// One element whose node ids (the file's numbering) are in element_nodes_.
void GmshReader::AddElement(int64_t id, const ElementTypeInfo& type, int64_t where) {
  AddId(&elements_, "element", id, where);
  std::array<int64_t, 4> corners{};
  for (size_t k = 0; k < element_nodes_.size(); ++k) {
    const int64_t index = nodes_.Find(element_nodes_[k]);
    if (index < 0) {
      FailAt(MeshErrorKind::kIndex, where,
             "element " + std::to_string(id) + " refers to node id " +
                 std::to_string(element_nodes_[k]) + ", which " + nodes_section_ +
                 " does not define");
    }
    if (k < corners.size()) corners[k] = index;
  }
  if (type.type == kTriangleType) {
    builder_.AddTriangle(corners[0], corners[1], corners[2], Loc(where));
  } else if (type.type == kTetrahedronType) {
    builder_.AddTetrahedron(corners[0], corners[1], corners[2], corners[3], Loc(where));
  } else {
    if (skipped_counts_[static_cast<size_t>(type.type)]++ == 0) skipped_order_.push_back(type.type);
  }
}

void GmshReader::FlushSkipped() {
  for (const int type : skipped_order_) {
    builder_.Skip(FindElementType(type)->name, skipped_counts_[static_cast<size_t>(type)]);
  }
}

void GmshReader::ParseNodeIds(size_t first, size_t count) {
  element_nodes_.resize(count);
  for (size_t k = 0; k < count; ++k) element_nodes_[k] = TokenInt(tokens_[first + k], "a node id");
}

ByteReader GmshReader::DataReader() const {
  return ByteReader(bytes_.substr(in_.offset()), file_name_, static_cast<int64_t>(in_.offset()));
}

}  // namespace gmsh_internal

MeshData ReadGmsh(std::string_view bytes, const std::string& file_name,
                  const ReadOptions& options) {
  gmsh_internal::GmshReader reader(bytes, file_name);
  return reader.Read(options);
}

}  // namespace somasim::mesh_io
