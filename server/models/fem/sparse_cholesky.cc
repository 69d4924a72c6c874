#include "server/models/fem/sparse_cholesky.h"

#include <cholmod.h>

#include <algorithm>
#include <array>
#include <stdexcept>
#include <string>
#include <vector>

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
  // InverseBlock: a simplicial copy of the factor and its workspace (made on first use).
  cholmod_factor* simplicial = nullptr;
  // UpdateDowndate's C (size × 16, room for 64 × 16 entries) and the factor's inverse
  // permutation; `ldl`: the factor has been turned into a simplicial LDL'.
  cholmod_sparse* updown = nullptr;
  std::vector<int32_t> updown_inverse_perm;
  bool ldl = false;
  std::vector<int32_t> inverse_perm;  // row of the permuted system of each original index
  std::vector<uint8_t> mark;          // size: on the current path
  std::vector<int32_t> path;
  std::vector<double> path_values;  // size × right-hand sides, zero off the current path
  std::vector<int32_t> order;       // blocks in elimination order

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
    cholmod_free_factor(&simplicial, &common);
    cholmod_free_sparse(&updown, &common);
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
  cholmod_free_factor(&impl_->simplicial, &impl_->common);
  impl_->ldl = false;
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
  cholmod_free_factor(&impl_->simplicial, &impl_->common);  // InverseBlock's copy is stale
  impl_->common.status = CHOLMOD_OK;  // a previous CHOLMOD_NOT_POSDEF is not sticky here
  const int ok = cholmod_factorize(&a, impl_->factor, &impl_->common);
  // minor = n on success; the column where positive definiteness failed otherwise.
  impl_->factorised = ok != 0 && impl_->common.status == CHOLMOD_OK &&
                      impl_->factor->minor == static_cast<size_t>(impl_->size);
  return impl_->factorised;
}

bool SparseCholesky::UpdateDowndate(bool update, const int32_t* rows, int32_t num_rows,
                                    const double* c, int32_t rank) {
  Impl& s = *impl_;
  constexpr int32_t kMaxRows = 256, kMaxRank = 16;
  if (num_rows < 1 || num_rows > kMaxRows || rank < 1 || rank > kMaxRank) {
    throw std::invalid_argument("SparseCholesky::UpdateDowndate: 1..256 rows, rank 1..16");
  }
  for (int32_t i = 0; i < num_rows; ++i) {
    if (rows[i] < 0 || rows[i] >= s.size) {
      throw std::out_of_range("SparseCholesky::UpdateDowndate: row out of range");
    }
  }
  if (!s.factorised) return false;
  const auto n = static_cast<size_t>(s.size);
  if (!s.ldl) {
    if (cholmod_change_factor(CHOLMOD_REAL, /*to_ll=*/0, /*to_super=*/0, /*to_packed=*/0,
                              /*to_monotonic=*/1, s.factor, &s.common) == 0) {
      throw std::runtime_error("cholmod: out of memory converting the factor to LDL'");
    }
    const auto* perm = static_cast<const int32_t*>(s.factor->Perm);
    s.updown_inverse_perm.resize(n);
    for (size_t k = 0; k < n; ++k) {
      s.updown_inverse_perm[static_cast<size_t>(perm[k])] = static_cast<int32_t>(k);
    }
    if (s.updown == nullptr) {
      s.updown = cholmod_allocate_sparse(n, kMaxRank, kMaxRows * kMaxRank, /*sorted=*/1,
                                         /*packed=*/1, /*stype=*/0, CHOLMOD_REAL, &s.common);
      if (s.updown == nullptr) throw std::runtime_error("cholmod: out of memory");
    }
    s.ldl = true;
  }
  cholmod_free_factor(&s.simplicial, &s.common);  // InverseBlock's copy is stale
  // C in the factor's permuted order (L is the factor of P A Pᵀ): rows sorted per column.
  std::array<std::pair<int32_t, int32_t>, kMaxRows> order{};
  for (int32_t i = 0; i < num_rows; ++i) {
    order[static_cast<size_t>(i)] = {s.updown_inverse_perm[static_cast<size_t>(rows[i])], i};
  }
  std::sort(order.begin(), order.begin() + num_rows);
  cholmod_sparse& cs = *s.updown;
  auto* p = static_cast<int32_t*>(cs.p);
  auto* ri = static_cast<int32_t*>(cs.i);
  auto* x = static_cast<double*>(cs.x);
  cs.ncol = static_cast<size_t>(rank);
  int32_t nz = 0;
  for (int32_t j = 0; j < rank; ++j) {
    p[j] = nz;
    for (int32_t i = 0; i < num_rows; ++i) {
      const auto [row, source] = order[static_cast<size_t>(i)];
      ri[nz] = row;
      x[nz] =
          c[static_cast<size_t>(j) * static_cast<size_t>(num_rows) + static_cast<size_t>(source)];
      ++nz;
    }
  }
  p[rank] = nz;
  s.common.status = CHOLMOD_OK;
  const int ok = cholmod_updown(update ? 1 : 0, &cs, s.factor, &s.common);
  s.factorised = ok != 0 && s.common.status == CHOLMOD_OK;
  // A downdate to a singular matrix need not fail outright: rounding can leave a pivot a hair
  // above zero. min D / max D at rounding level (CHOLMOD's estimate, O(n)) is singular too.
  if (s.factorised && !update && cholmod_rcond(s.factor, &s.common) < 1e-13) {
    s.factorised = false;
  }
  return s.factorised;
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

void SparseCholesky::SolveMany(const double* b, double* x, int32_t columns) {
  Impl& s = *impl_;
  if (!s.factorised) throw std::runtime_error("SparseCholesky::SolveMany: no factor");
  if (columns <= 0) return;
  const auto n = static_cast<size_t>(s.size);
  constexpr int32_t kChunk = 64;  // right-hand sides per CHOLMOD call: bounded workspace
  cholmod_dense* rhs = cholmod_allocate_dense(n, static_cast<size_t>(std::min(columns, kChunk)), n,
                                              CHOLMOD_REAL, &s.common);
  if (rhs == nullptr) throw std::runtime_error("SparseCholesky::SolveMany: out of memory");
  for (int32_t first = 0; first < columns; first += kChunk) {
    const auto count = static_cast<size_t>(std::min(kChunk, columns - first));
    rhs->ncol = count;
    const double* from = b + n * static_cast<size_t>(first);
    std::copy(from, from + n * count, static_cast<double*>(rhs->x));
    cholmod_dense* solution = cholmod_solve(CHOLMOD_A, s.factor, rhs, &s.common);
    if (solution == nullptr) {
      cholmod_free_dense(&rhs, &s.common);
      throw std::runtime_error("SparseCholesky::SolveMany: CHOLMOD failed");
    }
    const auto* values = static_cast<const double*>(solution->x);
    std::copy(values, values + n * count, x + n * static_cast<size_t>(first));
    cholmod_free_dense(&solution, &s.common);
  }
  cholmod_free_dense(&rhs, &s.common);
}

void SparseCholesky::InverseBlock(const int32_t* indices, int32_t count, double* block) {
  InverseBlocks(indices, count, 1, block);
}

void SparseCholesky::InverseBlocks(const int32_t* indices, int32_t count, int32_t blocks,
                                   double* out) {
  Impl& s = *impl_;
  if (!s.factorised) throw std::runtime_error("SparseCholesky::InverseBlocks: no factor");
  if (count <= 0 || blocks <= 0) return;
  const auto n = static_cast<size_t>(s.size);
  const auto c = static_cast<size_t>(count);
  const auto num_blocks = static_cast<size_t>(blocks);
  for (size_t t = 0; t < c * num_blocks; ++t) {
    if (indices[t] < 0 || indices[t] >= s.size) {
      throw std::out_of_range("SparseCholesky::InverseBlocks: index out of range");
    }
  }
  if (s.simplicial == nullptr) {
    // A simplicial LL' copy: CSC columns with the diagonal first and sorted rows below it, so
    // that the elimination-tree parent of column j is its first off-diagonal row.
    s.simplicial = cholmod_copy_factor(s.factor, &s.common);
    if (s.simplicial == nullptr ||
        cholmod_change_factor(CHOLMOD_REAL, /*to_ll=*/1, /*to_super=*/0, /*to_packed=*/1,
                              /*to_monotonic=*/1, s.simplicial, &s.common) == 0) {
      throw std::runtime_error("cholmod: out of memory converting the factor");
    }
    const auto* perm = static_cast<const int32_t*>(s.simplicial->Perm);
    s.inverse_perm.resize(n);
    for (size_t k = 0; k < n; ++k) {
      s.inverse_perm[static_cast<size_t>(perm[k])] = static_cast<int32_t>(k);
    }
    s.mark.assign(n, 0);
    s.path.reserve(n);
    s.path_values.clear();
  }
  // Blocks are solved in groups of about 48 right-hand sides, interleaved by row, so that each
  // entry of L on the groups' paths is loaded once for all of them; grouped in elimination order
  // (by their first index's row of the permuted system), so that a group's paths share most of
  // their length and the dense top of the tree is streamed once per group.
  const size_t group = std::max<size_t>(1, 48 / c);
  const size_t w_max = c * std::min(group, num_blocks);
  if (s.path_values.size() < n * w_max) s.path_values.assign(n * w_max, 0.0);
  std::vector<int32_t>& order = s.order;  // the blocks in elimination order
  order.resize(num_blocks);
  for (size_t b = 0; b < num_blocks; ++b) order[b] = static_cast<int32_t>(b);
  const auto first_row = [&](int32_t b) {
    return s.inverse_perm[static_cast<size_t>(indices[static_cast<size_t>(b) * c])];
  };
  std::sort(order.begin(), order.end(),
            [&](int32_t a, int32_t b) { return first_row(a) < first_row(b); });
  const auto* lp = static_cast<const int32_t*>(s.simplicial->p);
  const auto* li = static_cast<const int32_t*>(s.simplicial->i);
  const auto* lnz = static_cast<const int32_t*>(s.simplicial->nz);
  const auto* lx = static_cast<const double*>(s.simplicial->x);
  double* y = s.path_values.data();
  for (size_t g0 = 0; g0 < num_blocks; g0 += group) {
    const size_t members = std::min(group, num_blocks - g0);
    const size_t w = c * members;  // right-hand sides: member m's column a is m c + a
    const auto index = [&](size_t t) {
      return indices[static_cast<size_t>(order[g0 + t / c]) * c + t % c];
    };
    // The union of the paths from each permuted index to the root, marked and listed.
    s.path.clear();
    for (size_t t = 0; t < w; ++t) {
      for (int32_t j = s.inverse_perm[static_cast<size_t>(index(t))]; j >= 0;) {
        if (s.mark[static_cast<size_t>(j)] != 0) break;  // the rest of this path is listed
        s.mark[static_cast<size_t>(j)] = 1;
        s.path.push_back(j);
        j = lnz[j] > 1 ? li[lp[j] + 1] : -1;
      }
    }
    std::sort(s.path.begin(), s.path.end());  // a child precedes its parent: ascending order
    // y (n × w row-major, zero off the path) = L⁻¹ P E by columns j of L along the path: every
    // row below the diagonal of column j is an ancestor of j, hence on the path.
    for (size_t t = 0; t < w; ++t) {
      y[static_cast<size_t>(s.inverse_perm[static_cast<size_t>(index(t))]) * w + t] = 1.0;
    }
    for (const int32_t j : s.path) {
      const auto start = static_cast<size_t>(lp[j]);
      const auto end = start + static_cast<size_t>(lnz[j]);
      double* yj = y + static_cast<size_t>(j) * w;
      const double diagonal = lx[start];
      bool any = false;
      for (size_t t = 0; t < w; ++t) {
        yj[t] /= diagonal;
        any = any || yj[t] != 0.0;
      }
      if (!any) continue;  // on other members' paths only
      for (size_t q = start + 1; q < end; ++q) {
        double* yr = y + static_cast<size_t>(li[q]) * w;
        const double l = lx[q];
        for (size_t t = 0; t < w; ++t) yr[t] -= l * yj[t];
      }
    }
    for (size_t m = 0; m < members; ++m) {
      double* block = out + static_cast<size_t>(order[g0 + m]) * c * c;
      for (size_t a = 0; a < c; ++a) {
        for (size_t e = 0; e <= a; ++e) block[a * c + e] = 0.0;
      }
      for (const int32_t j : s.path) {
        const double* yj = y + static_cast<size_t>(j) * w + m * c;
        for (size_t a = 0; a < c; ++a) {
          for (size_t e = 0; e <= a; ++e) block[a * c + e] += yj[a] * yj[e];
        }
      }
      for (size_t a = 0; a < c; ++a) {
        for (size_t e = 0; e < a; ++e) block[e * c + a] = block[a * c + e];
      }
    }
    for (const int32_t j : s.path) {  // leave the workspace clean for the next group
      s.mark[static_cast<size_t>(j)] = 0;
      std::fill(y + static_cast<size_t>(j) * w, y + static_cast<size_t>(j + 1) * w, 0.0);
    }
  }
}

double SparseCholesky::ReciprocalConditionEstimate() {
  if (!impl_->factorised) return 0.0;
  return cholmod_rcond(impl_->factor, &impl_->common);
}

}  // namespace somasim::models::fem
