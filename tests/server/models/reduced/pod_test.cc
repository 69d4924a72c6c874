// Karhunen–Loève modes by the method of snapshots (server/models/reduced/pod.h).
#include "server/models/reduced/pod.h"

#include <gtest/gtest.h>

#include <Eigen/SVD>
#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>

namespace somasim::models::reduced {
namespace {

Eigen::MatrixXd Random(Eigen::Index rows, Eigen::Index cols, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> normal;
  Eigen::MatrixXd m(rows, cols);
  for (Eigen::Index j = 0; j < cols; ++j) {
    for (Eigen::Index i = 0; i < rows; ++i) m(i, j) = normal(rng);
  }
  return m;
}

// Q = U diag(sigma) Vᵀ with orthonormal U (K × M) and V (M × M).
Eigen::MatrixXd WithSingularValues(Eigen::Index rows, const Eigen::VectorXd& sigma, uint32_t seed) {
  const Eigen::Index m = sigma.size();
  const Eigen::MatrixXd u =
      Random(rows, m, seed).householderQr().householderQ() * Eigen::MatrixXd::Identity(rows, m);
  const Eigen::MatrixXd v = Random(m, m, seed + 1).householderQr().householderQ();
  return u * sigma.asDiagonal() * v.transpose();
}

TEST(Pod, MethodOfSnapshotsGivesTheSnapshotsLeftSingularVectors) {
  const Eigen::MatrixXd q = Random(300, 12, 7);
  PodSettings settings;
  settings.energy_fraction = 1.0;
  settings.max_modes = 12;
  const PodModes pod = ModesOfSnapshots(q, settings);
  const Eigen::JacobiSVD<Eigen::MatrixXd> svd(q, Eigen::ComputeThinU);
  ASSERT_EQ(pod.modes.cols(), 12);
  ASSERT_EQ(pod.eigenvalues.size(), 12);
  for (Eigen::Index k = 0; k < 12; ++k) {
    const double sigma = svd.singularValues()(k);
    EXPECT_NEAR(pod.eigenvalues(k), sigma * sigma, 1e-10 * sigma * sigma) << k;
    EXPECT_NEAR(std::abs(pod.modes.col(k).dot(svd.matrixU().col(k))), 1.0, 1e-8) << k;
  }
  EXPECT_LT(
      (pod.modes.transpose() * pod.modes - Eigen::MatrixXd::Identity(12, 12)).cwiseAbs().maxCoeff(),
      1e-13);
  EXPECT_DOUBLE_EQ(pod.kept_fraction, 1.0);
  // Every snapshot is in the modes' span.
  EXPECT_LT((q - pod.modes * (pod.modes.transpose() * q)).norm(), 1e-10 * q.norm());
}

TEST(Pod, EnergyCriterionKeepsTheFewestModesThatReachTheFraction) {
  Eigen::VectorXd sigma(5);
  sigma << 10.0, 1.0, 0.1, 0.01, 0.001;  // eigenvalues 100, 1, 1e-2, 1e-4, 1e-6
  const Eigen::MatrixXd q = WithSingularValues(200, sigma, 3);
  const double total = sigma.squaredNorm();
  PodSettings settings;
  settings.max_modes = 5;
  settings.energy_fraction = 0.995;  // the first holds 100 / 101.0101 = 0.990: a second is needed
  EXPECT_EQ(ModesOfSnapshots(q, settings).modes.cols(), 2);
  settings.energy_fraction = 0.9999 * 100.0 / total;  // just what the first holds
  EXPECT_EQ(ModesOfSnapshots(q, settings).modes.cols(), 1);
  settings.energy_fraction = 0.9999999;
  EXPECT_EQ(ModesOfSnapshots(q, settings).modes.cols(), 4);
  settings.max_modes = 3;
  const PodModes capped = ModesOfSnapshots(q, settings);
  EXPECT_EQ(capped.modes.cols(), 3);
  EXPECT_NEAR(capped.kept_fraction, 101.01 / total, 1e-12);
}

TEST(Pod, RankDeficientSnapshotsGiveNoNoiseModes) {
  Eigen::MatrixXd q(150, 6);
  q.leftCols(3) = Random(150, 3, 11);
  q.col(3) = q.col(0) + q.col(1);
  q.col(4) = 2.0 * q.col(2) - q.col(0);
  q.col(5) = q.col(1);
  PodSettings settings;
  settings.energy_fraction = 1.0;
  settings.max_modes = 6;
  const PodModes pod = ModesOfSnapshots(q, settings);
  EXPECT_EQ(pod.modes.cols(), 3);
  EXPECT_LT((q - pod.modes * (pod.modes.transpose() * q)).norm(), 1e-10 * q.norm());
}

TEST(Pod, RefusesBadSnapshotsAndSettingsByName) {
  const auto message = [](const Eigen::MatrixXd& q, const PodSettings& s) {
    try {
      ModesOfSnapshots(q, s);
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("accepted");
  };
  const PodSettings ok;
  EXPECT_NE(message(Eigen::MatrixXd(10, 0), ok).find("1 <= M <= K"), std::string::npos);
  EXPECT_NE(message(Random(3, 5, 1), ok).find("3 × 5"), std::string::npos);
  Eigen::MatrixXd nan = Random(20, 3, 1);
  nan(4, 1) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(message(nan, ok).find("not finite"), std::string::npos);
  EXPECT_NE(message(Eigen::MatrixXd::Zero(20, 3), ok).find("zero"), std::string::npos);
  PodSettings bad = ok;
  bad.energy_fraction = 1.5;
  EXPECT_NE(message(Random(20, 3, 1), bad).find("energy_fraction"), std::string::npos);
  bad = ok;
  bad.max_modes = 0;
  EXPECT_NE(message(Random(20, 3, 1), bad).find("max_modes"), std::string::npos);
}

}  // namespace
}  // namespace somasim::models::reduced
