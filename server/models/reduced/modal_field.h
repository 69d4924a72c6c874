// The full field of a reduced model from its coordinates (issue 12): for each DOF k,
//   x_k = X_k + Σ_j ξ_j B_kj,   v_k = Σ_j ξ̇_j B_kj,
// with B (3N × n) held in single precision, column j at j · stride (stride = 3N rounded up to
// 16), the sums in double. One pass over B (1.6 MB for liver4055 at 32 modes: it stays in a 2 MB
// L2 cache where the doubles would not), reading X and writing x and v: AVX-512 32 DOFs at a time
// where the CPU has it. Positions differ from a double reconstruction by ~1e-7 of the
// displacement. Allocation-free after construction; pure.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/tissue_model.h"

namespace somasim::models::reduced {

class ModalField {
 public:
  ModalField() = default;
  explicit ModalField(const Eigen::MatrixXd& modes);  // B [-], 3N × n

  int32_t num_modes() const { return n_; }
  size_t num_dofs() const { return dofs_; }
  // x = X + B ξ and v = B ξ̇ (each num_dofs; rest X likewise; xi and rate n values).
  void Reconstruct(const double* xi, const double* rate, const double* rest, double* x,
                   double* v) const;

 private:
  std::vector<float> modes_;
  size_t stride_ = 0, dofs_ = 0;
  int32_t n_ = 0;
};

// The part of a reduced model's state both models share: the coordinates ξ (the state proper:
// positions and velocities follow from ξ, the last step's ξ and dt), their last accepted copies,
// and the field they are rebuilt into. Models derive their states from it.
class ModalState : public TissueState {
 public:
  Eigen::VectorXd xi, xi_prev, rate;  // n: ξ, the last step's ξ, ξ̇ [1/s]
  double dt = 0.0;                    // [s] the last step's
  // Sizes the coordinates (n, zero) and points at the model's field and rest positions (3N).
  void InitialiseModal(const ModalField& modal_field, const double* rest_positions);
  // x and v from ξ, ξ_prev and dt.
  void Rebuild();

 protected:
  // Copy ξ, ξ_prev and dt to and from their last accepted values (RestoreModal rebuilds x, v).
  void SaveModal();
  void RestoreModal();

 private:
  Eigen::VectorXd good_xi_, good_xi_prev_;
  double good_dt_ = 0.0;
  const ModalField* field_ = nullptr;
  const double* rest_ = nullptr;
};

// r += Bᵀ f (B 3N × n, f 3 × N [N], r n): tools load a few nodes, so blocks of 8 nodes whose 24
// values are all ±0 are skipped on an OR of their bits without the sign (a loop the compiler
// vectorises). Returns the node with the largest load, or -1 when none is loaded. Allocates
// nothing.
int32_t AddProjectedLoads(const Eigen::MatrixXd& modes, const mesh::Points& f, Eigen::VectorXd* r);

// The springs of a reduced model's step: grasps (their stiffness), prescribed nodes and fixed
// nodes the modes can move (`moves`, N flags; to where they are in `positions`), each at
// `penalty` [N/m]. With B_i node i's rows of B (3 × n): matrix = Σ k B_iᵀ B_i (n × n) and
// rhs = Σ k B_iᵀ (target − X_i) (n), both zeroed first — only when some spring acts: returns
// whether one did (matrix and rhs are then untouched). Allocates nothing.
bool SpringTerms(const Eigen::MatrixXd& modes, const mesh::Points& rest, const uint8_t* moves,
                 double penalty, const StepInputs& inputs, const mesh::Points& positions,
                 Eigen::MatrixXd* matrix, Eigen::VectorXd* rhs);

}  // namespace somasim::models::reduced
