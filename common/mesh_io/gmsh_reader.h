// Internal to the Gmsh reader: the reader class. Its members are defined in gmsh_reader.cc (file
// and section structure, what all versions share), gmsh_reader_v1_v2.cc and gmsh_reader_v4.cc.
#pragma once

// Format references: the "MSH file format" chapter of the Gmsh reference manual (versions 4.1
// and 2.2, and the legacy version 1), and Gmsh's own reader (src/geo/GModelIO_MSH4.cpp,
// GModelIO_MSH2.cpp) for the details the manual leaves implicit: binary data starts right after
// the newline that ends a section's header line and is followed by "\n$End<Section>"; binary
// 4.1 numbers are `int` for dimensions, entity tags, element types and the parametric flag,
// `size_t` (8 bytes) for counts, node tags and element tags, `double` for coordinates.

#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/gmsh_element_types.h"
#include "common/mesh_io/gmsh_internal.h"
#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/mesh_error.h"
#include "common/mesh_io/text_reader.h"

namespace somasim::mesh_io::gmsh_internal {

class GmshReader {
 public:
  GmshReader(std::string_view bytes, const std::string& file_name)
      : bytes_(bytes), file_name_(file_name), in_(bytes, file_name), builder_(file_name, "Gmsh") {}

  MeshData Read(const ReadOptions& options);

 private:
  enum class Version { kV1, kV2, kV41 };

  // ----- Locations

  SourceLocation Loc(int64_t where) const {
    return binary_ ? SourceLocation::Byte(where) : SourceLocation::Line(where);
  }
  std::string Describe(int64_t where) const {
    return (binary_ ? "at byte " : "on line ") + std::to_string(where);
  }
  [[noreturn]] void FailAt(MeshErrorKind kind, int64_t where, const std::string& fault) const {
    in_.FailAt(kind, Loc(where), fault);
  }

  // ----- Header and section structure (gmsh_reader.cc)

  void ReadMeshFormat();
  void ReadSections();
  void SkipSection(const std::string& section);
  void ExpectEndMarker(const std::string& end, const std::string& section);
  void ExpectEndAfter(const std::string& end, const std::string& section, int64_t count,
                      const char* one, const char* many);
  void DataLine(const std::string& section, const std::string& items_said, int64_t read);
  std::string_view SectionToken(const std::string& section, const char* what);
  int64_t SectionInt(const std::string& section, const char* what);
  double SectionDouble(const std::string& section, const char* what);
  int64_t TokenInt(std::string_view token, std::string_view what) const;
  double TokenDouble(std::string_view token, std::string_view what) const;
  int64_t CountLine(const char* what);

  // ----- Nodes and elements, whatever the version (gmsh_reader.cc)

  // Records a node or element id (`what`) of the file, refusing a negative or repeated one.
  void AddId(IdMap* ids, const char* what, int64_t id, int64_t where);
  void AddNodeId(int64_t id, int64_t where);
  const ElementTypeInfo& ElementType(int64_t type, int64_t where) const;
  void AddElement(int64_t id, const ElementTypeInfo& type, int64_t where);
  void FlushSkipped();
  void ParseNodeIds(size_t first, size_t count);
  ByteReader DataReader() const;

  // ----- Versions 1 and 2 (gmsh_reader_v1_v2.cc)

  void ReadVersion1();
  void ReadNodesAscii(const std::string& section, const std::string& end);
  void ReadElements1();
  void ReadElements2Ascii();
  void ReadNodes2Binary();
  void ReadElements2Binary();

  // ----- Version 4.1 (gmsh_reader_v4.cc)

  void ReadEntities41Ascii();
  void ReadNodes41Ascii();
  void CheckBlockHeader(int64_t dim, int64_t parametric, int64_t where) const;
  void ReadElements41Ascii();
  int64_t ReadSize(ByteReader& br, std::string_view what) const;
  int64_t ReadTag(ByteReader& br, std::string_view what) const;
  void ReadEntities41Binary();
  void ReadNodes41Binary();
  void ReadElements41Binary();

  std::string_view bytes_;
  std::string file_name_;
  TextReader in_;
  MeshBuilder builder_;
  Version version_ = Version::kV2;
  std::string version_name_;
  std::string format_;
  std::string nodes_section_ = "$Nodes";
  bool binary_ = false;  // $MeshFormat says binary: node and element locations are byte offsets
  Endian endian_ = Endian::kLittle;
  IdMap nodes_;
  IdMap elements_;
  std::vector<std::string_view> tokens_;
  std::vector<int64_t> element_nodes_;
  std::array<int64_t, kNumTypeSlots> skipped_counts_{};
  std::vector<int> skipped_order_;
  std::vector<int64_t> block_tags_;
};

}  // namespace somasim::mesh_io::gmsh_internal
