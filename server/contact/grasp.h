// Grasping (SPEC §5.2): closing the grasper's jaws on tissue takes hold of the surface nodes
// near the jaws; each held node is pulled by a spring towards the point where it was taken,
// carried rigidly with the tool, so pulling the tool deforms the organ; the springs' force is
// what the hand feels; opening the jaws lets go. The springs reach the tissue model as
// Attachments (the model integrates them implicitly where it is implicit). Allocation-free
// after construction. Pure.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/contact/aabb_tree.h"
#include "server/contact/tool.h"
#include "server/models/tissue_model.h"

namespace somasim::contact {

struct GraspSettings {
  // Hysteresis on the jaw opening (0 closed .. 1 open): jaws close below close_below and open
  // above open_above (0 <= close_below < open_above <= 1), so a jittering hand does not grab
  // and drop at 1 kHz.
  double close_below = 0.2;
  double open_above = 0.4;
  double stiffness = 1000.0;              // [N/m] all the held nodes together (> 0), shared equally
  int32_t max_nodes = 64;                 // held at most (> 0); the nearest to the jaws are kept
  int32_t max_candidate_triangles = 512;  // triangles examined near the jaws (> 0)
};

class Grasp {
 public:
  // Throws std::invalid_argument on bad settings. Sizes every buffer.
  explicit Grasp(const GraspSettings& settings);

  // One update of a grasper at `pose` against a surface (tree refitted to `positions`, the
  // model's node positions, 3 × num_nodes; the tree's triangles index them). Closing on tissue
  // takes the surface nodes within shape.grasp_radius of the jaws (the segment from the tip
  // jaw_length up the shaft); opening releases them. Other tools never grasp.
  void Update(const ToolShape& shape, const ToolPose& pose, const AabbTree& tree,
              const mesh::Points& positions);
  // Lets go at once (a cut through the held tissue, a reset).
  void Release();

  bool holding() const { return num_held_ > 0; }
  bool jaws_closed() const { return jaws_closed_; }
  int32_t num_held() const { return num_held_; }
  // The springs on the held nodes at the last update's pose (targets there).
  std::span<const models::Attachment> attachments() const {
    return {attachments_.data(), static_cast<size_t>(num_held_)};
  }
  // The force the held tissue exerts on the tool [N]: Σ k (x_i - target_i) at `positions`.
  Eigen::Vector3d ToolForce(const mesh::Points& positions) const;

 private:
  GraspSettings settings_;
  bool jaws_closed_ = false;
  int32_t num_held_ = 0;
  std::vector<models::Attachment> attachments_;  // max_nodes
  std::vector<Eigen::Vector3d> held_offsets_;    // max_nodes: in the tool frame [m]
  std::vector<double> candidate_distances_;      // max_nodes: to the jaw segment [m]
  std::vector<int32_t> candidate_triangles_;     // max_candidate_triangles
};

}  // namespace somasim::contact
