#include "server/contact/grasp.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "server/contact/triangle_queries.h"

namespace somasim::contact {
Grasp::Grasp(const GraspSettings& settings) : settings_(settings) {
  if (!(settings.close_below >= 0.0 && settings.close_below < settings.open_above &&
        settings.open_above <= 1.0)) {
    throw std::invalid_argument("grasp: need 0 <= close_below < open_above <= 1");
  }
  if (!std::isfinite(settings.stiffness) || settings.stiffness <= 0.0) {
    throw std::invalid_argument("grasp: stiffness must be finite and > 0 N/m");
  }
  if (settings.max_nodes <= 0 || settings.max_candidate_triangles <= 0) {
    throw std::invalid_argument("grasp: max_nodes and max_candidate_triangles must be > 0");
  }
  const auto nodes = static_cast<size_t>(settings.max_nodes);
  attachments_.resize(nodes);
  held_offsets_.resize(nodes);
  candidate_distances_.resize(nodes);
  candidate_triangles_.resize(static_cast<size_t>(settings.max_candidate_triangles));
}

void Grasp::Release() { num_held_ = 0; }

void Grasp::Update(const ToolShape& shape, const ToolPose& pose, const AabbTree& tree,
                   const mesh::Points& positions) {
  if (shape.kind != ToolKind::kGrasper) {
    jaws_closed_ = false;
    num_held_ = 0;
    return;
  }
  const Eigen::Quaterniond rotation = pose.orientation.normalized();
  const bool was_closed = jaws_closed_;
  if (pose.jaw_opening < settings_.close_below) jaws_closed_ = true;
  if (pose.jaw_opening > settings_.open_above) jaws_closed_ = false;
  if (!jaws_closed_) {
    num_held_ = 0;
  } else if (!was_closed) {
    // The jaws just closed: take the surface nodes within grasp_radius of the jaws, keeping
    // the max_nodes nearest (insertion into a sorted list: max_nodes is small).
    const Eigen::Vector3d p = pose.tip;
    const Eigen::Vector3d q = PointOnShaft(pose, shape.jaw_length);
    const int32_t found = tree.CapsuleQuery(
        p, q, shape.grasp_radius, {candidate_triangles_.data(), candidate_triangles_.size()});
    const int32_t examined = std::min(found, static_cast<int32_t>(candidate_triangles_.size()));
    num_held_ = 0;
    for (int32_t c = 0; c < examined; ++c) {
      const auto tri = tree.triangles().col(candidate_triangles_[static_cast<size_t>(c)]);
      for (int corner = 0; corner < 3; ++corner) {
        const int32_t node = tri[corner];
        const double distance =
            (positions.col(node) - ClosestPointOnSegment(positions.col(node), p, q)).norm();
        if (distance > shape.grasp_radius) continue;
        bool seen = false;
        for (int32_t h = 0; h < num_held_ && !seen; ++h) {
          seen = attachments_[static_cast<size_t>(h)].node == node;
        }
        if (seen) continue;
        int32_t slot = num_held_;
        if (num_held_ == settings_.max_nodes) {
          if (distance >= candidate_distances_[static_cast<size_t>(num_held_ - 1)]) continue;
          slot = num_held_ - 1;
        } else {
          ++num_held_;
        }
        while (slot > 0 && candidate_distances_[static_cast<size_t>(slot - 1)] > distance) {
          attachments_[static_cast<size_t>(slot)] = attachments_[static_cast<size_t>(slot - 1)];
          candidate_distances_[static_cast<size_t>(slot)] =
              candidate_distances_[static_cast<size_t>(slot - 1)];
          --slot;
        }
        attachments_[static_cast<size_t>(slot)].node = node;
        candidate_distances_[static_cast<size_t>(slot)] = distance;
      }
    }
    // Where each was taken, in the tool's frame: the jaws carry it from now on.
    const double k = num_held_ > 0 ? settings_.stiffness / num_held_ : 0.0;
    for (int32_t h = 0; h < num_held_; ++h) {
      const auto i = static_cast<size_t>(h);
      held_offsets_[i] = rotation.inverse() * (positions.col(attachments_[i].node) - pose.tip);
      attachments_[i].stiffness = k;
    }
  }
  for (int32_t h = 0; h < num_held_; ++h) {
    const auto i = static_cast<size_t>(h);
    attachments_[i].target = pose.tip + rotation * held_offsets_[i];
  }
}

Eigen::Vector3d Grasp::ToolForce(const mesh::Points& positions) const {
  Eigen::Vector3d force = Eigen::Vector3d::Zero();
  for (int32_t h = 0; h < num_held_; ++h) {
    const models::Attachment& a = attachments_[static_cast<size_t>(h)];
    force += a.stiffness * (positions.col(a.node) - a.target);
  }
  return force;
}

}  // namespace somasim::contact
