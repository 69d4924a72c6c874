// The stiffness of a mesh being cut, kept solvable as elements go and vertices move (SPEC §5.3;
// seed 003 §4): linear elasticity (small strain) over the free degrees of freedom, and two ways
// to follow a cut without starting over —
//  (a) seed 003's: the dense inverse K⁻¹, changed by Sherman–Morrison–Woodbury: an element's
//      change K' = K + V ΔK_e Vᵀ (V the 3n × 12 selection of its corners' free DOFs) with
//      ΔK_e = W D Wᵀ (its eigen-decomposition: rank 6 for a removed element, ≤ 12 for a
//      relocated one) gives K'⁻¹ = K⁻¹ − K⁻¹ Z (D⁻¹ + Zᵀ K⁻¹ Z)⁻¹ Zᵀ K⁻¹ with Z = V W: O(n² r)
//      instead of O(n³);
//  (b) beyond the seed: a sparse CHOLMOD factor updated and downdated in place (its positive
//      part an update, its negative part a downdate).
// Pure numerics: no I/O. Every per-change buffer is sized at construction.
#pragma once

#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <Eigen/StdVector>
#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/sparse_cholesky.h"

namespace somasim::cutting {

using Matrix12d = Eigen::Matrix<double, 12, 12>;

// The small-strain stiffness of one linear tetrahedron [N/m], 12 × 12 in the corners' xyz order:
// K_ab = V (λ ∇N_a ∇N_bᵀ + μ ∇N_b ∇N_aᵀ + μ (∇N_a·∇N_b) I). `corners` 3 × 4 [m]; λ, μ [Pa]. A
// flat or inverted tetrahedron gives zero.
Matrix12d LinearTetStiffness(const Eigen::Matrix<double, 3, 4>& corners, double lambda, double mu);

// The stiffness of a tetrahedral mesh's alive elements over its free DOFs: the problem both
// update methods follow. `fixed[node]` != 0 holds a node (its DOFs are not unknowns).
class CutStiffness {
 public:
  // Throws std::invalid_argument for sizes that do not match, E <= 0 or ν outside (−1, 0.5).
  CutStiffness(const mesh::TetMesh& rest, const std::vector<uint8_t>& fixed, double youngs_modulus,
               double poisson_ratio);

  int32_t num_free() const { return num_free_; }
  int32_t num_tets() const { return static_cast<int32_t>(tets_.cols()); }
  bool alive(int32_t e) const { return alive_[static_cast<size_t>(e)] != 0; }
  // The free DOF of node's coordinate k (−1: held).
  int32_t dof(int32_t node, int k) const {
    return node_dof_[static_cast<size_t>(node)] < 0 ? -1 : node_dof_[static_cast<size_t>(node)] + k;
  }
  // Corner a (0..3) of element e.
  int32_t node(int32_t e, int a) const { return tets_(a, e); }
  // Element e's current stiffness (its corners where they are now).
  const Matrix12d& element(int32_t e) const { return ke_[static_cast<size_t>(e)]; }

  // Element e gone / its corners moved to `positions` (3 × num_nodes): the element's change
  // ΔK_e (12 × 12), which the caller passes on to the update methods; the problem records it.
  Matrix12d Remove(int32_t e);
  Matrix12d Relocate(int32_t e, const mesh::Points& positions);

  // From scratch, for references and baselines: the dense K, the lower triangle in CSC.
  Eigen::MatrixXd AssembleDense() const;
  models::fem::LowerCsc AssembleSparse() const;

 private:
  // fn(alive, row, column, value) for every free-DOF pair each element couples.
  template <typename Fn>
  void ForEachCoupling(Fn&& fn) const;

  mesh::Tetrahedra tets_;
  std::vector<int32_t> node_dof_;
  int32_t num_free_ = 0;
  double lambda_ = 0.0, mu_ = 0.0;
  std::vector<uint8_t> alive_;
  std::vector<Matrix12d, Eigen::aligned_allocator<Matrix12d>> ke_;
};

// The element's change split for a low-rank update: ΔK_e = Σ_i d_i w_i w_iᵀ over its
// eigenvalues |d_i| > 1e-12 max|d|, restricted to the free DOFs (rows: their indices).
struct LowRankChange {
  int32_t num_rows = 0;            // free DOFs among the 12
  std::array<int32_t, 12> rows{};  // their indices in the free system
  int32_t rank = 0;
  Eigen::Matrix<double, 12, 12> w;  // num_rows × rank used (column i = w_i on the rows)
  std::array<double, 12> d{};       // eigenvalues, rank used
};
LowRankChange SplitChange(const CutStiffness& problem, int32_t e, const Matrix12d& change);

// The changes of one blade step summed over the union of their free DOFs (at most kMaxRows),
// then split as one: Σ d_i w_i w_iᵀ over its eigenvalues |d_i| > 1e-12 max|d|. A step's
// relocations change many elements that share vertices: as one change their rank is the union's
// size, not the sum of the elements' ranks, and the factor is updated in far fewer passes. Sized
// at construction; Add and Split allocate nothing (Split decomposes the kMaxRows-square matrix,
// zero-padded).
class StepChange {
 public:
  static constexpr int32_t kMaxRows = 192;
  StepChange();
  void Clear();
  // Adds element e's change; false (nothing added) when its DOFs would not fit: Split and apply
  // what is there, Clear, then add again.
  bool Add(const CutStiffness& problem, int32_t e, const Matrix12d& change);
  void Split();

  int32_t num_rows() const { return num_rows_; }
  const int32_t* rows() const { return rows_.data(); }
  int32_t rank() const { return rank_; }
  // Column i of the split (num_rows values) and its eigenvalue.
  const double* w(int32_t i) const { return w_.col(i).data(); }
  double d(int32_t i) const { return d_[i]; }

 private:
  int32_t num_rows_ = 0;
  std::array<int32_t, kMaxRows> rows_{};
  Eigen::MatrixXd sum_;  // kMaxRows², the summed change over rows_
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eigen_;
  Eigen::MatrixXd w_;  // kMaxRows², the kept eigenvectors first
  Eigen::VectorXd d_;
  int32_t rank_ = 0;
};

// (a) Seed 003: the dense inverse, changed by Sherman–Morrison–Woodbury.
class DenseInverseStiffness {
 public:
  // Inverts the problem's K (dense Cholesky). Throws std::runtime_error when K is singular
  // (nothing held).
  explicit DenseInverseStiffness(const CutStiffness& problem);
  // K⁻¹ after K += Σ d_i z_i z_iᵀ. Allocates nothing.
  void Apply(const LowRankChange& change);
  const Eigen::MatrixXd& inverse() const { return inverse_; }
  void Solve(const Eigen::VectorXd& f, Eigen::VectorXd* u) const { u->noalias() = inverse_ * f; }

 private:
  Eigen::MatrixXd inverse_;
  Eigen::Matrix<double, Eigen::Dynamic, 12> kz_;  // K⁻¹ Z
  Eigen::Matrix<double, Eigen::Dynamic, 12> scratch_;
};

// (b) A sparse CHOLMOD factor updated and downdated in place.
class SparseFactorStiffness {
 public:
  explicit SparseFactorStiffness(const CutStiffness& problem);
  // Returns false when the factor became unusable (a change left K not positive definite).
  bool Apply(const LowRankChange& change);
  // A step's summed change (after Split), in passes of 16 columns. Allocates nothing.
  bool Apply(const StepChange& change);
  void Solve(const Eigen::VectorXd& f, Eigen::VectorXd* u);

 private:
  models::fem::SparseCholesky factor_;
  Eigen::Matrix<double, 12, 12> c_;  // scaled columns √|d_i| w_i
  std::vector<double> packed_;       // StepChange::kMaxRows × 16
};

}  // namespace somasim::cutting
