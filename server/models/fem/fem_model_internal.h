// What FemModel's source files share and its users do not see: the state class, the refusal of
// bad input, and the warped stiffness blocks of one element (the step's portable element pass
// and AssembleWarped write them alike).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/block_sparse.h"
#include "server/models/tissue_model.h"

namespace somasim::models::fem::internal {

[[noreturn]] inline void Refuse(const std::string& what) {
  throw std::invalid_argument("fem: " + what);
}

// The state of a FEM model: positions and velocities plus a step's matrix and scratch, all
// sized by MakeState.
class FemState final : public TissueState {
 public:
  BlockSparseMatrix matrix;  // A = (1 + dt α) M + (dt² + dt β) K
  CgScratch cg;
  std::vector<double> rotations;  // 9 × num_tets, column-major R per element
  // 4 × num_tets: R per element as (w, x, y, z), the next step's warm starts (they change its
  // result by rounding only, but a rollback restores them too, so that replays are bit-exact).
  std::vector<double> quaternions, good_quaternions;
  mesh::Points forces, rhs, dv, temp;  // 3 × num_nodes
  mesh::Points good_dv;  // dv of the last accepted step: CG's warm start, restored on rollback
  std::vector<uint8_t> constrained;  // num_nodes
  double last_cg_residual = 0.0;     // |r| / |b| of the last step's solve
  // QLV internal variables h_k (9 × num_prony × num_tets, element-major), the elastic stress of
  // the last accepted step S^e (9 × num_tets), a step's offset (9 × num_tets), and the copies
  // a rejected step restores.
  std::vector<double> history, elastic_last, offset, good_history, good_elastic_last;
  // The rest geometry the state is computed with (FemModel::ApplyCut): a copy of the model's at
  // first, then cut. rest 3 × num_nodes [m], gradients 3 × 4·num_tets [1/m], volumes num_tets
  // [m³] (0 for an element cut away).
  mesh::Points rest;
  Eigen::Matrix<double, 3, Eigen::Dynamic> gradients;
  std::vector<double> volumes;
  int32_t num_cut = 0;     // elements cut away
  mesh::Points rest_move;  // ApplyCut's scratch: per moved node its rest move, 3 × num_nodes

 protected:
  void SaveGood() override {
    good_dv = dv;  // same size: no allocation
    std::copy(quaternions.begin(), quaternions.end(), good_quaternions.begin());
    std::copy(history.begin(), history.end(), good_history.begin());
    std::copy(elastic_last.begin(), elastic_last.end(), good_elastic_last.begin());
  }
  void RestoreGood() override {
    dv = good_dv;
    std::copy(good_quaternions.begin(), good_quaternions.end(), quaternions.begin());
    std::copy(good_history.begin(), good_history.end(), history.begin());
    std::copy(good_elastic_last.begin(), good_elastic_last.end(), elastic_last.begin());
  }
};

// Adds one element's warped stiffness blocks R K_ab Rᵀ = V (λ r_a r_bᵀ + μ r_b r_aᵀ +
// μ (∇N_a·∇N_b) I), from its rotated gradients r_a = R ∇N_a (RestBlock's formula in the rotated
// frame; r_a·r_b = ∇N_a·∇N_b): 16 outer products instead of 32 3×3 matrix products. `blocks` are
// the element's 16 block indices (4 a + b; < 0 where upper storage keeps the transpose of (b, a)
// instead), `grad` its ∇N_a (3 each), cl = V k λ and cm = V k μ with the stiffness scale k;
// block (a, b) is added at values + 9 · blocks[4 a + b] (column-major).
inline void AddWarpedElementBlocks(const int32_t* blocks, const double* grad, const double r[4][3],
                                   double cl, double cm, double* values) {
  for (int a = 0; a < 4; ++a) {
    for (int b = 0; b < 4; ++b) {
      const int32_t block = blocks[4 * a + b];
      if (block < 0) continue;  // upper storage: the transpose of (b, a)
      const double* ga = grad + 3 * a;
      const double* gb = grad + 3 * b;
      const double diagonal = cm * (ga[0] * gb[0] + ga[1] * gb[1] + ga[2] * gb[2]);
      double* out = values + 9 * static_cast<size_t>(block);
      for (int c = 0; c < 3; ++c) {
        for (int i = 0; i < 3; ++i) {
          out[3 * c + i] += cl * r[a][i] * r[b][c] + cm * r[b][i] * r[a][c];
        }
        out[4 * c] += diagonal;
      }
    }
  }
}

}  // namespace somasim::models::fem::internal
