#include "server/models/fem/block_sparse.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cassert>
#include <cmath>

#include "server/models/cpu_features.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#endif

namespace somasim::models::fem {

BlockSparseMatrix BlockSparseMatrix::FromTets(const mesh::Tetrahedra& tets, int32_t num_nodes,
                                              bool upper) {
  BlockSparseMatrix m;
  m.upper_ = upper;
  const auto n = static_cast<size_t>(num_nodes);
  std::vector<std::vector<int32_t>> rows(n);
  for (Eigen::Index e = 0; e < tets.cols(); ++e) {
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        if (upper && tets(b, e) < tets(a, e)) continue;
        rows[static_cast<size_t>(tets(a, e))].push_back(tets(b, e));
      }
    }
  }
  for (size_t i = 0; i < n; ++i) {
    rows[i].push_back(static_cast<int32_t>(i));  // a node in no element keeps its diagonal
    std::sort(rows[i].begin(), rows[i].end());
    rows[i].erase(std::unique(rows[i].begin(), rows[i].end()), rows[i].end());
  }
  m.row_start_.assign(n + 1, 0);
  for (size_t i = 0; i < n; ++i) {
    m.row_start_[i + 1] = m.row_start_[i] + static_cast<int32_t>(rows[i].size());
  }
  m.columns_.reserve(static_cast<size_t>(m.row_start_[n]));
  m.diagonal_.resize(n);
  for (size_t i = 0; i < n; ++i) {
    for (const int32_t j : rows[i]) {
      if (j == static_cast<int32_t>(i)) m.diagonal_[i] = static_cast<int32_t>(m.columns_.size());
      m.columns_.push_back(j);
    }
  }
  const auto find = [&m](int32_t i, int32_t j) {
    const auto begin = m.columns_.begin() + m.row_start_[static_cast<size_t>(i)];
    const auto end = m.columns_.begin() + m.row_start_[static_cast<size_t>(i) + 1];
    return static_cast<int32_t>(std::lower_bound(begin, end, j) - m.columns_.begin());
  };
  m.element_blocks_.resize(16 * static_cast<size_t>(tets.cols()));
  for (Eigen::Index e = 0; e < tets.cols(); ++e) {
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        m.element_blocks_[static_cast<size_t>(16 * e + 4 * a + b)] =
            upper && tets(b, e) < tets(a, e) ? -1 : find(tets(a, e), tets(b, e));
      }
    }
  }
  m.values_.assign(9 * m.columns_.size(), 0.0);
  return m;
}

namespace {

// y = A x, the portable path (and the reference of the vector one).
// (sx, sy, sz) += B v for a 3×3 block B (column-major) and v = v[0..2].
inline void AddBlockProduct(const double* b, const double* v, double* sx, double* sy, double* sz) {
  *sx += b[0] * v[0] + b[3] * v[1] + b[6] * v[2];
  *sy += b[1] * v[0] + b[4] * v[1] + b[7] * v[2];
  *sz += b[2] * v[0] + b[5] * v[1] + b[8] * v[2];
}

void MultiplyScalar(const int32_t* row_start, const int32_t* columns, const double* values,
                    size_t n, const double* x, double* y, const uint8_t* constrained) {
  for (size_t i = 0; i < n; ++i) {
    if (constrained != nullptr && constrained[i] != 0) {
      y[3 * i] = x[3 * i];
      y[3 * i + 1] = x[3 * i + 1];
      y[3 * i + 2] = x[3 * i + 2];
      continue;
    }
    double sx = 0.0, sy = 0.0, sz = 0.0;
    for (auto k = static_cast<size_t>(row_start[i]); k < static_cast<size_t>(row_start[i + 1]);
         ++k) {
      const auto j = static_cast<size_t>(columns[k]);
      if (constrained != nullptr && constrained[j] != 0) continue;
      AddBlockProduct(values + 9 * k, x + 3 * j, &sx, &sy, &sz);
    }
    y[3 * i] = sx;
    y[3 * i + 1] = sy;
    y[3 * i + 2] = sz;
  }
}

// y = A x for upper storage: block ij (j > i) gives y_i += B x_j and y_j += Bᵀ x_i.
void MultiplyUpperScalar(const int32_t* row_start, const int32_t* columns, const double* values,
                         size_t n, const double* x, double* y, const uint8_t* constrained) {
  std::fill(y, y + 3 * n, 0.0);
  for (size_t i = 0; i < n; ++i) {
    if (constrained != nullptr && constrained[i] != 0) continue;
    const double xi = x[3 * i], yi = x[3 * i + 1], zi = x[3 * i + 2];
    double sx = 0.0, sy = 0.0, sz = 0.0;
    for (auto k = static_cast<size_t>(row_start[i]); k < static_cast<size_t>(row_start[i + 1]);
         ++k) {
      const auto j = static_cast<size_t>(columns[k]);
      if (constrained != nullptr && constrained[j] != 0) continue;
      const double* b = values + 9 * k;  // column-major
      AddBlockProduct(b, x + 3 * j, &sx, &sy, &sz);
      if (j == i) continue;
      y[3 * j] += b[0] * xi + b[1] * yi + b[2] * zi;
      y[3 * j + 1] += b[3] * xi + b[4] * yi + b[5] * zi;
      y[3 * j + 2] += b[6] * xi + b[7] * yi + b[8] * zi;
    }
    y[3 * i] += sx;
    y[3 * i + 1] += sy;
    y[3 * i + 2] += sz;
  }
  if (constrained == nullptr) return;
  for (size_t i = 0; i < n; ++i) {
    if (constrained[i] == 0) continue;
    y[3 * i] = x[3 * i];
    y[3 * i + 1] = x[3 * i + 1];
    y[3 * i + 2] = x[3 * i + 2];
  }
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
// The same with AVX-512: a block's first eight values (column-major: columns 0, 1 and the top
// of 2) in one 512-bit load times (x0 x0 x0 x1 x1 x1 x2 x2) of x_j, one FMA, and its last value
// times x2 as a scalar FMA; two blocks at a time into independent accumulators, so that a row
// is not serialised on the FMA latency. The row's sums are then folded lane by lane. Only the
// order of the additions differs from the scalar path (rounding).
#define SOMASIM_FEM_AVX512 __attribute__((target("avx2,fma,avx512f,avx512vl")))

// acc + block k's first eight values × (x0 x0 x0 x1 x1 x1 x2 x2) of its column's x; *last +=
// its ninth value × x2.
SOMASIM_FEM_AVX512 inline void BlockProduct(const double* values, const int32_t* columns,
                                            const double* x, size_t k, __m512d* acc, double* last) {
  const __m512i spread = _mm512_set_epi64(2, 2, 1, 1, 1, 0, 0, 0);
  const double* b = values + 9 * k;
  const double* xj = x + 3 * static_cast<size_t>(columns[k]);
  const __m512d xs = _mm512_maskz_permutexvar_pd(0xFF, spread, _mm512_maskz_loadu_pd(0x7, xj));
  *last += b[8] * xj[2];
  *acc = _mm512_fmadd_pd(_mm512_loadu_pd(b), xs, *acc);
}

SOMASIM_FEM_AVX512 void MultiplyAvx512(const int32_t* row_start, const int32_t* columns,
                                       const double* values, size_t n, const double* x, double* y,
                                       const uint8_t* constrained) {
  for (size_t i = 0; i < n; ++i) {
    if (constrained != nullptr && constrained[i] != 0) {
      y[3 * i] = x[3 * i];
      y[3 * i + 1] = x[3 * i + 1];
      y[3 * i + 2] = x[3 * i + 2];
      continue;
    }
    __m512d acc0 = _mm512_setzero_pd(), acc1 = _mm512_setzero_pd();
    double last0 = 0.0, last1 = 0.0;
    const auto begin = static_cast<size_t>(row_start[i]);
    const auto end = static_cast<size_t>(row_start[i + 1]);
    size_t k = begin;
    if (constrained == nullptr) {
      for (; k + 1 < end; k += 2) {
        BlockProduct(values, columns, x, k, &acc0, &last0);
        BlockProduct(values, columns, x, k + 1, &acc1, &last1);
      }
      if (k < end) BlockProduct(values, columns, x, k, &acc0, &last0);
    } else {
      for (; k < end; ++k) {
        if (constrained[columns[k]] != 0) continue;
        if (((k - begin) & 1U) == 0) {
          BlockProduct(values, columns, x, k, &acc0, &last0);
        } else {
          BlockProduct(values, columns, x, k, &acc1, &last1);
        }
      }
    }
    alignas(64) double lanes[8];
    _mm512_store_pd(lanes, _mm512_add_pd(acc0, acc1));
    y[3 * i] = lanes[0] + lanes[3] + lanes[6];
    y[3 * i + 1] = lanes[1] + lanes[4] + lanes[7];
    y[3 * i + 2] = lanes[2] + lanes[5] + (last0 + last1);
  }
}

// MultiplyUpperScalar with the row's own sums as in MultiplyAvx512 and the transposed blocks'
// contributions (three dot products each) in scalar FMAs.
SOMASIM_FEM_AVX512 void MultiplyUpperAvx512(const int32_t* row_start, const int32_t* columns,
                                            const double* values, size_t n, const double* x,
                                            double* y, const uint8_t* constrained) {
  std::fill(y, y + 3 * n, 0.0);
  for (size_t i = 0; i < n; ++i) {
    if (constrained != nullptr && constrained[i] != 0) continue;
    const double xi = x[3 * i], yi = x[3 * i + 1], zi = x[3 * i + 2];
    __m512d acc0 = _mm512_setzero_pd(), acc1 = _mm512_setzero_pd();
    double last0 = 0.0, last1 = 0.0;
    const auto begin = static_cast<size_t>(row_start[i]);
    const auto end = static_cast<size_t>(row_start[i + 1]);
    for (size_t k = begin; k < end; ++k) {
      const auto j = static_cast<size_t>(columns[k]);
      if (constrained != nullptr && constrained[j] != 0) continue;
      if (((k - begin) & 1U) == 0) {
        BlockProduct(values, columns, x, k, &acc0, &last0);
      } else {
        BlockProduct(values, columns, x, k, &acc1, &last1);
      }
      if (j == i) continue;
      const double* b = values + 9 * k;
      y[3 * j] += b[0] * xi + b[1] * yi + b[2] * zi;
      y[3 * j + 1] += b[3] * xi + b[4] * yi + b[5] * zi;
      y[3 * j + 2] += b[6] * xi + b[7] * yi + b[8] * zi;
    }
    alignas(64) double lanes[8];
    _mm512_store_pd(lanes, _mm512_add_pd(acc0, acc1));
    y[3 * i] += lanes[0] + lanes[3] + lanes[6];
    y[3 * i + 1] += lanes[1] + lanes[4] + lanes[7];
    y[3 * i + 2] += lanes[2] + lanes[5] + (last0 + last1);
  }
  if (constrained == nullptr) return;
  for (size_t i = 0; i < n; ++i) {
    if (constrained[i] == 0) continue;
    y[3 * i] = x[3 * i];
    y[3 * i + 1] = x[3 * i + 1];
    y[3 * i + 2] = x[3 * i + 2];
  }
}
#endif

}  // namespace

void BlockSparseMatrix::Multiply(const double* x, double* y, const uint8_t* constrained) const {
  const auto n = static_cast<size_t>(num_nodes());
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
  if (CpuHasAvx512() && !force_scalar_ && upper_) {
    MultiplyUpperAvx512(row_start_.data(), columns_.data(), values_.data(), n, x, y, constrained);
    return;
  }
  if (CpuHasAvx512() && !force_scalar_) {
    MultiplyAvx512(row_start_.data(), columns_.data(), values_.data(), n, x, y, constrained);
    return;
  }
#endif
  if (upper_) {
    MultiplyUpperScalar(row_start_.data(), columns_.data(), values_.data(), n, x, y, constrained);
    return;
  }
  MultiplyScalar(row_start_.data(), columns_.data(), values_.data(), n, x, y, constrained);
}

LowerCsc BlockSparseMatrix::ScalarLower(const std::vector<int32_t>& dof, int32_t num_dofs) const {
  std::vector<int32_t> source;
  LowerCsc out = ScalarLowerPattern(dof, num_dofs, &source);
  FillScalarLower(source, &out);
  return out;
}

LowerCsc BlockSparseMatrix::ScalarLowerPattern(const std::vector<int32_t>& dof, int32_t num_dofs,
                                               std::vector<int32_t>* source) const {
  assert(!upper_);  // the scalar lower triangle is built from the full pattern
  struct Entry {
    int32_t col, row, source;
  };
  std::vector<Entry> entries;
  entries.reserve(values_.size() / 2 + values_.size() / 9);
  const auto n = static_cast<size_t>(num_nodes());
  for (size_t i = 0; i < n; ++i) {
    for (auto k = static_cast<size_t>(row_start_[i]); k < static_cast<size_t>(row_start_[i + 1]);
         ++k) {
      const auto j = static_cast<size_t>(columns_[k]);
      for (size_t c = 0; c < 3; ++c) {
        const int32_t col = dof[3 * j + c];
        if (col < 0) continue;
        for (size_t r = 0; r < 3; ++r) {
          const int32_t row = dof[3 * i + r];
          if (row < col) continue;  // lower triangle (row >= col); -1 rows drop out too
          entries.push_back({col, row, static_cast<int32_t>(9 * k + 3 * c + r)});
        }
      }
    }
  }
  std::sort(entries.begin(), entries.end(), [](const Entry& a, const Entry& b) {
    return a.col != b.col ? a.col < b.col : a.row < b.row;
  });
  LowerCsc out;
  out.size = num_dofs;
  out.col_start.assign(static_cast<size_t>(num_dofs) + 1, 0);
  out.rows.reserve(entries.size());
  out.values.assign(entries.size(), 0.0);
  source->clear();
  source->reserve(entries.size());
  for (const Entry& e : entries) {
    ++out.col_start[static_cast<size_t>(e.col) + 1];
    out.rows.push_back(e.row);
    source->push_back(e.source);
  }
  for (size_t c = 0; c < static_cast<size_t>(num_dofs); ++c)
    out.col_start[c + 1] += out.col_start[c];
  return out;
}

void BlockSparseMatrix::FillScalarLower(const std::vector<int32_t>& source, LowerCsc* lower) const {
  for (size_t k = 0; k < source.size(); ++k) {
    lower->values[k] = values_[static_cast<size_t>(source[k])];
  }
}

CgScratch::CgScratch(int32_t num_nodes)
    : residual(3 * static_cast<size_t>(num_nodes)),
      preconditioned(3 * static_cast<size_t>(num_nodes)),
      search(3 * static_cast<size_t>(num_nodes)),
      product(3 * static_cast<size_t>(num_nodes)),
      inverse_diagonal(9 * static_cast<size_t>(num_nodes)) {}

CgResult ConjugateGradients(const BlockSparseMatrix& a, const uint8_t* constrained, const double* b,
                            double* x, double tolerance, int max_iterations, CgScratch* scratch,
                            bool exactly_max_iterations) {
  const auto n = static_cast<size_t>(a.num_nodes());
  const size_t size = 3 * n;
  double* const r = scratch->residual.data();
  double* const z = scratch->preconditioned.data();
  double* const p = scratch->search.data();
  double* const q = scratch->product.data();
  double* const inv = scratch->inverse_diagonal.data();
  for (size_t i = 0; i < n; ++i) {
    Eigen::Map<Eigen::Matrix3d> out(inv + 9 * i);
    if (constrained != nullptr && constrained[i] != 0) {
      out.setIdentity();
      x[3 * i] = b[3 * i];
      x[3 * i + 1] = b[3 * i + 1];
      x[3 * i + 2] = b[3 * i + 2];
      continue;
    }
    const Eigen::Matrix3d d = a.block(a.diagonal_block(static_cast<int32_t>(i)));
    // A symmetric positive definite A has positive definite diagonal blocks; a block that is
    // not (an isolated node) falls back to the identity.
    const Eigen::LLT<Eigen::Matrix3d> llt(d);
    if (llt.info() == Eigen::Success) {
      out = llt.solve(Eigen::Matrix3d::Identity());
    } else {
      out.setIdentity();
    }
  }
  const auto precondition = [&] {
    for (size_t i = 0; i < n; ++i) {
      const double* m = inv + 9 * i;
      const double rx = r[3 * i], ry = r[3 * i + 1], rz = r[3 * i + 2];
      z[3 * i] = m[0] * rx + m[3] * ry + m[6] * rz;
      z[3 * i + 1] = m[1] * rx + m[4] * ry + m[7] * rz;
      z[3 * i + 2] = m[2] * rx + m[5] * ry + m[8] * rz;
    }
  };
  double b_norm2 = 0.0;
  for (size_t k = 0; k < size; ++k) b_norm2 += b[k] * b[k];
  a.Multiply(x, q, constrained);
  double r_norm2 = 0.0;
  for (size_t k = 0; k < size; ++k) {
    r[k] = b[k] - q[k];
    r_norm2 += r[k] * r[k];
  }
  CgResult result;
  const double threshold2 = tolerance * tolerance * b_norm2;
  const auto done = [&](int iterations) {
    if (exactly_max_iterations) return iterations >= max_iterations;
    return r_norm2 <= threshold2 || iterations >= max_iterations;
  };
  precondition();
  double rz = 0.0;
  for (size_t k = 0; k < size; ++k) {
    p[k] = z[k];
    rz += r[k] * z[k];
  }
  int it = 0;
  while (!done(it) && rz > 0.0) {
    a.Multiply(p, q, constrained);
    double pq = 0.0;
    for (size_t k = 0; k < size; ++k) pq += p[k] * q[k];
    if (!(pq > 0.0)) break;  // not positive definite along p (or p = 0): stop where we are
    const double alpha = rz / pq;
    // One pass: x, r, then z = M⁻¹ r node by node and the sums (in the order of separate loops).
    r_norm2 = 0.0;
    double rz_next = 0.0;
    for (size_t i = 0; i < n; ++i) {
      double* ri = r + 3 * i;
      for (size_t c = 0; c < 3; ++c) {
        x[3 * i + c] += alpha * p[3 * i + c];
        ri[c] -= alpha * q[3 * i + c];
        r_norm2 += ri[c] * ri[c];
      }
      const double* m = inv + 9 * i;
      z[3 * i] = m[0] * ri[0] + m[3] * ri[1] + m[6] * ri[2];
      z[3 * i + 1] = m[1] * ri[0] + m[4] * ri[1] + m[7] * ri[2];
      z[3 * i + 2] = m[2] * ri[0] + m[5] * ri[1] + m[8] * ri[2];
      rz_next += ri[0] * z[3 * i];
      rz_next += ri[1] * z[3 * i + 1];
      rz_next += ri[2] * z[3 * i + 2];
    }
    ++it;
    const double beta = rz_next / rz;
    rz = rz_next;
    for (size_t k = 0; k < size; ++k) p[k] = z[k] + beta * p[k];
  }
  result.iterations = it;
  result.relative_residual = b_norm2 > 0.0 ? std::sqrt(r_norm2 / b_norm2) : std::sqrt(r_norm2);
  result.converged = r_norm2 <= threshold2;
  return result;
}

}  // namespace somasim::models::fem
