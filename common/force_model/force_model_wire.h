// The local force model on the wire (idl/tool.idl ForceModel) and back: one place for the layout
// both ends must agree on (3 × 3 matrices row-major, vectors x y z), and the grasped nodes the
// server publishes with it (so a viewer shows what the server holds, not a guess of its own).
// The tool id, organ, server and command fields are the caller's.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "common/force_model/local_force_model.h"
#include "idl/tool.h"

namespace somasim::force_model {

// The most grasped nodes a sample carries (idl/tool.idl ForceModel.held_nodes).
inline constexpr uint32_t kMaxHeldNodes = 64;

// Fills the model's fields of `wire` (seq, sim_time, contact, grasp, bias, stiffnesses,
// damping, force limit). Allocation-free.
void ToWire(const LocalForceModel& model, somasim_wire_ForceModel* wire);

// The grasped nodes (indices into the grasped organ's nodes) into `wire`: the first
// kMaxHeldNodes of `nodes`. Allocation-free.
void HeldNodesToWire(std::span<const int32_t> nodes, somasim_wire_ForceModel* wire);

// The model a received sample holds, or why it cannot be used ("" when it can): a format
// version other than `format_version`, or LocalForceModelError's reason.
std::string FromWire(const somasim_wire_ForceModel& wire, uint32_t format_version,
                     LocalForceModel* model);

// The grasped nodes a received sample holds, for an organ of `num_nodes` nodes, or why they
// cannot be used ("" when they can; `nodes` is then replaced): more than kMaxHeldNodes, or an
// index out of range.
std::string HeldNodesFromWire(const somasim_wire_ForceModel& wire, uint32_t num_nodes,
                              std::vector<uint32_t>* nodes);

}  // namespace somasim::force_model
