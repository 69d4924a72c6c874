// The full field of a reduced model from its coordinates (issue 12): x = X + B ξ and v = B ξ̇,
// from a single-precision copy of the modes in 32-DOF chunks (one sequential stream; AVX-512
// where present), checked as it is written (docs/reduced.md, "The reconstruction"); and the
// helpers both reduced models share. Allocation-free after construction; pure.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/tissue_model.h"

namespace somasim::models::reduced {

class ModalField {
 public:
  static constexpr size_t kChunk = 32;  // DOFs per block of the layout

  ModalField() = default;
  explicit ModalField(const Eigen::MatrixXd& modes);  // B [-], 3N × n

  int32_t num_modes() const { return n_; }
  size_t num_dofs() const { return dofs_; }
  // x = X + B ξ and v = B ξ̇ (each num_dofs; rest X likewise; xi and rate n values), and
  // the check of what it wrote against component_limit [m/s].
  StateCheck Reconstruct(const float* xi, const float* rate, const double* rest, double* x,
                         double* v, double component_limit) const;

 private:
  std::vector<float> modes_;  // ceil(num_dofs / kChunk) × n × kChunk, zero-padded
  size_t dofs_ = 0;
  int32_t n_ = 0;
};

// The part of a reduced model's state both models share: the coordinates ξ (the state proper:
// positions and velocities follow from ξ, the last step's ξ and dt), their last accepted copies,
// and the field they are rebuilt into. Models derive their states from it.
class ModalState : public TissueState {
 public:
  Eigen::VectorXd xi, xi_prev, rate;  // n: ξ, the last step's ξ, ξ̇ [1/s]
  double dt = 0.0;                    // [s] the last step's
  // Sizes the coordinates (n, zero) and points at the model's field and rest positions (3N);
  // speed_limit [m/s] is the model's (TissueModel::speed_limit).
  void InitialiseModal(const ModalField& modal_field, const double* rest_positions,
                       double speed_limit);
  // x and v from ξ, ξ_prev and dt, checked as they are written (the model's Step relies on it:
  // TissueModel::ChecksStateItself).
  void Rebuild();

 protected:
  // Copy ξ, ξ_prev and dt to and from their last accepted values (RestoreModal rebuilds x, v).
  void SaveModal();
  void RestoreModal();

 private:
  Eigen::VectorXd good_xi_, good_xi_prev_;
  Eigen::VectorXf xi_single_, rate_single_;  // n: ξ and ξ̇ rounded for the reconstruction
  double good_dt_ = 0.0;
  double component_limit_ = 0.0;  // [m/s]
  const ModalField* field_ = nullptr;
  const double* rest_ = nullptr;
};

// The data both reduced models check first: rest positions X (3 × N, N >= 1, finite), N masses
// [kg] (each finite and > 0), modes B (3N × n, 1 <= n <= 3N, finite). Throws
// std::invalid_argument(prefix + what is wrong).
void CheckModalData(const mesh::Points& rest, const std::vector<double>& masses,
                    const Eigen::MatrixXd& modes, const std::string& prefix);

// A node's stiffness [N/m] from its compliance C [m/N] (3 × 3, symmetric): C⁻¹ in C's
// eigenbasis, each direction's stiffness capped at max_stiffness [N/m] (where the modes barely
// move the node, C⁻¹ would be huge or infinite).
Eigen::Matrix3d CappedStiffness(const Eigen::Matrix3d& compliance, double max_stiffness);

// r += Bᵀ f (B 3N × n, f 3 × N [N], r n): tools load a few nodes, so blocks of 8 nodes whose 24
// values are all ±0 are skipped on an OR of their bits without the sign (a loop the compiler
// vectorises). Returns the node with the largest load, or -1 when none is loaded. Allocates
// nothing.
int32_t AddProjectedLoads(const Eigen::MatrixXd& modes, const mesh::Points& f, Eigen::VectorXd* r);

// The springs of a reduced model's step: grasps (their stiffness), prescribed nodes and fixed
// nodes the modes can move (`moves`, N flags; to where they are in `positions`), each at
// `penalty` [N/m]. With B_i and Ψ_i node i's rows of the modes and of the test modes (3 × n;
// Galerkin: the same matrix twice): matrix = Σ k Ψ_iᵀ B_i (n × n) and
// rhs = Σ k Ψ_iᵀ (target − X_i) (n), both zeroed first — only when some spring acts: returns
// whether one did (matrix and rhs are then untouched). Allocates nothing.
bool SpringTerms(const Eigen::MatrixXd& modes, const Eigen::MatrixXd& test_modes,
                 const mesh::Points& rest, const uint8_t* moves, double penalty,
                 const StepInputs& inputs, const mesh::Points& positions, Eigen::MatrixXd* matrix,
                 Eigen::VectorXd* rhs);

}  // namespace somasim::models::reduced
