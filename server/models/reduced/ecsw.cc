#include "server/models/reduced/ecsw.h"

#include <Eigen/QR>
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "common/checks/finite.h"
#include "server/models/fem/hyperelastic.h"
#include "server/models/reduced/nonlinear_model.h"

namespace somasim::models::reduced {
namespace {

void Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("ecsw: " + what);
}

// A QR factorisation G_P = Q R of the active columns, grown one column at a time.
class GrowingQr {
 public:
  GrowingQr(Eigen::Index rows, int max_columns)
      : q_(rows, max_columns), r_(max_columns, max_columns) {
    r_.setZero();
  }
  Eigen::Index size() const { return k_; }
  // Appends column v; false (nothing appended) if it is numerically in the span.
  bool Append(const Eigen::VectorXd& column) {
    Eigen::VectorXd v = column;
    Eigen::VectorXd coefficients = Eigen::VectorXd::Zero(k_);
    for (int pass = 0; pass < 2; ++pass) {  // twice is enough (Giraud et al. 2005)
      if (k_ == 0) break;
      const Eigen::VectorXd c = q_.leftCols(k_).transpose() * v;
      v.noalias() -= q_.leftCols(k_) * c;
      coefficients += c;
    }
    const double norm = v.norm();
    if (!(norm > 1e-10 * column.norm())) return false;
    q_.col(k_) = v / norm;
    r_.col(k_).head(k_) = coefficients;
    r_(k_, k_) = norm;
    ++k_;
    return true;
  }
  // Drops column p: R without it is upper Hessenberg from column p on; Givens rotations of rows
  // (j, j + 1) restore the triangle and the same rotations of Q's columns keep G_P = Q R.
  // O(k² + m k) instead of a new factorisation's O(m k²).
  void Remove(Eigen::Index p) {
    for (Eigen::Index j = p; j + 1 < k_; ++j) r_.col(j) = r_.col(j + 1);
    --k_;
    for (Eigen::Index j = p; j < k_; ++j) {
      const double a = r_(j, j), b = r_(j + 1, j);
      const double h = std::hypot(a, b);
      if (h == 0.0) continue;
      const double c = a / h, sn = b / h;
      for (Eigen::Index col = j; col < k_; ++col) {
        const double x = r_(j, col), y = r_(j + 1, col);
        r_(j, col) = c * x + sn * y;
        r_(j + 1, col) = -sn * x + c * y;
      }
      r_(j + 1, j) = 0.0;
      for (Eigen::Index row = 0; row < q_.rows(); ++row) {
        const double x = q_(row, j), y = q_(row, j + 1);
        q_(row, j) = c * x + sn * y;
        q_(row, j + 1) = -sn * x + c * y;
      }
    }
    r_.row(k_).setZero();
    r_.col(k_).setZero();
  }
  // argmin |G_P z − b|.
  Eigen::VectorXd Solve(const Eigen::VectorXd& b) const {
    const Eigen::VectorXd qb = q_.leftCols(k_).transpose() * b;
    return r_.topLeftCorner(k_, k_).triangularView<Eigen::Upper>().solve(qb);
  }

 private:
  Eigen::MatrixXd q_, r_;
  Eigen::Index k_ = 0;
};

}  // namespace

NnlsResult SparseNnls(const Eigen::MatrixXd& g, const Eigen::VectorXd& b, double tolerance,
                      int max_columns) {
  Require(g.rows() == b.size(),
          "G has " + std::to_string(g.rows()) + " rows, b " + std::to_string(b.size()) + " values");
  Require(g.cols() >= 1 && g.rows() >= 1, "G is empty");
  Require(g.allFinite() && b.allFinite(), "G or b is not finite");
  Require(checks::FinitePositive(tolerance), "tolerance must be > 0");
  Require(max_columns >= 1, "max_columns must be >= 1");
  const Eigen::Index columns = g.cols();
  const int limit = static_cast<int>(std::min<Eigen::Index>(max_columns, columns));
  NnlsResult result;
  const double b_norm = b.norm();
  if (b_norm == 0.0) {
    result.converged = true;
    return result;
  }
  GrowingQr qr(g.rows(), limit);
  std::vector<int32_t> active;  // the passive set P, in QR order
  Eigen::VectorXd w = Eigen::VectorXd::Zero(columns);
  std::vector<uint8_t> state(static_cast<size_t>(columns), 0);  // 1 active, 2 excluded
  Eigen::VectorXd residual = b, gradient(columns);
  while (residual.norm() > tolerance * b_norm && static_cast<int>(active.size()) < limit) {
    gradient.noalias() = g.transpose() * residual;
    Eigen::Index best = -1;
    double largest = 0.0;
    for (Eigen::Index j = 0; j < columns; ++j) {
      if (state[static_cast<size_t>(j)] == 0 && gradient(j) > largest) {
        largest = gradient(j);
        best = j;
      }
    }
    if (best < 0) break;  // optimal: no column improves the fit
    if (!qr.Append(g.col(best))) {
      state[static_cast<size_t>(best)] = 2;
      continue;
    }
    active.push_back(static_cast<int32_t>(best));
    state[static_cast<size_t>(best)] = 1;
    ++result.iterations;
    // The inner loop: step towards the unconstrained solution of the active set, dropping
    // columns whose weights reach zero, until it is positive.
    for (int inner = 0; inner < 4 * limit; ++inner) {
      const Eigen::VectorXd z = qr.Solve(b);
      double alpha = 1.0;
      bool positive = true;
      for (size_t i = 0; i < active.size(); ++i) {
        if (z(static_cast<Eigen::Index>(i)) <= 0.0) {
          positive = false;
          const double wi = w(active[i]);
          alpha = std::min(alpha, wi / (wi - z(static_cast<Eigen::Index>(i))));
        }
      }
      if (positive) {
        for (size_t i = 0; i < active.size(); ++i) w(active[i]) = z(static_cast<Eigen::Index>(i));
        break;
      }
      for (size_t i = 0; i < active.size(); ++i) {
        w(active[i]) += alpha * (z(static_cast<Eigen::Index>(i)) - w(active[i]));
      }
      // Drop the columns at zero (the one just added too, if rounding put it there: it is
      // excluded so that it is not picked again at once), last first.
      const double floor = 1e-14 * w.cwiseAbs().maxCoeff();
      for (auto i = static_cast<Eigen::Index>(active.size()) - 1; i >= 0; --i) {
        const int32_t j = active[static_cast<size_t>(i)];
        if (w(j) > floor) continue;
        w(j) = 0.0;
        state[static_cast<size_t>(j)] = j == best ? 2 : 0;
        qr.Remove(i);
        active.erase(active.begin() + i);
      }
    }
    residual = b;
    for (const int32_t j : active) residual.noalias() -= w(j) * g.col(j);
  }
  result.relative_residual = residual.norm() / b_norm;
  result.converged = result.relative_residual <= tolerance;
  std::vector<int32_t> sorted = active;
  std::sort(sorted.begin(), sorted.end());
  for (const int32_t j : sorted) {
    if (w(j) > 0.0) {
      result.columns.push_back(j);
      result.weights.push_back(w(j));
    }
  }
  return result;
}

Cubature TrainCubature(const fem::FemModel& full, const Eigen::MatrixXd& modes,
                       std::span<const mesh::Points> displacements,
                       const CubatureSettings& settings, const Eigen::MatrixXd* test_modes) {
  Require(full.kind() == fem::FemKind::kHyperelastic,
          "the nonlinear reduced model needs a hyperelastic full model");
  const Eigen::Index nodes = full.num_nodes(), n = modes.cols();
  Require(modes.rows() == 3 * nodes && n >= 1, "modes must be 3N × n");
  Require(test_modes == nullptr || (test_modes->rows() == modes.rows() && test_modes->cols() == n),
          "test modes must be 3N × n like the modes");
  Require(checks::FinitePositive(settings.tolerance) && settings.tolerance < 1.0,
          "tolerance must lie in (0, 1)");
  Require(settings.max_elements >= 1, "max_elements must be >= 1");
  // The projections ξ_s (least squares, for modes that need not be orthonormal).
  const Eigen::LDLT<Eigen::MatrixXd> gram(modes.transpose() * modes);
  std::vector<Eigen::VectorXd> xi;
  for (const mesh::Points& u : displacements) {
    Require(u.rows() == 3 && u.cols() == nodes, "a training displacement is not 3 × N");
    Require(u.allFinite(), "a training displacement is not finite");
    xi.push_back(
        gram.solve(modes.transpose() * Eigen::Map<const Eigen::VectorXd>(u.data(), u.size())));
  }
  const auto snapshots = static_cast<Eigen::Index>(xi.size());
  const int32_t elements = full.num_tets();
  Eigen::MatrixXd g = Eigen::MatrixXd::Zero(n * snapshots, elements);
  std::vector<uint8_t> inverted(static_cast<size_t>(snapshots), 0);
  for (int32_t e = 0; e < elements; ++e) {
    const double volume = full.elements().volumes[static_cast<size_t>(e)];
    const Eigen::Matrix<double, 9, Eigen::Dynamic> d = ElementGradientMap(
        modes, full.elements().tets.col(e), full.elements().gradients.middleCols<4>(4 * e));
    if (d.cwiseAbs().maxCoeff() == 0.0) continue;  // the modes do not strain it
    const Eigen::Matrix<double, 9, Eigen::Dynamic> test =
        test_modes == nullptr ? d
                              : ElementGradientMap(*test_modes, full.elements().tets.col(e),
                                                   full.elements().gradients.middleCols<4>(4 * e));
    for (Eigen::Index s = 0; s < snapshots; ++s) {
      Eigen::Matrix<double, 9, 1> h = d * xi[static_cast<size_t>(s)];
      const Eigen::Matrix3d f = Eigen::Matrix3d::Identity() + Eigen::Map<Eigen::Matrix3d>(h.data());
      if (!(f.determinant() > 0.0)) {  // its projection inverts an element: left out
        inverted[static_cast<size_t>(s)] = 1;
        continue;
      }
      const Eigen::Matrix3d p = fem::FirstPiolaStress(full.material(), f);
      g.block(n * s, e, n, 1) =
          -volume * (test.transpose() * Eigen::Map<const Eigen::Matrix<double, 9, 1>>(p.data()));
    }
  }
  Cubature result;
  for (Eigen::Index s = 0; s < snapshots; ++s) {
    if (inverted[static_cast<size_t>(s)] != 0) {
      g.middleRows(n * s, n).setZero();
      ++result.inverted;
    }
  }
  Eigen::VectorXd b = g.rowwise().sum();
  for (Eigen::Index s = 0; s < snapshots; ++s) {
    const double norm = b.segment(n * s, n).norm();
    if (norm > 0.0) {
      g.middleRows(n * s, n) /= norm;
      b.segment(n * s, n) /= norm;
      ++result.snapshots;
    }
  }
  Require(result.snapshots > 0, "no training displacement strains the modes");
  const NnlsResult nnls = SparseNnls(g, b, settings.tolerance, settings.max_elements);
  result.elements = nnls.columns;
  result.weights = nnls.weights;
  result.relative_residual = nnls.relative_residual;
  result.converged = nnls.converged;
  return result;
}

}  // namespace somasim::models::reduced
