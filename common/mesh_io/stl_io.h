// STL, ASCII and binary (detected from the content). STL stores each triangle with its own
// corners; exactly equal corners are merged into one node, in order of first appearance.
//
// Detection: binary when the file size is exactly 84 + 50·n for the triangle count n in its
// header (even when the 80-byte header text starts with "solid", as some exporters write);
// otherwise ASCII, which must start with "solid". Anything else is refused (kSyntax) saying
// why it is neither.
// ASCII: keywords in any case; `solid [name]` ... `endsolid [name]`, several solids one after
// the other are read as one mesh; a facet must have exactly 3 vertices.
// Facet normals are not read: the corner order (counter-clockwise seen from outside, as in
// mesh_types.h) carries the orientation, and many files hold zero normals.
// Merging compares coordinates as numbers with no tolerance (+0 and -0 are equal); unreferenced
// vertices and vertex order cannot be represented, so a round trip preserves the triangles up
// to a renumbering of the vertices (none when they are already in order of first appearance).
#pragma once

#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"

namespace somasim::mesh_io {

enum class Encoding { kAscii, kBinary };

MeshData ReadStl(std::string_view bytes, const std::string& file_name, const ReadOptions& options);
// Triangles only. Binary STL stores float32 coordinates (little-endian, 80-byte header
// "somasim", unit facet normals, attribute 0); a coordinate beyond the float32 range is refused
// (kValue). ASCII writes the shortest round-trip decimal text, so it is exact.
std::string WriteStl(const MeshData& mesh, Encoding encoding);

}  // namespace somasim::mesh_io
