// TetGen's .node / .ele / .face files (ASCII). A mesh is the .node file plus, when present,
// the .ele (tetrahedra) and .face (triangles) files of the same base name.
//
// Layout (TetGen manual; '#' starts a comment anywhere, blank lines are skipped):
//   .node: "<#points> <dim=3> <#attributes> <boundary markers 0|1>", then
//          "<index> x y z [attributes...] [marker]"
//   .ele:  "<#tets> <nodes per tet 4|10> <#attributes>", then "<index> n1 .. n4|n10 [attr...]"
//   .face: "<#faces> <boundary markers 0|1>", then "<index> n1 n2 n3 [n4 n5 n6] [marker]
//          [adjacent tet 1, adjacent tet 2]" (mid-edge nodes with tetgen -o2, adjacent
//          tetrahedra with -nn; the first face line tells which, every line must agree).
// Trailing header fields may be left out (TetGen's defaults: dim 3, no attributes or markers,
// 4 nodes per tetrahedron). Points are numbered from 0 or 1 (the first point's index decides);
// the elements are numbered the same way and refer to points in that numbering. Indices must
// be consecutive (kIndex naming a duplicate or a jump); counts must match the data (kCount).
// Attributes, markers and adjacency are read and checked as numbers but not kept. dim != 3 is
// kUnsupported.
// 10-node tetrahedra (and 6-node faces) are read as their 4 (3) corner nodes, which TetGen
// writes first; the mid-edge nodes stay in the mesh, unreferenced. This is not a Skip() (no
// element is dropped): MeshData::format says so, e.g. "TetGen (10-node tetrahedra read as their
// 4 corners; ...)".
//
// Orientation. TetGen's tetrahedra have somasim's orientation, (x1-x0)·((x2-x0)×(x3-x0)) > 0
// (checked on tetgen 1.5.0 output, for PLC meshes and Delaunay tetrahedralisations), so they are
// read and written unchanged: files made by TetGen read without --fix-orientation and files
// written here are valid TetGen input.
// TetGen's faces have no fixed orientation: tetgen 1.5.0 writes the boundary faces of a PLC mesh
// (-p) pointing into the volume and those of a convex hull pointing out. somasim's triangles
// face outwards (mesh_types.h), so when the .ele file is present, a face that bounds exactly one
// tetrahedron is turned (second and third corners swapped) to face away from it; interior faces
// and faces of no tetrahedron keep their order. MeshData::format counts the faces turned.
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"

namespace somasim::mesh_io {

struct TetGenInput {
  std::string_view node;                // contents of the .node file
  std::string node_name;                // its name, for errors
  std::optional<std::string_view> ele;  // .ele contents, if the file exists
  std::string ele_name;
  std::optional<std::string_view> face;  // .face contents, if the file exists
  std::string face_name;
};

// Errors name the file the fault is in (.node, .ele or .face) and its line.
MeshData ReadTetGen(const TetGenInput& input, const ReadOptions& options);

struct TetGenFiles {
  std::string node;
  std::string ele;   // empty when the mesh has no tetrahedra
  std::string face;  // empty when the mesh has no triangles
};
// Indices are written 0-based (TetGen's -z convention), as TetGen itself reads either; no
// attributes, no markers; tetrahedra and triangles in somasim's orientation (see above).
TetGenFiles WriteTetGen(const MeshData& mesh);

}  // namespace somasim::mesh_io
