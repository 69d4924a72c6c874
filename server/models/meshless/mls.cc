#include "server/models/meshless/mls.h"

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>

#include "common/checks/finite.h"
#include "server/models/cut_geometry.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix4d;
using Eigen::Vector3d;
using Eigen::Vector4d;

[[noreturn]] void Refuse(const std::string& what) { throw std::invalid_argument("mls: " + what); }

std::string PointName(const Vector3d& x) {
  std::ostringstream s;
  s.precision(9);
  s << "(" << x.x() << ", " << x.y() << ", " << x.z() << ") m";
  return s.str();
}

// A uniform grid over a box: cell coordinates of a point, clamped to the grid.
struct Grid {
  Vector3d origin;
  double cell = 1.0;
  Eigen::Vector3i size;

  Grid(const Vector3d& lo, const Vector3d& hi, double cell_edge, int64_t max_cells) {
    origin = lo;
    cell = cell_edge;
    // Enlarge the cells until the grid has at most max_cells (a long thin body, tiny radii).
    for (;;) {
      for (int a = 0; a < 3; ++a) {
        size[a] = static_cast<int>(std::floor((hi[a] - lo[a]) / cell)) + 1;
      }
      if (static_cast<int64_t>(size[0]) * size[1] * size[2] <= max_cells) break;
      cell *= 1.25;
    }
  }
  int Coord(double value, int axis) const {
    const double c = std::floor((value - origin[axis]) / cell);
    return static_cast<int>(std::clamp(c, 0.0, static_cast<double>(size[axis] - 1)));
  }
  int64_t Flat(int i, int j, int k) const {
    return static_cast<int64_t>(i) + static_cast<int64_t>(size[0]) * (j + int64_t{size[1]} * k);
  }
  int64_t num_cells() const { return int64_t{size[0]} * size[1] * size[2]; }
};

// Distance from node `self` to its k-th nearest other node, by rings of cells around it: after
// ring R every node within R cells' distance has been seen, so the search stops as soon as the
// k-th distance found is within that.
std::vector<double> KthNeighbourDistances(const mesh::Points& x, int k) {
  const auto n = static_cast<int32_t>(x.cols());
  const Vector3d lo = x.rowwise().minCoeff(), hi = x.rowwise().maxCoeff();
  const double extent = (hi - lo).maxCoeff();
  const double volume = std::max((hi - lo).prod(), extent * extent * extent * 1e-6);
  const double edge = std::max(std::cbrt(volume / n) * 1.5, extent * 1e-9);
  const Grid grid(lo, hi, edge, 4 * int64_t{n} + 64);
  std::vector<int32_t> start(static_cast<size_t>(grid.num_cells()) + 1, 0);
  std::vector<int32_t> items(static_cast<size_t>(n));
  std::vector<int64_t> cell_of(static_cast<size_t>(n));
  for (int32_t i = 0; i < n; ++i) {
    cell_of[size_t(i)] =
        grid.Flat(grid.Coord(x(0, i), 0), grid.Coord(x(1, i), 1), grid.Coord(x(2, i), 2));
    ++start[static_cast<size_t>(cell_of[size_t(i)]) + 1];
  }
  for (size_t c = 1; c < start.size(); ++c) start[c] += start[c - 1];
  std::vector<int32_t> fill(start.begin(), start.end() - 1);
  for (int32_t i = 0; i < n; ++i) items[size_t(fill[size_t(cell_of[size_t(i)])]++)] = i;

  std::vector<double> result(size_t(n), 0.0);
  std::vector<double> best;  // the k smallest distances so far, sorted
  const int max_ring = grid.size.maxCoeff();
  for (int32_t i = 0; i < n; ++i) {
    best.clear();
    const int ci = grid.Coord(x(0, i), 0), cj = grid.Coord(x(1, i), 1), ck = grid.Coord(x(2, i), 2);
    for (int ring = 0; ring <= max_ring; ++ring) {
      for (int a = ci - ring; a <= ci + ring; ++a) {
        for (int b = cj - ring; b <= cj + ring; ++b) {
          for (int c = ck - ring; c <= ck + ring; ++c) {
            const bool shell =
                std::abs(a - ci) == ring || std::abs(b - cj) == ring || std::abs(c - ck) == ring;
            if (!shell || a < 0 || b < 0 || c < 0 || a >= grid.size[0] || b >= grid.size[1] ||
                c >= grid.size[2]) {
              continue;
            }
            const auto cell = static_cast<size_t>(grid.Flat(a, b, c));
            for (int32_t t = start[cell]; t < start[cell + 1]; ++t) {
              const int32_t j = items[size_t(t)];
              if (j == i) continue;
              const double d = (x.col(j) - x.col(i)).norm();
              if (static_cast<int>(best.size()) < k || d < best.back()) {
                best.insert(std::upper_bound(best.begin(), best.end(), d), d);
                if (static_cast<int>(best.size()) > k) best.pop_back();
              }
            }
          }
        }
      }
      if (static_cast<int>(best.size()) == k && best.back() <= ring * grid.cell) break;
    }
    result[size_t(i)] = best.back();
  }
  return result;
}

}  // namespace

double CubicSplineWeight(double r) {
  if (r <= 0.5) return 2.0 / 3.0 - 4.0 * r * r + 4.0 * r * r * r;
  if (r < 1.0) return 4.0 / 3.0 - 4.0 * r + 4.0 * r * r - 4.0 / 3.0 * r * r * r;
  return 0.0;
}

double CubicSplineWeightDerivative(double r) {
  if (r <= 0.5) return -8.0 * r + 12.0 * r * r;
  if (r < 1.0) return -4.0 + 8.0 * r - 4.0 * r * r;
  return 0.0;
}

MlsShapeFunctions::MlsShapeFunctions(const mesh::Points& nodes, const MlsParameters& parameters,
                                     std::span<const double> min_radius)
    : nodes_(nodes), min_rcond_(parameters.min_reciprocal_condition) {
  const auto n = static_cast<int32_t>(nodes.cols());
  if (n < 4)
    Refuse("nodes: at least 4 nodes are needed for a linear basis, got " + std::to_string(n));
  for (int32_t i = 0; i < n; ++i) {
    if (!nodes.col(i).allFinite()) Refuse("nodes: node " + std::to_string(i) + " is not finite");
  }
  if (!(parameters.support_scale >= 1.0) || !std::isfinite(parameters.support_scale)) {
    Refuse("support_scale must be finite and >= 1");
  }
  if (parameters.support_neighbours < 1 || parameters.support_neighbours > 64 ||
      parameters.support_neighbours >= n) {
    Refuse("support_neighbours must lie in 1..64 and be < the number of nodes");
  }
  if (!(parameters.min_reciprocal_condition > 0.0 && parameters.min_reciprocal_condition < 1.0)) {
    Refuse("min_reciprocal_condition must lie in (0, 1)");
  }
  if (!min_radius.empty() && min_radius.size() != static_cast<size_t>(n)) {
    Refuse("min_radius must hold one radius per node or none");
  }

  // Support radii: scale × d_k, at least the caller's floor.
  radius_ = KthNeighbourDistances(nodes, parameters.support_neighbours);
  double sum = 0.0;
  for (int32_t i = 0; i < n; ++i) {
    double& r = radius_[size_t(i)];
    r *= parameters.support_scale;
    if (!min_radius.empty()) {
      if (!checks::FiniteNonNegative(min_radius[size_t(i)])) {
        Refuse("min_radius of node " + std::to_string(i) + " must be finite and >= 0");
      }
      r = std::max(r, min_radius[size_t(i)]);
    }
    if (!(r > 0.0)) Refuse("node " + std::to_string(i) + " coincides with its neighbours");
    sum += r;
  }
  basis_scale_ = sum / n;
  max_radius_ = *std::max_element(radius_.begin(), radius_.end());

  // The evaluation grid: cells of about the mean radius; node J in every cell its support's
  // bounding box overlaps.
  const Vector3d lo = nodes.rowwise().minCoeff(), hi = nodes.rowwise().maxCoeff();
  const Grid grid(lo, hi, basis_scale_, 16 * int64_t{n} + 64);
  grid_origin_ = grid.origin;
  cell_ = grid.cell;
  grid_size_ = grid.size;
  const auto num_cells = static_cast<size_t>(grid.num_cells());
  cell_start_.assign(num_cells + 1, 0);
  for (int pass = 0; pass < 2; ++pass) {
    std::vector<int32_t> fill;
    if (pass == 1) {
      for (size_t c = 1; c <= num_cells; ++c) cell_start_[c] += cell_start_[c - 1];
      cell_nodes_.assign(static_cast<size_t>(cell_start_[num_cells]), 0);
      fill.assign(cell_start_.begin(), cell_start_.end() - 1);
    }
    for (int32_t j = 0; j < n; ++j) {
      const double r = radius_[size_t(j)];
      Eigen::Vector3i a, b;
      for (int k = 0; k < 3; ++k) {
        a[k] = grid.Coord(nodes(k, j) - r, k);
        b[k] = grid.Coord(nodes(k, j) + r, k);
      }
      for (int kk = a[2]; kk <= b[2]; ++kk) {
        for (int jj = a[1]; jj <= b[1]; ++jj) {
          for (int ii = a[0]; ii <= b[0]; ++ii) {
            const auto cell = static_cast<size_t>(grid.Flat(ii, jj, kk));
            if (pass == 0) {
              ++cell_start_[cell + 1];
            } else {
              cell_nodes_[size_t(fill[cell]++)] = j;  // in node order: sorted per cell
            }
          }
        }
      }
    }
  }
}

int64_t MlsShapeFunctions::CellOf(const Vector3d& x) const {
  int c[3];
  for (int a = 0; a < 3; ++a) {
    const double v = std::floor((x[a] - grid_origin_[a]) / cell_);
    c[a] = static_cast<int>(std::clamp(v, 0.0, static_cast<double>(grid_size_[a] - 1)));
  }
  return static_cast<int64_t>(c[0]) +
         int64_t{grid_size_[0]} * (c[1] + int64_t{grid_size_[1]} * c[2]);
}

void MlsShapeFunctions::CoveringNodes(const Vector3d& x, std::vector<int32_t>* out) const {
  if (!x.allFinite()) return;
  const auto cell = static_cast<size_t>(CellOf(x));
  for (int32_t t = cell_start_[cell]; t < cell_start_[cell + 1]; ++t) {
    const int32_t j = cell_nodes_[size_t(t)];
    if ((x - nodes_.col(j)).norm() < radius_[size_t(j)]) out->push_back(j);
  }
}

void MlsShapeFunctions::Evaluate(const Vector3d& x, bool with_gradients,
                                 std::span<const Vector3d> cut_triangles,
                                 MlsEvaluation* out) const {
  if (!x.allFinite()) Refuse("evaluation point " + PointName(x) + " is not finite");
  out->nodes.clear();
  out->values.clear();
  // The covering nodes: their weights (and the weights' gradients) and shifted, scaled bases.
  const auto cell = static_cast<size_t>(CellOf(x));
  std::vector<double> w, dw_dr;
  for (int32_t t = cell_start_[cell]; t < cell_start_[cell + 1]; ++t) {
    const int32_t j = cell_nodes_[size_t(t)];
    const double r = (x - nodes_.col(j)).norm() / radius_[size_t(j)];
    if (r >= 1.0) continue;
    bool hidden = false;
    for (size_t k = 0; k + 2 < cut_triangles.size() && !hidden; k += 3) {
      hidden = SegmentCrossesTriangle(nodes_.col(j), x, cut_triangles[k], cut_triangles[k + 1],
                                      cut_triangles[k + 2]);
    }
    if (hidden) continue;
    out->nodes.push_back(j);
    w.push_back(CubicSplineWeight(r));
    dw_dr.push_back(CubicSplineWeightDerivative(r));
  }
  const size_t m = out->nodes.size();
  if (m < 4) {
    Refuse("the point " + PointName(x) + " is covered by " + std::to_string(m) +
           " node supports; a linear basis needs at least 4 (enlarge support_scale)");
  }
  const double h = basis_scale_;
  const auto basis = [&](size_t a) {
    Vector4d q;
    q << 1.0, (nodes_.col(out->nodes[a]) - x) / h;
    return q;
  };
  Matrix4d moments = Matrix4d::Zero();
  for (size_t a = 0; a < m; ++a) {
    const Vector4d q = basis(a);
    moments.noalias() += w[a] * q * q.transpose();
  }
  const Eigen::SelfAdjointEigenSolver<Matrix4d> eigen(moments, Eigen::EigenvaluesOnly);
  const double lmax = eigen.eigenvalues().maxCoeff(), lmin = eigen.eigenvalues().minCoeff();
  if (!(lmin > min_rcond_ * lmax)) {
    std::ostringstream s;
    s << "the moment matrix at " << PointName(x) << " is singular or ill-conditioned (rcond "
      << lmin / lmax << ", " << m << " supports; nodes nearly coplanar there)";
    Refuse(s.str());
  }
  const Matrix4d inverse = moments.inverse();
  // γ = A⁻¹ p(x), p(x) = e0 in the shifted basis; φ_J = w_J γ·q_J.
  const Vector4d gamma = inverse.col(0);
  out->values.resize(m);
  for (size_t a = 0; a < m; ++a) out->values[a] = w[a] * gamma.dot(basis(a));
  if (!with_gradients) return;
  // ∂_k w_J = w'(r) (x - X_J)_k / (|x - X_J| ρ_J); ∂_k A = Σ ∂_k w_J q_J q_Jᵀ;
  // ∂_k γ = A⁻¹ (∂_k p - ∂_k A γ), ∂_k p = e_{k+1} / h;
  // ∂_k φ_J = w_J ∂_k γ·q_J + ∂_k w_J γ·q_J.
  Eigen::Matrix<double, 3, Eigen::Dynamic> dw(3, static_cast<Eigen::Index>(m));
  Matrix4d dmoments[3] = {Matrix4d::Zero(), Matrix4d::Zero(), Matrix4d::Zero()};
  for (size_t a = 0; a < m; ++a) {
    const Vector3d d = x - nodes_.col(out->nodes[a]);
    const double dist = d.norm();
    const auto col = static_cast<Eigen::Index>(a);
    dw.col(col) = dist > 0.0 ? Vector3d(dw_dr[a] * d / (dist * radius_[size_t(out->nodes[a])]))
                             : Vector3d::Zero();
    const Vector4d q = basis(a);
    const Matrix4d qq = q * q.transpose();
    for (int k = 0; k < 3; ++k) dmoments[k] += dw(k, col) * qq;
  }
  Vector4d dgamma[3];
  for (int k = 0; k < 3; ++k) {
    Vector4d dp = Vector4d::Zero();
    dp[k + 1] = 1.0 / h;
    dgamma[k] = inverse * (dp - dmoments[k] * gamma);
  }
  out->gradients.resize(3, static_cast<Eigen::Index>(m));
  for (size_t a = 0; a < m; ++a) {
    const Vector4d q = basis(a);
    const auto col = static_cast<Eigen::Index>(a);
    const double gq = gamma.dot(q);
    for (int k = 0; k < 3; ++k) {
      out->gradients(k, col) = w[a] * dgamma[k].dot(q) + dw(k, col) * gq;
    }
  }
}

}  // namespace somasim::models::meshless
