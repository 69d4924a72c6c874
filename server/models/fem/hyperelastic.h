// Isotropic hyperelastic laws for total-Lagrangian tetrahedra (SPEC §4.4, seed 000): the reduced
// polynomial (seed 000 eq. 5, Nava et al. 2008, in Abaqus and CalculiX's convention), neo-Hookean
// and St Venant–Kirchhoff; the strain energy density W(F) [J/m³], the first Piola–Kirchhoff stress
// P = ∂W/∂F [Pa] and its differential dP. Pure. The formulas: docs/models.md, "Finite elements".
#pragma once

#include <Eigen/Core>
#include <array>
#include <string>

namespace somasim::models::fem {

enum class HyperelasticLaw { kReducedPolynomial, kStVenantKirchhoff };

struct HyperelasticMaterial {
  HyperelasticLaw law = HyperelasticLaw::kReducedPolynomial;
  std::array<double, 5> c{};      // C_10 .. C_50 [Pa] (reduced polynomial)
  std::array<double, 3> d{};      // D_1 .. D_3 [1/Pa]; D_1 > 0, a zero D_2, D_3 means no term
  double lambda = 0.0, mu = 0.0;  // [Pa] (St Venant–Kirchhoff)

  double InitialShearModulus() const;  // μ0 [Pa]
  double InitialBulkModulus() const;   // κ0 [Pa]
  double InitialPoissonRatio() const;  // ν0 [-]
};

// Seed 000 table 1 (Nava et al. 2008, in vivo human liver): C10..C50 = 0.8838, 1.7079, 1.4499,
// 2.6918, 1.7575 kPa. The seed treats the liver as incompressible and gives no D1; we state
// D1 = 3 (1 - 2ν0) / (μ0 (1 + ν0)) with ν0 = 0.49 (κ0 ≈ 50 μ0): nearly incompressible, yet
// solvable with linear tetrahedra (which stiffen — lock — as ν0 → 0.5; docs/models.md).
HyperelasticMaterial LiverNava2008(double poisson_ratio = 0.49);
// Neo-Hookean in the same convention: W = C10 (Ī1 - 3) + (J - 1)² / D1.
HyperelasticMaterial NeoHookean(double c10, double d1);
// St Venant–Kirchhoff from Young's modulus [Pa] and Poisson's ratio.
HyperelasticMaterial StVenantKirchhoff(double youngs_modulus, double poisson_ratio);
// Throws std::invalid_argument naming the bad coefficient (C10 <= 0, D1 <= 0, NaN, ...).
void CheckMaterial(const HyperelasticMaterial& material);

// W(F) [J/m³]; +inf for det F <= 0 (an inverted element has no finite energy).
double StrainEnergy(const HyperelasticMaterial& m, const Eigen::Matrix3d& f);
// P(F) [Pa]. Requires det F > 0.
Eigen::Matrix3d FirstPiolaStress(const HyperelasticMaterial& m, const Eigen::Matrix3d& f);
// dP for dF at F [Pa]. Requires det F > 0.
Eigen::Matrix3d StressDifferential(const HyperelasticMaterial& m, const Eigen::Matrix3d& f,
                                   const Eigen::Matrix3d& df);

// What dP at one F needs that does not depend on dF, computed once for the twelve dF of an
// element tangent (F⁻ᵀ, the invariants, W', W'', U', U'').
struct StressPoint {
  HyperelasticLaw law = HyperelasticLaw::kReducedPolynomial;
  Eigen::Matrix3d f, f_inv_t, a;  // a = 2F - (2/3) I1 F⁻ᵀ (∂Ī1/∂F = g a)
  Eigen::Matrix3d s;              // St Venant–Kirchhoff: the second Piola–Kirchhoff stress
  double j = 1.0, i1 = 3.0, g = 1.0, w1 = 0.0, w2 = 0.0, u1 = 0.0, u2 = 0.0;
  double lambda = 0.0, mu = 0.0;
};
StressPoint PrepareStressDifferential(const HyperelasticMaterial& m, const Eigen::Matrix3d& f);
// StressDifferential(m, f, df) with the point prepared (equal up to rounding).
Eigen::Matrix3d StressDifferential(const StressPoint& point, const Eigen::Matrix3d& df);

}  // namespace somasim::models::fem
