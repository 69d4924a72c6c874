// The local force model (SPEC §1, §5.1–5.2): what the server hands the haptic node so that its
// 1 kHz loop never waits on the network. The physics steps at 100 Hz–1 kHz and evaluates contact
// there; in between, the haptic node evaluates this model for every new device position.
//
// Contact is a god-object proxy on a plane (seed 002 §3.1, eq. 12: f = -K_t (x_device -
// x_proxy)): the tissue surface near the contact is the plane through `contact_point` with
// outward unit `normal`, where the surface would be with no force on it. The tool's coupling
// stiffness K_t and the tissue's compliance there act in series, so a device at penetration
// d = n·(contact_point - x) > 0 feels
//   f = k_n d n,   k_n = 1 / (1/K_t + nᵀ C n)   (C = K_tissue⁻¹, the local tissue compliance),
// frictionless (the proxy slides on the plane) and unilateral (the surface pushes, never pulls).
// A grasp is bilateral: f = -K_g (x - grasp_anchor), K_g = (K_t⁻¹ I + C)⁻¹ (3 × 3). Damping
// resists the device's velocity while in contact or grasping: in contact along n only, and
// never so much that the surface pulls (f_n = max(0, k_n d - b n·v)); in a grasp -b v in full
// (and then not again in the contact term). The sum is clamped to force_limit, keeping its
// direction. Evaluation allocates nothing and never returns a non-finite force: a model or
// device state that is not finite (or whose arithmetic overflows, only possible with absurd
// magnitudes ~1e150), a negative k_n or damping, or a force_limit that is not a positive
// normal double gives zero force and says so (ForceSample::invalid). It checks finiteness and
// signs only (a few ns); symmetry and definiteness are LocalForceModelError's, for the receiver
// to call once per arriving model. Ramping to zero for a stale model and the rate limit (SPEC
// §7) are the haptic node's.
#pragma once

#include <Eigen/Core>
#include <cstdint>

namespace somasim::contact {

// Fixed size, no pointers: travels over DDS as it is (the server issue maps it to IDL).
struct LocalForceModel {
  uint64_t sequence = 0;  // increases by one per model the server publishes
  double sim_time = 0.0;  // [s] simulation time of the physics state it comes from

  bool in_contact = false;
  Eigen::Vector3d contact_point = Eigen::Vector3d::Zero();  // [m] on the unloaded surface
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();        // outward, |n| = 1
  double contact_stiffness = 0.0;                           // k_n [N/m], >= 0

  bool grasping = false;
  Eigen::Vector3d grasp_anchor = Eigen::Vector3d::Zero();     // [m] device position of zero force
  Eigen::Matrix3d grasp_stiffness = Eigen::Matrix3d::Zero();  // K_g [N/m], symmetric PSD

  // A force [N] the same at every device position: what a rigid body held in the jaws weighs
  // (it moves with the hand, so it adds no stiffness; rigid_body.h). Zero otherwise.
  Eigen::Vector3d bias_force = Eigen::Vector3d::Zero();

  // The tissue's local stiffness K_tissue [N/m] at the contact (3 × 3 symmetric PSD): carried
  // for the viewer's display and the recording; the evaluation uses k_n and K_g, which include it.
  Eigen::Matrix3d tissue_stiffness = Eigen::Matrix3d::Zero();
  double damping = 0.0;       // [N s/m], >= 0, along the normal in contact, full in a grasp
  double force_limit = 10.0;  // [N], > 0: |f| never exceeds it
};

// Why a model cannot be used (nullptr: it can). For samples that arrive from outside (DDS).
// Checks: every number finite; |normal| = 1 within 1e-6 when in contact; stiffnesses >= 0;
// grasp_stiffness and tissue_stiffness symmetric (1e-9 relative) with no eigenvalue below
// -1e-9 of the largest; damping >= 0; force_limit > 0.
const char* LocalForceModelError(const LocalForceModel& model);

struct ForceSample {
  Eigen::Vector3d force = Eigen::Vector3d::Zero();  // [N] on the device (the hand feels it)
  bool in_contact = false;                          // the device is below the contact plane
  bool clamped = false;                             // |force| was limited to force_limit
  bool invalid = false;  // the model or device state was unusable: force is zero
};

// The force on a device at position x [m] moving at velocity v [m/s]. Allocation-free, no
// locks, bounded: |force| <= force_limit (or 0), always finite — whatever the model holds.
ForceSample EvaluateLocalForceModel(const LocalForceModel& model, const Eigen::Vector3d& x,
                                    const Eigen::Vector3d& v);

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
// the clamp), and around it it varies with the series stiffnesses above. With the proxy force
// f = K_t (proxy - device): contact_point = proxy + (n·f) (nᵀ C n) n (the load -f on the tissue
// moved its surface inward by that much, so the unloaded surface lies that far beyond the
// loaded one; at the device d = (n·f)(1/K_t + nᵀ C n) = (n·f)/k_n); grasp_anchor = device +
// K_g⁻¹ f with K_g⁻¹ = K_t⁻¹ I + C. C is symmetrised and its eigenvalues at rounding level below
// zero clipped; tissue_stiffness = C⁻¹ with a held (C = 0) direction shown as 1e12 N/m. Throws
// std::invalid_argument naming the field for non-finite data, tool_stiffness <= 0, an
// asymmetric or indefinite compliance, damping < 0, force_limit <= 0, a zero normal in contact
// (the normal is normalised). Allocates nothing.
LocalForceModel MakeLocalForceModel(const ContactForModel& contact, uint64_t sequence,
                                    double sim_time);

}  // namespace somasim::contact
