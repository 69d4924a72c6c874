// FemModel's sums over the elements: the elastic forces and energy, the step matrix of the
// hyperelastic kind (AssembleWarped) and the assembled element tangents of the static solves.
#include <Eigen/Core>
#include <algorithm>
#include <cstddef>
#include <cstdint>

#include "server/models/fem/fem_model.h"
#include "server/models/fem/fem_model_internal.h"

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
    // R K_ab Rᵀ from the rotated gradients r_a = R ∇N_a (AddWarpedElementBlocks).
    const double* rot = rotations + 9 * static_cast<size_t>(e);  // column-major
    const double* grad = sh.gradients.data() + 12 * static_cast<size_t>(e);
    double r[4][3];
    for (int a = 0; a < 4; ++a) {
      const double* g = grad + 3 * a;
      for (int i = 0; i < 3; ++i) r[a][i] = rot[i] * g[0] + rot[3 + i] * g[1] + rot[6 + i] * g[2];
    }
    const double v = scale * sh.volumes[static_cast<size_t>(e)];
    const double cl = v * lambda_, cm = v * mu_;
    internal::AddWarpedElementBlocks(matrix->element_blocks() + 16 * static_cast<size_t>(e), grad,
                                     r, cl, cm, matrix->values());
  }
  for (int32_t i = 0; i < num_nodes(); ++i) {
    matrix->block(matrix->diagonal_block(i)).diagonal().array() +=
        mass_scale * mass_[static_cast<size_t>(i)];
  }
}

void FemModel::AssembleTangent(const mesh::Points& x, BlockSparseMatrix* matrix) const {
  if (matrix->num_blocks() != pattern_.num_blocks()) *matrix = pattern_;
  AssembleElementTangents(ModelShape(), x, true, nullptr, matrix);
}

void FemModel::AssembleElementTangents(const Shape& sh, const mesh::Points& x, bool exact,
                                       const ViscousStep* viscous,
                                       BlockSparseMatrix* matrix) const {
  matrix->SetZero();
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const Eigen::Matrix<double, 12, 12> ke = ElementTangentOf(sh, x, e, exact, viscous);
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        matrix->block(matrix->element_block(e, a, b)) += ke.block<3, 3>(3 * a, 3 * b);
      }
    }
  }
}

}  // namespace somasim::models::fem
