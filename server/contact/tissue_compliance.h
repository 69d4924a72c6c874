// The tissue's local compliance at a surface node, for the local force model
// (local_force_model.h): C = (∂x_node/∂f_node) [m/N], 3 × 3 symmetric positive definite — how far
// the node moves per newton pushed on it, the rest of the organ free to follow.
//
// FEM (condensed compliance): C_i = [K⁻¹]_ii, the 3 × 3 diagonal block of the inverse of the
// stiffness with the organ's held nodes removed — exactly the static response of a linear organ
// to a point force, and what a static solve of the full model gives for a small displacement.
// It comes from CHOLMOD's factorisation of the rest stiffness K0 (once, at start-up): three
// solves per node, cached, then rotated into the current frame, C = R C0 Rᵀ, with R the polar
// rotation of the node's elements' mean deformation gradient (corotational and hyperelastic
// organs; identity for linear ones). Small-strain: at large strain the hyperelastic tangent
// stiffens and C0 overestimates the compliance (documented, not hidden).
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
  // a rigid motion free: the factorisation is not positive definite). Allocates; start-up only.
  // The model must outlive this object.
  FemCompliance(const models::fem::FemModel& model, std::span<const int32_t> fixed_nodes);
  ~FemCompliance();
  FemCompliance(const FemCompliance&) = delete;
  FemCompliance& operator=(const FemCompliance&) = delete;

  // Computes and caches C0 at `nodes` (e.g. every surface node at start-up; 3 solves each).
  void Precompute(std::span<const int32_t> nodes);
  // C at `node` in the state's current frame [m/N]. A held node has C = 0. A node not yet
  // cached costs three solves (milliseconds on liver4055), after which it is cached; with
  // every node precomputed this allocates nothing.
  Eigen::Matrix3d AtNode(const models::TissueState& state, int32_t node);
  // The rest compliance C0 at `node` (cached as above).
  Eigen::Matrix3d RestAtNode(int32_t node);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// The local compliance [m/N] of any model at `node`: FEM through `fem` (when given, for FEM
// models), the others as LocalStiffness(state, node)⁻¹ (pseudo-inverse where the stiffness is
// singular, e.g. a node with no springs: its compliance along free directions is capped at
// 1 m/N). Symmetric, finite.
Eigen::Matrix3d LocalCompliance(const models::TissueModel& model,
                                const models::TissueState& state, int32_t node,
                                FemCompliance* fem);

}  // namespace somasim::contact
