// The tissue's local compliance at a surface node, for the local force model
// (common/force_model/local_force_model.h): C = (∂x_node/∂f_node) [m/N], 3 × 3 symmetric
// positive definite — how far the node moves per newton pushed on it, the rest of the organ free
// to follow.
//
// FEM (condensed compliance): C_i = [K⁻¹]_ii, the 3 × 3 diagonal block of the inverse of the
// stiffness with the organ's held nodes removed — exactly the static response of a linear organ
// to a point force, and what a static solve of the full model gives for a small displacement.
// It comes from CHOLMOD's factorisation of the rest stiffness K0 (once, at start-up): with
// P K0 Pᵀ = L Lᵀ, C0_i = Y_iᵀ Y_i, Y_i = L⁻¹ P E_i (E_i: node i's three unit columns), and Y_i
// is nonzero only on the elimination-tree path above node i's rows — a sparse forward
// substitution, neighbouring nodes grouped (SparseCholesky::InverseBlocks). Cached, then rotated
// into the current frame, C = R C0 Rᵀ, with R the polar rotation of the node's elements'
// volume-weighted mean deformation gradient (corotational and hyperelastic organs; identity for
// linear ones). K0 is the instantaneous (elastic, G(0) = 1) stiffness of a QLV organ. Small
// strain: at large strain the hyperelastic tangent stiffens and C0 overestimates the compliance
// (documented, not hidden; docs/contact.md gives the errors against the full static solve and
// the costs).
// Other models (mass-spring, molecular, position-based): their own LocalStiffness, inverted —
// the stiffness the node has against its neighbours this step.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "server/models/tissue_model.h"

namespace somasim::models::fem {
class FemModel;
}

namespace somasim::contact {

class FemCompliance {
 public:
  // Factorises the rest stiffness of `model` with `fixed_nodes` held (each index in range;
  // throws std::invalid_argument naming the fault, e.g. nothing held, or a held set that leaves
  // a rigid motion free — a connected part of the mesh with no held node, or with its held
  // nodes on one line — checked geometrically, since rounding can let a Cholesky factorisation
  // of a singular K finish with a tiny pivot; a factorisation that fails or has a reciprocal
  // condition estimate below 1e-14 is refused too). Allocates; start-up only.
  // The model must outlive this object.
  FemCompliance(const models::fem::FemModel& model, std::span<const int32_t> fixed_nodes);
  ~FemCompliance();
  FemCompliance(const FemCompliance&) = delete;
  FemCompliance& operator=(const FemCompliance&) = delete;

  // Computes and caches C0 at `nodes` (e.g. every surface node at start-up). Throws
  // std::invalid_argument for a node out of range (then caches nothing).
  void Precompute(std::span<const int32_t> nodes);
  // C at `node` in the state's current frame [m/N]. A held node has C = 0. A node not yet
  // cached costs a sparse forward substitution (milliseconds on liver4055; the first one also
  // copies the factor), after which it is cached; with every node precomputed this allocates
  // nothing. Throws std::invalid_argument for a node out of range, a state that is not
  // 3 × num_nodes, or non-finite positions around the node.
  Eigen::Matrix3d AtNode(const models::TissueState& state, int32_t node);
  // The rest compliance C0 at `node` (cached as above).
  Eigen::Matrix3d RestAtNode(int32_t node);
  // The model it was built for.
  const models::fem::FemModel& model() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// The local compliance [m/N] of any model at `node`: FEM through `fem` (when given, for FEM
// models), the others as LocalStiffness(state, node)⁻¹ (pseudo-inverse where the stiffness is
// singular, e.g. a node with no springs: a free direction — stiffness below 1e-3 N/m, below
// 1e-9 of the node's largest, or negative — gets the compliance 1000 m/N, practically no force,
// yet finite; real soft directions, e.g. a membrane's bending at 0.1-5 N/m, are inverted
// exactly). A FEM model without `fem` gets the inverse of its LocalStiffness (the diagonal
// block of K alone: stiffer than the condensed compliance). Symmetric, finite. Throws
// std::invalid_argument for a node out of range, a state of the wrong size, a non-finite
// stiffness, or a `fem` built for another model.
// (Note: the cap was 1 m/N in the first version of this contract; that flattened the real
// bending stiffness of molecular membranes, 0.15 N/m at some spleen600 nodes, to 1 N/m.)
Eigen::Matrix3d LocalCompliance(const models::TissueModel& model, const models::TissueState& state,
                                int32_t node, FemCompliance* fem);

}  // namespace somasim::contact
