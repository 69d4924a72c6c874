// FemModel::ApplyCut: elements cut away and nodes relocated by the cutter, in the state's own
// copy of the rest geometry.
#include <Eigen/Dense>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

#include "server/models/fem/fem_model.h"
#include "server/models/fem/fem_model_internal.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using internal::FemState;
using internal::Refuse;

// Element e's rest gradients (3 × 4, column a = ∇N_a) and volume from the rest positions:
// with D = [X1 - X0, X2 - X0, X3 - X0], ∇N_1..3 are the columns of D⁻ᵀ and ∇N_0 = -Σ; V =
// det D / 6. False (nothing written) when det D <= 0.
bool RestGeometry(const mesh::Points& rest, const mesh::Tetrahedra& tets, int32_t e,
                  Eigen::Matrix<double, 3, 4>* gradients, double* volume) {
  Matrix3d d;
  for (int c = 0; c < 3; ++c) d.col(c) = rest.col(tets(c + 1, e)) - rest.col(tets(0, e));
  const double det = d.determinant();
  if (!(det > 0.0)) return false;
  const Matrix3d inv_t = d.inverse().transpose();
  gradients->rightCols<3>() = inv_t;
  gradients->col(0) = -inv_t.rowwise().sum();
  *volume = det / 6.0;
  return true;
}

}  // namespace

void FemModel::ApplyCut(std::span<const int32_t> removed, std::span<const int32_t> moved,
                        const mesh::Points& positions_before, TissueState* base) const {
  auto* state = static_cast<FemState*>(base);
  const int32_t n = num_nodes(), m = num_tets();
  for (const int32_t e : removed) {
    if (e < 0 || e >= m) Refuse("cut: element " + std::to_string(e) + " out of range");
    if (!(state->volumes[static_cast<size_t>(e)] > 0.0)) {
      Refuse("cut: element " + std::to_string(e) + " was already cut away");
    }
  }
  for (const int32_t node : moved) {
    if (node < 0 || node >= n) Refuse("cut: node " + std::to_string(node) + " out of range");
  }
  if (positions_before.cols() != n || !positions_before.allFinite()) {
    Refuse("cut: positions before the cut must be 3 x num_nodes and finite");
  }
  for (const int32_t e : removed) {
    state->volumes[static_cast<size_t>(e)] = 0.0;
    ++state->num_cut;
  }
  // The rest moves, all from the geometry before any of them (F̄ at positions_before).
  for (const int32_t node : moved) {
    Matrix3d f_sum = Matrix3d::Zero();
    int count = 0;
    const Shape sh = ShapeOf(*state);
    for (int32_t k = elements_.node_start[static_cast<size_t>(node)];
         k < elements_.node_start[static_cast<size_t>(node) + 1]; ++k) {
      const int32_t e = elements_.element_of_node[static_cast<size_t>(k)] / 4;
      if (!(state->volumes[static_cast<size_t>(e)] > 0.0)) continue;
      f_sum += Matrix3d::Identity() + DisplacementGradientOf(sh, positions_before, e);
      ++count;
    }
    const Vector3d dx = state->positions.col(node) - positions_before.col(node);
    Vector3d dr = dx;
    if (count > 0) {
      const Matrix3d f = f_sum / count;
      const double det = f.determinant();
      if (det > 0.1 && std::isfinite(det)) dr = f.inverse() * dx;
    }
    state->rest_move.col(node) = dr.allFinite() ? dr : dx;
  }
  // Apply each node's rest move, shortened until its alive elements keep 5 % of their
  // original volume; then their gradients and volumes follow.
  for (const int32_t node : moved) {
    const Vector3d from = state->rest.col(node);
    Vector3d step = state->rest_move.col(node);
    bool accepted = false;
    for (int attempt = 0; attempt <= 8 && !accepted; ++attempt, step *= 0.5) {
      state->rest.col(node) = from + step;
      accepted = true;
      for (int32_t k = elements_.node_start[static_cast<size_t>(node)];
           accepted && k < elements_.node_start[static_cast<size_t>(node) + 1]; ++k) {
        const int32_t e = elements_.element_of_node[static_cast<size_t>(k)] / 4;
        if (!(state->volumes[static_cast<size_t>(e)] > 0.0)) continue;
        Eigen::Matrix<double, 3, 4> g;
        double v = 0.0;
        accepted = RestGeometry(state->rest, elements_.tets, e, &g, &v) &&
                   v >= 0.05 * elements_.volumes[static_cast<size_t>(e)];
      }
    }
    if (!accepted) state->rest.col(node) = from;
    for (int32_t k = elements_.node_start[static_cast<size_t>(node)];
         k < elements_.node_start[static_cast<size_t>(node) + 1]; ++k) {
      const int32_t e = elements_.element_of_node[static_cast<size_t>(k)] / 4;
      if (!(state->volumes[static_cast<size_t>(e)] > 0.0)) continue;
      Eigen::Matrix<double, 3, 4> g;
      double v = 0.0;
      if (RestGeometry(state->rest, elements_.tets, e, &g, &v)) {
        state->gradients.middleCols<4>(4 * static_cast<Eigen::Index>(e)) = g;
        state->volumes[static_cast<size_t>(e)] = v;
      }
    }
    double* good = LastGoodPositions(state);
    for (int c = 0; c < 3; ++c) good[3 * static_cast<size_t>(node) + c] = state->positions(c, node);
  }
}

}  // namespace somasim::models::fem
