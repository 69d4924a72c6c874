// Karhunen–Loève modes (proper orthogonal decomposition) of displacement snapshots by the method
// of snapshots (SPEC §4.5; seed 000 §3, after Sirovich 1987): the eigen-decomposition of the
// M × M QᵀQ instead of the K × K correlation (docs/reduced.md, "The modes"). Pure: no I/O.
// Allocates (offline, `somasim-reduce`).
#pragma once

#include <Eigen/Core>
#include <cstdint>

namespace somasim::models::reduced {

struct PodSettings {
  // Keep the fewest leading modes whose eigenvalues sum to at least this share of the total
  // (Σ_{k≤n} λ_k ≥ energy_fraction Σ_k λ_k), in (0, 1] ...
  double energy_fraction = 0.9999;
  // ... but at most this many (> 0), and never a mode whose eigenvalue is below
  // rank_tolerance × λ_1 (such a mode is rounding noise: Q has no such direction).
  int32_t max_modes = 32;
  double rank_tolerance = 1e-12;
};

struct PodModes {
  Eigen::MatrixXd modes;        // B: K × n, orthonormal columns θ_1..θ_n [-]
  Eigen::VectorXd eigenvalues;  // all M eigenvalues λ_k of QᵀQ, descending [m² for metres]
  double kept_fraction = 0.0;   // Σ_{k≤n} λ_k / Σ_k λ_k
};

// The leading modes of `snapshots` (K × M, M ≥ 1, K ≥ M, finite, not all zero) by the method of
// snapshots and the settings' criterion. The modes are re-orthonormalised (Gram–Schmidt, twice)
// against the rounding the division by √λ_k amplifies for small λ_k. Throws
// std::invalid_argument naming what is wrong (sizes, a non-finite value, no nonzero snapshot,
// settings out of range).
// With `weighted` = W Q (K × M; W symmetric positive semi-definite, e.g. the stiffness: the
// energy inner product), the decomposition is of QᵀWQ: the leading modes then span the
// snapshots best in the W-norm (a mode may carry little displacement and much strain energy —
// a loaded node's near field — which the Euclidean criterion would drop, while a Galerkin model
// is only as good as its basis in the energy norm). The modes returned span the same subspace,
// orthonormalised in the Euclidean sense; the eigenvalues are QᵀWQ's.
PodModes ModesOfSnapshots(const Eigen::MatrixXd& snapshots, const PodSettings& settings,
                          const Eigen::MatrixXd* weighted = nullptr);

}  // namespace somasim::models::reduced
