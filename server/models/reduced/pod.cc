#include "server/models/reduced/pod.h"

#include <Eigen/Eigenvalues>
#include <cmath>
#include <stdexcept>
#include <string>

namespace somasim::models::reduced {

PodModes ModesOfSnapshots(const Eigen::MatrixXd& snapshots, const PodSettings& settings,
                          const Eigen::MatrixXd* weighted) {
  const Eigen::Index dofs = snapshots.rows(), count = snapshots.cols();
  if (count < 1 || dofs < count) {
    throw std::invalid_argument("POD: snapshots must be K × M with 1 <= M <= K, got " +
                                std::to_string(dofs) + " × " + std::to_string(count));
  }
  if (!snapshots.allFinite()) throw std::invalid_argument("POD: a snapshot is not finite");
  if (!(settings.energy_fraction > 0.0 && settings.energy_fraction <= 1.0)) {
    throw std::invalid_argument("POD: energy_fraction must be in (0, 1]");
  }
  if (settings.max_modes < 1) throw std::invalid_argument("POD: max_modes must be > 0");
  if (!(settings.rank_tolerance >= 0.0 && settings.rank_tolerance < 1.0)) {
    throw std::invalid_argument("POD: rank_tolerance must be in [0, 1)");
  }
  if (weighted != nullptr && (weighted->rows() != dofs || weighted->cols() != count)) {
    throw std::invalid_argument("POD: the weighted snapshots are not K × M");
  }
  // The M × M correlation of the snapshots and its eigenpairs (ascending from Eigen).
  Eigen::MatrixXd correlation =
      snapshots.transpose() * (weighted != nullptr ? *weighted : snapshots);
  correlation = 0.5 * (correlation + correlation.transpose()).eval();
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eigen(correlation);
  if (eigen.info() != Eigen::Success) throw std::invalid_argument("POD: eigensolver failed");
  PodModes out;
  out.eigenvalues = eigen.eigenvalues().reverse().cwiseMax(0.0);
  const double total = out.eigenvalues.sum();
  if (!(total > 0.0)) throw std::invalid_argument("POD: every snapshot is zero");
  const double floor = settings.rank_tolerance * out.eigenvalues(0);
  Eigen::Index kept = 0;
  double sum = 0.0;
  while (kept < count && kept < settings.max_modes && out.eigenvalues(kept) > floor &&
         sum < settings.energy_fraction * total) {
    sum += out.eigenvalues(kept);
    ++kept;
  }
  out.kept_fraction = sum / total;
  out.modes.resize(dofs, kept);
  for (Eigen::Index k = 0; k < kept; ++k) {
    const Eigen::Index column = count - 1 - k;  // descending
    out.modes.col(k) = snapshots * eigen.eigenvectors().col(column) / std::sqrt(out.eigenvalues(k));
  }
  // θ_k are orthonormal in exact arithmetic; rounding in v_k is amplified by 1/√λ_k.
  for (int pass = 0; pass < 2; ++pass) {
    for (Eigen::Index k = 0; k < kept; ++k) {
      for (Eigen::Index j = 0; j < k; ++j) {
        out.modes.col(k) -= out.modes.col(j).dot(out.modes.col(k)) * out.modes.col(j);
      }
      out.modes.col(k).normalize();
    }
  }
  return out;
}

}  // namespace somasim::models::reduced
