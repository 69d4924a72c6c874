// Wavefront OBJ: `v` vertices and `f` faces (triangles; convex polygons are fan-triangulated
// and reported). Texture/normal indices (`f 1/2/3`) and negative (relative) indices are read.
#pragma once

#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"

namespace somasim::mesh_io {

MeshData ReadObj(std::string_view bytes, const std::string& file_name,
                 const ReadOptions& options);
// Writes vertices and triangles (tetrahedra are not representable; the caller decides).
std::string WriteObj(const MeshData& mesh);

}  // namespace somasim::mesh_io
