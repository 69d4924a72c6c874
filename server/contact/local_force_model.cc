#include "server/contact/local_force_model.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace somasim::contact {
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

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("MakeLocalForceModel: " + what);
}

}  // namespace

const char* LocalForceModelError(const LocalForceModel& model) {
  if (!Finite(model.sim_time)) return "sim_time is not finite";
  if (!model.contact_point.allFinite()) return "contact_point is not finite";
  if (!model.normal.allFinite()) return "normal is not finite";
  if (!Finite(model.contact_stiffness)) return "contact_stiffness is not finite";
  if (!model.grasp_anchor.allFinite()) return "grasp_anchor is not finite";
  if (!model.grasp_stiffness.allFinite()) return "grasp_stiffness is not finite";
  if (!model.tissue_stiffness.allFinite()) return "tissue_stiffness is not finite";
  if (!model.bias_force.allFinite()) return "bias_force is not finite";
  if (!Finite(model.damping)) return "damping is not finite";
  if (!Finite(model.force_limit)) return "force_limit is not finite";
  if (model.in_contact && !(std::abs(model.normal.norm() - 1.0) <= 1e-6)) {
    return "normal is not a unit vector";
  }
  if (!(model.contact_stiffness >= 0.0)) return "contact_stiffness is negative";
  if (const char* e = StiffnessError(model.grasp_stiffness, "grasp_stiffness is not symmetric",
                                     "grasp_stiffness is not positive semi-definite")) {
    return e;
  }
  if (const char* e = StiffnessError(model.tissue_stiffness, "tissue_stiffness is not symmetric",
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
  // Everything the evaluation reads must be finite, and the scalars in range (a sum of finite
  // numbers is finite unless it overflows; NaN compares false, so `ok` catches it). Branch-free
  // so that the check costs a few nanoseconds at 1 kHz. The matrices are not checked for
  // symmetry or definiteness here (LocalForceModelError does that when a model arrives): a
  // wrong one can only give a wrong force, which the clamp below still bounds.
  const double sum = x.sum() + v.sum() + model.contact_point.sum() + model.normal.sum() +
                     model.grasp_anchor.sum() + model.grasp_stiffness.sum() +
                     model.bias_force.sum() + model.contact_stiffness + model.damping +
                     model.force_limit;
  // A limit below the smallest normal double (a subnormal) is treated as no limit at all: the
  // clamp's rescaling could not keep its digits there.
  const bool ok = Finite(sum) && model.force_limit >= std::numeric_limits<double>::min() &&
                  model.contact_stiffness >= 0.0 && model.damping >= 0.0;
  if (!ok) {
    sample.invalid = true;
    return sample;
  }
  Vector3d f = model.bias_force;
  if (model.in_contact) {
    // God-object proxy on the unloaded plane (seed 002 eq. 12) with the tool and the tissue in
    // series: f = k_n d n for a penetration d > 0. Damping acts along the normal only (the proxy
    // slides frictionless) and never turns the push into a pull: f_n = max(0, k_n d - b n·v).
    const double d = model.normal.dot(model.contact_point - x);  // [m], > 0 below the plane
    if (d > 0.0) {
      sample.in_contact = true;
      const double damping = model.grasping ? 0.0 : model.damping;  // the grasp damps fully
      const double push = model.contact_stiffness * d - damping * model.normal.dot(v);  // [N]
      f += std::max(push, 0.0) * model.normal;
    }
  }
  if (model.grasping) {
    // Bilateral spring to the anchor, f = -K_g (x - anchor), and full viscous damping -b v.
    f.noalias() -= model.grasp_stiffness * (x - model.grasp_anchor);
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

LocalForceModel MakeLocalForceModel(const ContactForModel& contact, uint64_t sequence,
                                    double sim_time) {
  const double kt = contact.tool_stiffness;
  if (!(kt > 0.0) || !Finite(kt)) Refuse("tool_stiffness must be > 0 and finite");
  if (!contact.proxy.allFinite() || !contact.normal.allFinite() || !contact.device.allFinite() ||
      !contact.grasp_force.allFinite() || !contact.bias_force.allFinite()) {
    Refuse("proxy, normal, device, grasp_force and bias_force must be finite");
  }
  if (!contact.tissue_compliance.allFinite()) Refuse("tissue_compliance must be finite");
  if (!(contact.damping >= 0.0) || !Finite(contact.damping)) Refuse("damping must be >= 0");
  if (!(contact.force_limit > 0.0) || !Finite(contact.force_limit)) {
    Refuse("force_limit must be > 0 and finite");
  }
  if (!Finite(sim_time)) Refuse("sim_time must be finite");
  const Matrix3d& c_in = contact.tissue_compliance;
  const double c_scale = c_in.cwiseAbs().maxCoeff();
  if ((c_in - c_in.transpose()).cwiseAbs().maxCoeff() > 1e-9 * c_scale) {
    Refuse("tissue_compliance must be symmetric");
  }
  // C = V diag(c) Vᵀ, its eigenvalues clipped at 0 (rounding may leave -1e-18 on a held node).
  const Eigen::SelfAdjointEigenSolver<Matrix3d> eigen(0.5 * (c_in + c_in.transpose()));
  const Vector3d& c_values = eigen.eigenvalues();
  if (c_values[0] < -1e-9 * c_values.cwiseAbs().maxCoeff()) {
    Refuse("tissue_compliance must be positive semi-definite");
  }
  const Matrix3d& basis = eigen.eigenvectors();
  Vector3d c_clipped = c_values.cwiseMax(0.0);
  const Matrix3d compliance = basis * c_clipped.asDiagonal() * basis.transpose();  // [m/N]

  LocalForceModel model;
  model.sequence = sequence;
  model.sim_time = sim_time;
  model.damping = contact.damping;
  model.force_limit = contact.force_limit;
  model.bias_force = contact.bias_force;
  // Tissue stiffness C⁻¹ for display; a held (C = 0) direction shows as 1e12 N/m, "rigid".
  const Vector3d k_values = c_clipped.cwiseMax(1e-12).cwiseInverse();
  model.tissue_stiffness = basis * k_values.asDiagonal() * basis.transpose();

  if (contact.in_contact) {
    const double length = contact.normal.norm();
    if (!(length > 0.0)) Refuse("normal must not be zero");
    const Vector3d n = contact.normal / length;
    // Tool spring and tissue in series along n: k_n = 1 / (1/K_t + nᵀ C n).
    const double cnn = n.dot(compliance * n);  // [m/N], >= 0
    model.in_contact = true;
    model.normal = n;
    model.contact_stiffness = 1.0 / (1.0 / kt + cnn);
    // The proxy force f = K_t (proxy - device) loads the tissue with -f, which moved the
    // surface inward by (n·f) nᵀ C n: the unloaded plane lies that far beyond the proxy, so at
    // x = device the penetration is (n·f)(1/K_t + nᵀ C n) and the force k_n d n = (n·f) n.
    const double fn = kt * n.dot(contact.proxy - contact.device);  // [N]
    model.contact_point = contact.proxy + fn * cnn * n;
  }
  if (contact.grasping) {
    // Tool spring and tissue in series in all three directions: K_g = (K_t⁻¹ I + C)⁻¹, exactly
    // symmetric through the eigenbasis of C; the anchor is where K_g gives zero force,
    // device + K_g⁻¹ f (K_g⁻¹ = K_t⁻¹ I + C needs no inverse).
    const Vector3d g_values = (c_clipped.array() + 1.0 / kt).inverse().matrix();
    model.grasping = true;
    model.grasp_stiffness = basis * g_values.asDiagonal() * basis.transpose();
    model.grasp_anchor =
        contact.device + contact.grasp_force / kt + compliance * contact.grasp_force;
  }
  return model;
}

}  // namespace somasim::contact
