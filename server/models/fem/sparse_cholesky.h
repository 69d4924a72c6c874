// CHOLMOD's sparse Cholesky factorisation (SuiteSparse; supernodal, BLAS from OpenBLAS) behind
// a small RAII type: analyse a pattern once, factorise new values of that pattern many times,
// solve; update or downdate a factor in place (the cutting issue).
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

namespace somasim::models::fem {

// A symmetric matrix's lower triangle in compressed columns: column c's entries are
// rows[col_start[c] .. col_start[c+1]) (sorted, all >= c) with values at the same positions.
struct LowerCsc {
  int32_t size = 0;
  std::vector<int32_t> col_start;  // size + 1
  std::vector<int32_t> rows;
  std::vector<double> values;
};

class SparseCholesky {
 public:
  SparseCholesky();
  ~SparseCholesky();
  SparseCholesky(const SparseCholesky&) = delete;
  SparseCholesky& operator=(const SparseCholesky&) = delete;

  // Orders and analyses the pattern of `matrix` (its values are not read). Throws
  // std::runtime_error with CHOLMOD's status if CHOLMOD fails (out of memory).
  void Analyse(const LowerCsc& matrix);
  // Factorises `matrix`, which must have the analysed pattern. Returns false (and keeps no
  // usable factor) when the matrix is not positive definite.
  bool Factorise(const LowerCsc& matrix);
  // x = A⁻¹ b (size doubles each) with the last successful factorisation.
  void Solve(const double* b, double* x);
  // X = A⁻¹ B for `columns` right-hand sides at once (size × columns each, column-major; b and x
  // may be the same array): the
  // supernodal factor then solves with dense blocks (BLAS 3), several times faster per column
  // than Solve. Allocates (CHOLMOD's dense blocks); not for the 1 kHz path.
  void SolveMany(const double* b, double* x, int32_t columns);
  // The count × count block of A⁻¹ at rows and columns `indices` (count distinct indices in
  // 0..size-1; `block` column-major), from the last successful factorisation P A Pᵀ = L Lᵀ:
  // A⁻¹ = (L⁻¹ P)ᵀ (L⁻¹ P), so [A⁻¹]_jk = y_j · y_k with y_j = L⁻¹ P e_j, and y_j is nonzero
  // only on the elimination-tree path from row j of the permuted system to the root (Gilbert's
  // theorem): a sparse forward substitution along the union of the paths, a fraction of a
  // solve (a condensed compliance: the 3 × 3 block of one node). Throws std::out_of_range for
  // an index out of range. The first call copies the factor into simplicial form and sizes its
  // workspace (allocates); later calls as large or smaller allocate nothing.
  void InverseBlock(const int32_t* indices, int32_t count, double* block);
  // `blocks` such blocks (indices: count × blocks, block b's indices at indices + b count;
  // block b's result at out + b count²). Grouped internally in elimination order, ~48
  // right-hand sides interleaved per group: each entry of L on a group's paths is loaded once
  // for all of them, and neighbouring blocks share most of their paths (the dense top of the
  // tree). Allocates nothing once its workspace has the size a call needs.
  void InverseBlocks(const int32_t* indices, int32_t count, int32_t blocks, double* out);
  // The factorised matrix A becomes A + C Cᵀ (update) or A − C Cᵀ (downdate), in place by
  // CHOLMOD's update/downdate (Davis & Hager), for C of `rank` columns (1..16) whose nonzero
  // rows are `rows` (num_rows distinct indices in 0..size-1, at most 256); `c` holds those rows'
  // values, column-major (num_rows × rank). For the cutting issue: an element removed is a
  // rank-6 downdate of its stiffness, a relocated element a change of rank ≤ 12. The first call
  // turns the factor into a simplicial LDLᵀ (allocates; solves keep working on it); later calls
  // whose rows are already coupled in A allocate nothing. Returns false — and the factor is
  // then unusable until the next Factorise — when a downdate leaves A not positive definite
  // (or singular up to rounding: min D / max D below 1e-13).
  // Throws std::invalid_argument for sizes out of range, std::out_of_range for a bad row.
  bool UpdateDowndate(bool update, const int32_t* rows, int32_t num_rows, const double* c,
                      int32_t rank);

  // CHOLMOD's rough reciprocal condition estimate of the last factorisation, (min diag L /
  // max diag L)²: near machine epsilon for a matrix that is singular up to rounding (which a
  // Cholesky factorisation may still complete with a tiny pivot). 0 without a factorisation.
  double ReciprocalConditionEstimate();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace somasim::models::fem
