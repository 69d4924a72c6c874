// Moving-least-squares (MLS) shape functions for the element-free Galerkin model (SPEC §4.6,
// seed 001: "无网格迦辽金", element-free Galerkin with MLS approximation; Belytschko, Lu & Gu
// 1994). Pure numerical functions on Eigen: no I/O.
//
// Approximation: u(x) = Σ_J φ_J(x) û_J over the nodes J whose support contains x, with
//   φ_J(x) = p(x)ᵀ A(x)⁻¹ w_J(x) p(X_J),   A(x) = Σ_J w_J(x) p(X_J) p(X_J)ᵀ   (4 × 4 moments),
// linear basis p = (1, x, y, z), so Σ_J φ_J = 1 and Σ_J φ_J X_J = x exactly (linear
// reproduction: the patch test's condition). The basis is evaluated shifted to the evaluation
// point and scaled by the mean support radius, (1, (X - x)/h): an affine change of the basis
// leaves its span, hence φ_J, unchanged, and keeps A well conditioned at any coordinate offset.
// Gradients: with γ = A⁻¹ p(x), φ_J = w_J γ·p(X_J) and ∂_k γ = A⁻¹ (∂_k p - ∂_k A γ),
//   ∂_k φ_J = w_J ∂_k γ·p(X_J) + ∂_k w_J γ·p(X_J)   (Belytschko, Krongauz et al. 1996).
//
// Weight: the cubic spline w(r), r = |x - X_J| / ρ_J in [0, 1] (C², compact, w(1) = 0):
//   w = 2/3 - 4 r² + 4 r³                 for r <= 1/2,
//   w = 4/3 - 4 r + 4 r² - 4/3 r³         for 1/2 < r <= 1,   0 beyond.
// Support radius of node J: ρ_J = max(support_scale · d_k(J), min_radius_J), with d_k(J) the
// distance from X_J to its k-th nearest other node (k = support_neighbours). Defaults: scale
// 2.0, k = 4: on a regular grid of spacing h, d_4 = h and ρ = 2h, about 33 nodes cover a point
// (the usual 3D EFG density). min_radius lets a caller guarantee invertibility where node
// spacing is irregular: the EFG model passes 1.2 × each node's longest incident tet edge, so
// every point of a tetrahedron is inside the supports of its four (non-coplanar) corners with
// r <= 0.83 and A is never singular inside the mesh.
//
// Neighbour search: a uniform grid of cells of edge ≈ the mean support radius in which each
// node is listed in every cell its support's bounding box overlaps; an evaluation reads the one
// cell holding x (O(nodes per cell), no O(N²)). Building the radii costs one grid query per
// node as well.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"

namespace somasim::models::meshless {

struct MlsParameters {
  double support_scale = 2.0;  // ρ_J / d_k(J) [-], finite, >= 1
  int support_neighbours = 4;  // k [-], in 1..64 and < num_nodes
  // The smallest accepted reciprocal condition number of the (scaled) moment matrix A(x),
  // λ_min / λ_max; below it an evaluation throws.
  double min_reciprocal_condition = 1e-10;
};

// The cubic spline weight w(r) and its derivative dw/dr (r >= 0; 0 for r >= 1).
double CubicSplineWeight(double r);
double CubicSplineWeightDerivative(double r);

// One evaluation: the nodes whose support contains x, in increasing index order, with φ_J(x)
// and ∇φ_J(x) [1/m] at the same positions.
struct MlsEvaluation {
  std::vector<int32_t> nodes;
  std::vector<double> values;
  Eigen::Matrix<double, 3, Eigen::Dynamic> gradients;  // 3 × nodes.size()
};

class MlsShapeFunctions {
 public:
  // nodes: [m], 3 × num_nodes, finite, at least 4. min_radius: [m], num_nodes values or empty.
  // Throws std::invalid_argument naming the bad parameter or node.
  MlsShapeFunctions(const mesh::Points& nodes, const MlsParameters& parameters,
                    std::span<const double> min_radius = {});

  int32_t num_nodes() const { return static_cast<int32_t>(nodes_.cols()); }
  const mesh::Points& nodes() const { return nodes_; }
  const std::vector<double>& support_radii() const { return radius_; }  // ρ_J [m], num_nodes

  // φ_J(x) and, when `with_gradients`, ∇φ_J(x) at the point x [m]. Allocates (into `out`, reused
  // across calls): for precomputation, not for a real-time step. Throws std::invalid_argument
  // naming x when fewer than 4 supports cover it or A(x) is ill-conditioned.
  void Evaluate(const Eigen::Vector3d& x, bool with_gradients, MlsEvaluation* out) const {
    Evaluate(x, with_gradients, {}, out);
  }
  // The same with the visibility criterion (Belytschko, Lu & Gu 1994; seed 001's cutting in
  // the meshless region): a node J whose segment X_J–x crosses one of the cut triangles
  // (cut_triangles: [m], 3 vertices per triangle; SegmentCrossesTriangle) does not cover x.
  // The caller passes the triangles near x (the cost is O(supports × triangles)).
  void Evaluate(const Eigen::Vector3d& x, bool with_gradients,
                std::span<const Eigen::Vector3d> cut_triangles, MlsEvaluation* out) const;
  // The nodes whose support contains x, without the visibility criterion or the moment matrix
  // (cheap: a grid cell's list), appended to `out` in the grid's order.
  void CoveringNodes(const Eigen::Vector3d& x, std::vector<int32_t>* out) const;
  // The largest support radius, max ρ_J [m].
  double max_support_radius() const { return max_radius_; }

 private:
  // The flattened index of the grid cell containing x (clamped to the grid).
  int64_t CellOf(const Eigen::Vector3d& x) const;

  mesh::Points nodes_;          // [m], 3 × num_nodes
  std::vector<double> radius_;  // ρ_J [m], num_nodes
  double basis_scale_ = 1.0;    // h [m]: the mean support radius
  double max_radius_ = 0.0;     // max ρ_J [m]
  double min_rcond_ = 1e-10;
  Eigen::Vector3d grid_origin_;      // [m]
  double cell_ = 1.0;                // cell edge [m]
  Eigen::Vector3i grid_size_;        // cells per axis
  std::vector<int32_t> cell_start_;  // num_cells + 1 (CSR into cell_nodes_)
  std::vector<int32_t> cell_nodes_;  // nodes whose support box overlaps each cell
};

}  // namespace somasim::models::meshless
