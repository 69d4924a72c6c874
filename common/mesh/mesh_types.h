// Mesh types shared by every process: tetrahedral volume meshes and triangle surface meshes.
//
// Layout follows the libigl habit of documenting array shapes, but stores one element per
// column so that a node's xyz are contiguous (the layout of a 3·num_nodes DOF vector).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>

namespace somasim::mesh {

// Node positions [m], 3 × num_nodes, column j = node j.
using Points = Eigen::Matrix<double, 3, Eigen::Dynamic>;
// Triangles, 3 × num_triangles, 0-based node indices; counter-clockwise seen from outside.
using Triangles = Eigen::Matrix<int32_t, 3, Eigen::Dynamic>;
// Tetrahedra, 4 × num_tets, 0-based node indices; positively oriented:
// (x1 - x0) · ((x2 - x0) × (x3 - x0)) > 0.
using Tetrahedra = Eigen::Matrix<int32_t, 4, Eigen::Dynamic>;

// A triangle surface (closed or open). Vertices not referenced by a triangle are allowed.
struct SurfaceMesh {
  Points vertices;
  Triangles triangles;
};

// A tetrahedral volume mesh.
struct TetMesh {
  Points vertices;
  Tetrahedra tetrahedra;
};

}  // namespace somasim::mesh
