// Isosurface stuffing: a tetrahedral mesh of an implicit solid with guaranteed dihedral angles.
//
// Labelle F., Shewchuk J. R., "Isosurface Stuffing: Fast Tetrahedral Meshes with Good Dihedral
// Angles", ACM Trans. Graph. 26(3) (SIGGRAPH 2007). The solid is overlaid with a body-centred
// cubic (BCC) lattice; lattice vertices too close to the surface are warped onto it, and the
// lattice tetrahedra that cross the surface are cut along it by fixed stencils. With the
// paper's warping parameters the dihedral angles stay between about 10.7° and 164.8°, whatever
// the surface. Pure kernel: no I/O.
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "common/mesh/mesh_types.h"
#include "common/mesh_gen/implicit.h"

namespace somasim::mesh_gen {

struct StuffingOptions {
  // Edge length of the lattice's cubes [m], > 0: black vertices at origin + spacing·(i, j, k),
  // red vertices at the cube centres. Nodes scale like volume / spacing³.
  double spacing = 0.01;
  // Shift of the lattice, as a fraction of spacing per axis, each in [0, 1). Different offsets
  // give different (equally valid) meshes; the built-in organs fix one to hit their counts.
  Eigen::Vector3d offset = Eigen::Vector3d::Zero();
  // Warping thresholds (the paper's α_long and α_short, section 3): a lattice vertex closer to a
  // cut point than α times the edge length moves onto it. The defaults are the paper's values
  // for the 10.7°–164.8° guarantee; each must lie in (0, 0.5).
  double alpha_long = 0.24999;
  double alpha_short = 0.41189;
};

struct StuffingStatistics {
  int64_t lattice_vertices = 0;  // black + red vertices evaluated
  int64_t warped_vertices = 0;   // lattice vertices moved onto the surface
  int64_t cut_points = 0;        // surface vertices on lattice edges
  int64_t lattice_tets_cut = 0;  // lattice tetrahedra filled by a cutting stencil
};

// Meshes the region Value < 0 of `solid` (which must lie inside solid.Bounds()). Output nodes are
// the lattice vertices inside or warped onto the surface plus the cut points, numbered in lattice
// order; every tetrahedron is positively oriented. The result is empty if the solid is thinner
// than the lattice. Throws std::invalid_argument for bad options (named) or an empty/non-finite
// Bounds(), or if the lattice would exceed max_lattice_vertices.
mesh::TetMesh StuffIsosurface(const ImplicitSolid& solid, const StuffingOptions& options,
                              StuffingStatistics* statistics = nullptr,
                              int64_t max_lattice_vertices = 50'000'000);

}  // namespace somasim::mesh_gen
