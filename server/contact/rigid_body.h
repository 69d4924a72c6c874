// Rigid bodies of a scene (issue 6): a kidney stone in a kidney, which tools push and grasp and
// which tissue holds. A rigid sphere (radius, mass) with translation and orientation: it rests
// on tissue, is pushed by a tool's tip (a god-object on the sphere, as on an organ), and is
// carried by a grasper whose closed jaws hold it. Pure; allocation-free after construction.
//
// Contacts are penalty springs: tissue triangle within the sphere (nearest point p at distance
// d < r from the centre c) is pushed out by k_c (r - d) along (p - c)/d, shared among the
// triangle's corners by p's barycentric weights — springs the tissue model integrates (the
// Attachments it is given) — and the sphere takes the opposite. A grasp is a spring (and
// damper) between the sphere's centre and the point it was held at, carried with the tool.
// The sphere's motion is implicit Euler on its own springs (m + dt c + dt² k) Δv = dt (f - c v
// - dt k v), so stiff contacts and grasps are stable at any physics step.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/contact/aabb_tree.h"
#include "server/contact/tool.h"
#include "server/models/tissue_model.h"

namespace somasim::contact {

struct RigidSphereSettings {
  double radius = 0.005;             // [m] (0, 0.2]
  double density = 2000.0;           // [kg/m³] > 0 (calcium oxalate stones: ~2000)
  double tissue_stiffness = 2000.0;  // k_c [N/m] per touching triangle, > 0
  double tool_stiffness = 1000.0;    // [N/m] a tool tip pushing the sphere, > 0
  double grasp_stiffness = 1000.0;   // [N/m] the jaws holding it, > 0
  // [N s/m] >= 0: drag of the fluid around the stone, Stokes 6π μ r for water at r = 5 mm.
  // (A held stone is also damped critically on the grasp's spring.)
  double damping = 1e-4;
  int32_t max_tissue_contacts = 64;  // triangles touching at once, > 0
};

class RigidSphere {
 public:
  // Throws std::invalid_argument naming the bad setting or a non-finite position.
  RigidSphere(const RigidSphereSettings& settings, const Eigen::Vector3d& position);

  // Before the tissue's step: the organ's triangles inside the sphere (tree refitted to the
  // model's `positions`) become springs on the tissue (attachments()), and the sphere remembers
  // their stiffness for its own step.
  void CollectTissueContacts(const AabbTree& tree, const mesh::Points& positions);
  // The tool's effect before the sphere's step: a grasper whose jaws close with the sphere
  // within shape.grasp_radius of its jaws holds it until they open (same hysteresis as Grasp:
  // close below 0.2, open above 0.4); any other contacting tool tip pushes it (proxy on the
  // sphere). A bad pose is ignored.
  void UpdateTool(const ToolShape& shape, const ToolPose& pose);
  // Advances the sphere by dt [s] under gravity [m/s²], the tissue springs at the tissue's
  // positions after its step, the tool and the grasp. Non-finite results are rejected (the
  // sphere stays; returns false).
  bool Step(double dt, const Eigen::Vector3d& gravity, const mesh::Points& tissue_positions);

  std::span<const models::Attachment> attachments() const {
    return {attachments_.data(), static_cast<size_t>(num_attachments_)};
  }
  // The force [N] the sphere exerts on the tool (pushing or held), at the last step.
  const Eigen::Vector3d& tool_force() const { return tool_force_; }
  bool grasped() const { return grasped_; }
  double radius() const { return settings_.radius; }
  double mass() const { return mass_; }                          // [kg]
  const Eigen::Vector3d& position() const { return position_; }  // [m] the centre
  const Eigen::Vector3d& velocity() const { return velocity_; }  // [m/s]
  const Eigen::Quaterniond& orientation() const { return orientation_; }
  void set_position(const Eigen::Vector3d& position) { position_ = position; }

 private:
  RigidSphereSettings settings_;
  double mass_ = 0.0;
  Eigen::Vector3d position_;
  Eigen::Vector3d velocity_ = Eigen::Vector3d::Zero();
  Eigen::Quaterniond orientation_ = Eigen::Quaterniond::Identity();
  // Tissue springs: per corner an Attachment and the direction it pushes the tissue (unit,
  // away from the centre), 3 × max_tissue_contacts each.
  std::vector<models::Attachment> attachments_;
  std::vector<Eigen::Vector3d> directions_;
  int32_t num_attachments_ = 0;
  std::vector<int32_t> candidates_;
  // Tool: pushing (target of the tip spring) or holding (centre's point in the tool frame).
  bool pushed_ = false;
  Eigen::Vector3d push_target_ = Eigen::Vector3d::Zero();  // where the tip puts the centre
  Eigen::Vector3d push_direction_ = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d last_tip_ = Eigen::Vector3d::Constant(1e300);  // none yet
  bool jaws_closed_ = false;
  bool grasped_ = false;
  Eigen::Vector3d grasp_offset_ = Eigen::Vector3d::Zero();              // centre in the tool frame
  Eigen::Quaterniond grasp_rotation_ = Eigen::Quaterniond::Identity();  // tool → sphere
  Eigen::Vector3d grasp_target_ = Eigen::Vector3d::Zero();
  Eigen::Quaterniond tool_orientation_ = Eigen::Quaterniond::Identity();
  Eigen::Vector3d tool_force_ = Eigen::Vector3d::Zero();
};

}  // namespace somasim::contact
