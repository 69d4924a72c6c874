// FemModel's sums over the elements: the elastic forces and energy, the step matrix of the
// hyperelastic kind (AssembleWarped) and the assembled element tangents of the static solves.
#include <Eigen/Core>
#include <algorithm>
#include <cstddef>
#include <cstdint>

#include "server/models/fem/fem_model.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

}  // namespace

void FemModel::ElasticForces(const Shape& sh, const mesh::Points& x, double* forces,
                             double* rotations, const ViscousStep* viscous) const {
  std::fill(forces, forces + 3 * static_cast<size_t>(num_nodes()), 0.0);
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    Matrix3d r, strain, p;
    ElementStress(sh, x, e, &r, &strain, &p, viscous);
    if (rotations != nullptr) Eigen::Map<Matrix3d>(rotations + 9 * static_cast<size_t>(e)) = r;
    const double v = sh.volumes[static_cast<size_t>(e)];
    for (int a = 0; a < 4; ++a) {
      const Vector3d fa = -v * (p * sh.gradients.col(4 * e + a));
      double* out = forces + 3 * static_cast<size_t>(elements_.tets(a, e));
      out[0] += fa.x();
      out[1] += fa.y();
      out[2] += fa.z();
    }
  }
}

double FemModel::ElasticEnergy(const Shape& sh, const mesh::Points& x,
                               const ViscousStep* viscous) const {
  double energy = 0.0;
  const double g = viscous != nullptr ? viscous->g : 1.0;
  const bool has_offset = viscous != nullptr && viscous->offset != nullptr;
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const double v = sh.volumes[static_cast<size_t>(e)];
    Matrix3d r, strain, p;
    double w = 0.0;
    if (kind_ == FemKind::kHyperelastic) {
      const Matrix3d h = DisplacementGradientOf(sh, x, e);
      w = StrainEnergy(material_, Matrix3d::Identity() + h);
      strain = 0.5 * (h + h.transpose() + h.transpose() * h);  // Green's E
    } else {
      ElementStress(sh, x, e, &r, &strain, &p);
      const double tr = strain.trace();
      w = mu_ * strain.squaredNorm() + 0.5 * lambda_ * tr * tr;
    }
    energy += v * g * w;
    if (has_offset) {  // + offset : strain (its gradient is the offset's stress)
      const Eigen::Map<const Matrix3d> c(viscous->offset + 9 * static_cast<size_t>(e));
      energy += v * (c.array() * strain.array()).sum();
    }
  }
  return energy;
}

void FemModel::AssembleWarped(const Shape& sh, const mesh::Points& x, const double* rotations,
                              double scale, double mass_scale, BlockSparseMatrix* matrix,
                              const ViscousStep* viscous) const {
  matrix->SetZero();
  // A viscous step's effective stiffness is g times the elastic one (hyperelastic: plus the
  // offset's geometric term, inside ElementTangent).
  if (viscous != nullptr && kind_ != FemKind::kHyperelastic) scale *= viscous->g;
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    if (kind_ == FemKind::kHyperelastic) {  // the exact tangent: there is no rotated one
      const Eigen::Matrix<double, 12, 12> k = ElementTangentOf(sh, x, e, true, viscous);
      for (int a = 0; a < 4; ++a) {
        for (int b = 0; b < 4; ++b) {
          if (matrix->element_block(e, a, b) < 0) continue;
          matrix->block(matrix->element_block(e, a, b)).noalias() +=
              scale * k.block<3, 3>(3 * a, 3 * b);
        }
      }
      continue;
    }
    // R K_ab Rᵀ = V (λ r_a r_bᵀ + μ r_b r_aᵀ + μ (r_a·r_b) I) with the rotated gradients
    // r_a = R ∇N_a (RestBlock's formula in the rotated frame; r_a·r_b = ∇N_a·∇N_b): 16 outer
    // products instead of 32 3×3 matrix products.
    const double* rot = rotations + 9 * static_cast<size_t>(e);  // column-major
    const double* grad = sh.gradients.data() + 12 * static_cast<size_t>(e);
    double r[4][3];
    for (int a = 0; a < 4; ++a) {
      const double* g = grad + 3 * a;
      for (int i = 0; i < 3; ++i) r[a][i] = rot[i] * g[0] + rot[3 + i] * g[1] + rot[6 + i] * g[2];
    }
    const double v = scale * sh.volumes[static_cast<size_t>(e)];
    const double cl = v * lambda_, cm = v * mu_;
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        const double* ga = grad + 3 * a;
        const double* gb = grad + 3 * b;
        const int32_t block = matrix->element_block(e, a, b);
        if (block < 0) continue;  // upper storage: the transpose of (b, a)
        const double diagonal = cm * (ga[0] * gb[0] + ga[1] * gb[1] + ga[2] * gb[2]);
        double* out = matrix->block(block).data();
        for (int c = 0; c < 3; ++c) {
          for (int i = 0; i < 3; ++i) {
            out[3 * c + i] += cl * r[a][i] * r[b][c] + cm * r[b][i] * r[a][c];
          }
          out[4 * c] += diagonal;
        }
      }
    }
  }
  for (int32_t i = 0; i < num_nodes(); ++i) {
    matrix->block(matrix->diagonal_block(i)).diagonal().array() +=
        mass_scale * mass_[static_cast<size_t>(i)];
  }
}

void FemModel::AssembleTangent(const mesh::Points& x, BlockSparseMatrix* matrix) const {
  if (matrix->num_blocks() != pattern_.num_blocks()) *matrix = pattern_;
  AssembleExact(ModelShape(), x, matrix, nullptr);
}

void FemModel::AssembleExact(const Shape& sh, const mesh::Points& x, BlockSparseMatrix* matrix,
                             const ViscousStep* viscous) const {
  matrix->SetZero();
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const Eigen::Matrix<double, 12, 12> ke = ElementTangentOf(sh, x, e, true, viscous);
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        matrix->block(matrix->element_block(e, a, b)) += ke.block<3, 3>(3 * a, 3 * b);
      }
    }
  }
}

}  // namespace somasim::models::fem
