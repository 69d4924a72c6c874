#include "server/models/fem/sparse_cholesky.h"

#include <cholmod.h>

#include <algorithm>
#include <stdexcept>
#include <string>

namespace somasim::models::fem {

struct SparseCholesky::Impl {
  cholmod_common common{};
  cholmod_factor* factor = nullptr;
  cholmod_dense* rhs = nullptr;
  cholmod_dense* solution = nullptr;
  cholmod_dense* work_y = nullptr;
  cholmod_dense* work_e = nullptr;
  int32_t size = 0;
  bool factorised = false;

  Impl() {
    cholmod_start(&common);
    common.print = 0;  // a pure kernel prints nothing: errors come back as statuses
    common.error_handler = nullptr;
    // Always supernodal LLᵀ: it fails on a matrix that is not positive definite (the default
    // for small matrices, simplicial LDLᵀ, would factorise an indefinite one silently) and is
    // the form the BLAS speeds up.
    common.supernodal = CHOLMOD_SUPERNODAL;
    common.final_ll = 1;
  }
  ~Impl() {
    cholmod_free_factor(&factor, &common);
    cholmod_free_dense(&rhs, &common);
    cholmod_free_dense(&solution, &common);
    cholmod_free_dense(&work_y, &common);
    cholmod_free_dense(&work_e, &common);
    cholmod_finish(&common);
  }
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;

  // A view of `matrix` as a cholmod_sparse (no copy; CHOLMOD does not write it).
  static cholmod_sparse View(const LowerCsc& matrix) {
    cholmod_sparse a{};
    a.nrow = a.ncol = static_cast<size_t>(matrix.size);
    a.nzmax = matrix.rows.size();
    a.p = const_cast<int32_t*>(matrix.col_start.data());
    a.i = const_cast<int32_t*>(matrix.rows.data());
    a.x = const_cast<double*>(matrix.values.data());
    a.stype = -1;  // symmetric, lower triangle stored
    a.itype = CHOLMOD_INT;
    a.xtype = CHOLMOD_REAL;
    a.dtype = CHOLMOD_DOUBLE;
    a.sorted = 1;
    a.packed = 1;
    return a;
  }
};

SparseCholesky::SparseCholesky() : impl_(std::make_unique<Impl>()) {}
SparseCholesky::~SparseCholesky() = default;

void SparseCholesky::Analyse(const LowerCsc& matrix) {
  cholmod_sparse a = Impl::View(matrix);
  cholmod_free_factor(&impl_->factor, &impl_->common);
  impl_->factor = cholmod_analyze(&a, &impl_->common);
  if (impl_->factor == nullptr) {
    throw std::runtime_error("cholmod_analyze failed, status " +
                             std::to_string(impl_->common.status));
  }
  impl_->size = matrix.size;
  impl_->factorised = false;
  cholmod_free_dense(&impl_->rhs, &impl_->common);
  impl_->rhs = cholmod_zeros(static_cast<size_t>(matrix.size), 1, CHOLMOD_REAL, &impl_->common);
  if (impl_->rhs == nullptr) throw std::runtime_error("cholmod: out of memory");
}

bool SparseCholesky::Factorise(const LowerCsc& matrix) {
  cholmod_sparse a = Impl::View(matrix);
  impl_->common.status = CHOLMOD_OK;  // a previous CHOLMOD_NOT_POSDEF is not sticky here
  const int ok = cholmod_factorize(&a, impl_->factor, &impl_->common);
  // minor = n on success; the column where positive definiteness failed otherwise.
  impl_->factorised = ok != 0 && impl_->common.status == CHOLMOD_OK &&
                      impl_->factor->minor == static_cast<size_t>(impl_->size);
  return impl_->factorised;
}

void SparseCholesky::Solve(const double* b, double* x) {
  auto* r = static_cast<double*>(impl_->rhs->x);
  std::copy(b, b + impl_->size, r);
  // solve2 reuses its solution and workspace once they exist: repeated solves do not allocate.
  cholmod_solve2(CHOLMOD_A, impl_->factor, impl_->rhs, nullptr, &impl_->solution, nullptr,
                 &impl_->work_y, &impl_->work_e, &impl_->common);
  const auto* s = static_cast<const double*>(impl_->solution->x);
  std::copy(s, s + impl_->size, x);
}

}  // namespace somasim::models::fem
