// Seed 001 §1.2 (Chen, Zhao & Zhu 2015; SPEC §4.1): the generalised surface mesh of the
// non-surgical region. Far from the tools nothing is cut or sutured, so the organ there is
// simulated as a shell: only nodes in the outer fifth of the thickness carry mass ("只在非手术区
// 表层的1/5厚度具有质点分布"), joined by the structural springs of the mass-spring model, and each
// is tied to its own rest position by a zero-rest-length spring, f_i = k_s (x0_i - x_i) (seed 001
// eq. 10), which stands in for the unsimulated core. MassSpringModel::FromGeneralisedSurface
// builds the model from these pieces. Pure: used at construction only.
#pragma once

#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {

// The outer shell of a tetrahedral organ. Depth is each node's Euclidean distance to the
// boundary surface; the organ's thickness is T = 2 · (deepest node's depth), the diameter of the
// largest inscribed sphere centred on a node; the shell is every node with depth <= fraction · T.
// For a slab this is exactly the outer `fraction` of its thickness on each side.
struct OuterShell {
  std::vector<double> depth;      // [m], num_nodes, >= 0 (0 on the boundary)
  std::vector<uint8_t> in_shell;  // num_nodes: 1 = carries mass and moves
  double thickness = 0.0;         // T [m]
  int32_t num_shell_nodes = 0;
};

// Throws std::invalid_argument naming the fault: fraction outside (0, 0.5], a mesh without
// tetrahedra, an index out of range or a non-finite coordinate.
OuterShell SelectOuterShell(const mesh::TetMesh& mesh, double fraction);

// The tetrahedra's edges with both ends in the shell (the structural springs), with the summed
// volume of the tetrahedra containing each edge (Van Gelder's rule, as for every tetrahedral
// mass-spring model), and the lumped volume per node, zero off the shell: the core's mass is not
// simulated.
MeshEdges ShellEdges(const mesh::TetMesh& mesh, const OuterShell& shell);

// The distance [m] from point p to the triangle (a, b, c) (exact, including edges and corners).
double PointTriangleDistance(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                             const Eigen::Vector3d& b, const Eigen::Vector3d& c);

}  // namespace somasim::models
