// Internal to the EFG model's translation units (efg_model.cc, efg_model_build.cc, efg_cut.cc)
// and the hybrid's: its state and the cut helpers they share. Not part of the model's
// interface.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <cstdint>
#include <memory>
#include <vector>

#include "server/models/meshless/efg_model.h"
#include "server/models/meshless/efg_system.h"
#include "server/models/meshless/low_rank_update.h"

namespace somasim::models::meshless {
namespace efg_internal {

using Eigen::Vector3d;

// The state of an EFG model: the system's (the nodal parameters, the factors, the step's
// buffers), the attachments' low-rank update of the step's factor, and the cut.
class EfgState final : public EfgSystemState {
 public:
  LowRankSlots slots;                 // capacity max_low_rank_nodes; z is 3N × 3c
  std::vector<double> unit_rhs;       // R_Iᵀ e_k, zero between uses, 3N
  std::unique_ptr<EfgCutValues> cut;  // nullptr until the first cut
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
