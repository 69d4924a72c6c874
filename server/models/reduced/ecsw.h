// Energy-conserving sampling and weighting (ECSW; Farhat, Avery, Chapman & Cortial 2014, "Dimen-
// sional reduction of nonlinear finite element dynamic models with finite rotations and energy-
// based mesh sampling and weighting for computational efficiency"; issue 12, docs/reduced.md):
// the cubature the nonlinear reduced model (nonlinear_model.h) evaluates its forces on. For
// training displacements u_s (s = 1..S) projected onto the modes, ξ_s = Bᵀ u_s (least squares),
// each element's reduced internal force g_es = −V_e D_eᵀ vec P(I + D_e ξ_s) (n values) is a
// column block of G (nS × E), and the full reduced force b_s = Σ_e g_es the right-hand side.
// Rows of snapshot s are divided by |b_s| (every snapshot counts alike, small loads too). A
// snapshot whose projection onto the modes inverts an element (a large load's local dent the
// modes do not hold) is left out and counted.
// Weights w >= 0 with few non-zeros and |G w − b| <= tolerance |b| come from the
// non-negative least squares of Lawson & Hanson (1974), stopped at the tolerance: a greedy
// active set that adds the element with the largest gradient Gᵀ(b − G w) and keeps the weights
// positive. Offline: allocates, seconds to a minute on liver4055.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/fem_model.h"

namespace somasim::models::reduced {

struct NnlsResult {
  std::vector<int32_t> columns;  // the non-zero weights' columns, ascending
  std::vector<double> weights;   // their weights, each > 0
  double relative_residual = 0;  // |G w − b| / |b|
  int iterations = 0;            // columns added
  bool converged = false;        // the tolerance was reached
};

// Lawson–Hanson NNLS on G (m × E) and b (m), stopped once |G w − b| <= tolerance |b| (> 0), at
// the optimum, or with max_columns (>= 1) non-zero weights. The least-squares problems of the
// active set are solved by an incrementally updated QR factorisation (modified Gram–Schmidt,
// twice), so a column costs O(m k) instead of O(m k²). Throws std::invalid_argument for sizes
// that do not match, a non-finite value or a bad tolerance.
NnlsResult SparseNnls(const Eigen::MatrixXd& g, const Eigen::VectorXd& b, double tolerance,
                      int max_columns);

struct CubatureSettings {
  double tolerance = 0.01;  // relative error of the reduced forces on the training set, (0, 1)
  int max_elements = 3000;  // >= 1
};

struct Cubature {
  std::vector<int32_t> elements;  // indices into the full model's tetrahedra, ascending
  std::vector<double> weights;    // each > 0
  double relative_residual = 0.0;
  bool converged = false;
  int snapshots = 0;  // training displacements used (those with non-zero reduced force)
  int inverted = 0;   // training displacements left out: their projection inverts an element
};

// ECSW weights for the hyperelastic `full` model (FemKind::kHyperelastic) on `modes`
// (3N × n) from training displacements (each 3 × N [m]). With `test_modes` Ψ (3N × n; a
// Petrov–Galerkin model, nonlinear_model.h) the forces fitted are Ψᵀ f (g_es = −V_e D̃_eᵀ vec P,
// D̃_e from Ψ), the equations that model solves. Throws std::invalid_argument for another kind
// of model, sizes that do not match, or no usable snapshot.
Cubature TrainCubature(const fem::FemModel& full, const Eigen::MatrixXd& modes,
                       std::span<const mesh::Points> displacements,
                       const CubatureSettings& settings,
                       const Eigen::MatrixXd* test_modes = nullptr);

}  // namespace somasim::models::reduced
