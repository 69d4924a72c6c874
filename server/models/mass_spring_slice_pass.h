// The explicit mass-spring pass, seed 002 §2.1 eq. 1–5 (the step and InternalForces): one pass
// over the nodes in slices of 8, one SIMD lane a node, over the springs in their slice layout
// (mass_spring_slice_layout.h); each spring's force reaches its later end through a ring of
// recent columns, and each slice's nodes are integrated as soon as its last spring is done. How
// and why: docs/models.md, "The explicit mass-spring pass".
#pragma once

#include <cstddef>
#include <cstdint>

#include "server/models/tissue_model.h"

namespace somasim::models {

// What the slice pass reads and writes (docs/models.md). Arrays of
// positions, velocities and forces are 3 × num_nodes, column-major (x, y, z of node 0, then of
// node 1, ...): "flat" below.
struct SlicePass {
  const double* x;  // [m], flat
  const double* v;  // [m/s], flat
  size_t num_nodes;
  const int32_t* column_start;  // num_slices + 1
  const int32_t* other3;        // 8 per column
  const double* rest;           // [m], 8 per column
  const uint8_t* lanes;         // 1 per column
  // The AVX-512 pass's: the state's lanes, those of cut springs cleared (F = 0 there).
  const uint8_t* live_lanes;        // 1 per column
  const double* stiffness_damping;  // 16 per column, or nullptr: `material` instead
  // When the springs share few (k, d) pairs: each lane's pair as an index into `material_kd`
  // (k [N/m], d [N s/m] interleaved; pair 0 is (0, 0): empty lanes and cut springs).
  const uint16_t* material;  // 8 per column
  const double* material_kd;
  // With `material`: per column, the one pair of all its springs (cut ones aside: index 0 in
  // `material`), or 0 when they have several.
  const uint16_t* column_pair;
  const int32_t* gathered_column;    // num_slices: the first column not consecutive
  const int32_t* incoming_start;     // num_slices + 1
  const int32_t* incoming_slot;      // 8 per incoming column
  const uint8_t* incoming_lanes;     // 1 per incoming column
  const int32_t* gathered_incoming;  // num_slices: the first not rotated incoming column
  double* ring;                      // [N], 24 per column, ring_mask + 1 columns
  size_t ring_mask;
  // Forces [N], flat. Integrating: what anchors and grasps add, zero again when the pass is
  // done, or nullptr when nothing was added (no anchors, no grasps: the pass then neither
  // reads nor clears 48 bytes per node). Otherwise the output: the internal forces are added
  // to it.
  double* pending;
  bool integrate;
  // Integrating only: seed 002 eq. 4–5 with gravity and external forces, into buffers other
  // than x and v (the pass still reads x and v of later slices' nodes).
  double* moved_x;             // [m], flat, written
  double* moved_v;             // [m/s], flat, written
  const double* external;      // [N], flat, or nullptr
  const double* inverse_mass;  // [1/kg], num_nodes (0: the node does not move)
  double dt;                   // [s]
  double gravity[3];           // [m/s²]
  double component_limit;      // [m/s]: a velocity component above it is flagged
  // The AVX-512 pass's window of x and v (MassSpringSliceLayout::window_slices): rows x, y, z, vx,
  // vy, vz of window_mask + 9 values each (64-byte aligned, window_stride apart), node i at
  // i & window_mask, the first 8 again after the last; slice s + window_lead is copied in at
  // the start of slice s. column_window: each column's lane 0 other node & window_mask.
  double* window;
  size_t window_stride;
  size_t window_mask;
  size_t window_lead;
  const int32_t* column_window;
};

// The slice pass one spring and one node at a time: the reference the AVX-512 pass must match
// to rounding, and the path of CPUs without AVX-512.
StateCheck SlicePassScalar(const SlicePass& p);

// The slice pass with AVX-512 (mass_spring_slice_pass_avx512.cc; compiled for AVX-512 F, so
// only for CPUs that have it), or the scalar pass off x86-64.
StateCheck SlicePassAvx512(const SlicePass& pass);

// The AVX-512 pass where the CPU has it (and tests have not switched it off), else the scalar
// one.
StateCheck RunSlicePass(const SlicePass& p);

}  // namespace somasim::models
