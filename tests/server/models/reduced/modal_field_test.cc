// The reduced models' field reconstruction (modal_field.h): x = X + B ξ and v = B ξ̇ from the
// single-precision chunked layout agree with a double computation, for DOF counts that do and
// do not fill the last 32-DOF chunk, and the reconstruction's own check sees what it wrote.
#include "server/models/reduced/modal_field.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

namespace somasim::models::reduced {
namespace {

struct Field {
  Eigen::MatrixXd modes;
  Eigen::VectorXd rest, xi, rate;
  Eigen::VectorXf xi_single, rate_single;
};

Field RandomField(Eigen::Index dofs, Eigen::Index n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Field f;
  f.modes = Eigen::MatrixXd::NullaryExpr(dofs, n, [&] { return 0.05 * u(rng); });
  f.rest = Eigen::VectorXd::NullaryExpr(dofs, [&] { return 0.1 * u(rng); });
  f.xi = Eigen::VectorXd::NullaryExpr(n, [&] { return 0.02 * u(rng); });
  f.rate = Eigen::VectorXd::NullaryExpr(n, [&] { return 0.5 * u(rng); });
  f.xi_single = f.xi.cast<float>();
  f.rate_single = f.rate.cast<float>();
  return f;
}

TEST(ModalField, ReconstructionEqualsTheDoubleSumForFullAndPartialChunks) {
  for (const Eigen::Index dofs : {Eigen::Index{96}, Eigen::Index{12165}, Eigen::Index{7}}) {
    for (const Eigen::Index n : {Eigen::Index{1}, Eigen::Index{8}, Eigen::Index{33}}) {
      const Field f = RandomField(dofs, n, static_cast<uint32_t>(dofs + n));
      const ModalField field(f.modes);
      Eigen::VectorXd x(dofs), v(dofs);
      const StateCheck check = field.Reconstruct(f.xi_single.data(), f.rate_single.data(),
                                                 f.rest.data(), x.data(), v.data(), 1e3);
      EXPECT_FALSE(check.non_finite);
      EXPECT_FALSE(check.maybe_too_fast);
      const Eigen::VectorXd u = f.modes * f.xi;
      const Eigen::VectorXd w = f.modes * f.rate;
      // Single precision: the modes' and coordinates' rounding, ~1e-7 of the sums' terms.
      const double u_scale = f.modes.cwiseAbs().maxCoeff() * f.xi.cwiseAbs().sum();
      const double w_scale = f.modes.cwiseAbs().maxCoeff() * f.rate.cwiseAbs().sum();
      EXPECT_LE((x - f.rest - u).cwiseAbs().maxCoeff(), 1e-6 * u_scale) << dofs << " " << n;
      EXPECT_LE((v - w).cwiseAbs().maxCoeff(), 1e-6 * w_scale) << dofs << " " << n;
    }
  }
}

TEST(ModalField, TheReconstructionFlagsNonFiniteValuesAndFastComponentsItWrote) {
  for (const Eigen::Index dofs : {Eigen::Index{12165}, Eigen::Index{7}}) {
    Field f = RandomField(dofs, 8, 5);
    const ModalField field(f.modes);
    Eigen::VectorXd x(dofs), v(dofs);
    f.xi_single(3) = std::numeric_limits<float>::quiet_NaN();
    EXPECT_TRUE(field
                    .Reconstruct(f.xi_single.data(), f.rate_single.data(), f.rest.data(), x.data(),
                                 v.data(), 1e3)
                    .non_finite);
    f.xi_single(3) = std::numeric_limits<float>::infinity();
    EXPECT_TRUE(field
                    .Reconstruct(f.xi_single.data(), f.rate_single.data(), f.rest.data(), x.data(),
                                 v.data(), 1e3)
                    .non_finite);
    f.xi_single = f.xi.cast<float>();
    const StateCheck slow = field.Reconstruct(f.xi_single.data(), f.rate_single.data(),
                                              f.rest.data(), x.data(), v.data(), 1e3);
    EXPECT_FALSE(slow.non_finite);
    EXPECT_FALSE(slow.maybe_too_fast);
    const double fastest = v.cwiseAbs().maxCoeff();
    const StateCheck fast = field.Reconstruct(f.xi_single.data(), f.rate_single.data(),
                                              f.rest.data(), x.data(), v.data(), 0.5 * fastest);
    EXPECT_FALSE(fast.non_finite);
    EXPECT_TRUE(fast.maybe_too_fast);
  }
}

}  // namespace
}  // namespace somasim::models::reduced
