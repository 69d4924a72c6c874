// Hyperelastic laws (seed 000, SPEC §4.4): stress is the energy's derivative and its differential
// the stress's, at small strain every law is Hooke's with its initial moduli, the liver's stated
// D1 gives the stated Poisson ratio, and bad coefficients are refused.
#include "server/models/fem/hyperelastic.h"

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <cmath>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;

std::vector<HyperelasticMaterial> Materials() {
  return {LiverNava2008(), NeoHookean(600.0, 1e-4), StVenantKirchhoff(5000.0, 0.35)};
}

// A deformation gradient with large stretch, shear and rotation (det > 0).
Matrix3d SomeF(unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> value(-0.25, 0.25);
  Matrix3d f = Matrix3d::Identity();
  for (int k = 0; k < 9; ++k) f.data()[k] += value(rng);
  return f;
}

TEST(Hyperelastic, StressIsTheEnergyDerivative) {
  for (const HyperelasticMaterial& m : Materials()) {
    for (unsigned seed = 1; seed <= 3; ++seed) {
      const Matrix3d f = SomeF(seed);
      ASSERT_GT(f.determinant(), 0.0);
      const Matrix3d p = FirstPiolaStress(m, f);
      const double h = 1e-6;
      for (int k = 0; k < 9; ++k) {
        Matrix3d fp = f, fm = f;
        fp.data()[k] += h;
        fm.data()[k] -= h;
        const double fd = (StrainEnergy(m, fp) - StrainEnergy(m, fm)) / (2.0 * h);
        EXPECT_NEAR(p.data()[k], fd, 1e-6 * p.cwiseAbs().maxCoeff()) << k;
      }
    }
  }
}

TEST(Hyperelastic, StressDifferentialIsTheStressDerivative) {
  for (const HyperelasticMaterial& m : Materials()) {
    const Matrix3d f = SomeF(7);
    const Matrix3d df = SomeF(8) - Matrix3d::Identity();
    const double h = 1e-6;
    const Matrix3d fd =
        (FirstPiolaStress(m, f + h * df) - FirstPiolaStress(m, f - h * df)) / (2.0 * h);
    const Matrix3d dp = StressDifferential(m, f, df);
    EXPECT_LT((dp - fd).norm(), 1e-6 * dp.norm());
  }
}

// At F = I every law linearises to Hooke's law with λ0 = κ0 - 2μ0/3 and μ0.
// The prepared form (what an element tangent uses for its twelve dF) equals the direct one, and
// a material with all three D terms too.
TEST(Hyperelastic, PreparedStressDifferentialEqualsTheDirectOne) {
  std::vector<HyperelasticMaterial> materials = Materials();
  HyperelasticMaterial three = LiverNava2008();
  three.d[1] = 2.0 * three.d[0];
  three.d[2] = 5.0 * three.d[0];
  materials.push_back(three);
  for (const HyperelasticMaterial& m : materials) {
    for (unsigned seed = 1; seed <= 3; ++seed) {
      const Matrix3d f = SomeF(seed);
      const StressPoint point = PrepareStressDifferential(m, f);
      const Matrix3d df = SomeF(seed + 10) - Matrix3d::Identity();
      const Matrix3d direct = StressDifferential(m, f, df);
      EXPECT_LT((StressDifferential(point, df) - direct).norm(), 1e-12 * direct.norm());
    }
  }
}

TEST(Hyperelastic, SmallStrainIsHookesLawWithTheInitialModuli) {
  for (const HyperelasticMaterial& m : Materials()) {
    const double mu = m.InitialShearModulus();
    const double lambda = m.InitialBulkModulus() - 2.0 * mu / 3.0;
    const Matrix3d df = SomeF(9) - Matrix3d::Identity();
    const Matrix3d eps = 0.5 * (df + df.transpose());
    const Matrix3d hooke = lambda * eps.trace() * Matrix3d::Identity() + 2.0 * mu * eps;
    EXPECT_LT((StressDifferential(m, Matrix3d::Identity(), df) - hooke).norm(),
              1e-9 * hooke.norm());
    EXPECT_LT(FirstPiolaStress(m, Matrix3d::Identity()).norm(), 1e-9 * mu);
  }
}

TEST(Hyperelastic, LiverD1GivesTheStatedPoissonRatio) {
  const HyperelasticMaterial liver = LiverNava2008();
  EXPECT_DOUBLE_EQ(liver.InitialShearModulus(), 1767.6);  // 2 C10 [Pa]
  EXPECT_NEAR(liver.InitialPoissonRatio(), 0.49, 1e-12);
  EXPECT_NEAR(liver.d[0], 3.0 * 0.02 / (1767.6 * 1.49), 1e-18);
  EXPECT_NEAR(LiverNava2008(0.45).InitialPoissonRatio(), 0.45, 1e-12);
}

TEST(Hyperelastic, RefusesBadCoefficients) {
  const auto refused = [](const HyperelasticMaterial& m, const std::string& what) {
    try {
      CheckMaterial(m);
      ADD_FAILURE() << "accepted: " << what;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  };
  refused(NeoHookean(0.0, 1e-4), "C10");
  refused(NeoHookean(500.0, 0.0), "D1");
  refused(NeoHookean(500.0, std::nan("")), "D1");
  HyperelasticMaterial m = LiverNava2008();
  m.c[3] = std::nan("");
  refused(m, "C40");
  m = LiverNava2008();
  m.d[1] = -1.0;
  refused(m, "D2");
  refused(StVenantKirchhoff(-5.0, 0.3), "mu > 0");
  EXPECT_NO_THROW(CheckMaterial(LiverNava2008()));
}

TEST(Hyperelastic, InvertedElementHasNoFiniteEnergy) {
  Matrix3d f = Matrix3d::Identity();
  f(2, 2) = -0.5;
  EXPECT_TRUE(std::isinf(StrainEnergy(LiverNava2008(), f)));
}

}  // namespace
}  // namespace somasim::models::fem
