// Internal to EfgHybridModel's translation units (efg_hybrid_model.cc, efg_hybrid_region.cc,
// efg_hybrid_step.cc): its state and the helpers they share. Not part of the model's interface.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/meshless/low_rank_update.h"
#include "server/models/tissue_model.h"

namespace somasim::models::meshless::hybrid_internal {

using Eigen::Index;
using Eigen::Matrix3d;
using Eigen::MatrixXd;
using Eigen::Vector3d;
using Eigen::VectorXd;
using RowMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// The extension's shift without supports, K̃ = K + σ M̂ [1/s²] (a basis only).
constexpr double kFreeShift = 1.0;

// The hybrid's state: the surgical region's parameters q and velocities, the partition's dense
// matrices, the static factor of K̃ and every buffer a step needs. Buffers whose size depends
// on the region (k) are sized by each partition; the rest by MakeState.
class HybridState final : public TissueState {
 public:
  // --- the partition (sized by Partition) ---
  bool partitioned = false;
  Vector3d centre = Vector3d::Zero();
  std::vector<int32_t> kept;         // the region's nodes, nearest the centre first (k)
  std::vector<int32_t> kept_of;      // num_nodes: index into kept, -1 for far nodes
  std::vector<uint8_t> touches_far;  // num_nodes: node's MLS row holds a far parameter
  MatrixXd t;                        // T [-], 3N × 3k: û = T q
  RowMatrix d;                       // D = Φ T [-], 3N × 3k, by rows: node I's rows 3I..3I+2
  MatrixXd s_inv;                    // S⁻¹ = (Tᵀ K̃ T)⁻¹ [m/N], 3k × 3k
  MatrixXd m_r, k_r, p_r;            // M_r [kg], K_r and P_r [N/m], 3k × 3k
  MatrixXd g_r;                      // Dᵀ (m ⊗ e_c) [kg], 3k × 3
  MatrixXd offset_g;                 // physical far response per unit gravity [m/(m/s²)], 3N × 3
  MatrixXd param_offset_g;           // the same in parameters, 3N × 3
  VectorXd q, vq, good_q, good_vq;   // [m], [m/s], 3k
  VectorXd b, work;                  // 3k
  MatrixXd a;                        // A, 3k × 3k
  Eigen::LLT<MatrixXd> a_llt;
  double cached_dt = 0.0;
  bool a_valid = false;
  // --- the tool springs' low-rank update of A's factor (capacity c; z is 3k × 3c, sized by
  // Partition) ---
  LowRankSlots slots;
  // --- supports (sized by MakeState) ---
  std::vector<double> support, cached_support;  // s_I [N/m], num_nodes
  mesh::Points support_target;                  // Σ s (target - X) per node [N], 3 × num_nodes
  mesh::Points anchor;                          // [m] where each fixed node is held
  std::vector<uint8_t> fixed_now, fixed_prev;   // num_nodes
  std::vector<int32_t> support_nodes;           // this step's supported nodes, distinct
  std::vector<uint8_t> support_listed;          // num_nodes
  bool has_supports = false;
  // The shift σ of K̃ = K + P_s + σ M̂: 0 with supports, kFreeShift for a free body or when a cut
  // has severed a piece without supports (K + P_s singular); statics are exact only for 0.
  double shift = 0.0;
  bool static_valid = false;  // static_factor holds K̃ for cached_support
  fem::LowerCsc system;
  std::vector<double> blocks;
  std::unique_ptr<fem::SparseCholesky> static_factor;
  // --- loads reaching far parameters ---
  mesh::Points far_loads, cached_far_loads;        // [N], 3 × num_nodes
  mesh::Points offset_l, param_offset_l;           // their far response [m], 3 × num_nodes
  mesh::Points full_rhs, full_solution, full_phi;  // scratch, 3 × num_nodes
  // --- outputs and caches ---
  mesh::Points offsets;  // this step's physical particular displacement [m], 3 × num_nodes
  Vector3d gravity = Vector3d::Zero();  // [m/s²] of the last step or static solve
  MatrixXd local_work;                  // S⁻¹ D_Iᵀ, 3k × 3 (LocalStiffness)
  std::vector<double> local_stiffness;  // 9 × num_nodes
  std::vector<uint8_t> local_valid;     // num_nodes
  int64_t partitions = 0, factorisations = 0, far_solves = 0, adaptations = 0;
  // Adaptivity: nodes the intensity added to the region (num_nodes), steps since the last one.
  std::vector<uint8_t> refined;
  int32_t steps_since_adapt = 0;
  // Cutting: the cut EFG values (nullptr before the first cut); a cut since the last step (the
  // next step factorises K̃ and partitions again) and the field it carries over (parameters of
  // the physical field under the cut Φ, 3 × num_nodes each) when `carry`.
  std::unique_ptr<EfgCutValues> cut;
  bool cut_pending = false, carry = false;
  mesh::Points carried_params, carried_vparams;

 protected:
  void SaveGood() override {
    good_q = q;  // same size: no allocation
    good_vq = vq;
  }
  void RestoreGood() override {
    q = good_q;
    vq = good_vq;
  }
};

// Whether node I's load (3 values) is not all zero.
inline bool NonZero(const double* f) { return f[0] != 0.0 || f[1] != 0.0 || f[2] != 0.0; }

}  // namespace somasim::models::meshless::hybrid_internal
