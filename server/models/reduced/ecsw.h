// Energy-conserving sampling and weighting (ECSW; Farhat, Avery, Chapman & Cortial 2014; issue
// 12): the cubature the nonlinear reduced model (nonlinear_model.h) evaluates its forces on —
// a few elements with positive weights from Lawson–Hanson non-negative least squares on training
// displacements. Derivation: docs/reduced.md, "The cubature". Offline: allocates.
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
