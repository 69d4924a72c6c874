// Structured built-in meshes: meshes whose node layout is fixed by a formula rather than fitted to
// an implicit shape. Pure functions: no I/O, deterministic (same arguments → bit-identical output).
//
//   BoxGridTets    a regular box grid, every cell cut into 6 tetrahedra (SOFA's benchmark beam).
//   Plate192       the 200 × 200 × 10 mm plate of seed 003 (192 nodes, 392 tetrahedra).
//   TissuePatch45  the "simple tissue" open surface patch of seed 002 (45 vertices, 66 triangles).
#pragma once

#include <Eigen/Core>

#include "common/mesh/mesh_types.h"

namespace somasim::mesh_gen {

// A regular grid of nx · ny · nz nodes spanning the box [min, max] [m]; node (i, j, k) has index
// i + nx · (j + ny · k) and position min + (max - min) ∘ (i, j, k) / (n - 1), the last node of each
// axis landing exactly on max. Every hexahedral cell is cut into the 6 tetrahedra of the Kuhn
// (Freudenthal) split around its main diagonal from the (0,0,0) corner to the (1,1,1) corner; the
// same split in every cell gives the same face diagonals on both sides of a shared face, so the
// mesh is conforming. All tetrahedra are positively oriented. Tetrahedra are ordered by cell
// (x fastest, then y, then z), 6 per cell: 6 · (nx-1)(ny-1)(nz-1) in all.
//
// beam19k, SOFA's CPU benchmark beam, is BoxGridTets(40, 10, 10, (0,0,0), (16,4,4)): 4000 nodes,
// 18954 tetrahedra, 256 m³.
//
// Throws std::invalid_argument when an n is < 2, when the node count does not fit an int32 index,
// or when min/max are not finite or not min < max on every axis.
mesh::TetMesh BoxGridTets(int nx, int ny, int nz, const Eigen::Vector3d& min,
                          const Eigen::Vector3d& max);

// The plate of seed 003 (vertex-preserving cutting, table 1: "Plate 192 / 392"): exactly 192 nodes
// and 392 tetrahedra filling the box [0, 0.2] × [0, 0.2] × [0, 0.01] m (x, y in the plate's plane,
// z through its thickness). Nodes: a 12 (x) × 8 (y) × 2 (z) grid, index i + 12 · (j + 8 · k).
// Cells: 11 × 7 hexahedra, 70 cut into 5 tetrahedra and the 7 of the x = 0 column (i = 0) into 6;
// see structured_meshes.cc for why this gives the exact count and stays conforming. Conforming,
// positively oriented, minimum dihedral angle about 19.3°.
mesh::TetMesh Plate192();

// The "simple tissue" patch of seed 002 (table 1: 66 triangles, 45 points): an open, gently domed
// elliptical patch, 50 mm (x) × 40 mm (y) across, rim at z = 0 and apex at z = 4 mm over the
// origin. Exactly 45 vertices (22 on the rim) and 66 triangles, counter-clockwise seen from +z
// (normals point up), one component, manifold with a single boundary loop of 22 edges. Smallest
// triangle angle about 39.9°.
mesh::SurfaceMesh TissuePatch45();

}  // namespace somasim::mesh_gen
