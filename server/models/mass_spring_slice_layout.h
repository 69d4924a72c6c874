// The springs of a mass-spring model in the explicit slice pass's own layout (SELL-8, see
// mass_spring_slice_pass.h), and its builder. Internal to server/models; pure, built once per
// model.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "server/models/huge_pages.h"

namespace somasim::models {

// Nodes go in slices of 8 consecutive nodes, one SIMD lane each; each spring belongs to the lane
// of its end in the earlier slice (either end when both share one) and sits in one column of its
// slice (8 lanes, at most one spring each): first the slice's run columns (one offset Δ = other
// node − lane node each, so lane l's other node is lane 0's + l; lanes without a spring of that
// Δ are empty), then its gathered ones.
struct MassSpringSliceLayout {
  std::vector<int32_t> slice_column_start;  // num_slices + 1: columns of each slice
  // 8 per column: 3 × the lane's other node (a gathered column's empty lanes: 0; a run column's:
  // the node lane 0's + l would be).
  HugePageVector<int32_t> column_other3;
  HugePageVector<double> column_rest;    // [m], 8 per column: l0 (0: empty)
  HugePageVector<uint8_t> column_lanes;  // 1 per column: bit l set when lane l has a spring
  // num_slices: each slice's first gathered column (after its run columns).
  std::vector<int32_t> slice_gathered_column;
  std::vector<int32_t> spring_slot;  // num_springs: 8 × column + lane of each spring
  // When the springs share few (k, d) pairs (the builder decides): the pairs (k [N/m], d [N s/m]
  // interleaved; pair 0 is (0, 0), for empty lanes and cut springs) and each spring's pair; the
  // state then holds MassSpringState::column_material instead of column_stiffness_damping. Both
  // empty otherwise.
  std::vector<double> material_kd;
  std::vector<uint16_t> spring_material;
  // With the pairs: each column's one pair when all its springs have it (cut ones have pair 0 in
  // the state), else 0.
  HugePageVector<uint16_t> column_pair;
  // Each column's forces go to a ring (MassSpringState::column_forces) of ring_columns columns
  // (24 doubles each: x of the 8 lanes, then y, then z) and one zero column after them (never
  // written), whence the other nodes' slices take them: a slice's rotated incoming columns (one
  // per Δ of run columns ending on it: lanes r..7 of one ring column and 0..r-1 of another, or of
  // the zero column), then gathered ones (column k: each lane's k-th other spring).
  int32_t ring_columns = 1;  // a power of two
  // The AVX-512 pass reads the nodes' start-of-step x and v from a window of recent slices
  // (MassSpringState::window: x, y, z, vx, vy, vz rows of 8 window_slices nodes, a node at its
  // index mod 8 window_slices, and a copy of the first 8 after the last), filled window_lead
  // slices ahead: a run column's other nodes are then 6 loads, with no transpose.
  int32_t window_slices = 1;  // a power of two >= window_lead + 2
  int32_t window_lead = 0;    // slices: the farthest a run column reads past its own slice
  // Per column: lane 0's other node mod 8 window_slices (a run column's place in the window).
  HugePageVector<int32_t> column_window;
  std::vector<int32_t> slice_incoming_start;  // num_slices + 1: incoming columns of each slice
  // 8 per incoming column: rotated, the two ring columns' indices and r; gathered, each lane's
  // ring index of the x.
  HugePageVector<int32_t> incoming_slot;
  HugePageVector<uint8_t> incoming_lanes;  // 1 per incoming column: lanes with a spring
  // num_slices: each slice's first gathered incoming column (after its rotated ones).
  std::vector<int32_t> slice_gathered_incoming;
};

// The layout of the springs (spring_i[s], spring_j[s]) (i < j, sorted) over num_nodes nodes, with
// their rest lengths [m], stiffness [N/m] and damping [N s/m] (num_springs each).
MassSpringSliceLayout BuildSliceLayout(size_t num_nodes, const std::vector<int32_t>& spring_i,
                                       const std::vector<int32_t>& spring_j,
                                       const std::vector<double>& rest_length,
                                       const std::vector<double>& stiffness,
                                       const std::vector<double>& damping);

}  // namespace somasim::models
