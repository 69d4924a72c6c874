// Internal to the EFG model's translation units (efg_model.cc, efg_model_build.cc, efg_cut.cc):
// its state, Φ's LU factors and the helpers they share. Not part of the model's interface.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/efg_model.h"

namespace somasim::models::meshless {

// Φ's sparse LU (num_nodes × num_nodes) and Φᵀ's: û = Φ⁻¹ u and f = Φ⁻ᵀ f̂, for the state
// reports (Energy, InternalForces), not for the step.
struct EfgModel::Factors {
  Eigen::SparseLU<Eigen::SparseMatrix<double>> phi;
  Eigen::SparseLU<Eigen::SparseMatrix<double>> phi_transposed;
};

namespace efg_internal {

using Eigen::Vector3d;

// The state of an EFG model: the nodal parameters (the truth; positions are derived), the
// caches of the step's factorisation and of the attachments' low-rank update, and every buffer
// a step needs, sized by MakeState.
class EfgState final : public TissueState {
 public:
  mesh::Points params, vparams;                // û [m], v̂ [m/s], 3 × num_nodes
  mesh::Points good_params, good_vparams;      // the last accepted step's
  mesh::Points u, v, h, rhs, dv, work;         // scratch, 3 × num_nodes
  mesh::Points springs;                        // Σ k (target - X) per node [N], 3 × num_nodes
  mesh::Points anchor;                         // [m] where each fixed node is held
  std::vector<uint8_t> fixed_now, fixed_prev;  // num_nodes
  std::vector<double> support;                 // the supports' s_I [N/m], num_nodes: this step's
  std::vector<double> stiffness;               // all springs' s_I [N/m], num_nodes: this step's
  // This step's distinct attached nodes with a summed stiffness k > 0, in order of first
  // appearance: node and k [N/m] (num_attached of num_nodes used), and per node the summed k
  // while the step gathers them (num_nodes; zero between steps).
  std::vector<int32_t> attached_nodes;
  std::vector<double> attached_stiffness, attached_sum;
  int32_t num_attached = 0;
  std::vector<double> cached_stiffness;  // the s_I the step's factor was made with, num_nodes
  std::vector<double> cached_support;    // the s_I the static factor was made with, num_nodes
  double cached_dt = 0.0;
  bool factor_valid = false;
  bool static_current = false;   // static_factor (or its absence) matches cached_support
  bool static_valid = false;     // static_factor holds K + P_s (P_s non-zero)
  int64_t factorisations = 0;    // numeric factorisations, both factors
  std::vector<double> a_blocks;  // 9 × blocks: a system's blocks before the scalar gather
  fem::LowerCsc system;          // the model's scalar pattern, values per factorisation
  std::unique_ptr<fem::SparseCholesky> factor, static_factor;
  // The low-rank slots (capacity c = max_low_rank_nodes), valid while the step's factor holds
  // A0: slot s holds node slot_node[s] (-1: free) with Z's columns 3s..3s+2 and G's rows and
  // columns 3s..3s+2; slot_of_node maps back (num_nodes, -1: none); slot_stamp[s] the last step
  // (stamp) that used it.
  Eigen::MatrixXd z;                                            // A0⁻¹ U, 3N × 3c
  Eigen::MatrixXd gram;                                         // Uᵀ A0⁻¹ U, 3c × 3c
  std::vector<int32_t> slot_node, slot_of_node, attached_slot;  // c, num_nodes, c
  std::vector<int64_t> slot_stamp;                              // c
  int64_t stamp = 0;
  Eigen::MatrixXd small;         // I + W G W for this step's nodes (leading 3m × 3m), 3c × 3c
  Eigen::VectorXd small_rhs;     // 3c
  std::vector<double> unit_rhs;  // Φ_Iᵀ e_k, zero between uses, 3N
  // LocalStiffness: scratch (3N each) and its per-node cache (9 × num_nodes, column-major
  // 3 × 3 blocks; valid flags, num_nodes), cleared when the static factor changes.
  mutable std::vector<double> local_rhs, local_solution;
  mutable std::vector<double> local_stiffness;
  mutable std::vector<uint8_t> local_valid;
  std::unique_ptr<EfgCutValues> cut;  // nullptr until the first cut

 protected:
  void SaveGood() override {
    good_params = params;  // same sizes: no allocation
    good_vparams = vparams;
  }
  void RestoreGood() override {
    params = good_params;
    vparams = good_vparams;
  }
};

// The triangles of `cut` (3 vertices each) with a vertex-box within `radius` of x, appended
// to `out`.
inline void TrianglesNear(const std::vector<Vector3d>& triangles, size_t begin, size_t end,
                          const Vector3d& x, double radius, std::vector<Vector3d>* out) {
  for (size_t k = begin; k + 2 < end; k += 3) {
    const Vector3d lo = triangles[k].cwiseMin(triangles[k + 1]).cwiseMin(triangles[k + 2]);
    const Vector3d hi = triangles[k].cwiseMax(triangles[k + 1]).cwiseMax(triangles[k + 2]);
    if (((x - hi).array() > radius).any() || ((lo - x).array() > radius).any()) continue;
    out->insert(out->end(), {triangles[k], triangles[k + 1], triangles[k + 2]});
  }
}

// Φ (num_nodes × num_nodes) from its row pattern and values.
inline Eigen::SparseMatrix<double> PhiMatrix(int32_t n, const std::vector<int32_t>& start,
                                             const std::vector<int32_t>& node,
                                             const double* value) {
  std::vector<Eigen::Triplet<double>> triplets;
  triplets.reserve(node.size());
  for (int32_t i = 0; i < n; ++i) {
    for (int32_t k = start[size_t(i)]; k < start[size_t(i) + 1]; ++k) {
      if (value[k] != 0.0) triplets.emplace_back(i, node[size_t(k)], value[k]);
    }
  }
  Eigen::SparseMatrix<double> phi(n, n);
  phi.setFromTriplets(triplets.begin(), triplets.end());
  return phi;
}

// Solves Φ X = B (transposed: Φᵀ X = B) for B 3 × n given as n × 3; false when singular.
inline bool SolvePhi(const Eigen::SparseMatrix<double>& phi, bool transposed,
                     const Eigen::MatrixXd& b, Eigen::MatrixXd* x) {
  Eigen::SparseLU<Eigen::SparseMatrix<double>> lu;
  if (transposed) {
    const Eigen::SparseMatrix<double> phi_t = phi.transpose();
    lu.compute(phi_t);
  } else {
    lu.compute(phi);
  }
  if (lu.info() != Eigen::Success) return false;
  *x = lu.solve(b);
  return x->allFinite();
}

}  // namespace efg_internal
}  // namespace somasim::models::meshless
