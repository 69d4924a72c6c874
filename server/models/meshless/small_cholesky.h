// A small dense Cholesky factorisation by hand, on caller-owned storage: the 3m × 3m systems of
// the attachments' low-rank (Woodbury) updates in the EFG models. By hand rather than Eigen's
// blocked LLT, whose products may take heap workspace: these run on the 1 kHz path and must not
// allocate.
#pragma once

#include <cmath>
#include <cstddef>

namespace somasim::models::meshless {

// In-place Cholesky L Lᵀ of the n × n lower triangle of a column-major matrix `a` (leading
// dimension ld), left-looking by columns (contiguous inner loops): the 3m × 3m system of the
// attachments' update. By hand rather than Eigen's blocked LLT, whose products may take heap
// workspace. False when a pivot is not positive.
inline bool CholeskyInPlace(double* a, int n, int ld) {
  for (int j = 0; j < n; ++j) {
    double* col_j = a + static_cast<ptrdiff_t>(j) * ld;
    for (int k = 0; k < j; ++k) {
      const double* col_k = a + static_cast<ptrdiff_t>(k) * ld;
      const double l_jk = col_k[j];
      for (int i = j; i < n; ++i) col_j[i] -= l_jk * col_k[i];
    }
    if (!(col_j[j] > 0.0)) return false;
    const double pivot = std::sqrt(col_j[j]);
    col_j[j] = pivot;
    for (int i = j + 1; i < n; ++i) col_j[i] /= pivot;
  }
  return true;
}

// x = (L Lᵀ)⁻¹ x in place, L from CholeskyInPlace.
inline void CholeskySolveInPlace(const double* l, int n, int ld, double* x) {
  for (int j = 0; j < n; ++j) {  // L y = x, by columns
    const double* col = l + static_cast<ptrdiff_t>(j) * ld;
    x[j] /= col[j];
    for (int i = j + 1; i < n; ++i) x[i] -= col[i] * x[j];
  }
  for (int j = n - 1; j >= 0; --j) {  // Lᵀ x = y, by rows of Lᵀ (columns of L)
    const double* col = l + static_cast<ptrdiff_t>(j) * ld;
    double sum = x[j];
    for (int i = j + 1; i < n; ++i) sum -= col[i] * x[i];
    x[j] = sum / col[j];
  }
}

}  // namespace somasim::models::meshless
