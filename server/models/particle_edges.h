// What the edge-based particle models (mass-spring, position-based) build alike from their
// edges: edges given as node pairs checked and sorted, rest lengths, lumped masses, and each
// node's list of edges; and the stiffness block of one edge for LocalStiffness. Pure; used at
// construction, except AddEdgeStiffness.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"

namespace somasim::models {

// Edges given as node pairs (FromEdges), each ordered (i < j), sorted by (i, j). Throws
// std::invalid_argument "<model>: <noun> e joins nodes a and b, not two distinct nodes of
// 0..num_nodes-1" for the first pair that does not join two distinct nodes of 0..num_nodes-1.
std::vector<std::array<int32_t, 2>> SortedEdges(const std::vector<std::array<int32_t, 2>>& edges,
                                                Eigen::Index num_nodes, const char* model,
                                                const char* noun);

// |x_j - x_i| [m] of the rest positions (3 × num_nodes). Throws std::invalid_argument "<model>:
// nodes i and j coincide (a zero-length <noun>)" unless it is > 0.
double EdgeRestLength(const mesh::Points& rest, int32_t i, int32_t j, const char* model,
                      const char* noun);

// Lumped masses [kg], one per node: node_mass for every node when it is > 0, else density
// [kg/m³] × node_size [m³] (MeshEdges::node_size), and their inverses [1/kg], 0 for a massless
// node (one no element touches: it cannot move).
void LumpMasses(const std::vector<double>& node_size, double density, double node_mass,
                std::vector<double>* mass, std::vector<double>* inverse_mass);

// The edges of each node (CSR): the edges touching node i, in edge order, are
// edges[start[i]] .. edges[start[i + 1] - 1]; start has num_nodes + 1 entries, edges
// 2 × num_edges.
void NodeEdgeLists(size_t num_nodes, const std::vector<int32_t>& edge_i,
                   const std::vector<int32_t>& edge_j, std::vector<int32_t>* start,
                   std::vector<int32_t>* edges);

// k_local += k [u uᵀ + (1 - l0/l)(I - u uᵀ)], -∂f_i/∂x_i of an edge d = x_j - x_i (l = |d|,
// u = d/l) of rest length l0 [m] and stiffness k [N/m], the geometric term included; nothing for
// an edge of zero length.
void AddEdgeStiffness(const Eigen::Vector3d& d, double rest_length, double k,
                      Eigen::Matrix3d* k_local);

}  // namespace somasim::models
