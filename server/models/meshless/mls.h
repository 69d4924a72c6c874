// Moving-least-squares (MLS) shape functions for the element-free Galerkin models (SPEC §4.6,
// seed 001; Belytschko, Lu & Gu 1994): linear basis, cubic-spline weight, supports from the k-th
// nearest node, neighbours from a uniform grid, and the visibility criterion for cuts.
// Derivations: docs/models.md, "MLS shape functions in detail". Pure: no I/O.
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
