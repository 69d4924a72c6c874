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
  if (upper) {
    m.transposed_lanes_.assign(8 * n + 8, 0.0);  // + 8: room to start on a 64-byte boundary
    m.transposed_last_.assign(n, 0.0);
  }
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

// MultiplyUpperScalar with the row's own sums as in MultiplyAvx512. The transposed block's
// contribution Bᵀ x_i to row j > i is accumulated in the same lane layout: B's first eight
// values permuted to (b0 b3 b6 b1 b4 b7 b2 b5) times (x_i x_i x_i y_i y_i y_i z_i z_i) into row
// j's eight lanes `lanes` (8 × n), and b8 z_i into `last` (n); row j starts its sums from them
// (every contribution to row j comes from a row above it) and zeroes them for the next product.
// Every row is written whole, so y needs no clearing.
// One off-diagonal block k = (i, j) of MultiplyUpperAvx512: its row product into (acc, last),
// its transposed product into row j's lanes.
SOMASIM_FEM_AVX512 inline void UpperBlock(const double* values, const int32_t* columns,
                                          const double* x, size_t k, __m512d xi, double zi,
                                          __m512d* acc, double* last, double* lanes_of,
                                          double* last_of) {
  const __m512i spread = _mm512_set_epi64(2, 2, 1, 1, 1, 0, 0, 0);
  const __m512i transpose = _mm512_set_epi64(5, 2, 7, 4, 1, 6, 3, 0);
  const auto j = static_cast<size_t>(columns[k]);
  const double* b = values + 9 * k;
  const __m512d block = _mm512_loadu_pd(b);
  const double* xj = x + 3 * j;
  *acc = _mm512_fmadd_pd(
      block, _mm512_maskz_permutexvar_pd(0xFF, spread, _mm512_maskz_loadu_pd(0x7, xj)), *acc);
  const double b8 = b[8];
  *last += b8 * xj[2];
  double* const their_lanes = lanes_of + 8 * j;
  _mm512_store_pd(their_lanes, _mm512_fmadd_pd(_mm512_maskz_permutexvar_pd(0xFF, transpose, block),
                                               xi, _mm512_load_pd(their_lanes)));
  last_of[j] += b8 * zi;
}

// MultiplyUpperScalar with the row's own sums as in MultiplyAvx512. The transposed block's
// contribution Bᵀ x_i to row j > i is accumulated in the same lane layout: B's first eight
// values permuted to (b0 b3 b6 b1 b4 b7 b2 b5) times (x_i x_i x_i y_i y_i y_i z_i z_i) into row
// j's eight lanes (`lanes_of`, 8 × n, 64-byte aligned), and b8 z_i into `last_of` (n); row j
// starts its sums from them (every contribution to row j comes from a row above it) and zeroes
// them for the next product. Every row is written whole, so y needs no clearing. A row's first
// block is its diagonal (upper storage, sorted columns).
SOMASIM_FEM_AVX512 void MultiplyUpperAvx512(const int32_t* row_start, const int32_t* columns,
                                            const double* values, size_t n, const double* x,
                                            double* y, const uint8_t* constrained, double* lanes_of,
                                            double* last_of) {
  const __m512i spread = _mm512_set_epi64(2, 2, 1, 1, 1, 0, 0, 0);
  for (size_t i = 0; i < n; ++i) {
    double* const own_lanes = lanes_of + 8 * i;
    __m512d acc0 = _mm512_load_pd(own_lanes);
    double last0 = last_of[i];
    _mm512_store_pd(own_lanes, _mm512_setzero_pd());
    last_of[i] = 0.0;
    if (constrained != nullptr && constrained[i] != 0) {
      y[3 * i] = x[3 * i];
      y[3 * i + 1] = x[3 * i + 1];
      y[3 * i + 2] = x[3 * i + 2];
      continue;
    }
    const __m512d xi =
        _mm512_maskz_permutexvar_pd(0xFF, spread, _mm512_maskz_loadu_pd(0x7, x + 3 * i));
    const double zi = x[3 * i + 2];
    const auto begin = static_cast<size_t>(row_start[i]);
    const auto end = static_cast<size_t>(row_start[i + 1]);
    const double* diagonal = values + 9 * begin;
    acc0 = _mm512_fmadd_pd(_mm512_loadu_pd(diagonal), xi, acc0);
    last0 += diagonal[8] * zi;
    __m512d acc1 = _mm512_setzero_pd();
    double last1 = 0.0;
    size_t k = begin + 1;
    if (constrained == nullptr) {
      for (; k + 1 < end; k += 2) {
        UpperBlock(values, columns, x, k, xi, zi, &acc0, &last0, lanes_of, last_of);
        UpperBlock(values, columns, x, k + 1, xi, zi, &acc1, &last1, lanes_of, last_of);
      }
      if (k < end) UpperBlock(values, columns, x, k, xi, zi, &acc0, &last0, lanes_of, last_of);
    } else {
      for (; k < end; ++k) {
        if (constrained[columns[k]] == 0) {
          UpperBlock(values, columns, x, k, xi, zi, &acc1, &last1, lanes_of, last_of);
        }
      }
    }
    alignas(64) double sums[8];
    _mm512_store_pd(sums, _mm512_add_pd(acc0, acc1));
    y[3 * i] = sums[0] + sums[3] + sums[6];
    y[3 * i + 1] = sums[1] + sums[4] + sums[7];
    y[3 * i + 2] = sums[2] + sums[5] + (last0 + last1);
  }
}
#endif

}  // namespace

void BlockSparseMatrix::Multiply(const double* x, double* y, const uint8_t* constrained) const {
  const auto n = static_cast<size_t>(num_nodes());
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
  if (CpuHasAvx512() && !force_scalar_ && upper_) {
    MultiplyUpperAvx512(row_start_.data(), columns_.data(), values_.data(), n, x, y, constrained,
                        TransposedLanes(), transposed_last_.data());
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

double* BlockSparseMatrix::TransposedLanes() const {
  // Each node's eight lanes on one cache line (an unaligned 64-byte store splits across two).
  auto* p = transposed_lanes_.data();
  const auto misalignment = reinterpret_cast<uintptr_t>(p) % 64;
  return misalignment == 0 ? p : p + (64 - misalignment) / sizeof(double);
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

namespace {

// Σ_k u[k] v[k] over `size` values in eight interleaved partial sums (independent chains, which
// the compiler may also pack into vector lanes), added pairwise at the end.
__attribute__((always_inline)) inline double Dot(const double* u, const double* v, size_t size) {
  double s[8] = {};
  size_t k = 0;
  for (; k + 8 <= size; k += 8) {
    for (size_t l = 0; l < 8; ++l) s[l] += u[k + l] * v[k + l];
  }
  for (; k < size; ++k) s[k % 8] += u[k] * v[k];
  return ((s[0] + s[1]) + (s[2] + s[3])) + ((s[4] + s[5]) + (s[6] + s[7]));
}

// z_i = M_i r_i for each node's 3×3 block M_i (column-major in inv); returns Σ r·z, in three
// partial sums (one per component).
__attribute__((always_inline)) inline double Precondition(const double* inv, const double* r,
                                                          double* z, size_t n) {
  double s0 = 0.0, s1 = 0.0, s2 = 0.0;
  for (size_t i = 0; i < n; ++i) {
    const double* m = inv + 9 * i;
    const double rx = r[3 * i], ry = r[3 * i + 1], rz = r[3 * i + 2];
    const double zx = m[0] * rx + m[3] * ry + m[6] * rz;
    const double zy = m[1] * rx + m[4] * ry + m[7] * rz;
    const double zz = m[2] * rx + m[5] * ry + m[8] * rz;
    z[3 * i] = zx;
    z[3 * i + 1] = zy;
    z[3 * i + 2] = zz;
    s0 += rx * zx;
    s1 += ry * zy;
    s2 += rz * zz;
  }
  return (s0 + s1) + s2;
}

// x += α p, r -= α q; returns |r|² (Dot's partial sums).
__attribute__((always_inline)) inline double Update(double alpha, const double* p, const double* q,
                                                    double* x, double* r, size_t size) {
  double s[8] = {};
  size_t k = 0;
  for (; k + 8 <= size; k += 8) {
    for (size_t l = 0; l < 8; ++l) {
      x[k + l] += alpha * p[k + l];
      r[k + l] -= alpha * q[k + l];
      s[l] += r[k + l] * r[k + l];
    }
  }
  for (; k < size; ++k) {
    x[k] += alpha * p[k];
    r[k] -= alpha * q[k];
    s[k % 8] += r[k] * r[k];
  }
  return ((s[0] + s[1]) + (s[2] + s[3])) + ((s[4] + s[5]) + (s[6] + s[7]));
}

__attribute__((always_inline)) inline CgResult ConjugateGradientsBody(
    const BlockSparseMatrix& a, const uint8_t* constrained, const double* b, double* x,
    double tolerance, int max_iterations, CgScratch* scratch, bool exactly_max_iterations) {
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
    // A symmetric positive definite A has positive definite diagonal blocks; a block that is
    // not (an isolated node) falls back to the identity. The inverse in closed form (adjugate
    // over determinant; Sylvester's leading minors say whether the block is positive
    // definite, as a Cholesky factorisation's pivots would): a tenth of the time of Eigen's
    // LLT solve per block.
    const double* d = a.block(a.diagonal_block(static_cast<int32_t>(i))).data();
    const double d00 = d[0], d11 = d[4], d22 = d[8];
    const double d01 = 0.5 * (d[1] + d[3]), d02 = 0.5 * (d[2] + d[6]), d12 = 0.5 * (d[5] + d[7]);
    const double c00 = d11 * d22 - d12 * d12, c01 = d02 * d12 - d01 * d22;
    const double c02 = d01 * d12 - d02 * d11, c11 = d00 * d22 - d02 * d02;
    const double c12 = d01 * d02 - d00 * d12, c22 = d00 * d11 - d01 * d01;
    const double det = d00 * c00 + d01 * c01 + d02 * c02;
    // Negated tests: a NaN fails them too.
    if (!(d00 > 0.0) || !(c22 > 0.0) || !(det > 0.0) || !std::isfinite(det)) {
      out.setIdentity();
      continue;
    }
    const double s = 1.0 / det;
    out << s * c00, s * c01, s * c02,  //
        s * c01, s * c11, s * c12,     //
        s * c02, s * c12, s * c22;
  }
  const double b_norm2 = Dot(b, b, size);
  a.Multiply(x, q, constrained);
  for (size_t k = 0; k < size; ++k) r[k] = b[k] - q[k];
  double r_norm2 = Dot(r, r, size);
  CgResult result;
  const double threshold2 = tolerance * tolerance * b_norm2;
  const auto done = [&](int iterations) {
    if (exactly_max_iterations) return iterations >= max_iterations;
    return r_norm2 <= threshold2 || iterations >= max_iterations;
  };
  double rz = Precondition(inv, r, z, n);
  std::copy(z, z + size, p);
  int it = 0;
  while (!done(it) && rz > 0.0) {
    a.Multiply(p, q, constrained);
    const double pq = Dot(p, q, size);
    if (!(pq > 0.0)) break;  // not positive definite along p (or p = 0): stop where we are
    const double alpha = rz / pq;
    r_norm2 = Update(alpha, p, q, x, r, size);
    const double rz_next = Precondition(inv, r, z, n);
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

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
// The same compiled for AVX-512 and FMA (its loops vectorise 8 wide; FMA rounds differently).
SOMASIM_FEM_AVX512 CgResult ConjugateGradientsAvx512(const BlockSparseMatrix& a,
                                                     const uint8_t* constrained, const double* b,
                                                     double* x, double tolerance,
                                                     int max_iterations, CgScratch* scratch,
                                                     bool exactly_max_iterations) {
  return ConjugateGradientsBody(a, constrained, b, x, tolerance, max_iterations, scratch,
                                exactly_max_iterations);
}
#endif

}  // namespace

CgResult ConjugateGradients(const BlockSparseMatrix& a, const uint8_t* constrained, const double* b,
                            double* x, double tolerance, int max_iterations, CgScratch* scratch,
                            bool exactly_max_iterations) {
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
  if (CpuHasAvx512()) {
    return ConjugateGradientsAvx512(a, constrained, b, x, tolerance, max_iterations, scratch,
                                    exactly_max_iterations);
  }
#endif
  return ConjugateGradientsBody(a, constrained, b, x, tolerance, max_iterations, scratch,
                                exactly_max_iterations);
}

}  // namespace somasim::models::fem
