// A sparse symmetric matrix of 3×3 blocks on a tetrahedral mesh's node graph (block compressed
// rows, both blocks ij and ji stored), its pattern fixed when the model is built so that
// re-assembling it in a step allocates nothing; and conjugate gradients on it, preconditioned by
// its inverse diagonal blocks, with nodes held by Dirichlet conditions taken out. Pure.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/sparse_cholesky.h"

namespace somasim::models::fem {

class BlockSparseMatrix {
 public:
  BlockSparseMatrix() = default;
  // The pattern: row i holds a block for i and for every node sharing a tetrahedron with i.
  // With `upper`, only the blocks ij with j >= i are stored (half the memory, which is what a
  // product streams): the matrix is then symmetric by definition, block ji being block ijᵀ, and
  // element_block is -1 for a block left out. Multiply and the diagonal blocks work on both;
  // ScalarLower needs the full pattern.
  static BlockSparseMatrix FromTets(const mesh::Tetrahedra& tets, int32_t num_nodes,
                                    bool upper = false);
  bool upper() const { return upper_; }

  int32_t num_nodes() const { return static_cast<int32_t>(row_start_.size()) - 1; }
  int32_t num_blocks() const { return static_cast<int32_t>(columns_.size()); }
  // The block of corners (a, b) of element e: block index element_block(e, a, b).
  int32_t element_block(int32_t e, int a, int b) const {
    return element_blocks_[16 * static_cast<size_t>(e) + 4 * static_cast<size_t>(a) +
                           static_cast<size_t>(b)];
  }
  // All element_block values (16 × num_tets, element-major) and all block values (9 ×
  // num_blocks), for kernels that walk them in bulk.
  const int32_t* element_blocks() const { return element_blocks_.data(); }
  double* values() { return values_.data(); }
  int32_t diagonal_block(int32_t node) const { return diagonal_[static_cast<size_t>(node)]; }
  // Block k, 3×3 column-major [unit of the matrix].
  Eigen::Map<Eigen::Matrix3d> block(int32_t k) {
    return Eigen::Map<Eigen::Matrix3d>(values_.data() + 9 * static_cast<size_t>(k));
  }
  Eigen::Map<const Eigen::Matrix3d> block(int32_t k) const {
    return Eigen::Map<const Eigen::Matrix3d>(values_.data() + 9 * static_cast<size_t>(k));
  }
  void SetZero() { std::fill(values_.begin(), values_.end(), 0.0); }
  // y = A x (3 × num_nodes each, flat). With `constrained` (num_nodes, or null): rows and columns
  // of constrained nodes are replaced by the identity.
  // Takes an AVX-512 path where the CPU has it (equal to the scalar one up to rounding).
  void Multiply(const double* x, double* y, const uint8_t* constrained) const;
  // Tests: take the scalar path of Multiply even where AVX-512 is available.
  void set_force_scalar(bool scalar) { force_scalar_ = scalar; }
  // The matrix restricted to the unconstrained nodes' DOFs as a scalar lower triangle, numbered
  // by `dof` (3 × num_nodes, -1 where constrained; free DOFs 0..num_dofs-1 in node order).
  // Allocates: for static solves.
  LowerCsc ScalarLower(const std::vector<int32_t>& dof, int32_t num_dofs) const;
  // ScalarLower in two parts, so that a sequence of matrices of one pattern is converted without
  // sorting: the pattern (values left zero) and, in `source`, the index into this matrix's block
  // storage of each value (allocates), then the values (allocates nothing).
  LowerCsc ScalarLowerPattern(const std::vector<int32_t>& dof, int32_t num_dofs,
                              std::vector<int32_t>* source) const;
  void FillScalarLower(const std::vector<int32_t>& source, LowerCsc* lower) const;

 private:
  std::vector<int32_t> row_start_;       // num_nodes + 1
  std::vector<int32_t> columns_;         // num_blocks, sorted within a row
  std::vector<int32_t> diagonal_;        // num_nodes: index of block (i, i)
  std::vector<int32_t> element_blocks_;  // 16 × num_tets
  std::vector<double> values_;           // 9 × num_blocks
  // Upper storage's AVX-512 product: the transposed blocks' contributions to each node's row, in
  // the row sums' lane layout (8 per node) and the ninth value (1 per node), added when the
  // product reaches that row and zeroed there. Scratch, zero between products.
  mutable std::vector<double> transposed_lanes_, transposed_last_;
  double* TransposedLanes() const;  // transposed_lanes_ from its first 64-byte boundary
  bool force_scalar_ = false;
  bool upper_ = false;
};

// Scratch for ConjugateGradients, sized once (3 × num_nodes vectors, 9 × num_nodes inverse
// diagonal blocks).
struct CgScratch {
  explicit CgScratch(int32_t num_nodes = 0);
  std::vector<double> residual, preconditioned, search, product, inverse_diagonal;
};

struct CgResult {
  int iterations = 0;
  double relative_residual = 0.0;  // |b - A x| / |b| at the end (0 when b = 0)
  bool converged = false;
};

// Solves A x = b by block-Jacobi preconditioned CG from the initial x (a warm start), with the
// constrained nodes' x held at their b. Stops at |r| <= tolerance |b| or after max_iterations
// (with exactly_max_iterations it runs max_iterations whatever the residual, as a benchmark of
// a fixed budget does). Allocates nothing.
CgResult ConjugateGradients(const BlockSparseMatrix& a, const uint8_t* constrained, const double* b,
                            double* x, double tolerance, int max_iterations, CgScratch* scratch,
                            bool exactly_max_iterations = false);

}  // namespace somasim::models::fem
