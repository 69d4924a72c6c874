#include "server/contact/force_model_maker.h"

#include <Eigen/Eigenvalues>
#include <cmath>
#include <stdexcept>
#include <string>

#include "common/checks/finite.h"

namespace somasim::contact {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using force_model::Mat;
using force_model::Vec;

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("MakeLocalForceModel: " + what);
}

}  // namespace

LocalForceModel MakeLocalForceModel(const ContactForModel& contact, uint64_t sequence,
                                    double sim_time) {
  const double kt = contact.tool_stiffness;
  if (!checks::FinitePositive(kt)) Refuse("tool_stiffness must be > 0 and finite");
  if (!contact.proxy.allFinite() || !contact.normal.allFinite() || !contact.device.allFinite() ||
      !contact.grasp_force.allFinite() || !contact.bias_force.allFinite()) {
    Refuse("proxy, normal, device, grasp_force and bias_force must be finite");
  }
  if (!contact.tissue_compliance.allFinite()) Refuse("tissue_compliance must be finite");
  if (!checks::FiniteNonNegative(contact.damping)) Refuse("damping must be >= 0");
  if (!checks::FinitePositive(contact.force_limit)) Refuse("force_limit must be > 0 and finite");
  if (!std::isfinite(sim_time)) Refuse("sim_time must be finite");
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
  Vec(model.bias_force) = contact.bias_force;
  // Tissue stiffness C⁻¹ for display; a held (C = 0) direction shows as 1e12 N/m, "rigid".
  const Vector3d k_values = c_clipped.cwiseMax(1e-12).cwiseInverse();
  Mat(model.tissue_stiffness) = basis * k_values.asDiagonal() * basis.transpose();

  if (contact.in_contact) {
    const double length = contact.normal.norm();
    if (!(length > 0.0)) Refuse("normal must not be zero");
    const Vector3d n = contact.normal / length;
    // Tool spring and tissue in series along n: k_n = 1 / (1/K_t + nᵀ C n).
    const double cnn = n.dot(compliance * n);  // [m/N], >= 0
    model.in_contact = true;
    Vec(model.normal) = n;
    model.contact_stiffness = 1.0 / (1.0 / kt + cnn);
    // The proxy force f = K_t (proxy - device) loads the tissue with -f, which moved the
    // surface inward by (n·f) nᵀ C n: the unloaded plane lies that far beyond the proxy, so at
    // x = device the penetration is (n·f)(1/K_t + nᵀ C n) and the force k_n d n = (n·f) n.
    const double fn = kt * n.dot(contact.proxy - contact.device);  // [N]
    Vec(model.contact_point) = contact.proxy + fn * cnn * n;
  }
  if (contact.grasping) {
    // Tool spring and tissue in series in all three directions: K_g = (K_t⁻¹ I + C)⁻¹, exactly
    // symmetric through the eigenbasis of C; the anchor is where K_g gives zero force,
    // device + K_g⁻¹ f (K_g⁻¹ = K_t⁻¹ I + C needs no inverse).
    const Vector3d g_values = (c_clipped.array() + 1.0 / kt).inverse().matrix();
    model.grasping = true;
    Mat(model.grasp_stiffness) = basis * g_values.asDiagonal() * basis.transpose();
    Vec(model.grasp_anchor) =
        contact.device + contact.grasp_force / kt + compliance * contact.grasp_force;
  }
  return model;
}

}  // namespace somasim::contact
