// The mutable state of a mass-spring model (internal to server/models: the explicit and the
// implicit integrators share it).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/huge_pages.h"
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
  // stiffness and damping in the explicit layout (16 per column: k of the 8 lanes [N/m], then d
  // [N s/m]; 0 in empty lanes). MakeState and Cut keep them equal to the two vectors above.
  HugePageVector<double> column_stiffness_damping;
  // Or, when the model's springs share few (k, d) pairs (MassSpringSliceLayout::material_kd), each
  // lane's pair (8 per column; 0: (0, 0), an empty lane or a cut spring). Exactly one of the
  // two is non-empty.
  HugePageVector<uint16_t> column_material;
  // The lanes of each column (1 per column, bit l: lane l) whose spring is not cut: the model's
  // (MassSpringSliceLayout::column_lanes) less those Cut has removed.
  HugePageVector<uint8_t> column_lanes;
  // The ring of the latest columns' spring forces [N] (24 per column: x, y, z of the 8 lanes).
  // Scratch, also of InternalForces on a const state.
  mutable HugePageVector<double> column_forces;
  // The AVX-512 pass's window of the start-of-step x and v of recent slices (see
  // MassSpringSliceLayout::window_slices): 6 rows of 8 W + 8 values, and 8 to align them to 64
  // bytes. Scratch, also of InternalForces on a const state.
  mutable HugePageVector<double> window;
  // --- end of explicit-step scratch ---
  // --- implicit-step scratch (mass_spring_implicit*.cc) ---
  // Per spring and one zero dummy spring past them (records of 8): w_s (x, y, z), a_s, K_s (v_i -
  // v_j) (x, y, z) and 0, the step's linearisation.
  std::vector<double> implicit_springs;
  std::vector<double> implicit_gather;  // 4 × P: records (x, y, z, 0) the sweeps read
  std::vector<double> implicit_rows;    // per row of 8 slots: w_x[8], w_y[8], w_z[8], a[8]
  // Per lane (see MassSpringModel::implicit_node_): the diagonal blocks of A and their inverses
  // (xx, xy, xz, yy, yz, zz; 6 × P), 1 on free lanes and 0 on held ones or padding (P), and the
  // solver's vectors (3 × P each: x block, y block, z block).
  std::vector<double> implicit_diagonal, implicit_inverse, implicit_keep;
  std::vector<double> implicit_rhs, implicit_dv, implicit_residual, implicit_z, implicit_search,
      implicit_product, implicit_az, implicit_dy;
  std::vector<double> implicit_dv_previous;  // the Δv of the step before the last, 3 × P
  // --- end of implicit-step scratch ---
};

}  // namespace somasim::models
