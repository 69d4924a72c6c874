// Pure geometric measures of meshes: bounding box, signed volumes, enclosed volume.
#pragma once

#include <Eigen/Core>

#include "common/mesh/mesh_types.h"

namespace somasim::mesh {

struct BoundingBox {
  Eigen::Vector3d min = Eigen::Vector3d::Zero();  // [m]
  Eigen::Vector3d max = Eigen::Vector3d::Zero();  // [m]
  bool empty = true;                              // no points
};

// Axis-aligned bounding box of all points (referenced or not).
BoundingBox ComputeBoundingBox(const Points& points);

// Signed volume [m³] of the tetrahedron (a, b, c, d): (b-a)·((c-a)×(d-a)) / 6.
// Positive for the orientation convention of mesh_types.h.
double TetSignedVolume(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                       const Eigen::Vector3d& d);
double TetSignedVolume(const Points& points, const Eigen::Ref<const Eigen::Vector4i>& tet);

// Sum of signed tetrahedron volumes [m³].
double TetMeshVolume(const TetMesh& mesh);

// Volume [m³] enclosed by a closed, consistently oriented surface (divergence theorem);
// positive when triangles face outwards. Meaningless for an open surface.
double SurfaceEnclosedVolume(const SurfaceMesh& surface);

// Total area [m²] of the triangles.
double SurfaceArea(const SurfaceMesh& surface);

}  // namespace somasim::mesh
