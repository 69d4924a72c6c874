// TetGen's .node / .ele / .face files (ASCII). A mesh is the .node file plus, when present,
// the .ele (tetrahedra) and .face (triangles) files of the same base name.
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"

namespace somasim::mesh_io {

struct TetGenInput {
  std::string_view node;               // contents of the .node file
  std::string node_name;               // its name, for errors
  std::optional<std::string_view> ele;  // .ele contents, if the file exists
  std::string ele_name;
  std::optional<std::string_view> face;  // .face contents, if the file exists
  std::string face_name;
};

MeshData ReadTetGen(const TetGenInput& input, const ReadOptions& options);

struct TetGenFiles {
  std::string node;
  std::string ele;   // empty when the mesh has no tetrahedra
  std::string face;  // empty when the mesh has no triangles
};
// Indices are written 0-based (TetGen's -z convention), as TetGen itself reads either.
TetGenFiles WriteTetGen(const MeshData& mesh);

}  // namespace somasim::mesh_io
