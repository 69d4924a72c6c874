// Reading and writing mesh files by name: the format comes from the extension.
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "common/mesh_io/gmsh_io.h"
#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/mesh_error.h"
#include "common/mesh_io/stl_io.h"
#include "common/mesh_io/vtu_io.h"

namespace somasim::mesh_io {

enum class FileFormat { kObj, kStl, kVtkLegacy, kVtu, kGmsh, kTetGen };

// .obj .stl .vtk .vtu .msh .node/.ele/.face (case-insensitive); nullopt for anything else.
std::optional<FileFormat> FormatFromPath(std::string_view path);
const char* FormatName(FileFormat format);
bool FormatHoldsTetrahedra(FileFormat format);

// Reads a whole file into memory. Fails with kIo naming the file.
std::string ReadFileBytes(const std::string& path);

// Reads and checks a mesh file. For TetGen, any of .node/.ele/.face names the mesh.
MeshData ReadMeshFile(const std::string& path, const ReadOptions& options);
// Reads a mesh held in memory (every format but TetGen, which spans several files).
MeshData ReadMeshBytes(FileFormat format, std::string_view bytes, const std::string& name,
                       const ReadOptions& options);

struct WriteOptions {
  Unit unit = Unit::kMetre;              // unit of the written coordinates
  Encoding encoding = Encoding::kAscii;  // STL, legacy VTK, Gmsh 2.2/4.1, VTU (kBinary)
  GmshVersion gmsh_version = GmshVersion::kV41;
  bool vtu_base64 = false;  // VTU binary: inline base64 instead of appended raw data
  bool big_endian = false;  // VTU binary byte order
};

struct WriteReport {
  // True when the format holds no tetrahedra and the boundary surface of the volume mesh was
  // written instead.
  bool wrote_boundary_surface = false;
  std::string files;  // what was written (several names for TetGen)
};

// `mesh` is in metres. Writes atomically enough for a tool: to the final name, checked.
WriteReport WriteMeshFile(const std::string& path, const MeshData& mesh,
                          const WriteOptions& options);

}  // namespace somasim::mesh_io
