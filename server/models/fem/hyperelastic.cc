#include "server/models/fem/hyperelastic.h"

#include <Eigen/Dense>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;

// W'(Ī1) and W''(Ī1) of Σ C_i0 (Ī1 - 3)^i; U'(J) and U''(J) of Σ (J - 1)^{2i} / D_i.
struct Derivatives {
  double w1 = 0.0, w2 = 0.0, u1 = 0.0, u2 = 0.0;
};

Derivatives PolynomialDerivatives(const HyperelasticMaterial& m, double i1_bar, double j) {
  Derivatives out;
  const double a = i1_bar - 3.0;
  for (int i = 1; i <= 5; ++i) {
    const double c = m.c[static_cast<size_t>(i - 1)];
    out.w1 += i * c * std::pow(a, i - 1);
    if (i >= 2) out.w2 += i * (i - 1) * c * std::pow(a, i - 2);
  }
  const double b = j - 1.0;
  for (int i = 1; i <= 3; ++i) {
    const double d = m.d[static_cast<size_t>(i - 1)];
    if (d == 0.0) continue;
    out.u1 += 2.0 * i / d * std::pow(b, 2 * i - 1);
    out.u2 += 2.0 * i * (2 * i - 1) / d * std::pow(b, 2 * i - 2);
  }
  return out;
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
    if (!(m.mu > 0.0) || !std::isfinite(m.mu) || !std::isfinite(m.lambda) ||
        !(m.lambda + 2.0 * m.mu / 3.0 > 0.0)) {
      bad("St Venant-Kirchhoff needs mu > 0 and a bulk modulus lambda + 2 mu / 3 > 0");
    }
    return;
  }
  for (size_t i = 0; i < m.c.size(); ++i) {
    if (!std::isfinite(m.c[i])) bad("C" + std::to_string(i + 1) + "0 is not finite");
  }
  if (!(m.c[0] > 0.0)) bad("C10 must be > 0 (the initial shear modulus is 2 C10)");
  if (!(m.d[0] > 0.0) || !std::isfinite(m.d[0])) {
    bad("D1 must be a finite value > 0 (the initial bulk modulus is 2 / D1)");
  }
  for (size_t i = 1; i < m.d.size(); ++i) {
    if (!(m.d[i] >= 0.0) || !std::isfinite(m.d[i])) {
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
  const double i1_bar = std::pow(j, -2.0 / 3.0) * f.squaredNorm();
  double w = 0.0;
  for (int i = 1; i <= 5; ++i) w += m.c[static_cast<size_t>(i - 1)] * std::pow(i1_bar - 3.0, i);
  for (int i = 1; i <= 3; ++i) {
    const double d = m.d[static_cast<size_t>(i - 1)];
    if (d != 0.0) w += std::pow(j - 1.0, 2 * i) / d;
  }
  return w;
}

Matrix3d FirstPiolaStress(const HyperelasticMaterial& m, const Matrix3d& f) {
  if (m.law == HyperelasticLaw::kStVenantKirchhoff) {
    const Matrix3d e = 0.5 * (f.transpose() * f - Matrix3d::Identity());
    return f * (m.lambda * e.trace() * Matrix3d::Identity() + 2.0 * m.mu * e);
  }
  // P = W'(Ī1) ∂Ī1/∂F + U'(J) J F⁻ᵀ, ∂Ī1/∂F = J^{-2/3} (2F - (2/3) I1 F⁻ᵀ).
  const double j = f.determinant();
  const Matrix3d f_inv_t = f.inverse().transpose();
  const double i1 = f.squaredNorm();
  const double g = std::pow(j, -2.0 / 3.0);
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
  const double g = std::pow(j, -2.0 / 3.0);
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

}  // namespace somasim::models::fem
