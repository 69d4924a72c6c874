// The explicit mass-spring step (and InternalForces), seed 002 §2.1 eq. 1–5: one pass
// over the nodes in slices of 8 consecutive nodes, one SIMD lane per node (a SELL-8 layout,
// built once: mass_spring_slice_layout.h), with no scatter and no scalar work per spring:
//  - every spring belongs to the lane of its end in the earlier slice (either end when both
//    share a slice: the less loaded one) and sits in one column of that slice (8 lanes, at most
//    one spring each). A lane's own x and v are loaded once per slice and its forces summed in
//    a register. A "run" column holds the slice's springs of one offset Δ = other node − lane
//    node (an edge kind of a structured numbering; lanes without one stay empty): the other
//    ends are 8 consecutive nodes; the other springs sit in gathered columns, whose other ends'
//    x and v are gathered. Runs are 99.99 % of the columns on the 53³ grid and 94 % on
//    gallbladder5400 (how many lanes a run needs is chosen per slice, BuildSliceLayout).
//  - the AVX-512 pass transposes each slice's x and v once, into a window of recent slices
//    (x, y, z, vx, vy, vz rows: MassSpringState::window), as far ahead as the farthest run
//    column reads; a slice's own x and v and a run column's other ends are then 6 loads each
//    from the window, wherever the 8 consecutive nodes start, instead of 6 loads and 12 permutes
//    per column (grid1m −8 % on Emerald Rapids, where the permutes share one port).
//  - each column stores its 8 forces F (3 vector stores, 0 in empty lanes) into a ring of
//    recent columns; each slice then subtracts the forces of the springs ending on its nodes
//    ("incoming columns"). Those of one Δ start in lanes r..7 of one run column and lanes
//    0..r-1 of the next slice's (r = -Δ mod 8): two loads and a permute, lanes without such a
//    spring reading an empty lane or the ring's zero column. The rest are gathered from the
//    ring by precomputed slots. No read-modify-write of shared memory: the old pass's scalar
//    scatter `pending[j] -= F` and its per-node bookkeeping (a mispredicted branch per node)
//    are gone. The ring (a power of two of columns, sized in Build so that no column is
//    overwritten before its last reader's slice) stays in L1/L2 however large the mesh.
//  - when a slice's columns are done, every spring touching its nodes is done too (springs that
//    end in a slice start in it or in an earlier one), and no later spring reads them (later
//    springs start in later slices and end beyond their start), so the slice's 8 nodes are
//    integrated at once (symplectic Euler on the 24 flat x, y, z values) while their data is
//    still in L1: one pass over memory. The pass reads the state the step starts from and
//    writes the new one into other buffers: Advance swaps the state's positions and velocities
//    with its last-good ones first (SavesGoodStateItself without a copy), so nothing is saved
//    for a rollback; and the pass checks the values it writes for NaN and speed
//    (ChecksStateItself), so Step makes no second pass over them.
//  - per spring the pass streams about 32 bytes (other node, l0, k, d, incoming slot); k and d
//    live in the state in the column layout (MakeState fills and Cut zeroes both copies). When
//    the springs share few exact (k, d) pairs (a structured mesh: 20 pairs for the 1M springs
//    of a 53³ grid, once Build has merged constants that differ by rounding only), the state
//    keeps instead a 2-byte index per spring into the model's table of pairs (pair 0 is (0, 0):
//    Cut just sets the index to 0), gathered from L1/L2: 18 bytes per spring instead of 32 of
//    the pass's traffic. A column whose springs share one pair (82 % of the grid's) has it
//    broadcast instead of gathered.
//  - without anchors or grasps nothing is added to a node's force before the pass, which then
//    neither reads nor clears `pending` (48 bytes per node less).
//  - the pass's streams (columns, incoming columns) and scratch (ring, window, the state's
//    constants) live on transparent huge pages where the kernel gives them (huge_pages.h): on the
//    1M-spring grid they span ~30 MB, and with 4 KiB pages their TLB misses cost ~10 % of the
//    step under a hypervisor.
#pragma once

#include <cstddef>
#include <cstdint>

#include "server/models/tissue_model.h"

namespace somasim::models {

// What the slice pass reads and writes (see the comment at the top of the file). Arrays of
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
