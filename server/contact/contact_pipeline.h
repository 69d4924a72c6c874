// One tool against one organ, per physics step (SPEC §5.1–5.2): refit the organ's surface tree
// to the model's positions, move the god-object proxy to the tool's new tip, update the grasp,
// and hand the tissue model the springs that carry the contact and grasp forces (Attachments in
// its StepInputs); afterwards, the force on the tool and the local force model for the haptic
// node. Allocation-free per step. Pure.
//
// The contact force reaches the tissue through the touched triangle's corners: corner i (weight
// w_i, the proxy's barycentric coordinate) gets a spring of stiffness w_i K_t towards
// x_i + (x_device - x_surface). At the step's start the springs push with Σ w_i K_t (x_device -
// x_surface) = K_t (x_device - x_proxy), the reaction of seed 002 eq. 12; as the surface gives way
// they relax with it, inside the model's own (implicit, where it is) integration — a penalty
// integrated this way stays stable at the physics rate where an explicit force would ring.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/contact/aabb_tree.h"
#include "server/contact/force_model_maker.h"
#include "server/contact/god_object.h"
#include "server/contact/grasp.h"
#include "server/contact/tissue_compliance.h"
#include "server/contact/tool.h"
#include "server/models/tissue_model.h"

namespace somasim::contact {

// The surface of an organ that tools touch: triangles over the model's nodes (a volume organ's
// boundary, mesh::ExtractBoundarySurface, keeps the volume's numbering; a surface organ's own
// triangles) and the AABB tree over them.
class OrganSurface {
 public:
  // Throws std::invalid_argument on a bad triangle index or non-finite position.
  OrganSurface(const mesh::Points& positions, const mesh::Triangles& triangles);
  // The tree follows the model's current positions (3 × num_nodes, as at construction).
  void Refit(const mesh::Points& positions) { tree_.Refit(positions); }
  const AabbTree& tree() const { return tree_; }
  // Watertight and consistently oriented (mesh::AnalyseSurfaceTopology): it has an inside, and
  // a tool it moves onto is pushed out (GodObject::Update).
  bool closed() const { return closed_; }

 private:
  AabbTree tree_;
  bool closed_ = false;
};

struct ContactSettings {
  double tool_stiffness = 1000.0;  // K_t [N/m], seed 002 eq. 12's proxy spring, > 0
  GraspSettings grasp;
  double damping = 1.0;        // [N s/m] for the haptic node's local model, >= 0
  double force_limit = 8.0;    // [N] the arm's limit, > 0
  double proxy_offset = 1e-6;  // [m] see GodObject
};

class ToolContact {
 public:
  // Throws std::invalid_argument on a bad shape, pose or settings (naming the field).
  ToolContact(const ToolShape& shape, const ContactSettings& settings, const ToolPose& start);

  // One update before the model's step: `surface` refitted to `positions` (the model state's).
  // A non-finite or otherwise bad pose is ignored (the tool stays where it was). Allocation-free.
  void Update(const ToolPose& pose, const OrganSurface& surface, const mesh::Points& positions);
  // Forgets contact and grasp (after the surface's triangles change: a cut, a reload).
  void Reset(const ToolPose& pose);

  // The springs the contact and the grasp put on the tissue, for StepInputs::attachments.
  std::span<const models::Attachment> attachments() const {
    return {attachments_.data(), static_cast<size_t>(num_attachments_)};
  }
  // The force on the tool [N] at `positions` (after the step: what the hand should feel).
  Eigen::Vector3d ToolForce(const mesh::Points& positions) const;
  // What the local force model is made from (local_force_model.h), with the tissue's compliance
  // at the touched or grasped node (LocalCompliance; FEM through `fem` when given).
  ContactForModel ForLocalModel(const models::TissueModel& model, const models::TissueState& state,
                                FemCompliance* fem) const;

  const ToolShape& shape() const { return shape_; }
  const ToolPose& pose() const { return pose_; }
  const GodObject& proxy() const { return proxy_; }
  const Grasp& grasp() const { return grasp_; }
  const ContactSettings& settings() const { return settings_; }

 private:
  ToolShape shape_;
  ContactSettings settings_;
  ToolPose pose_;
  GodObject proxy_;
  Grasp grasp_;
  std::vector<models::Attachment> attachments_;  // 3 contact corners + the grasp's
  int32_t num_attachments_ = 0;
  // The touched triangle's corners when the contact springs were made (valid when touching_).
  bool touching_ = false;
  std::array<int32_t, 3> contact_nodes_{-1, -1, -1};
};

}  // namespace somasim::contact
