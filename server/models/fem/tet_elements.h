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

// The same rotation without a singular value decomposition: R maximises tr(Rᵀ F) over proper
// rotations (for det F < 0 too, where it is U diag(1, 1, -1) Vᵀ, PolarRotation's answer), found
// by Newton's method on that maximum from the unit quaternion q = (w, x, y, z) of a nearby
// rotation (the element's rotation in the last step; (1, 0, 0, 0) when none is known), which is
// updated to R's. With R = R_k cay(ω), the gradient of tr(Rᵀ F) is the axial vector g of
// A - Aᵀ, A = R_kᵀ F, and the Hessian is -(tr(S) I - S), S = sym(A): each step solves
// (tr(S) I - S) ω = g, quadratically convergent, so a warm start takes 2–3 steps of ~150
// flops instead of a Jacobi SVD's ~2000. A Hessian that is not negative definite means a
// saddle or a far start (the maximum is the only stationary point where it is): then, or
// without convergence in 8 steps, PolarRotation decides.
Eigen::Matrix3d PolarRotationFrom(const Eigen::Matrix3d& f, double* q);

// PolarRotationFrom for `count` matrices: f and r 9 × count (3 × 3 column-major each), q
// 4 × count (in: the starts; out: the rotations). With AVX-512, eight at a time, one per
// vector lane (the serial Newton chain of one matrix is latency-bound; eight interleave), with
// a lane that does not converge handed to PolarRotationFrom; equal to it up to rounding.
// `force_scalar` (tests) takes the portable path. r may be f (in place). Allocates nothing.
void PolarRotations(const double* f, double* q, double* r, size_t count, bool force_scalar = false);

}  // namespace somasim::models::fem
