// The tools' springs as a low-rank (Sherman–Morrison–Woodbury) update of a step's factor, shared
// by EfgModel and EfgHybridModel: the distinct attached nodes, their cached columns Z = A0⁻¹ U in
// least-recently-used slots, and the 3m × 3m correction (docs/models.md, "The EFG model in
// detail"). Internal to the meshless models; allocation-free once sized. Pure: no I/O.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <span>
#include <vector>

#include "server/models/meshless/small_cholesky.h"
#include "server/models/tissue_model.h"

namespace somasim::models::meshless {

struct LowRankSlots {
  // The slots (capacity c), valid while the factor holds A0: slot s holds node slot_node[s]
  // (-1: free) with Z's columns 3s..3s+2 and G's rows and columns 3s..3s+2; slot_of_node maps
  // back (num_nodes, -1: none); slot_stamp[s] the last step (stamp) that used it.
  Eigen::MatrixXd z;                  // A0⁻¹ U, unknowns × 3c (sized by the caller)
  Eigen::MatrixXd gram;               // Uᵀ A0⁻¹ U, 3c × 3c
  std::vector<int32_t> slot_node;     // c
  std::vector<int32_t> slot_of_node;  // num_nodes
  std::vector<int64_t> slot_stamp;    // c
  int64_t stamp = 0;
  Eigen::MatrixXd small;      // I + W G W for this step's nodes (leading 3m × 3m), 3c × 3c
  Eigen::VectorXd small_rhs;  // 3c: first Uᵀ x0 (3 per attached node), then the solution
  // This step's distinct attached nodes with a summed stiffness k > 0, in order of first
  // appearance: node and k [N/m] (num_attached used of their capacity), and per node the
  // summed k while a step gathers them (num_nodes; zero between steps).
  std::vector<int32_t> attached_nodes, attached_slot;  // capacity, c
  std::vector<double> attached_stiffness;              // capacity
  std::vector<double> attached_sum;                    // num_nodes
  int32_t num_attached = 0;

  // Sizes everything but z for c slots, num_nodes nodes and `capacity` attached nodes a step
  // may list (allocates).
  void Size(int32_t slots, int32_t num_nodes, int32_t capacity) {
    const auto c = static_cast<Eigen::Index>(slots);
    gram = Eigen::MatrixXd::Zero(3 * c, 3 * c);
    small = Eigen::MatrixXd::Zero(3 * c, 3 * c);
    small_rhs = Eigen::VectorXd::Zero(3 * c);
    slot_node.assign(size_t(slots), -1);
    slot_of_node.assign(size_t(num_nodes), -1);
    slot_stamp.assign(size_t(slots), -1);
    attached_nodes.assign(size_t(capacity), -1);
    attached_slot.assign(size_t(slots), -1);
    attached_stiffness.assign(size_t(capacity), 0.0);
    attached_sum.assign(size_t(num_nodes), 0.0);
  }

  // The distinct attached nodes of a step with their summed stiffness (each node once, in
  // order of first appearance; a node whose springs sum to zero is not attached). False when
  // more than the capacity are attached (those beyond it are left out).
  bool Gather(std::span<const Attachment> attachments) {
    for (const Attachment& grasp : attachments) {
      attached_sum[size_t(grasp.node)] += grasp.stiffness;
    }
    num_attached = 0;
    bool fits = true;
    for (const Attachment& grasp : attachments) {  // in order; each node once
      const auto i = size_t(grasp.node);
      const double k = attached_sum[i];
      if (k > 0.0) {
        if (size_t(num_attached) < attached_nodes.size()) {
          attached_nodes[size_t(num_attached)] = grasp.node;
          attached_stiffness[size_t(num_attached)] = k;
          ++num_attached;
        } else {
          fits = false;
        }
      }
      attached_sum[i] = 0.0;  // marks the node taken and leaves the sums zero
    }
    return fits;
  }

  // Frees every slot: Z = A0⁻¹ U belongs to a factor that has just changed.
  void FreeAll() {
    for (int32_t& node : slot_node) {
      if (node >= 0) slot_of_node[size_t(node)] = -1;
      node = -1;
    }
    std::fill(slot_stamp.begin(), slot_stamp.end(), int64_t{-1});
  }

  // The attached nodes' slots: those already cached are kept (stamped), each new node takes the
  // least recently used slot, which no node of this step holds (num_attached <= slots), and
  // fill(slot, node) computes its Z columns and G's row and column (slot_node and
  // slot_of_node already name the node).
  template <class Fill>
  void Assign(const Fill& fill) {
    ++stamp;
    const auto m = size_t(num_attached);
    for (size_t j = 0; j < m; ++j) {
      const int32_t slot = slot_of_node[size_t(attached_nodes[j])];
      attached_slot[j] = slot;
      if (slot >= 0) slot_stamp[size_t(slot)] = stamp;
    }
    for (size_t j = 0; j < m; ++j) {
      if (attached_slot[j] >= 0) continue;
      const auto oldest = std::min_element(slot_stamp.begin(), slot_stamp.end());
      const auto slot = static_cast<int32_t>(oldest - slot_stamp.begin());
      if (slot_node[size_t(slot)] >= 0) slot_of_node[size_t(slot_node[size_t(slot)])] = -1;
      slot_node[size_t(slot)] = attached_nodes[j];
      slot_of_node[size_t(attached_nodes[j])] = slot;
      fill(slot, attached_nodes[j]);
      slot_stamp[size_t(slot)] = stamp;
      attached_slot[j] = slot;
    }
  }

  // x = A⁻¹ b from x = x0 = A0⁻¹ b, with Uᵀ x0 in small_rhs (3 per attached node, in order).
  // False when the 3m × 3m system is not positive definite (cannot happen but by rounding: the
  // step is then rejected).
  bool Correct(double dt, Eigen::Ref<Eigen::VectorXd> x) {
    const auto m = static_cast<Eigen::Index>(num_attached);
    const Eigen::Index r = 3 * m;
    // W Uᵀ x0 (W = S^½: dt √k_j per node) and the lower triangle of I + W G W.
    for (Eigen::Index i = 0; i < m; ++i) {
      const double wi = dt * std::sqrt(attached_stiffness[size_t(i)]);
      small_rhs.segment<3>(3 * i) *= wi;
      const auto si = static_cast<Eigen::Index>(attached_slot[size_t(i)]);
      for (Eigen::Index j = 0; j <= i; ++j) {
        const double wj = dt * std::sqrt(attached_stiffness[size_t(j)]);
        const auto sj = static_cast<Eigen::Index>(attached_slot[size_t(j)]);
        small.block<3, 3>(3 * i, 3 * j) = (wi * wj) * gram.block<3, 3>(3 * si, 3 * sj);
      }
      small.block<3, 3>(3 * i, 3 * i).diagonal().array() += 1.0;
    }
    const auto ld = static_cast<int>(small.rows());
    if (!CholeskyInPlace(small.data(), static_cast<int>(r), ld)) return false;
    CholeskySolveInPlace(small.data(), static_cast<int>(r), ld, small_rhs.data());
    // x = x0 - Σ_j Z_j (W y)_j.
    for (Eigen::Index j = 0; j < m; ++j) {
      const double wj = dt * std::sqrt(attached_stiffness[size_t(j)]);
      const auto sj = static_cast<Eigen::Index>(attached_slot[size_t(j)]);
      const Eigen::Vector3d y = wj * small_rhs.segment<3>(3 * j);
      x.noalias() -= z.middleCols<3>(3 * sj) * y;
    }
    return true;
  }
};

}  // namespace somasim::models::meshless
