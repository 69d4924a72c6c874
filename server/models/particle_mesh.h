// Building blocks shared by the particle models (mass-spring, molecular, position-based): the
// unique edges of a mesh with the element sizes the material rules need, mesh checks, and the
// handling of fixed and prescribed nodes after an explicit update. Pure; used at construction,
// except ApplyFixedAndPrescribed, which runs in the step and allocates nothing.
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/tissue_model.h"

namespace somasim::models {

// The unique edges of a mesh, sorted, each with the summed size of the elements containing it,
// and each node's share of the element sizes (size / corners per element). Size is volume [m³]
// for tetrahedra and area × thickness [m³] for triangles: Van Gelder's rule
// k_e = E · edge_size / |e|² and lumped masses ρ · node_size use them.
struct MeshEdges {
  std::vector<std::array<int32_t, 2>> edges;  // i < j, sorted by (i, j)
  std::vector<double> edge_size;              // [m³], one per edge
  std::vector<double> node_size;              // [m³], one per node
};

// Both throw std::invalid_argument, prefixed with `model` (e.g. "mass-spring"), when the mesh
// has no nodes or no elements, a non-finite coordinate, or an element index out of range.
MeshEdges TetMeshEdges(const mesh::TetMesh& mesh, const char* model);
MeshEdges SurfaceEdges(const mesh::SurfaceMesh& surface, double thickness, const char* model);

// Throws std::invalid_argument (prefixed with `model`) if there are no points or one is not
// finite.
void CheckFinitePoints(const mesh::Points& points, const char* model);

// report->kinetic += ½ Σ m |v|², report->gravity -= Σ m g·x, report->momentum += Σ m v over the
// state's nodes (masses [kg], one per node).
void AddKineticAndGravity(const std::vector<double>& masses, const TissueState& state,
                          const Eigen::Vector3d& gravity, EnergyReport* report);

// After an explicit update moved every node by dt·v: fixed nodes go back and stop; prescribed
// nodes move to their targets with the velocity that takes them there in dt.
void ApplyFixedAndPrescribed(const StepInputs& inputs, TissueState* state);

}  // namespace somasim::models
