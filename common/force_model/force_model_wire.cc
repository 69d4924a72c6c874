#include "common/force_model/force_model_wire.h"

#include <algorithm>

namespace somasim::force_model {

void ToWire(const LocalForceModel& m, somasim_wire_ForceModel* w) {
  w->seq = m.sequence;
  w->sim_time = m.sim_time;
  w->in_contact = m.in_contact;
  w->grasping = m.grasping;
  std::copy_n(m.contact_point, 3, w->contact_point);
  std::copy_n(m.normal, 3, w->normal);
  std::copy_n(m.grasp_anchor, 3, w->grasp_anchor);
  std::copy_n(m.bias_force, 3, w->bias_force);
  std::copy_n(m.grasp_stiffness, 9, w->grasp_stiffness);
  std::copy_n(m.tissue_stiffness, 9, w->tissue_stiffness);
  w->contact_stiffness = m.contact_stiffness;
  w->damping = m.damping;
  w->force_limit = m.force_limit;
}

void HeldNodesToWire(std::span<const int32_t> nodes, somasim_wire_ForceModel* w) {
  const size_t n = std::min<size_t>(nodes.size(), kMaxHeldNodes);
  w->num_held = static_cast<uint32_t>(n);
  for (size_t i = 0; i < n; ++i) w->held_nodes[i] = static_cast<uint32_t>(nodes[i]);
  std::fill(w->held_nodes + n, w->held_nodes + kMaxHeldNodes, 0U);
}

std::string FromWire(const somasim_wire_ForceModel& w, uint32_t format_version,
                     LocalForceModel* m) {
  if (w.format_version != format_version) {
    return "format_version " + std::to_string(w.format_version);
  }
  m->sequence = w.seq;
  m->sim_time = w.sim_time;
  m->in_contact = w.in_contact;
  m->grasping = w.grasping;
  std::copy_n(w.contact_point, 3, m->contact_point);
  std::copy_n(w.normal, 3, m->normal);
  std::copy_n(w.grasp_anchor, 3, m->grasp_anchor);
  std::copy_n(w.bias_force, 3, m->bias_force);
  std::copy_n(w.grasp_stiffness, 9, m->grasp_stiffness);
  std::copy_n(w.tissue_stiffness, 9, m->tissue_stiffness);
  m->contact_stiffness = w.contact_stiffness;
  m->damping = w.damping;
  m->force_limit = w.force_limit;
  const char* error = LocalForceModelError(*m);
  return error == nullptr ? "" : error;
}

std::string HeldNodesFromWire(const somasim_wire_ForceModel& w, uint32_t num_nodes,
                              std::vector<uint32_t>* nodes) {
  if (w.num_held > kMaxHeldNodes) {
    return "num_held " + std::to_string(w.num_held) + " is over " + std::to_string(kMaxHeldNodes);
  }
  for (uint32_t i = 0; i < w.num_held; ++i) {
    if (w.held_nodes[i] >= num_nodes) {
      return "held node " + std::to_string(w.held_nodes[i]) + " is not below the organ's " +
             std::to_string(num_nodes) + " nodes";
    }
  }
  nodes->assign(w.held_nodes, w.held_nodes + w.num_held);
  return "";
}

}  // namespace somasim::force_model
