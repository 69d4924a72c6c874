// Gmsh .msh: version 1 ($NOD/$ELM), 2.2 and 4.1 ($MeshFormat...), ASCII and binary (2.2, 4.1).
// Mixed element types: triangles and tetrahedra are kept, every other type is counted in
// MeshData::skipped. Node ids may be sparse; they are mapped to 0-based indices in file order.
#pragma once

#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/stl_io.h"  // Encoding

namespace somasim::mesh_io {

enum class GmshVersion { kV1, kV22, kV41 };

MeshData ReadGmsh(std::string_view bytes, const std::string& file_name,
                  const ReadOptions& options);
// Version 1 has no binary form; asking for it fails with kUnsupported.
std::string WriteGmsh(const MeshData& mesh, GmshVersion version, Encoding encoding);

}  // namespace somasim::mesh_io
