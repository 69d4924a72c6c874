// Linear tetrahedra (SPEC §4.4): the rest-shape data every finite-element model needs — shape
// function gradients, volumes, lumped node volumes — and the deformation gradient. Pure; built
// once when a model is made.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"

namespace somasim::models::fem {

struct TetElements {
  mesh::Tetrahedra tets;  // 4 × num_tets, positively oriented
  // ∇N_a [1/m] of corner a's linear shape function (constant on the element), column 4e + a,
  // 3 × 4·num_tets. Σ_a ∇N_a = 0, and Σ_a X_a ∇N_aᵀ = I at rest.
  Eigen::Matrix<double, 3, Eigen::Dynamic> gradients;
  std::vector<double> volumes;      // [m³] at rest, num_tets, > 0
  std::vector<double> node_volume;  // [m³], num_nodes: Σ V_e / 4 over the node's elements
  // Elements per node (CSR): node i's elements are element_of_node[node_start[i] ..
  // node_start[i+1]), as (e, corner) packed into 4 e + corner.
  std::vector<int32_t> node_start;  // num_nodes + 1
  std::vector<int32_t> element_of_node;

  int32_t num_tets() const { return static_cast<int32_t>(tets.cols()); }
  int32_t num_nodes() const { return static_cast<int32_t>(node_volume.size()); }
  // The displacement gradient H = F - I = Σ_a (x_a - X_a) ∇N_aᵀ, from displacements so that a
  // small strain keeps its digits (F - I from positions loses them: |x| ≫ |x - X|).
  Eigen::Matrix3d DisplacementGradient(const mesh::Points& x, const mesh::Points& rest,
                                       int32_t e) const {
    Eigen::Matrix3d h = Eigen::Matrix3d::Zero();
    for (int a = 0; a < 4; ++a) {
      const int32_t node = tets(a, e);
      h.noalias() += (x.col(node) - rest.col(node)) * gradients.col(4 * e + a).transpose();
    }
    return h;
  }
};

// Throws std::invalid_argument prefixed with `model` naming the fault: no nodes or no
// tetrahedra, a non-finite coordinate, an index out of range, a repeated corner, or an element
// that is inverted or flat (volume <= 1e-12 × its longest edge cubed).
TetElements BuildTetElements(const mesh::TetMesh& mesh, const char* model);

// The rotation R of the polar decomposition F = R S (S symmetric), a proper rotation (det R = 1)
// also for an inverted element (det F < 0), from the singular value decomposition.
Eigen::Matrix3d PolarRotation(const Eigen::Matrix3d& f);

}  // namespace somasim::models::fem
