// The server's side of the local force model (common/force_model/local_force_model.h): the
// model consistent with what a contact update found, for the haptic node to evaluate at 1 kHz.
// Pure, allocation-free.
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "common/force_model/local_force_model.h"

namespace somasim::contact {

using force_model::LocalForceModel;

// What the server knows after a contact update, from which it makes the model.
struct ContactForModel {
  // Contact: the proxy on the deformed surface, its outward normal, and the device position at
  // the update [m]. The proxy force there is K_t (proxy - device).
  bool in_contact = false;
  Eigen::Vector3d proxy = Eigen::Vector3d::Zero();
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d device = Eigen::Vector3d::Zero();
  // Grasp: the force the grasped tissue exerts on the tool [N] at `device`.
  bool grasping = false;
  Eigen::Vector3d grasp_force = Eigen::Vector3d::Zero();
  double tool_stiffness = 1000.0;  // K_t [N/m], > 0
  // The tissue's local compliance C [m/N] (3 × 3 symmetric PSD) at the contact or grasp.
  Eigen::Matrix3d tissue_compliance = Eigen::Matrix3d::Zero();
  // A held rigid body's force on the tool [N] (its weight when carried), passed on as is.
  Eigen::Vector3d bias_force = Eigen::Vector3d::Zero();
  double damping = 0.0;
  double force_limit = 10.0;
};

// The local force model consistent with `contact`: at x = contact.device it reproduces the
// server's force (the proxy force in contact — its normal part, which is all of it for a
// god-object proxy, whose offset from the device is along n — grasp_force in a grasp, up to
// the clamp), and around it it varies with the series stiffnesses k_n = 1 / (1/K_t + nᵀ C n)
// and K_g = (K_t⁻¹ I + C)⁻¹. With the proxy force f = K_t (proxy - device): contact_point =
// proxy + (n·f) (nᵀ C n) n (the load -f on the tissue moved its surface inward by that much, so
// the unloaded surface lies that far beyond the loaded one; at the device d = (n·f)(1/K_t +
// nᵀ C n) = (n·f)/k_n); grasp_anchor = device + K_g⁻¹ f with K_g⁻¹ = K_t⁻¹ I + C. C is
// symmetrised and its eigenvalues at rounding level below zero clipped; tissue_stiffness = C⁻¹
// with a held (C = 0) direction shown as 1e12 N/m. Throws std::invalid_argument naming the
// field for non-finite data, tool_stiffness <= 0, an asymmetric or indefinite compliance,
// damping < 0, force_limit <= 0, a zero normal in contact (the normal is normalised).
// Allocates nothing.
LocalForceModel MakeLocalForceModel(const ContactForModel& contact, uint64_t sequence,
                                    double sim_time);

}  // namespace somasim::contact
