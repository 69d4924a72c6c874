// Wavefront OBJ: `v` vertices and `f` faces (triangles; convex polygons are fan-triangulated
// and reported). Texture/normal indices (`f 1/2/3`) and negative (relative) indices are read.
//
// Reading:
//  - `v x y z`, also `v x y z w` (w ignored) and the common colour extension `v x y z r g b`.
//  - `f` corners as `v`, `v/vt`, `v//vn` or `v/vt/vn`; only the vertex index is used. Indices
//    are 1-based, negative ones count back from the last vertex defined so far, 0 is an error
//    (kIndex). Vertices may come after the faces that use them.
//  - A face with more than 3 corners is split into a fan of triangles from its first corner,
//    which is right only for a convex polygon: a non-convex one is refused (kUnsupported). The
//    split faces are kept, not dropped, so they are not listed in MeshData::skipped; instead
//    MeshData::format says how many were split, e.g. "Wavefront OBJ (6 polygon faces with more
//    than 3 corners fan-triangulated into 12 triangles)".
//  - `l` (polylines) and `p` (points) are skipped and counted.
//  - Statements without geometry somasim uses are ignored: vt vn vp g o s mg usemtl mtllib
//    usemap maplib lod shadow_obj trace_obj bevel c_interp d_interp, and the free-form
//    attributes cstype deg bmat step curv2 parm trim hole scrv sp end con. Free-form geometry
//    itself (`curv`, `surf`) is refused (kUnsupported); any other keyword is kSyntax.
//  - `#` starts a comment anywhere on a line; a line ending in `\` continues on the next one;
//    LF or CRLF line ends.
// OBJ has no counts and no end marker, so a truncated file cannot be told from a complete one.
#pragma once

#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"

namespace somasim::mesh_io {

MeshData ReadObj(std::string_view bytes, const std::string& file_name, const ReadOptions& options);
// Writes vertices and triangles (tetrahedra are not representable; the caller decides):
// "v x y z" lines with the shortest round-trip decimal text, then "f a b c" with 1-based
// indices.
std::string WriteObj(const MeshData& mesh);

}  // namespace somasim::mesh_io
