// The mutable state of a mass-spring model (internal to server/models: the explicit and the
// implicit integrators share it).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/tissue_model.h"

namespace somasim::models {

// The state of a mass-spring model: the base state plus the scratch of a step, all sized by
// MakeState so that stepping allocates nothing.
class MassSpringState final : public TissueState {
 public:
  mesh::Points forces;  // [N], 3 × num_nodes
  // Each spring's stiffness [N/m] and damping [N s/m] in this state, num_springs: the model's,
  // or 0 once Cut has removed the spring.
  std::vector<double> stiffness;
  std::vector<double> damping;
  // Explicit step only: forces [N] accumulated at nodes whose own turn in the pass has not come
  // yet (3 × num_nodes); zero between steps.
  mesh::Points pending;
  // --- explicit-step scratch (mass_spring_model.cc) ---
  // --- end of explicit-step scratch ---
  // Implicit Euler only.
  mesh::Points spring_direction;          // u, 3 × num_springs
  std::vector<double> spring_transverse;  // (1 - l0/l)₊, num_springs
  std::vector<uint8_t> constrained;       // fixed or prescribed this step, num_nodes
  mesh::Points rhs, dv, residual, preconditioned, search, product;  // 3 × num_nodes each
  Eigen::Matrix<double, 9, Eigen::Dynamic> inverse_diagonal;        // 3×3 blocks, num_nodes
  // The diagonal blocks of A on massless nodes (xx, xy, xz, yy, yz, zz; zero when constrained).
  Eigen::Matrix<double, 6, Eigen::Dynamic> diagonal;
  mesh::Points preconditioned_product;  // A z, 3 × num_nodes
  // --- implicit-step scratch (mass_spring_implicit.cc) ---
  // --- end of implicit-step scratch ---
};

}  // namespace somasim::models
