// The local force model (SPEC §1, §5.1–5.2): what the server hands the haptic node so that its
// 1 kHz loop never waits on the network, and what a viewer shows of a tool's contact. Plain,
// trivially copyable data (fixed arrays: it crosses threads through seqlock slots and DDS as it
// is), its checks and its evaluation. Shared by the server (which makes it:
// server/contact/force_model_maker.h), the haptic node and the viewer; Eigen only.
//
// Contact is a god-object proxy on a plane (seed 002 §3.1, eq. 12: f = -K_t (x_device -
// x_proxy)): the tissue surface near the contact is the plane through `contact_point` with
// outward unit `normal`, where the surface would be with no force on it. A device at
// penetration d = n·(contact_point - x) > 0 feels f = k_n d n (k_n: the tool's coupling and the
// tissue in series), frictionless and unilateral. A grasp is bilateral: f = -K_g (x -
// grasp_anchor). Damping resists the device's velocity: in contact along n only and never so
// much that the surface pulls; in a grasp -b v in full. The sum is clamped to force_limit.
// The derivation: docs/contact.md.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <type_traits>

namespace somasim::force_model {

struct LocalForceModel {
  uint64_t sequence = 0;  // increases by one per model the server publishes for the tool
  double sim_time = 0.0;  // [s] simulation time of the physics state it comes from

  bool in_contact = false;
  double contact_point[3] = {};        // [m] on the unloaded surface
  double normal[3] = {0.0, 0.0, 1.0};  // outward, |n| = 1
  double contact_stiffness = 0.0;      // k_n [N/m], >= 0

  bool grasping = false;
  double grasp_anchor[3] = {};     // [m] device position of zero force
  double grasp_stiffness[9] = {};  // K_g [N/m], 3 × 3 row-major, symmetric PSD

  // A force [N] the same at every device position: what a rigid body held in the jaws weighs
  // (it moves with the hand, so it adds no stiffness). Zero otherwise.
  double bias_force[3] = {};

  // The tissue's local stiffness K_tissue [N/m] at the contact (3 × 3 row-major, symmetric
  // PSD): carried for the viewer's display and the recording; the evaluation uses k_n and K_g,
  // which include it.
  double tissue_stiffness[9] = {};
  double damping = 0.0;       // [N s/m], >= 0, along the normal in contact, full in a grasp
  double force_limit = 10.0;  // [N], > 0: |f| never exceeds it
};
static_assert(std::is_trivially_copyable_v<LocalForceModel>, "a model crosses threads as bytes");

// The fields as Eigen objects, without copying: a 3-vector, a row-major 3 × 3 matrix.
using Matrix3RowMajor = Eigen::Matrix<double, 3, 3, Eigen::RowMajor>;
inline Eigen::Map<Eigen::Vector3d> Vec(double (&v)[3]) { return Eigen::Map<Eigen::Vector3d>(v); }
inline Eigen::Map<const Eigen::Vector3d> Vec(const double (&v)[3]) {
  return Eigen::Map<const Eigen::Vector3d>(v);
}
inline Eigen::Map<Matrix3RowMajor> Mat(double (&m)[9]) { return Eigen::Map<Matrix3RowMajor>(m); }
inline Eigen::Map<const Matrix3RowMajor> Mat(const double (&m)[9]) {
  return Eigen::Map<const Matrix3RowMajor>(m);
}

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
// locks, bounded: |force| <= force_limit (or 0), always finite — whatever the model holds: a
// model or device state that is not finite (or whose arithmetic overflows), a negative k_n or
// damping, or a force_limit that is not a positive normal double gives zero force and says so
// (ForceSample::invalid). It checks finiteness and signs only (a few ns); symmetry and
// definiteness are LocalForceModelError's, for the receiver to call once per arriving model.
// Ramping to zero for a stale model and the rate limit (SPEC §7) are the haptic node's.
ForceSample EvaluateLocalForceModel(const LocalForceModel& model, const Eigen::Vector3d& x,
                                    const Eigen::Vector3d& v);

}  // namespace somasim::force_model
