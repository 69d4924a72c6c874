// Meshes and checks shared by the contact tests: a closed organ surface over a volume's nodes,
// a flat patch, and the generalised winding number (inside/outside of a closed surface).
#pragma once

#include <Eigen/Core>

#include "common/mesh/mesh_types.h"

namespace somasim::testing {

// A volume organ (built-in name) with its boundary triangles in the volume's numbering.
struct OrganWithSurface {
  mesh::TetMesh volume;
  mesh::Triangles surface;
};
OrganWithSurface VolumeOrgan(const char* name);

// The box [lo, hi] as tetrahedra (n × n × n cells) with its boundary, outward normals.
OrganWithSurface BoxOrgan(int n, const Eigen::Vector3d& lo, const Eigen::Vector3d& hi);

// A flat n × n square patch on z = 0 over [-half, half]², normals +z.
mesh::SurfaceMesh FlatPatch(int n, double half);

// The generalised winding number of x with respect to a closed surface (Jacobson et al. 2013):
// 1 inside, 0 outside (Σ of signed solid angles / 4π, Van Oosterom & Strackee 1983).
double WindingNumber(const mesh::Points& positions, const mesh::Triangles& triangles,
                     const Eigen::Vector3d& x);

}  // namespace somasim::testing
