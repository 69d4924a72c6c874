// What the EFG models share besides their system (efg_system.h): the parameter checks, the
// Gauss rules, the scalar lower CSC pattern of their 3N × 3N block systems, the penalty's scale,
// the node-value matrix's LU factors (build; defined in efg_model_build.cc where not inline), and
// the supports as penalty springs (static solves and each step). Pure: no I/O.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/tissue_model.h"

namespace somasim::models::meshless {

// From the lower block pattern (column c's blocks are block_row[block_start[c] ..
// block_start[c+1]), sorted rows >= c, N columns): the scalar lower CSC pattern (col_start, 3N + 1
// entries; rows) and per scalar entry its source in the column-major block storage
// (9 × block + r + 3 c).
inline void ScalarLowerPattern(const std::vector<int64_t>& block_start,
                               const std::vector<int32_t>& block_row,
                               std::vector<int32_t>* col_start, std::vector<int32_t>* rows,
                               std::vector<int64_t>* source) {
  const auto n = static_cast<int32_t>(block_start.size()) - 1;
  col_start->assign(3 * size_t(n) + 1, 0);
  rows->clear();
  source->clear();
  for (int32_t c = 0; c < n; ++c) {
    const int64_t begin = block_start[size_t(c)], end = block_start[size_t(c) + 1];
    for (int cc = 0; cc < 3; ++cc) {
      for (int64_t slot = begin; slot < end; ++slot) {
        const int32_t row = block_row[size_t(slot)];
        for (int r = row == c ? cc : 0; r < 3; ++r) {
          rows->push_back(3 * row + r);
          source->push_back(9 * slot + r + 3 * cc);
        }
      }
      (*col_start)[3 * size_t(c) + size_t(cc) + 1] = static_cast<int32_t>(rows->size());
    }
  }
}

// Refuses EFG parameters out of range: std::invalid_argument(prefix + the field and the rule).
void CheckEfgParameters(const EfgParameters& p, const std::string& prefix);

// A symmetric Gauss rule on a tetrahedron: barycentric points and weights summing to 1
// (multiply by the volume). 4 points: degree 2; 14 points: degree 5 (Walkington).
struct TetRule {
  std::vector<Eigen::Vector4d> points;
  std::vector<double> weights;
};
TetRule MakeTetRule(int points);

// The largest diagonal entry of the N diagonal blocks (each column's first block; 3 × 3,
// column-major in `blocks`) [N/m]: the scale of the supports' penalty.
inline double MaxBlockDiagonal(const std::vector<int64_t>& block_start,
                               const std::vector<double>& blocks) {
  double max_diagonal = 0.0;
  for (size_t c = 0; c + 1 < block_start.size(); ++c) {
    const Eigen::Map<const Eigen::Matrix3d> block(blocks.data() + 9 * block_start[c]);
    max_diagonal = std::max(max_diagonal, block.diagonal().maxCoeff());
  }
  return max_diagonal;
}

// LU factors of the N × N node-value matrix (row I: φ_J(X_I) for its CSR entries start[I] ..
// start[I+1] of cols and values) and of its transpose, for u = Φ û and back. False when
// either is singular (nodes too close together).
inline bool FactorNodeValueMatrix(const std::vector<int32_t>& start,
                                  const std::vector<int32_t>& cols,
                                  const std::vector<double>& values,
                                  Eigen::SparseLU<Eigen::SparseMatrix<double>>* lu,
                                  Eigen::SparseLU<Eigen::SparseMatrix<double>>* lu_transposed) {
  const auto n = static_cast<Eigen::Index>(start.size()) - 1;
  std::vector<Eigen::Triplet<double>> triplets;
  triplets.reserve(values.size());
  for (Eigen::Index i = 0; i < n; ++i) {
    for (int32_t k = start[size_t(i)]; k < start[size_t(i) + 1]; ++k) {
      triplets.emplace_back(i, cols[size_t(k)], values[size_t(k)]);
    }
  }
  Eigen::SparseMatrix<double> phi(n, n);
  phi.setFromTriplets(triplets.begin(), triplets.end());
  lu->compute(phi);
  const Eigen::SparseMatrix<double> phi_t = phi.transpose();
  lu_transposed->compute(phi_t);
  return lu->info() == Eigen::Success && lu_transposed->info() == Eigen::Success;
}

// The supports of static loads as penalty springs κ at the node points: each fixed node's (held
// at rest) and each prescribed node's, summed into `s` [N/m] (num_nodes), the prescribed ones'
// κ (target − X_I) [N] added to `h` (3 × num_nodes).
inline void AddStaticSupports(const EfgStaticLoads& loads, const mesh::Points& rest, double penalty,
                              std::vector<double>* s, mesh::Points* h) {
  for (const int32_t node : loads.fixed_nodes) (*s)[size_t(node)] += penalty;
  for (size_t k = 0; k < loads.prescribed_nodes.size(); ++k) {
    const int32_t node = loads.prescribed_nodes[k];
    (*s)[size_t(node)] += penalty;
    h->col(node) +=
        penalty * (loads.prescribed_positions->col(static_cast<Eigen::Index>(k)) - rest.col(node));
  }
}

// A step's supports, node by node: add(node, target) for every fixed node (held where it was
// when it became fixed: `anchor`, kept across steps; `fixed_now` / `fixed_prev` mark the fixed
// nodes of this step and the last, swapped here; a node listed twice counts once) and every
// prescribed node (its prescribed position). `State` has those members and `positions`.
template <class State, class Add>
void ForEachSupport(const StepInputs& inputs, State* st, const Add& add) {
  std::fill(st->fixed_now.begin(), st->fixed_now.end(), uint8_t{0});
  for (const int32_t node : inputs.fixed_nodes) {
    const auto i = size_t(node);
    if (st->fixed_now[i] != 0) continue;  // listed twice
    st->fixed_now[i] = 1;
    if (st->fixed_prev[i] == 0) st->anchor.col(node) = st->positions.col(node);
    add(node, st->anchor.col(node));
  }
  std::swap(st->fixed_now, st->fixed_prev);  // no allocation
  for (size_t k = 0; k < inputs.prescribed_nodes.size(); ++k) {
    add(inputs.prescribed_nodes[k], inputs.prescribed_positions->col(static_cast<Eigen::Index>(k)));
  }
}

// The supports as penalty springs at the node points (the first thing the EFG models' steps
// do): per node the supports' summed stiffness s_I [N/m] (`support`, num_nodes) and
// Σ k (target − X_I) [N] (`springs`, 3 × num_nodes), both zeroed first (grasps are the
// caller's to add).
template <class State>
void GatherSupportSprings(const StepInputs& inputs, const mesh::Points& rest, double penalty,
                          State* st) {
  std::fill(st->support.begin(), st->support.end(), 0.0);
  st->springs.setZero();
  ForEachSupport(inputs, st, [st, penalty, &rest](int32_t node, const auto& target) {
    st->support[size_t(node)] += penalty;
    st->springs.col(node) += penalty * (target - rest.col(node));
  });
}

}  // namespace somasim::models::meshless
