// FemModel's element kernels for the three kinds: the displacement gradient, the stress (with a
// viscous step's context), the rest stiffness blocks and the 12 × 12 element tangent, exact (with
// the derivative of R) or warped.
#include <Eigen/Dense>
#include <cstddef>
#include <cstdint>

#include "server/models/fem/fem_model.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

// The skew matrix [w]× with [w]× u = w × u.
Matrix3d Skew(const Vector3d& w) {
  Matrix3d m;
  m << 0.0, -w.z(), w.y(), w.z(), 0.0, -w.x(), -w.y(), w.x(), 0.0;
  return m;
}

}  // namespace

Matrix3d FemModel::RestBlock(const Shape& sh, int32_t e, int a, int b) const {
  const Vector3d ga = sh.gradients.col(4 * e + a);
  const Vector3d gb = sh.gradients.col(4 * e + b);
  const double v = sh.volumes[static_cast<size_t>(e)];
  return v * (lambda_ * ga * gb.transpose() + mu_ * gb * ga.transpose() +
              mu_ * ga.dot(gb) * Matrix3d::Identity());
}

Matrix3d FemModel::DisplacementGradientOf(const Shape& sh, const mesh::Points& x, int32_t e) {
  Matrix3d h = Matrix3d::Zero();
  for (int a = 0; a < 4; ++a) {
    const int32_t node = sh.tets(a, e);
    h.noalias() += (x.col(node) - sh.rest.col(node)) * sh.gradients.col(4 * e + a).transpose();
  }
  return h;
}

void FemModel::ElementStress(const Shape& sh, const mesh::Points& x, int32_t e, Matrix3d* rotation,
                             Matrix3d* strain, Matrix3d* stress, const ViscousStep* viscous) const {
  const Matrix3d h = DisplacementGradientOf(sh, x, e);  // F - I
  const bool has_offset = viscous != nullptr && viscous->offset != nullptr;
  if (kind_ == FemKind::kHyperelastic) {
    rotation->setIdentity();
    strain->setZero();  // no caller reads it for this model (ElasticEnergy has its own E)
    const Matrix3d f = Matrix3d::Identity() + h;
    *stress = FirstPiolaStress(material_, f);
    if (viscous != nullptr) {  // P = F (g S^e + offset) = g P^e + F offset
      *stress *= viscous->g;
      if (has_offset) {
        *stress += f * Eigen::Map<const Matrix3d>(viscous->offset + 9 * static_cast<size_t>(e));
      }
    }
    return;
  }
  if (kind_ == FemKind::kLinear) {
    rotation->setIdentity();
    *strain = 0.5 * (h + h.transpose());
  } else {
    double identity[4] = {1.0, 0.0, 0.0, 0.0};  // a cold start (PolarRotationFrom)
    *rotation = PolarRotationFrom(Matrix3d::Identity() + h, identity);
    // S - I = Rᵀ (I + H) - I = (Rᵀ - I) + Rᵀ H, symmetric up to rounding.
    const Matrix3d s_minus_i =
        (rotation->transpose() - Matrix3d::Identity()) + rotation->transpose() * h;
    *strain = 0.5 * (s_minus_i + s_minus_i.transpose());
  }
  Matrix3d sigma = lambda_ * strain->trace() * Matrix3d::Identity() + 2.0 * mu_ * *strain;
  if (viscous != nullptr) {  // rotated frame: S = g σ^e + offset
    sigma *= viscous->g;
    if (has_offset) {
      sigma += Eigen::Map<const Matrix3d>(viscous->offset + 9 * static_cast<size_t>(e));
    }
  }
  *stress = *rotation * sigma;
}

Matrix3d FemModel::ElasticStress(const Shape& sh, const mesh::Points& x, int32_t e) const {
  Matrix3d r, strain, p;
  ElementStress(sh, x, e, &r, &strain, &p);
  if (kind_ == FemKind::kHyperelastic) {  // S^e = F⁻¹ P^e
    return (Matrix3d::Identity() + DisplacementGradientOf(sh, x, e)).inverse() * p;
  }
  return r.transpose() * p;  // σ^e in the rotated frame
}

Eigen::Matrix<double, 12, 12> FemModel::ElementTangent(const mesh::Points& x, int32_t e, bool exact,
                                                       const ViscousStep* viscous) const {
  return ElementTangentOf(ModelShape(), x, e, exact, viscous);
}

Eigen::Matrix<double, 12, 12> FemModel::ElementTangentOf(const Shape& sh, const mesh::Points& x,
                                                         int32_t e, bool exact,
                                                         const ViscousStep* viscous) const {
  Eigen::Matrix<double, 12, 12> k;
  Matrix3d r = Matrix3d::Identity(), strain = Matrix3d::Zero(), p = Matrix3d::Zero();
  // The stress enters the linear and corotational tangents only (the hyperelastic one is dP).
  if (kind_ != FemKind::kHyperelastic) ElementStress(sh, x, e, &r, &strain, &p, viscous);
  // A viscous step scales the elastic response by g and adds a constant offset stress:
  // hyperelastic dP = g dP^e + dF offset; rotated frame d(R (g σ + offset)).
  const double g = viscous != nullptr ? viscous->g : 1.0;
  const bool has_offset = viscous != nullptr && viscous->offset != nullptr;
  if (kind_ == FemKind::kHyperelastic) {
    const Matrix3d f = Matrix3d::Identity() + DisplacementGradientOf(sh, x, e);
    const double v = sh.volumes[static_cast<size_t>(e)];
    const StressPoint point = PrepareStressDifferential(material_, f);  // once for 12 dF
    if (material_.law == HyperelasticLaw::kReducedPolynomial) {
      // dF = e_c ∇N_bᵀ is rank one, so StressDifferential's terms applied to ∇N_a reduce to
      // vectors of the element: with A_a = a ∇N_a, Q_a = F⁻ᵀ ∇N_a, P_a = F ∇N_a,
      //   F⁻ᵀ : dF = Q_b[c],  dI1 = 2 P_b[c],  dF⁻ᵀ ∇N_a = -Q_b Q_a[c],
      //   da ∇N_a = 2 (∇N_a·∇N_b) e_c - (2/3) (dI1 Q_a - I1 Q_b Q_a[c]),
      // and column (b, c) of the block (a, b) is V (g dP + dF offset) ∇N_a (~20 flops each instead
      // of a 3 × 3 differential).
      Vector3d ga[4], aa[4], qa[4], pa[4];
      for (int a = 0; a < 4; ++a) {
        ga[a] = sh.gradients.col(4 * e + a);
        aa[a] = point.a * ga[a];
        qa[a] = point.f_inv_t * ga[a];
        pa[a] = f * ga[a];
      }
      Vector3d offset_ga[4];  // offset ∇N_a
      if (has_offset) {
        const Eigen::Map<const Matrix3d> offset(viscous->offset + 9 * static_cast<size_t>(e));
        for (int a = 0; a < 4; ++a) offset_ga[a] = offset * ga[a];
      }
      const double jj = point.j;
      for (int b = 0; b < 4; ++b) {
        for (int c = 0; c < 3; ++c) {
          const double tr = qa[b][c];
          const double d_i1 = 2.0 * pa[b][c];
          const double dg = -(2.0 / 3.0) * point.g * tr;
          const double d_i1_bar = dg * point.i1 + point.g * d_i1;
          const double s_a = point.w2 * d_i1_bar * point.g + point.w1 * dg;
          const double s_q = point.u2 * jj * tr * jj + point.u1 * jj * tr;
          for (int a = 0; a < 4; ++a) {
            Vector3d da = -(2.0 / 3.0) * (d_i1 * qa[a] - point.i1 * qa[a][c] * qa[b]);
            da[c] += 2.0 * ga[a].dot(ga[b]);
            Vector3d column = s_a * aa[a] + point.w1 * point.g * da + s_q * qa[a] -
                              point.u1 * jj * qa[a][c] * qa[b];
            column *= g;
            if (has_offset) column[c] += ga[b].dot(offset_ga[a]);
            k.block<3, 1>(3 * a, 3 * b + c) = v * column;
          }
        }
      }
      return k;
    }
    for (int b = 0; b < 4; ++b) {
      const Vector3d gb = sh.gradients.col(4 * e + b);
      for (int c = 0; c < 3; ++c) {
        const Matrix3d df = Vector3d::Unit(c) * gb.transpose();
        Matrix3d dp = g * StressDifferential(point, df);
        if (has_offset) {
          dp += df * Eigen::Map<const Matrix3d>(viscous->offset + 9 * static_cast<size_t>(e));
        }
        for (int a = 0; a < 4; ++a) {
          k.block<3, 1>(3 * a, 3 * b + c) = v * (dp * sh.gradients.col(4 * e + a));
        }
      }
    }
    return k;
  }
  if (!exact) {
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        k.block<3, 3>(3 * a, 3 * b) = g * (r * RestBlock(sh, e, a, b) * r.transpose());
      }
    }
    return k;
  }
  const double v = sh.volumes[static_cast<size_t>(e)];
  const Matrix3d sigma = r.transpose() * p;          // g σ(ε) + offset
  const Matrix3d s = strain + Matrix3d::Identity();  // Rᵀ F, symmetrised
  // dP for dF: linear, dP = σ(sym dF); corotational, P = R σ(S - I) with dR = R [ω]×, where
  // (tr S I - S) ω = axial(Rᵀ dF - dFᵀ R) and dS = Rᵀ dF - [ω]× S.
  const Matrix3d t = s.trace() * Matrix3d::Identity() - s;
  const Eigen::FullPivLU<Matrix3d> t_lu(t);
  for (int b = 0; b < 4; ++b) {
    const Vector3d gb = sh.gradients.col(4 * e + b);
    for (int c = 0; c < 3; ++c) {
      const Matrix3d df = Vector3d::Unit(c) * gb.transpose();
      Matrix3d dp;
      if (kind_ == FemKind::kLinear) {
        const Matrix3d de = 0.5 * (df + df.transpose());
        dp = g * (lambda_ * de.trace() * Matrix3d::Identity() + 2.0 * mu_ * de);
      } else {
        const Matrix3d w = r.transpose() * df;
        const Vector3d axial(w(2, 1) - w(1, 2), w(0, 2) - w(2, 0), w(1, 0) - w(0, 1));
        const Vector3d omega = t_lu.isInvertible() ? Vector3d(t_lu.solve(axial)) : Vector3d::Zero();
        const Matrix3d ds = w - Skew(omega) * s;
        const Matrix3d de = 0.5 * (ds + ds.transpose());
        const Matrix3d dsigma = lambda_ * de.trace() * Matrix3d::Identity() + 2.0 * mu_ * de;
        dp = r * (Skew(omega) * sigma + g * dsigma);
      }
      for (int a = 0; a < 4; ++a) {
        k.block<3, 1>(3 * a, 3 * b + c) = v * (dp * sh.gradients.col(4 * e + a));
      }
    }
  }
  return k;
}

}  // namespace somasim::models::fem
