#include "server/models/fem/block_sparse.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

namespace somasim::models::fem {

BlockSparseMatrix BlockSparseMatrix::FromTets(const mesh::Tetrahedra& tets, int32_t num_nodes) {
  BlockSparseMatrix m;
  const auto n = static_cast<size_t>(num_nodes);
  std::vector<std::vector<int32_t>> rows(n);
  for (Eigen::Index e = 0; e < tets.cols(); ++e) {
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) rows[static_cast<size_t>(tets(a, e))].push_back(tets(b, e));
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
        m.element_blocks_[static_cast<size_t>(16 * e + 4 * a + b)] = find(tets(a, e), tets(b, e));
      }
    }
  }
  m.values_.assign(9 * m.columns_.size(), 0.0);
  return m;
}

void BlockSparseMatrix::Multiply(const double* x, double* y, const uint8_t* constrained) const {
  const auto n = static_cast<size_t>(num_nodes());
  for (size_t i = 0; i < n; ++i) {
    if (constrained != nullptr && constrained[i] != 0) {
      y[3 * i] = x[3 * i];
      y[3 * i + 1] = x[3 * i + 1];
      y[3 * i + 2] = x[3 * i + 2];
      continue;
    }
    double sx = 0.0, sy = 0.0, sz = 0.0;
    for (auto k = static_cast<size_t>(row_start_[i]); k < static_cast<size_t>(row_start_[i + 1]);
         ++k) {
      const auto j = static_cast<size_t>(columns_[k]);
      if (constrained != nullptr && constrained[j] != 0) continue;
      const double* b = values_.data() + 9 * k;  // column-major
      const double xj = x[3 * j], yj = x[3 * j + 1], zj = x[3 * j + 2];
      sx += b[0] * xj + b[3] * yj + b[6] * zj;
      sy += b[1] * xj + b[4] * yj + b[7] * zj;
      sz += b[2] * xj + b[5] * yj + b[8] * zj;
    }
    y[3 * i] = sx;
    y[3 * i + 1] = sy;
    y[3 * i + 2] = sz;
  }
}

LowerCsc BlockSparseMatrix::ScalarLower(const std::vector<int32_t>& dof, int32_t num_dofs) const {
  struct Entry {
    int32_t col, row;
    double value;
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
          entries.push_back({col, row, values_[9 * k + 3 * c + r]});
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
  out.values.reserve(entries.size());
  for (const Entry& e : entries) {
    ++out.col_start[static_cast<size_t>(e.col) + 1];
    out.rows.push_back(e.row);
    out.values.push_back(e.value);
  }
  for (size_t c = 0; c < static_cast<size_t>(num_dofs); ++c)
    out.col_start[c + 1] += out.col_start[c];
  return out;
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
    r_norm2 = 0.0;
    for (size_t k = 0; k < size; ++k) {
      x[k] += alpha * p[k];
      r[k] -= alpha * q[k];
      r_norm2 += r[k] * r[k];
    }
    ++it;
    precondition();
    double rz_next = 0.0;
    for (size_t k = 0; k < size; ++k) rz_next += r[k] * z[k];
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
