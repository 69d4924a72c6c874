// CHOLMOD's sparse Cholesky factorisation (SuiteSparse; supernodal, BLAS from OpenBLAS) behind
// a small RAII type: analyse a pattern once, factorise new values of that pattern many times,
// solve. The cutting issue will add CHOLMOD's in-place update/downdate here.
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

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace somasim::models::fem
