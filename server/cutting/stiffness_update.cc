#include "server/cutting/stiffness_update.h"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <Eigen/SparseCore>
#include <cmath>
#include <stdexcept>
#include <string>

namespace somasim::cutting {

Matrix12d LinearTetStiffness(const Eigen::Matrix<double, 3, 4>& x, double lambda, double mu) {
  Eigen::Matrix3d d;
  d << x.col(1) - x.col(0), x.col(2) - x.col(0), x.col(3) - x.col(0);
  const double det = d.determinant();
  const double longest = std::max({(x.col(1) - x.col(0)).norm(), (x.col(2) - x.col(0)).norm(),
                                   (x.col(3) - x.col(0)).norm(), (x.col(2) - x.col(1)).norm(),
                                   (x.col(3) - x.col(1)).norm(), (x.col(3) - x.col(2)).norm()});
  Matrix12d k = Matrix12d::Zero();
  if (!(det > 1e-12 * longest * longest * longest)) return k;  // flat or inverted
  const double volume = det / 6.0;
  // ∇N_1..3 are the rows of D⁻¹ (N_i(X) = e_iᵀ D⁻¹ (X − X_0)); ∇N_0 = −Σ.
  const Eigen::Matrix3d inverse = d.inverse();
  Eigen::Matrix<double, 3, 4> g;
  g.rightCols<3>() = inverse.transpose();
  g.col(0) = -g.rightCols<3>().rowwise().sum();
  for (int a = 0; a < 4; ++a) {
    for (int b = 0; b < 4; ++b) {
      k.block<3, 3>(3 * a, 3 * b) =
          volume *
          (lambda * g.col(a) * g.col(b).transpose() + mu * g.col(b) * g.col(a).transpose() +
           mu * g.col(a).dot(g.col(b)) * Eigen::Matrix3d::Identity());
    }
  }
  return k;
}

CutStiffness::CutStiffness(const mesh::TetMesh& rest, const std::vector<uint8_t>& fixed,
                           double youngs_modulus, double poisson_ratio)
    : tets_(rest.tetrahedra) {
  const auto num_nodes = static_cast<size_t>(rest.vertices.cols());
  if (fixed.size() != num_nodes) {
    throw std::invalid_argument("cut stiffness: " + std::to_string(fixed.size()) +
                                " fixed flags for " + std::to_string(num_nodes) + " nodes");
  }
  if (!(youngs_modulus > 0.0) || !(poisson_ratio > -1.0 && poisson_ratio < 0.5)) {
    throw std::invalid_argument("cut stiffness: E must be > 0 and ν within (−1, 0.5)");
  }
  lambda_ = youngs_modulus * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio));
  mu_ = youngs_modulus / (2.0 * (1.0 + poisson_ratio));
  node_dof_.assign(num_nodes, -1);
  for (size_t v = 0; v < num_nodes; ++v) {
    if (fixed[v] != 0) continue;
    node_dof_[v] = num_free_;
    num_free_ += 3;
  }
  alive_.assign(static_cast<size_t>(tets_.cols()), 1);
  ke_.resize(static_cast<size_t>(tets_.cols()));
  for (Eigen::Index e = 0; e < tets_.cols(); ++e) {
    Eigen::Matrix<double, 3, 4> corners;
    for (int a = 0; a < 4; ++a) {
      const int32_t node = tets_(a, e);
      if (node < 0 || static_cast<size_t>(node) >= num_nodes) {
        throw std::invalid_argument("cut stiffness: tetrahedron " + std::to_string(e) +
                                    " has a node out of range");
      }
      corners.col(a) = rest.vertices.col(node);
    }
    ke_[static_cast<size_t>(e)] = LinearTetStiffness(corners, lambda_, mu_);
  }
}

Matrix12d CutStiffness::Remove(int32_t e) {
  Matrix12d change = -ke_[static_cast<size_t>(e)];
  ke_[static_cast<size_t>(e)].setZero();
  alive_[static_cast<size_t>(e)] = 0;
  return change;
}

Matrix12d CutStiffness::Relocate(int32_t e, const mesh::Points& positions) {
  if (alive_[static_cast<size_t>(e)] == 0) return Matrix12d::Zero();
  Eigen::Matrix<double, 3, 4> corners;
  for (int a = 0; a < 4; ++a) corners.col(a) = positions.col(tets_(a, e));
  const Matrix12d now = LinearTetStiffness(corners, lambda_, mu_);
  Matrix12d change = now - ke_[static_cast<size_t>(e)];
  ke_[static_cast<size_t>(e)] = now;
  return change;
}

template <typename Fn>
void CutStiffness::ForEachCoupling(Fn&& fn) const {
  for (Eigen::Index e = 0; e < tets_.cols(); ++e) {
    const bool alive = alive_[static_cast<size_t>(e)] != 0;
    const Matrix12d& ke = ke_[static_cast<size_t>(e)];
    for (int i = 0; i < 12; ++i) {
      const int32_t r = dof(tets_(i / 3, e), i % 3);
      if (r < 0) continue;
      for (int j = 0; j < 12; ++j) {
        const int32_t c = dof(tets_(j / 3, e), j % 3);
        if (c >= 0) fn(alive, r, c, ke(i, j));
      }
    }
  }
}

Eigen::MatrixXd CutStiffness::AssembleDense() const {
  Eigen::MatrixXd k = Eigen::MatrixXd::Zero(num_free_, num_free_);
  ForEachCoupling([&](bool alive, int32_t r, int32_t c, double value) {
    if (alive) k(r, c) += value;
  });
  return k;
}

models::fem::LowerCsc CutStiffness::AssembleSparse() const {
  std::vector<Eigen::Triplet<double>> triplets;
  triplets.reserve(static_cast<size_t>(tets_.cols()) * 78);
  // The pattern keeps every pair an element couples, removed or not (an explicit zero): later
  // updates then never add fill to the factor.
  ForEachCoupling([&](bool alive, int32_t r, int32_t c, double value) {
    if (r >= c) triplets.emplace_back(r, c, alive ? value : 0.0);
  });
  Eigen::SparseMatrix<double, Eigen::ColMajor, int32_t> m(num_free_, num_free_);
  m.setFromTriplets(triplets.begin(), triplets.end());
  m.makeCompressed();
  models::fem::LowerCsc csc;
  csc.size = num_free_;
  csc.col_start.assign(m.outerIndexPtr(), m.outerIndexPtr() + num_free_ + 1);
  csc.rows.assign(m.innerIndexPtr(), m.innerIndexPtr() + m.nonZeros());
  csc.values.assign(m.valuePtr(), m.valuePtr() + m.nonZeros());
  return csc;
}

LowRankChange SplitChange(const CutStiffness& problem, int32_t e, const Matrix12d& change) {
  LowRankChange c;
  std::array<int, 12> local{};
  for (int i = 0; i < 12; ++i) {
    // The element's corner i / 3, coordinate i % 3 — its free DOF, if any.
    const int32_t r = problem.dof(problem.node(e, i / 3), i % 3);
    if (r < 0) continue;
    local[static_cast<size_t>(c.num_rows)] = i;
    c.rows[static_cast<size_t>(c.num_rows)] = r;
    ++c.num_rows;
  }
  if (c.num_rows == 0) return c;
  using Small = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 12, 12>;
  Small s(c.num_rows, c.num_rows);
  for (int i = 0; i < c.num_rows; ++i) {
    for (int j = 0; j < c.num_rows; ++j) {
      s(i, j) = change(local[static_cast<size_t>(i)], local[static_cast<size_t>(j)]);
    }
  }
  const Eigen::SelfAdjointEigenSolver<Small> eig(s);
  const double largest = eig.eigenvalues().cwiseAbs().maxCoeff();
  for (int i = 0; i < c.num_rows; ++i) {
    const double d = eig.eigenvalues()[i];
    if (!(std::abs(d) > 1e-12 * largest)) continue;
    c.w.col(c.rank).head(c.num_rows) = eig.eigenvectors().col(i);
    c.d[static_cast<size_t>(c.rank)] = d;
    ++c.rank;
  }
  return c;
}

StepChange::StepChange()
    : sum_(Eigen::MatrixXd::Zero(kMaxRows, kMaxRows)),
      eigen_(kMaxRows),
      w_(kMaxRows, kMaxRows),
      d_(kMaxRows) {}

void StepChange::Clear() {
  sum_.topLeftCorner(num_rows_, num_rows_).setZero();
  num_rows_ = 0;
  rank_ = 0;
}

bool StepChange::Add(const CutStiffness& problem, int32_t e, const Matrix12d& change) {
  std::array<int32_t, 12> local{};  // the element's free DOFs' places in rows_ (−1: held)
  int32_t added = 0;
  for (int i = 0; i < 12; ++i) {
    const int32_t r = problem.dof(problem.node(e, i / 3), i % 3);
    local[static_cast<size_t>(i)] = -1;
    if (r < 0) continue;
    int32_t at = -1;
    for (int32_t k = 0; k < num_rows_ + added && at < 0; ++k) {
      if (rows_[static_cast<size_t>(k)] == r) at = k;
    }
    if (at < 0) {
      if (num_rows_ + added == kMaxRows) return false;  // rows_ past num_rows_ are unused
      at = num_rows_ + added++;
      rows_[static_cast<size_t>(at)] = r;
    }
    local[static_cast<size_t>(i)] = at;
  }
  num_rows_ += added;
  for (int i = 0; i < 12; ++i) {
    if (local[static_cast<size_t>(i)] < 0) continue;
    for (int j = 0; j < 12; ++j) {
      if (local[static_cast<size_t>(j)] < 0) continue;
      sum_(local[static_cast<size_t>(i)], local[static_cast<size_t>(j)]) += change(i, j);
    }
  }
  return true;
}

void StepChange::Split() {
  rank_ = 0;
  if (num_rows_ == 0) return;
  eigen_.compute(sum_);  // the padded square: its extra eigenvalues are zero
  const Eigen::VectorXd& values = eigen_.eigenvalues();
  const double largest = values.cwiseAbs().maxCoeff();
  for (int32_t i = 0; i < kMaxRows; ++i) {
    if (!(std::abs(values[i]) > 1e-12 * largest)) continue;
    w_.col(rank_) = eigen_.eigenvectors().col(i);
    d_[rank_] = values[i];
    ++rank_;
  }
}

DenseInverseStiffness::DenseInverseStiffness(const CutStiffness& problem) {
  const Eigen::MatrixXd k = problem.AssembleDense();
  const Eigen::LLT<Eigen::MatrixXd> llt(k);
  if (llt.info() != Eigen::Success) {
    throw std::runtime_error("dense inverse: the stiffness is not positive definite");
  }
  inverse_ = llt.solve(Eigen::MatrixXd::Identity(k.rows(), k.cols()));
  kz_.resize(k.rows(), 12);
  scratch_.resize(k.rows(), 12);
}

void DenseInverseStiffness::Apply(const LowRankChange& c) {
  if (c.rank == 0) return;
  const Eigen::Index n = inverse_.rows();
  const int m = c.num_rows, r = c.rank;
  // K⁻¹ Z, Z = V W: the rows' columns of K⁻¹ times W.
  auto kz = kz_.leftCols(r);
  kz.setZero();
  for (int j = 0; j < m; ++j) {
    for (int i = 0; i < r; ++i)
      kz.col(i) += c.w(j, i) * inverse_.col(c.rows[static_cast<size_t>(j)]);
  }
  // S = D⁻¹ + Zᵀ K⁻¹ Z (r × r).
  using Small = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 12, 12>;
  Small s(r, r);
  for (int a = 0; a < r; ++a) {
    for (int b = 0; b < r; ++b) {
      double zkz = 0.0;
      for (int j = 0; j < m; ++j) zkz += c.w(j, a) * kz(c.rows[static_cast<size_t>(j)], b);
      s(a, b) = zkz + (a == b ? 1.0 / c.d[static_cast<size_t>(a)] : 0.0);
    }
  }
  // K'⁻¹ = K⁻¹ − (K⁻¹ Z) S⁻¹ (K⁻¹ Z)ᵀ.
  const Eigen::PartialPivLU<Small> lu(s);
  Small sinv = lu.inverse();
  auto t = scratch_.leftCols(r);
  t.noalias() = kz * sinv;
  for (Eigen::Index j = 0; j < n; ++j) {
    inverse_.col(j).noalias() -= t * kz.row(j).transpose();
  }
}

SparseFactorStiffness::SparseFactorStiffness(const CutStiffness& problem)
    : packed_(static_cast<size_t>(StepChange::kMaxRows) * 16, 0.0) {
  const models::fem::LowerCsc k = problem.AssembleSparse();
  factor_.Analyse(k);
  if (!factor_.Factorise(k)) {
    throw std::runtime_error("sparse factor: the stiffness is not positive definite");
  }
}

bool SparseFactorStiffness::Apply(const LowRankChange& c) {
  if (c.rank == 0) return true;
  // The positive part first (an update), then the negative part (a downdate): K stays positive
  // definite in between whenever it is at the end.
  for (const bool update : {true, false}) {
    int k = 0;
    for (int i = 0; i < c.rank; ++i) {
      const double d = c.d[static_cast<size_t>(i)];
      if ((d > 0.0) != update) continue;
      c_.col(k).head(c.num_rows) = std::sqrt(std::abs(d)) * c.w.col(i).head(c.num_rows);
      ++k;
    }
    if (k == 0) continue;
    // c_ is 12 × 12 column-major: column j's num_rows values are contiguous only when the leading
    // dimension is num_rows; copy into that layout.
    std::array<double, 144> packed{};
    for (int j = 0; j < k; ++j) {
      for (int i = 0; i < c.num_rows; ++i)
        packed[static_cast<size_t>(j) * static_cast<size_t>(c.num_rows) + static_cast<size_t>(i)] =
            c_(i, j);
    }
    if (!factor_.UpdateDowndate(update, c.rows.data(), c.num_rows, packed.data(), k)) return false;
  }
  return true;
}

bool SparseFactorStiffness::Apply(const StepChange& c) {
  constexpr int32_t kColumns = 16;
  const auto m = static_cast<size_t>(c.num_rows());
  for (const bool update : {true, false}) {
    int32_t k = 0;
    for (int32_t i = 0; i <= c.rank(); ++i) {
      const bool last = i == c.rank();
      if (!last && (c.d(i) > 0.0) == update) {
        const double scale = std::sqrt(std::abs(c.d(i)));
        const double* w = c.w(i);
        for (size_t r = 0; r < m; ++r) packed_[static_cast<size_t>(k) * m + r] = scale * w[r];
        ++k;
      }
      if (k == kColumns || (last && k > 0)) {
        if (!factor_.UpdateDowndate(update, c.rows(), c.num_rows(), packed_.data(), k)) {
          return false;
        }
        k = 0;
      }
    }
  }
  return true;
}

void SparseFactorStiffness::Solve(const Eigen::VectorXd& f, Eigen::VectorXd* u) {
  u->resize(f.size());
  factor_.Solve(f.data(), u->data());
}

}  // namespace somasim::cutting
