#include "server/contact/force_model_wire.h"

namespace somasim::contact {

void ToWire(const LocalForceModel& m, somasim_wire_ForceModel* w) {
  w->seq = m.sequence;
  w->sim_time = m.sim_time;
  w->in_contact = m.in_contact;
  w->grasping = m.grasping;
  for (int i = 0; i < 3; ++i) {
    w->contact_point[i] = m.contact_point[i];
    w->normal[i] = m.normal[i];
    w->grasp_anchor[i] = m.grasp_anchor[i];
    w->bias_force[i] = m.bias_force[i];
    for (int j = 0; j < 3; ++j) {
      w->grasp_stiffness[3 * i + j] = m.grasp_stiffness(i, j);
      w->tissue_stiffness[3 * i + j] = m.tissue_stiffness(i, j);
    }
  }
  w->contact_stiffness = m.contact_stiffness;
  w->damping = m.damping;
  w->force_limit = m.force_limit;
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
  for (int i = 0; i < 3; ++i) {
    m->contact_point[i] = w.contact_point[i];
    m->normal[i] = w.normal[i];
    m->grasp_anchor[i] = w.grasp_anchor[i];
    m->bias_force[i] = w.bias_force[i];
    for (int j = 0; j < 3; ++j) {
      m->grasp_stiffness(i, j) = w.grasp_stiffness[3 * i + j];
      m->tissue_stiffness(i, j) = w.tissue_stiffness[3 * i + j];
    }
  }
  m->contact_stiffness = w.contact_stiffness;
  m->damping = w.damping;
  m->force_limit = w.force_limit;
  const char* error = LocalForceModelError(*m);
  return error == nullptr ? "" : error;
}

}  // namespace somasim::contact
