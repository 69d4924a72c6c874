#include "common/force_model/local_force_model.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>

namespace somasim::force_model {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

bool Finite(double value) { return std::isfinite(value); }

// Why a 3 × 3 stiffness cannot be used (nullptr: it can): symmetric to 1e-9 of its largest
// entry and no eigenvalue below -1e-9 of the largest in magnitude (header contract).
const char* StiffnessError(const Matrix3d& k, const char* asymmetric, const char* indefinite) {
  const double scale = k.cwiseAbs().maxCoeff();
  if (scale == 0.0) return nullptr;
  if ((k - k.transpose()).cwiseAbs().maxCoeff() > 1e-9 * scale) return asymmetric;
  const Eigen::SelfAdjointEigenSolver<Matrix3d> eigen(0.5 * (k + k.transpose()),
                                                      Eigen::EigenvaluesOnly);
  const Vector3d& values = eigen.eigenvalues();  // ascending
  if (values[0] < -1e-9 * values.cwiseAbs().maxCoeff()) return indefinite;
  return nullptr;
}

}  // namespace

const char* LocalForceModelError(const LocalForceModel& model) {
  const Matrix3d grasp_stiffness = Mat(model.grasp_stiffness);
  const Matrix3d tissue_stiffness = Mat(model.tissue_stiffness);
  if (!Finite(model.sim_time)) return "sim_time is not finite";
  if (!Vec(model.contact_point).allFinite()) return "contact_point is not finite";
  if (!Vec(model.normal).allFinite()) return "normal is not finite";
  if (!Finite(model.contact_stiffness)) return "contact_stiffness is not finite";
  if (!Vec(model.grasp_anchor).allFinite()) return "grasp_anchor is not finite";
  if (!grasp_stiffness.allFinite()) return "grasp_stiffness is not finite";
  if (!tissue_stiffness.allFinite()) return "tissue_stiffness is not finite";
  if (!Vec(model.bias_force).allFinite()) return "bias_force is not finite";
  if (!Finite(model.damping)) return "damping is not finite";
  if (!Finite(model.force_limit)) return "force_limit is not finite";
  if (model.in_contact && !(std::abs(Vec(model.normal).norm() - 1.0) <= 1e-6)) {
    return "normal is not a unit vector";
  }
  if (!(model.contact_stiffness >= 0.0)) return "contact_stiffness is negative";
  if (const char* e = StiffnessError(grasp_stiffness, "grasp_stiffness is not symmetric",
                                     "grasp_stiffness is not positive semi-definite")) {
    return e;
  }
  if (const char* e = StiffnessError(tissue_stiffness, "tissue_stiffness is not symmetric",
                                     "tissue_stiffness is not positive semi-definite")) {
    return e;
  }
  if (!(model.damping >= 0.0)) return "damping is negative";
  if (!(model.force_limit > 0.0)) return "force_limit is not positive";
  return nullptr;
}

ForceSample EvaluateLocalForceModel(const LocalForceModel& model, const Eigen::Vector3d& x,
                                    const Eigen::Vector3d& v) {
  ForceSample sample;
  const Vector3d contact_point = Vec(model.contact_point);
  const Vector3d normal = Vec(model.normal);
  const Vector3d grasp_anchor = Vec(model.grasp_anchor);
  const Matrix3d grasp_stiffness = Mat(model.grasp_stiffness);
  const Vector3d bias_force = Vec(model.bias_force);
  // Everything the evaluation reads must be finite, and the scalars in range (a sum of finite
  // numbers is finite unless it overflows; NaN compares false, so `ok` catches it). Branch-free
  // so that the check costs a few nanoseconds at 1 kHz. The matrices are not checked for
  // symmetry or definiteness here (LocalForceModelError does that when a model arrives): a
  // wrong one can only give a wrong force, which the clamp below still bounds.
  const double sum = x.sum() + v.sum() + contact_point.sum() + normal.sum() + grasp_anchor.sum() +
                     grasp_stiffness.sum() + bias_force.sum() + model.contact_stiffness +
                     model.damping + model.force_limit;
  // A limit below the smallest normal double (a subnormal) is treated as no limit at all: the
  // clamp's rescaling could not keep its digits there.
  const bool ok = Finite(sum) && model.force_limit >= std::numeric_limits<double>::min() &&
                  model.contact_stiffness >= 0.0 && model.damping >= 0.0;
  if (!ok) {
    sample.invalid = true;
    return sample;
  }
  Vector3d f = bias_force;
  if (model.in_contact) {
    // God-object proxy on the unloaded plane (seed 002 eq. 12) with the tool and the tissue in
    // series: f = k_n d n for a penetration d > 0. Damping acts along the normal only (the proxy
    // slides frictionless) and never turns the push into a pull: f_n = max(0, k_n d - b n·v).
    const double d = normal.dot(contact_point - x);  // [m], > 0 below the plane
    if (d > 0.0) {
      sample.in_contact = true;
      const double damping = model.grasping ? 0.0 : model.damping;  // the grasp damps fully
      const double push = model.contact_stiffness * d - damping * normal.dot(v);  // [N]
      f += std::max(push, 0.0) * normal;
    }
  }
  if (model.grasping) {
    // Bilateral spring to the anchor, f = -K_g (x - anchor), and full viscous damping -b v.
    f.noalias() -= grasp_stiffness * (x - grasp_anchor);
    f -= model.damping * v;
  }
  // Clamp |f| to force_limit without overflowing: |f| = m |f/m| with m the largest component,
  // compared as |f/m| > limit/m (f/m has components in [-1, 1]; nothing squares a huge number).
  const double largest = f.cwiseAbs().maxCoeff();  // (maxCoeff may skip a NaN: test f itself)
  if (!f.allFinite()) {  // finite inputs whose products overflowed: no meaningful force
    sample.invalid = true;
    sample.in_contact = false;
    return sample;
  }
  if (largest > 0.0) {
    const Vector3d unit = f / largest;
    const double unit_norm = unit.norm();  // in [1, √3]
    if (unit_norm > model.force_limit / largest) {
      f = unit * (model.force_limit / unit_norm);
      sample.clamped = true;
    }
  }
  sample.force = f;
  return sample;
}

}  // namespace somasim::force_model
