// The local force model on the wire (idl/tool.idl ForceModel) and back: one place for the layout
// both ends must agree on (3 × 3 matrices row-major, vectors x y z). The tool id, organ and
// server fields are the caller's.
#pragma once

#include <string>

#include "idl/tool.h"
#include "server/contact/local_force_model.h"

namespace somasim::contact {

// Fills the model's fields of `wire` (format_version, seq, sim_time, contact, grasp, bias,
// stiffnesses, damping, force limit). Allocation-free.
void ToWire(const LocalForceModel& model, somasim_wire_ForceModel* wire);

// The model a received sample holds, or why it cannot be used ("" when it can): a format
// version other than `format_version`, or LocalForceModelError's reason.
std::string FromWire(const somasim_wire_ForceModel& wire, uint32_t format_version,
                     LocalForceModel* model);

}  // namespace somasim::contact
