// STL, ASCII and binary (detected from the content). STL stores each triangle with its own
// corners; exactly equal corners are merged into one node, in order of first appearance.
#pragma once

#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"

namespace somasim::mesh_io {

enum class Encoding { kAscii, kBinary };

MeshData ReadStl(std::string_view bytes, const std::string& file_name,
                 const ReadOptions& options);
// Triangles only. Binary STL stores float32 coordinates.
std::string WriteStl(const MeshData& mesh, Encoding encoding);

}  // namespace somasim::mesh_io
