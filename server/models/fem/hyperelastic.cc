#include "server/models/fem/hyperelastic.h"

#include <Eigen/Dense>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "common/checks/finite.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;

// W'(Ī1) and W''(Ī1) of Σ C_i0 (Ī1 - 3)^i; U'(J) and U''(J) of Σ (J - 1)^{2i} / D_i.
struct Derivatives {
  double w1 = 0.0, w2 = 0.0, u1 = 0.0, u2 = 0.0;
};

// Horner forms of the sums (no std::pow: it dominated the force evaluation).
Derivatives PolynomialDerivatives(const HyperelasticMaterial& m, double i1_bar, double j) {
  Derivatives out;
  const double a = i1_bar - 3.0;
  const std::array<double, 5>& c = m.c;
  out.w1 = c[0] + a * (2.0 * c[1] + a * (3.0 * c[2] + a * (4.0 * c[3] + a * 5.0 * c[4])));
  out.w2 = 2.0 * c[1] + a * (6.0 * c[2] + a * (12.0 * c[3] + a * 20.0 * c[4]));
  const double b = j - 1.0, b2 = b * b;
  // 1/D_i, 0 for an absent term.
  const double e1 = 1.0 / m.d[0];
  const double e2 = m.d[1] != 0.0 ? 1.0 / m.d[1] : 0.0;
  const double e3 = m.d[2] != 0.0 ? 1.0 / m.d[2] : 0.0;
  out.u1 = b * (2.0 * e1 + b2 * (4.0 * e2 + b2 * 6.0 * e3));
  out.u2 = 2.0 * e1 + b2 * (12.0 * e2 + b2 * 30.0 * e3);
  return out;
}

// J^{-2/3}.
double IsochoricFactor(double j) {
  const double c = std::cbrt(j);
  return 1.0 / (c * c);
}

}  // namespace

double HyperelasticMaterial::InitialShearModulus() const {
  return law == HyperelasticLaw::kStVenantKirchhoff ? mu : 2.0 * c[0];
}

double HyperelasticMaterial::InitialBulkModulus() const {
  return law == HyperelasticLaw::kStVenantKirchhoff ? lambda + 2.0 * mu / 3.0 : 2.0 / d[0];
}

double HyperelasticMaterial::InitialPoissonRatio() const {
  const double k = InitialBulkModulus(), g = InitialShearModulus();
  return (3.0 * k - 2.0 * g) / (2.0 * (3.0 * k + g));
}

HyperelasticMaterial LiverNava2008(double poisson_ratio) {
  HyperelasticMaterial m;
  m.c = {883.8, 1707.9, 1449.9, 2691.8, 1757.5};  // [Pa], seed 000 table 1
  const double mu0 = 2.0 * m.c[0];
  m.d[0] = 3.0 * (1.0 - 2.0 * poisson_ratio) / (mu0 * (1.0 + poisson_ratio));
  return m;
}

HyperelasticMaterial NeoHookean(double c10, double d1) {
  HyperelasticMaterial m;
  m.c[0] = c10;
  m.d[0] = d1;
  return m;
}

HyperelasticMaterial StVenantKirchhoff(double youngs_modulus, double poisson_ratio) {
  HyperelasticMaterial m;
  m.law = HyperelasticLaw::kStVenantKirchhoff;
  m.lambda = youngs_modulus * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio));
  m.mu = youngs_modulus / (2.0 * (1.0 + poisson_ratio));
  return m;
}

void CheckMaterial(const HyperelasticMaterial& m) {
  const auto bad = [](const std::string& what) {
    throw std::invalid_argument("fem: hyperelastic material: " + what);
  };
  if (m.law == HyperelasticLaw::kStVenantKirchhoff) {
    if (!checks::FinitePositive(m.mu) || !std::isfinite(m.lambda) ||
        !(m.lambda + 2.0 * m.mu / 3.0 > 0.0)) {
      bad("St Venant-Kirchhoff needs mu > 0 and a bulk modulus lambda + 2 mu / 3 > 0");
    }
    return;
  }
  for (size_t i = 0; i < m.c.size(); ++i) {
    if (!std::isfinite(m.c[i])) bad("C" + std::to_string(i + 1) + "0 is not finite");
  }
  if (!(m.c[0] > 0.0)) bad("C10 must be > 0 (the initial shear modulus is 2 C10)");
  if (!checks::FinitePositive(m.d[0])) {
    bad("D1 must be a finite value > 0 (the initial bulk modulus is 2 / D1)");
  }
  for (size_t i = 1; i < m.d.size(); ++i) {
    if (!checks::FiniteNonNegative(m.d[i])) {
      bad("D" + std::to_string(i + 1) + " must be finite and >= 0 (0: no term)");
    }
  }
}

double StrainEnergy(const HyperelasticMaterial& m, const Matrix3d& f) {
  const double j = f.determinant();
  if (!(j > 0.0)) return std::numeric_limits<double>::infinity();
  if (m.law == HyperelasticLaw::kStVenantKirchhoff) {
    const Matrix3d e = 0.5 * (f.transpose() * f - Matrix3d::Identity());
    return m.mu * e.squaredNorm() + 0.5 * m.lambda * e.trace() * e.trace();
  }
  const double a = IsochoricFactor(j) * f.squaredNorm() - 3.0;  // Ī1 - 3
  const std::array<double, 5>& c = m.c;
  double w = a * (c[0] + a * (c[1] + a * (c[2] + a * (c[3] + a * c[4]))));
  const double b2 = (j - 1.0) * (j - 1.0);
  for (int i = 1; i <= 3; ++i) {
    const double d = m.d[static_cast<size_t>(i - 1)];
    if (d != 0.0) w += (i == 1 ? b2 : i == 2 ? b2 * b2 : b2 * b2 * b2) / d;
  }
  return w;
}

Matrix3d FirstPiolaStress(const HyperelasticMaterial& m, const Matrix3d& f) {
  if (m.law == HyperelasticLaw::kStVenantKirchhoff) {
    const Matrix3d e = 0.5 * (f.transpose() * f - Matrix3d::Identity());
    return f * (m.lambda * e.trace() * Matrix3d::Identity() + 2.0 * m.mu * e);
  }
  // P = W'(Ī1) ∂Ī1/∂F + U'(J) J F⁻ᵀ, ∂Ī1/∂F = J^{-2/3} (2F - (2/3) I1 F⁻ᵀ). F⁻ᵀ = cof(F) / J
  // with the cofactors (columns: cross products of F's columns), J from them: one pass.
  Matrix3d cof;
  cof.col(0) = f.col(1).cross(f.col(2));
  cof.col(1) = f.col(2).cross(f.col(0));
  cof.col(2) = f.col(0).cross(f.col(1));
  const double j = f.col(0).dot(cof.col(0));
  const Matrix3d f_inv_t = cof / j;
  const double i1 = f.squaredNorm();
  const double g = IsochoricFactor(j);
  const Derivatives d = PolynomialDerivatives(m, g * i1, j);
  return d.w1 * g * (2.0 * f - (2.0 / 3.0) * i1 * f_inv_t) + d.u1 * j * f_inv_t;
}

Matrix3d StressDifferential(const HyperelasticMaterial& m, const Matrix3d& f, const Matrix3d& df) {
  if (m.law == HyperelasticLaw::kStVenantKirchhoff) {
    const Matrix3d e = 0.5 * (f.transpose() * f - Matrix3d::Identity());
    const Matrix3d de = 0.5 * (f.transpose() * df + df.transpose() * f);
    const Matrix3d s = m.lambda * e.trace() * Matrix3d::Identity() + 2.0 * m.mu * e;
    const Matrix3d ds = m.lambda * de.trace() * Matrix3d::Identity() + 2.0 * m.mu * de;
    return df * s + f * ds;
  }
  const double j = f.determinant();
  const Matrix3d f_inv_t = f.inverse().transpose();
  const double i1 = f.squaredNorm();
  const double g = IsochoricFactor(j);
  const Derivatives d = PolynomialDerivatives(m, g * i1, j);
  const double tr = (f_inv_t.array() * df.array()).sum();  // F⁻ᵀ : dF = d(ln J)
  const Matrix3d d_f_inv_t = -f_inv_t * df.transpose() * f_inv_t;
  const Matrix3d a = 2.0 * f - (2.0 / 3.0) * i1 * f_inv_t;   // ∂Ī1/∂F = g a
  const double d_i1 = 2.0 * (f.array() * df.array()).sum();  // dI1
  const Matrix3d da = 2.0 * df - (2.0 / 3.0) * (d_i1 * f_inv_t + i1 * d_f_inv_t);
  const double dg = -(2.0 / 3.0) * g * tr;
  const double d_i1_bar = dg * i1 + g * d_i1;
  // d(U' J F⁻ᵀ) = U'' (J tr) J F⁻ᵀ + U' (J tr F⁻ᵀ + J dF⁻ᵀ).
  return d.w2 * d_i1_bar * g * a + d.w1 * (dg * a + g * da) + d.u2 * j * tr * j * f_inv_t +
         d.u1 * j * (tr * f_inv_t + d_f_inv_t);
}

StressPoint PrepareStressDifferential(const HyperelasticMaterial& m, const Matrix3d& f) {
  StressPoint p;
  p.law = m.law;
  p.f = f;
  if (m.law == HyperelasticLaw::kStVenantKirchhoff) {
    const Matrix3d e = 0.5 * (f.transpose() * f - Matrix3d::Identity());
    p.s = m.lambda * e.trace() * Matrix3d::Identity() + 2.0 * m.mu * e;
    p.lambda = m.lambda;
    p.mu = m.mu;
    return p;
  }
  p.j = f.determinant();
  p.f_inv_t = f.inverse().transpose();
  p.i1 = f.squaredNorm();
  p.g = IsochoricFactor(p.j);
  const Derivatives d = PolynomialDerivatives(m, p.g * p.i1, p.j);
  p.w1 = d.w1;
  p.w2 = d.w2;
  p.u1 = d.u1;
  p.u2 = d.u2;
  p.a = 2.0 * f - (2.0 / 3.0) * p.i1 * p.f_inv_t;
  return p;
}

Matrix3d StressDifferential(const StressPoint& p, const Matrix3d& df) {
  if (p.law == HyperelasticLaw::kStVenantKirchhoff) {  // as StressDifferential(m, f, df)
    const Matrix3d de = 0.5 * (p.f.transpose() * df + df.transpose() * p.f);
    const Matrix3d ds = p.lambda * de.trace() * Matrix3d::Identity() + 2.0 * p.mu * de;
    return df * p.s + p.f * ds;
  }
  const double tr = (p.f_inv_t.array() * df.array()).sum();  // F⁻ᵀ : dF = d(ln J)
  const Matrix3d d_f_inv_t = -p.f_inv_t * df.transpose() * p.f_inv_t;
  const double d_i1 = 2.0 * (p.f.array() * df.array()).sum();  // dI1
  const Matrix3d da = 2.0 * df - (2.0 / 3.0) * (d_i1 * p.f_inv_t + p.i1 * d_f_inv_t);
  const double dg = -(2.0 / 3.0) * p.g * tr;
  const double d_i1_bar = dg * p.i1 + p.g * d_i1;
  return p.w2 * d_i1_bar * p.g * p.a + p.w1 * (dg * p.a + p.g * da) +
         p.u2 * p.j * tr * p.j * p.f_inv_t + p.u1 * p.j * (tr * p.f_inv_t + d_f_inv_t);
}

}  // namespace somasim::models::fem
