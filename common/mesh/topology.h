// Combinatorial structure of meshes: adjacency, boundary surface, watertightness, manifoldness.
#pragma once

#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"

namespace somasim::mesh {

// Compressed adjacency: the neighbours of item i are entries[offsets[i] .. offsets[i+1]).
struct Adjacency {
  std::vector<int32_t> offsets;  // num_items + 1
  std::vector<int32_t> entries;  // sorted ascending within each item
  int32_t Count(size_t i) const { return offsets[i + 1] - offsets[i]; }
};

// Tetrahedra incident to each node (num_nodes items).
Adjacency NodeToTets(int32_t num_nodes, const Tetrahedra& tets);
// Triangles incident to each node (num_nodes items).
Adjacency NodeToTriangles(int32_t num_nodes, const Triangles& triangles);

// For each tetrahedron and local face f (the face opposite corner f), the neighbouring
// tetrahedron across it or -1 on the boundary. 4 × num_tets. Faces shared by more than two
// tetrahedra (non-manifold input) get -2.
Eigen::Matrix<int32_t, 4, Eigen::Dynamic> TetFaceNeighbours(int32_t num_nodes,
                                                            const Tetrahedra& tets);

// The boundary faces of a tetrahedral mesh (faces belonging to exactly one tetrahedron),
// oriented outwards for positively oriented tetrahedra. The returned surface keeps the volume's
// vertex array and numbering, so surface index == volume index. Faces are ordered by
// (tetrahedron, local face), which makes the result deterministic.
SurfaceMesh ExtractBoundarySurface(const TetMesh& mesh);

// The nodes (ascending) of 0 .. num_nodes-1 that no triangle and no tetrahedron uses. Indices
// out of range are ignored.
std::vector<int32_t> UnreferencedNodes(int32_t num_nodes, const Triangles& triangles,
                                       const Tetrahedra& tets);

// Surface with unreferenced vertices removed; old_to_new (num old vertices, -1 = dropped) maps.
SurfaceMesh CompactSurface(const SurfaceMesh& surface, std::vector<int32_t>* old_to_new);

struct SurfaceTopology {
  int64_t num_edges = 0;
  int64_t num_boundary_edges = 0;        // edges with exactly one triangle
  int64_t num_nonmanifold_edges = 0;     // edges with three or more triangles
  int64_t num_misoriented_edges = 0;     // two-triangle edges traversed the same way by both
  int64_t num_nonmanifold_vertices = 0;  // vertices whose triangle fan is not one disc/half-disc
  int64_t num_degenerate_triangles = 0;  // a repeated index
  int64_t num_components = 0;            // connected components of triangles (by shared edges)
  // Closed: every edge has exactly two triangles, consistently oriented, no degenerate triangle.
  bool watertight = false;
  // Every edge has one or two triangles and every vertex has a single fan.
  bool manifold = false;
  // Euler characteristic V - E + F over referenced vertices.
  int64_t euler_characteristic = 0;
};

SurfaceTopology AnalyseSurfaceTopology(const SurfaceMesh& surface);

}  // namespace somasim::mesh
