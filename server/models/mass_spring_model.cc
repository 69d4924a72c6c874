// Mass-spring model, seed 002 §2.1 eq. 1–5. The explicit step (and InternalForces) is one pass
// over the nodes in slices of 8 consecutive nodes, one SIMD lane per node (a SELL-8 layout,
// built once in BuildExplicitLayout), with no scatter and no scalar work per spring:
//  - every spring belongs to the lane of its end in the earlier slice (either end when both
//    share a slice: the less loaded one) and sits in one column of that slice (8 lanes, at most
//    one spring each). A lane's own x and v are loaded once per slice and its forces summed in
//    a register. A "run" column holds the slice's springs of one offset Δ = other node − lane
//    node (an edge kind of a structured numbering; lanes without one stay empty): the other
//    ends are 8 consecutive nodes; the other springs sit in gathered columns, whose other ends'
//    x and v are gathered. Runs are 99.99 % of the columns on the 53³ grid and 94 % on
//    gallbladder5400 (how many lanes a run needs is chosen per slice, BuildExplicitLayout).
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
#include "server/models/mass_spring_model.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cassert>
#include <cmath>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/checks/finite.h"
#include "server/models/cpu_features.h"
#include "server/models/generalised_surface.h"
#include "server/models/mass_spring_state.h"
#include "server/models/particle_edges.h"
#include "server/models/particle_mesh.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_MSS_AVX512 1
#endif

namespace somasim::models {
namespace {

using Eigen::Vector3d;

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
  // The AVX-512 pass's window of x and v (MassSpringModel::window_slices_): rows x, y, z, vx,
  // vy, vz of window_mask + 9 values each (64-byte aligned, window_stride apart), node i at
  // i & window_mask, the first 8 again after the last; slice s + window_lead is copied in at
  // the start of slice s. column_window: each column's lane 0 other node & window_mask.
  double* window;
  size_t window_stride;
  size_t window_mask;
  size_t window_lead;
  const int32_t* column_window;
};

// Seed 002 eq. 1–3 for one spring: the force F [N] on the lane's node a (the other node b gets
// -F): F = (K (l - l0) + D ((v_b - v_a)·u)) u, l = |x_b - x_a|, u = (x_b - x_a) / l (u = 0 for a
// spring of zero length).
inline void SpringForce(const double* xa, const double* va, const double* xb, const double* vb,
                        double k, double d, double l0, double* f) {
  const double dx = xb[0] - xa[0], dy = xb[1] - xa[1], dz = xb[2] - xa[2];
  const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
  const double inv = length > 0.0 ? 1.0 / length : 0.0;
  const double ux = dx * inv, uy = dy * inv, uz = dz * inv;
  const double closing = (vb[0] - va[0]) * ux + (vb[1] - va[1]) * uy + (vb[2] - va[2]) * uz;
  const double magnitude = k * (length - l0) + d * closing;
  f[0] = magnitude * ux;
  f[1] = magnitude * uy;
  f[2] = magnitude * uz;
}

// The slice pass one spring and one node at a time: the reference the AVX-512 pass must match
// to rounding, and the path of CPUs without AVX-512.
StateCheck SlicePassScalar(const SlicePass& p) {
  StateCheck check;
  const size_t num_slices = (p.num_nodes + 7) / 8;
  for (size_t slice = 0; slice < num_slices; ++slice) {
    const size_t first = 8 * slice;
    const size_t count = std::min<size_t>(8, p.num_nodes - first);
    double sum[8][3] = {};
    for (auto c = static_cast<size_t>(p.column_start[slice]);
         c < static_cast<size_t>(p.column_start[slice + 1]); ++c) {
      for (size_t lane = 0; lane < 8; ++lane) {
        if (((p.lanes[c] >> lane) & 1U) == 0) continue;
        const size_t a = 3 * (first + lane);
        const auto b = static_cast<size_t>(p.other3[8 * c + lane]);
        double f[3];
        double k = 0.0, d = 0.0;
        if (p.material != nullptr) {
          const size_t pair = 2 * size_t{p.material[8 * c + lane]};
          k = p.material_kd[pair];
          d = p.material_kd[pair + 1];
        } else {
          k = p.stiffness_damping[16 * c + lane];
          d = p.stiffness_damping[16 * c + 8 + lane];
        }
        SpringForce(p.x + a, p.v + a, p.x + b, p.v + b, k, d, p.rest[8 * c + lane], f);
        for (size_t axis = 0; axis < 3; ++axis) {
          sum[lane][axis] += f[axis];
          p.ring[24 * (c & p.ring_mask) + 8 * axis + lane] = f[axis];
        }
      }
    }
    const auto rotated_end = static_cast<size_t>(p.gathered_incoming[slice]);
    for (auto c = static_cast<size_t>(p.incoming_start[slice]);
         c < static_cast<size_t>(p.incoming_start[slice + 1]); ++c) {
      for (size_t lane = 0; lane < 8; ++lane) {
        if (((p.incoming_lanes[c] >> lane) & 1U) == 0) continue;
        const int32_t* const q = p.incoming_slot + 8 * c;
        auto slot = static_cast<size_t>(q[lane]);
        if (c < rotated_end) {  // lanes r.. of column q[0], then lanes 0.. of q[1]
          const auto r = static_cast<size_t>(q[2]);
          slot = r + lane < 8 ? static_cast<size_t>(q[0]) + r + lane
                              : static_cast<size_t>(q[1]) + r + lane - 8;
        }
        for (size_t axis = 0; axis < 3; ++axis) sum[lane][axis] -= p.ring[slot + 8 * axis];
      }
    }
    for (size_t lane = 0; lane < count; ++lane) {
      const size_t node = first + lane;
      const size_t a = 3 * node;
      if (!p.integrate) {
        for (size_t axis = 0; axis < 3; ++axis) p.pending[a + axis] += sum[lane][axis];
        continue;
      }
      const double w = p.inverse_mass[node];
      const double moves = w > 0.0 ? 1.0 : 0.0;
      for (size_t axis = 0; axis < 3; ++axis) {
        double f = sum[lane][axis];
        if (p.pending != nullptr) {
          f += p.pending[a + axis];
          p.pending[a + axis] = 0.0;
        }
        if (p.external != nullptr) f += p.external[a + axis];
        const double v0 = p.v[a + axis], x0 = p.x[a + axis];
        const double v1 = v0 + p.dt * (w * f + moves * p.gravity[axis]);
        const double x1 = x0 + p.dt * v1;
        p.moved_v[a + axis] = v1;
        p.moved_x[a + axis] = x1;
        check.Add(x1, v1, p.component_limit);
      }
    }
  }
  return check;
}

#ifdef SOMASIM_MSS_AVX512
#define SOMASIM_MSS_TARGET __attribute__((target("avx512f,avx2,fma")))

SOMASIM_MSS_TARGET inline __m512i Indices(int64_t e0, int64_t e1, int64_t e2, int64_t e3,
                                          int64_t e4, int64_t e5, int64_t e6, int64_t e7) {
  return _mm512_set_epi64(e7, e6, e5, e4, e3, e2, e1, e0);
}

// The x, y and z of 8 nodes from their 24 flat values in chunks a, b, c (8 each).
SOMASIM_MSS_TARGET inline void Deinterleave(__m512d a, __m512d b, __m512d c, __m512d* x, __m512d* y,
                                            __m512d* z) {
  *x = _mm512_mask_permutexvar_pd(_mm512_permutex2var_pd(a, Indices(0, 3, 6, 9, 12, 15, 0, 0), b),
                                  0xC0, Indices(0, 0, 0, 0, 0, 0, 2, 5), c);
  *y = _mm512_mask_permutexvar_pd(_mm512_permutex2var_pd(a, Indices(1, 4, 7, 10, 13, 0, 0, 0), b),
                                  0xE0, Indices(0, 0, 0, 0, 0, 0, 3, 6), c);
  *z = _mm512_mask_permutexvar_pd(_mm512_permutex2var_pd(a, Indices(2, 5, 8, 11, 14, 0, 0, 0), b),
                                  0xE0, Indices(0, 0, 0, 0, 0, 1, 4, 7), c);
}

// The inverse: 8 nodes' x, y and z as 24 flat values in chunks a, b, c.
SOMASIM_MSS_TARGET inline void Interleave(__m512d x, __m512d y, __m512d z, __m512d* a, __m512d* b,
                                          __m512d* c) {
  *a = _mm512_mask_permutexvar_pd(_mm512_permutex2var_pd(x, Indices(0, 8, 0, 1, 9, 0, 2, 10), y),
                                  0x24, Indices(0, 0, 0, 0, 0, 1, 0, 0), z);
  *b = _mm512_mask_permutexvar_pd(_mm512_permutex2var_pd(x, Indices(0, 3, 11, 0, 4, 12, 0, 5), y),
                                  0x49, Indices(2, 0, 0, 3, 0, 0, 4, 0), z);
  *c = _mm512_mask_permutexvar_pd(_mm512_permutex2var_pd(x, Indices(13, 0, 6, 14, 0, 7, 15, 0), y),
                                  0x92, Indices(0, 5, 0, 0, 6, 0, 0, 7), z);
}

// The masked gather of 8 doubles base[index[l]] (lanes off the mask read nothing and give 0).
SOMASIM_MSS_TARGET inline __m512d Gather(__mmask8 lanes, __m256i index, const double* base) {
  return _mm512_mask_i32gather_pd(_mm512_setzero_pd(), lanes, index, base, 8);
}

// One column of springs (SlicePassAvx512): the forces F on the 8 lanes' nodes a from their
// other nodes b, added to f and stored in the ring. Lanes are off `lanes`' mask: F = 0.
struct Lanes8 {
  __m512d x, y, z, vx, vy, vz;
};
SOMASIM_MSS_TARGET __attribute__((always_inline)) inline void SpringColumn(
    const SlicePass& p, size_t c, __mmask8 lanes, const Lanes8& a, const Lanes8& b, __m512d* fx,
    __m512d* fy, __m512d* fz) {
  const __m512d tiny = _mm512_set1_pd(1e-200);  // [m²]
  const __m512d half = _mm512_set1_pd(0.5);
  const __m512d one = _mm512_set1_pd(1.0);
  const __m512d xa = a.x, ya = a.y, za = a.z, vxa = a.vx, vya = a.vy, vza = a.vz;
  const __m512d xb = b.x, yb = b.y, zb = b.z, vxb = b.vx, vyb = b.vy, vzb = b.vz;
  const __m512d dx = _mm512_sub_pd(xb, xa);
  const __m512d dy = _mm512_sub_pd(yb, ya);
  const __m512d dz = _mm512_sub_pd(zb, za);
  const __m512d dvx = _mm512_sub_pd(vxb, vxa);
  const __m512d dvy = _mm512_sub_pd(vyb, vya);
  const __m512d dvz = _mm512_sub_pd(vzb, vza);
  const __m512d l2 = _mm512_fmadd_pd(dz, dz, _mm512_fmadd_pd(dy, dy, _mm512_mul_pd(dx, dx)));
  // 1/l from y0 = rsqrt14(l²) (relative error < 2^-14) by one third-order correction
  // (PositionBasedModel's): with r = 1 - l² y0², 1/l = y0 (1 + r/2 + 3r²/8 + 5r³/16 + O(r⁴)),
  // O(r⁴) < 2^-56. Lanes without a direction (empty, or a spring shorter than 1e-100 m: as
  // good as zero length) get F = 0 below; the mask is not waited for before it, as the chain
  // from l² to t is what bounds the pass.
  const __mmask8 has_direction = _mm512_mask_cmp_pd_mask(lanes, l2, tiny, _CMP_GT_OQ);
  __m512d inv = _mm512_maskz_rsqrt14_pd(lanes, l2);
  const __m512d r = _mm512_fnmadd_pd(l2, _mm512_mul_pd(inv, inv), one);
  const __m512d series =
      _mm512_fmadd_pd(r, _mm512_fmadd_pd(r, _mm512_set1_pd(0.3125), _mm512_set1_pd(0.375)), half);
  inv = _mm512_fmadd_pd(_mm512_mul_pd(inv, r), series, inv);
  // dv · (x_b - x_a) = l × the closing speed.
  const __m512d closing_l =
      _mm512_fmadd_pd(dvz, dz, _mm512_fmadd_pd(dvy, dy, _mm512_mul_pd(dvx, dx)));
  __m512d k, d;
  if (p.material != nullptr) {
    // 2 bytes per spring instead of 16: the pairs' table stays in L1/L2.
    const size_t uniform = p.column_pair[c];
    if (uniform != 0) {
      // One pair for the whole column (most of a structured mesh): two broadcasts instead of
      // two gathers. Cut springs (index 0) are off `lanes` (the state's live lanes): F = 0.
      k = _mm512_set1_pd(p.material_kd[2 * uniform]);
      d = _mm512_set1_pd(p.material_kd[2 * uniform + 1]);
    } else {
      const __m128i index = _mm_loadu_si128(reinterpret_cast<const __m128i*>(p.material + 8 * c));
      const __m256i pair = _mm256_slli_epi32(_mm256_cvtepu16_epi32(index), 1);
      k = Gather(lanes, pair, p.material_kd);
      d = Gather(lanes, pair, p.material_kd + 1);
    }
  } else {
    k = _mm512_loadu_pd(p.stiffness_damping + 16 * c);
    d = _mm512_loadu_pd(p.stiffness_damping + 16 * c + 8);
  }
  // F = t (x_b - x_a) with t = (k (l - l0) + d closing) / l = k - k l0 / l + d (dv · Δx) /
  // l²: the unit vector is never formed, and k l0 and d (dv · Δx) are ready before 1/l.
  const __m512d kl0 = _mm512_mul_pd(k, _mm512_loadu_pd(p.rest + 8 * c));
  // F = 0 off has_direction: exactly 0 for lanes without a spring, whatever their x and v.
  const __m512d t = _mm512_fmadd_pd(_mm512_mul_pd(d, closing_l), _mm512_mul_pd(inv, inv),
                                    _mm512_fnmadd_pd(kl0, inv, k));
  const __m512d sx = _mm512_maskz_mul_pd(has_direction, t, dx);
  const __m512d sy = _mm512_maskz_mul_pd(has_direction, t, dy);
  const __m512d sz = _mm512_maskz_mul_pd(has_direction, t, dz);
  *fx = _mm512_add_pd(*fx, sx);
  *fy = _mm512_add_pd(*fy, sy);
  *fz = _mm512_add_pd(*fz, sz);
  double* const out = p.ring + 24 * (c & p.ring_mask);
  _mm512_storeu_pd(out, sx);
  _mm512_storeu_pd(out + 8, sy);
  _mm512_storeu_pd(out + 16, sz);
}

// The masks of the flat values (3 chunks of 8) of a slice of `count` nodes: 3 × count of the 24.
inline std::array<__mmask8, 3> FlatChunks(size_t count) {
  const uint32_t valid = (1U << (3 * count)) - 1U;
  return {static_cast<__mmask8>(valid), static_cast<__mmask8>(valid >> 8U),
          static_cast<__mmask8>(valid >> 16U)};
}

// The x, y and z of up to 8 nodes from their flat values at `flat` (chunk: FlatChunks; 0 in the
// values past the last node), and the inverse: masked stores of the existing values.
SOMASIM_MSS_TARGET inline void LoadFlat(const double* flat, const std::array<__mmask8, 3>& chunk,
                                        __m512d* x, __m512d* y, __m512d* z) {
  Deinterleave(_mm512_maskz_loadu_pd(chunk[0], flat), _mm512_maskz_loadu_pd(chunk[1], flat + 8),
               _mm512_maskz_loadu_pd(chunk[2], flat + 16), x, y, z);
}
SOMASIM_MSS_TARGET inline void StoreFlat(__m512d x, __m512d y, __m512d z,
                                         const std::array<__mmask8, 3>& chunk, double* flat) {
  __m512d values[3];
  Interleave(x, y, z, &values[0], &values[1], &values[2]);
  for (size_t k = 0; k < 3; ++k) _mm512_mask_storeu_pd(flat + 8 * k, chunk[k], values[k]);
}

// Copies slice `slice`'s start-of-step x and v into the pass's window, transposed (x of its 8
// nodes, then y, ...; 0 past the last node), and the window's first 8 nodes also after its last,
// so that 8 consecutive nodes are one load however they straddle its end.
SOMASIM_MSS_TARGET inline void FillWindow(const SlicePass& p, size_t slice) {
  const size_t first = 8 * slice;
  const size_t count = std::min<size_t>(8, p.num_nodes - first);
  const std::array<__mmask8, 3> chunk = FlatChunks(count);
  __m512d rows[6];
  LoadFlat(p.x + 3 * first, chunk, &rows[0], &rows[1], &rows[2]);
  LoadFlat(p.v + 3 * first, chunk, &rows[3], &rows[4], &rows[5]);
  const size_t place = first & p.window_mask;
  for (size_t r = 0; r < 6; ++r) _mm512_store_pd(p.window + r * p.window_stride + place, rows[r]);
  if (place == 0) {
    for (size_t r = 0; r < 6; ++r) {
      _mm512_store_pd(p.window + r * p.window_stride + p.window_mask + 1, rows[r]);
    }
  }
}

// The x, y, z, vx, vy, vz of the 8 consecutive nodes whose x is at `at` in the window (rows
// `stride` apart), wherever they start.
SOMASIM_MSS_TARGET inline Lanes8 WindowLanes(const double* at, size_t stride) {
  return {_mm512_loadu_pd(at),
          _mm512_loadu_pd(at + stride),
          _mm512_loadu_pd(at + 2 * stride),
          _mm512_loadu_pd(at + 3 * stride),
          _mm512_loadu_pd(at + 4 * stride),
          _mm512_loadu_pd(at + 5 * stride)};
}

// SlicePassScalar, the 8 nodes of a slice in the 8 lanes. The start-of-step x and v reach the
// pass through a window of recent slices, transposed once per slice as the slice enters it
// (FillWindow, window_lead slices ahead): the lanes' own x and v are 6 loads, and so are a run
// column's other nodes' (8 consecutive nodes: 6 loads wherever they start), with no transpose
// per column; gathered columns gather theirs from x and v. The lanes' forces are summed in
// registers; each column stores its forces in the ring of columns, whence later slices take -F
// (the rotated incoming columns first, then the gathered ones, each kind in a loop of its own: no
// branch per column); 1/l comes from rsqrt14 and a third-order correction instead of a square
// root and a division, which would bound the throughput, and the force is t (x_b - x_a) with the
// scale t = F/l, so the unit vector is never formed. The slice's 8 nodes are integrated in their
// lanes and transposed back once, for x and for v. Results differ from the scalar pass by
// rounding only.
SOMASIM_MSS_TARGET StateCheck SlicePassAvx512(const SlicePass& pass) {
  // Local copies: the scatters could alias `pass` as far as the compiler knows.
  const SlicePass p = pass;
  const __m512d dt = _mm512_set1_pd(p.dt);
  const __m512d component_limit = _mm512_set1_pd(p.component_limit);
  __mmask8 non_finite = 0, maybe_too_fast = 0;
  const size_t num_slices = (p.num_nodes + 7) / 8;
  const size_t stride = p.window_stride;
  for (size_t slice = 0; slice < std::min(p.window_lead, num_slices); ++slice) {
    FillWindow(p, slice);
  }
  for (size_t slice = 0; slice < num_slices; ++slice) {
    if (slice + p.window_lead < num_slices) FillWindow(p, slice + p.window_lead);
    const size_t first = 8 * slice;
    const size_t count = std::min<size_t>(8, p.num_nodes - first);
    const Lanes8 a = WindowLanes(p.window + (first & p.window_mask), stride);
    __m512d fx = _mm512_setzero_pd(), fy = _mm512_setzero_pd(), fz = _mm512_setzero_pd();
    const auto gathered_start = static_cast<size_t>(p.gathered_column[slice]);
    for (auto c = static_cast<size_t>(p.column_start[slice]); c < gathered_start; ++c) {
      const Lanes8 other = WindowLanes(p.window + p.column_window[c], stride);
      SpringColumn(p, c, p.live_lanes[c], a, other, &fx, &fy, &fz);
    }
    const auto columns_end = static_cast<size_t>(p.column_start[slice + 1]);
    for (size_t c = gathered_start; c < columns_end; ++c) {
      const __mmask8 lanes = p.live_lanes[c];
      const __m256i b = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p.other3 + 8 * c));
      const Lanes8 other{Gather(lanes, b, p.x),     Gather(lanes, b, p.x + 1),
                         Gather(lanes, b, p.x + 2), Gather(lanes, b, p.v),
                         Gather(lanes, b, p.v + 1), Gather(lanes, b, p.v + 2)};
      SpringColumn(p, c, lanes, a, other, &fx, &fy, &fz);
    }
    // -F of the springs ending on the slice's nodes, from their columns' places in the ring.
    const auto rotated_end = static_cast<size_t>(p.gathered_incoming[slice]);
    // The incoming forces are summed apart from the outgoing ones (incoming_x, incoming_y,
    // incoming_z): two shorter chains of additions instead of one.
    __m512d incoming_x = _mm512_setzero_pd(), incoming_y = _mm512_setzero_pd(),
            incoming_z = _mm512_setzero_pd();
    for (auto c = static_cast<size_t>(p.incoming_start[slice]); c < rotated_end; ++c) {
      const int32_t* const q = p.incoming_slot + 8 * c;
      const double* const first_column = p.ring + q[0];
      const double* const second_column = p.ring + q[1];
      const __m512i rotation =
          _mm512_add_epi64(_mm512_set1_epi64(q[2]), Indices(0, 1, 2, 3, 4, 5, 6, 7));
      incoming_x =
          _mm512_add_pd(incoming_x, _mm512_permutex2var_pd(_mm512_loadu_pd(first_column), rotation,
                                                           _mm512_loadu_pd(second_column)));
      incoming_y = _mm512_add_pd(incoming_y,
                                 _mm512_permutex2var_pd(_mm512_loadu_pd(first_column + 8), rotation,
                                                        _mm512_loadu_pd(second_column + 8)));
      incoming_z = _mm512_add_pd(
          incoming_z, _mm512_permutex2var_pd(_mm512_loadu_pd(first_column + 16), rotation,
                                             _mm512_loadu_pd(second_column + 16)));
    }
    const auto incoming_end = static_cast<size_t>(p.incoming_start[slice + 1]);
    for (size_t c = rotated_end; c < incoming_end; ++c) {
      const int32_t* const q = p.incoming_slot + 8 * c;
      const __mmask8 lanes = p.incoming_lanes[c];
      const __m256i slot = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(q));
      incoming_x = _mm512_add_pd(incoming_x, Gather(lanes, slot, p.ring));
      incoming_y = _mm512_add_pd(incoming_y, Gather(lanes, slot, p.ring + 8));
      incoming_z = _mm512_add_pd(incoming_z, Gather(lanes, slot, p.ring + 16));
    }
    fx = _mm512_sub_pd(fx, incoming_x);
    fy = _mm512_sub_pd(fy, incoming_y);
    fz = _mm512_sub_pd(fz, incoming_z);
    // Masks of the slice's flat values and of its lanes.
    const std::array<__mmask8, 3> chunk = FlatChunks(count);
    const auto lanes = static_cast<__mmask8>((1U << count) - 1U);
    if (!p.integrate) {
      __m512d sum[3];
      Interleave(fx, fy, fz, &sum[0], &sum[1], &sum[2]);
      double* const pending = p.pending + 3 * first;
      for (size_t k = 0; k < 3; ++k) {
        _mm512_mask_storeu_pd(
            pending + 8 * k, chunk[k],
            _mm512_add_pd(sum[k], _mm512_maskz_loadu_pd(chunk[k], pending + 8 * k)));
      }
      continue;
    }
    // What anchors and grasps added (pending, zeroed once read) and the external forces, in
    // the lanes.
    if (p.pending != nullptr) {
      double* const pending = p.pending + 3 * first;
      __m512d px, py, pz;
      LoadFlat(pending, chunk, &px, &py, &pz);
      for (size_t k = 0; k < 3; ++k) {
        _mm512_mask_storeu_pd(pending + 8 * k, chunk[k], _mm512_setzero_pd());
      }
      fx = _mm512_add_pd(fx, px);
      fy = _mm512_add_pd(fy, py);
      fz = _mm512_add_pd(fz, pz);
    }
    if (p.external != nullptr) {
      __m512d ex, ey, ez;
      LoadFlat(p.external + 3 * first, chunk, &ex, &ey, &ez);
      fx = _mm512_add_pd(fx, ex);
      fy = _mm512_add_pd(fy, ey);
      fz = _mm512_add_pd(fz, ez);
    }
    const __m512d w = _mm512_maskz_loadu_pd(lanes, p.inverse_mass + first);
    // Massless nodes (w = 0) do not move: no gravity on them either.
    const __mmask8 moves = _mm512_cmp_pd_mask(w, _mm512_setzero_pd(), _CMP_GT_OQ);
    const __m512d vx = _mm512_fmadd_pd(
        dt, _mm512_fmadd_pd(w, fx, _mm512_maskz_mov_pd(moves, _mm512_set1_pd(p.gravity[0]))), a.vx);
    const __m512d vy = _mm512_fmadd_pd(
        dt, _mm512_fmadd_pd(w, fy, _mm512_maskz_mov_pd(moves, _mm512_set1_pd(p.gravity[1]))), a.vy);
    const __m512d vz = _mm512_fmadd_pd(
        dt, _mm512_fmadd_pd(w, fz, _mm512_maskz_mov_pd(moves, _mm512_set1_pd(p.gravity[2]))), a.vz);
    const __m512d x = _mm512_fmadd_pd(dt, vx, a.x);
    const __m512d y = _mm512_fmadd_pd(dt, vy, a.y);
    const __m512d z = _mm512_fmadd_pd(dt, vz, a.z);
    for (const auto& [position, velocity] :
         {std::pair{x, vx}, std::pair{y, vy}, std::pair{z, vz}}) {
      non_finite |= _mm512_mask_cmp_pd_mask(lanes, _mm512_sub_pd(position, position),
                                            _mm512_sub_pd(velocity, velocity), _CMP_UNORD_Q);
      maybe_too_fast |=
          _mm512_mask_cmp_pd_mask(lanes, _mm512_abs_pd(velocity), component_limit, _CMP_GT_OQ);
    }
    StoreFlat(vx, vy, vz, chunk, p.moved_v + 3 * first);
    StoreFlat(x, y, z, chunk, p.moved_x + 3 * first);
  }
  return {non_finite != 0, maybe_too_fast != 0};
}

#else
StateCheck SlicePassAvx512(const SlicePass& p) { return SlicePassScalar(p); }
#endif

// Tests switch the AVX-512 pass off to compare it with the scalar one
// (SetMassSpringAvx512ForTesting, declared where the tests use it).
bool g_use_avx512 = true;

StateCheck RunSlicePass(const SlicePass& p) {
  if (g_use_avx512 && CpuHasAvx512()) return SlicePassAvx512(p);
  return SlicePassScalar(p);
}

// Points the pass at the state's spring constants in whichever form it holds them.
void SetSpringConstants(const MassSpringState& state, const std::vector<double>& material_kd,
                        const HugePageVector<uint16_t>& column_pair, SlicePass* pass) {
  if (!state.column_material.empty()) {
    pass->material = state.column_material.data();
    pass->material_kd = material_kd.data();
    pass->column_pair = column_pair.data();
  } else {
    pass->stiffness_damping = state.column_stiffness_damping.data();
  }
}

// Points the pass at the state's window (MassSpringModel::window_slices_), 64-byte aligned.
void SetWindow(const MassSpringState& state, int32_t window_slices, int32_t window_lead,
               const HugePageVector<int32_t>& column_window, SlicePass* pass) {
  const size_t span = 8 * static_cast<size_t>(window_slices);
  void* start = state.window.data();
  size_t space = state.window.size() * sizeof(double);
  pass->window =
      static_cast<double*>(std::align(64, 6 * (span + 8) * sizeof(double), start, space));
  pass->window_stride = span + 8;
  pass->window_mask = span - 1;
  pass->window_lead = static_cast<size_t>(window_lead);
  pass->column_window = column_window.data();
}

// Values (>= 0) that agree to kMergeTolerance relative become one: each group of values sorted
// within the tolerance of its least takes that least. Rounding makes the constants of congruent
// springs differ in their last bits (the 53³ grid: 2,103 distinct (k, d) pairs, 20 once merged),
// which would keep the explicit pass from treating a column of them as one material; 1e-12 of a
// tissue's stiffness is far below anything measured of it.
constexpr double kMergeTolerance = 1e-12;
void MergeNearlyEqual(std::vector<double>* values) {
  std::vector<size_t> order(values->size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return (*values)[a] < (*values)[b]; });
  for (size_t b = 0; b < order.size();) {
    const double least = (*values)[order[b]];
    size_t e = b + 1;
    while (e < order.size() && (*values)[order[e]] <= least + kMergeTolerance * least) {
      (*values)[order[e]] = least;
      ++e;
    }
    b = e;
  }
}

void CheckParameters(const MassSpringParameters& p) {
  const auto positive_or_raw = [](double physical, double raw, const char* what) {
    if (raw > 0.0) return;
    if (!checks::FinitePositive(physical)) {
      throw std::invalid_argument(std::string("mass-spring: ") + what +
                                  " must be a finite value > 0");
    }
  };
  positive_or_raw(p.youngs_modulus, p.spring_stiffness, "youngs_modulus [Pa]");
  positive_or_raw(p.density, p.node_mass, "density [kg/m^3]");
  if (!checks::FiniteNonNegative(p.damping_ratio)) {
    throw std::invalid_argument("mass-spring: damping_ratio must be a finite value >= 0");
  }
  if (!checks::FinitePositive(p.thickness)) {
    throw std::invalid_argument("mass-spring: thickness [m] must be a finite value > 0");
  }
  checks::RequireFiniteNonNegative("mass-spring", "spring_stiffness [N/m]", p.spring_stiffness);
  checks::RequireFiniteNonNegative("mass-spring", "node_mass [kg]", p.node_mass);
  if (!(p.cg_tolerance > 0.0) || !(p.cg_max_iterations > 0)) {
    throw std::invalid_argument("mass-spring: cg_tolerance and cg_max_iterations must be > 0");
  }
  if (!(p.speed_limit > 0.0)) {
    throw std::invalid_argument("mass-spring: speed_limit [m/s] must be > 0");
  }
  checks::RequireFiniteNonNegative("mass-spring", "anchor_stiffness [N/m]", p.anchor_stiffness);
}

}  // namespace

void SetMassSpringAvx512ForTesting(bool enabled) { g_use_avx512 = enabled; }

bool MassSpringStateUsesPairTableForTesting(const TissueState& state) {
  return !static_cast<const MassSpringState&>(state).column_material.empty();
}

std::unique_ptr<MassSpringModel> MassSpringModel::FromTetMesh(
    const mesh::TetMesh& mesh, const MassSpringParameters& parameters) {
  CheckParameters(parameters);
  const MeshEdges edges = TetMeshEdges(mesh, "mass-spring");
  std::unique_ptr<MassSpringModel> model(new MassSpringModel());
  model->Build(mesh.vertices, edges.edges, edges.edge_size, edges.node_size, parameters);
  return model;
}

std::unique_ptr<MassSpringModel> MassSpringModel::FromSurface(
    const mesh::SurfaceMesh& surface, const MassSpringParameters& parameters) {
  CheckParameters(parameters);
  const MeshEdges edges = SurfaceEdges(surface, parameters.thickness, "mass-spring");
  std::unique_ptr<MassSpringModel> model(new MassSpringModel());
  model->Build(surface.vertices, edges.edges, edges.edge_size, edges.node_size, parameters);
  return model;
}

std::unique_ptr<MassSpringModel> MassSpringModel::FromGeneralisedSurface(
    const mesh::TetMesh& mesh, const MassSpringParameters& parameters) {
  CheckParameters(parameters);
  if (!(parameters.anchor_stiffness > 0.0)) {
    throw std::invalid_argument(
        "mass-spring: a generalised surface mesh needs anchor_stiffness [N/m] > 0");
  }
  const OuterShell shell = SelectOuterShell(mesh, parameters.shell_fraction);
  const MeshEdges edges = ShellEdges(mesh, shell);
  std::unique_ptr<MassSpringModel> model(new MassSpringModel());
  model->Build(mesh.vertices, edges.edges, edges.edge_size, edges.node_size, parameters);
  return model;
}

std::unique_ptr<MassSpringModel> MassSpringModel::FromEdges(
    const mesh::Points& rest, const std::vector<std::array<int32_t, 2>>& edges,
    const MassSpringParameters& parameters) {
  CheckParameters(parameters);
  CheckFinitePoints(rest, "mass-spring");
  if (!(parameters.spring_stiffness > 0.0) || !(parameters.node_mass > 0.0)) {
    throw std::invalid_argument(
        "mass-spring: springs given as edges need spring_stiffness and node_mass > 0");
  }
  if (edges.empty()) throw std::invalid_argument("mass-spring: no springs");
  // Sorted as a mesh's edges are: the layouts, and so the results, follow the spring order.
  const std::vector<std::array<int32_t, 2>> ordered =
      SortedEdges(edges, rest.cols(), "mass-spring", "spring");
  std::unique_ptr<MassSpringModel> model(new MassSpringModel());
  model->Build(rest, ordered, std::vector<double>(ordered.size(), 0.0),
               std::vector<double>(static_cast<size_t>(rest.cols()), 0.0), parameters);
  return model;
}

void MassSpringModel::Build(const mesh::Points& rest,
                            const std::vector<std::array<int32_t, 2>>& edges,
                            const std::vector<double>& edge_size_sum,
                            const std::vector<double>& node_size, const MassSpringParameters& p) {
  rest_ = rest;
  const auto n = static_cast<size_t>(rest.cols());
  LumpMasses(node_size, p.density, p.node_mass, &mass_, &inverse_mass_);
  const size_t m = edges.size();
  spring_i_.resize(m);
  spring_j_.resize(m);
  rest_length_.resize(m);
  stiffness_.resize(m);
  damping_.resize(m);
  for (size_t s = 0; s < m; ++s) {
    const auto [i, j] = edges[s];
    spring_i_[s] = i;
    spring_j_[s] = j;
    const double length = EdgeRestLength(rest, i, j, "mass-spring", "spring");
    rest_length_[s] = length;
    // Van Gelder 1998: k_e = E Σ size / |e|².
    stiffness_[s] = p.spring_stiffness > 0.0
                        ? p.spring_stiffness
                        : p.youngs_modulus * edge_size_sum[s] / (length * length);
    const double mi = mass_[static_cast<size_t>(i)];
    const double mj = mass_[static_cast<size_t>(j)];
    const double reduced = mi + mj > 0.0 ? mi * mj / (mi + mj) : 0.0;
    damping_[s] = 2.0 * p.damping_ratio * std::sqrt(stiffness_[s] * reduced);
  }
  MergeNearlyEqual(&stiffness_);
  MergeNearlyEqual(&damping_);
  NodeEdgeLists(n, spring_i_, spring_j_, &node_spring_start_, &node_springs_);
  anchor_nodes_.clear();
  anchor_damping_.clear();
  anchor_stiffness_ = p.anchor_stiffness;
  if (anchor_stiffness_ > 0.0) {
    for (size_t i = 0; i < n; ++i) {
      if (mass_[i] > 0.0) {
        anchor_nodes_.push_back(static_cast<int32_t>(i));
        anchor_damping_.push_back(2.0 * p.damping_ratio * std::sqrt(anchor_stiffness_ * mass_[i]));
      }
    }
  }
  set_speed_limit(p.speed_limit);
  integrator_ = p.integrator;
  cg_tolerance_ = p.cg_tolerance;
  cg_max_iterations_ = p.cg_max_iterations;
  BuildExplicitLayout();
  if (integrator_ == MassSpringIntegrator::kImplicitEuler) BuildImplicitData();
}

void MassSpringModel::BuildExplicitLayout() {
  const auto n = static_cast<size_t>(rest_.cols());
  const size_t m = spring_i_.size();
  const size_t num_slices = (n + 7) / 8;
  // Each spring's lane node: the end in the earlier slice, which lets the pass move a slice's
  // nodes at its end (every spring touching them is done, none still to come reads them).
  // Springs within one slice go to the end with fewer springs so far, to keep slices narrow.
  std::vector<int32_t> lane_node(m), per_node(n, 0);
  std::vector<size_t> inner;
  for (size_t s = 0; s < m; ++s) {
    const int32_t i = spring_i_[s], j = spring_j_[s];
    if (i / 8 == j / 8) {
      inner.push_back(s);
    } else {
      lane_node[s] = i;
      ++per_node[static_cast<size_t>(i)];
    }
  }
  for (const size_t s : inner) {
    const int32_t i = spring_i_[s], j = spring_j_[s];
    lane_node[s] = per_node[static_cast<size_t>(j)] < per_node[static_cast<size_t>(i)] ? j : i;
    ++per_node[static_cast<size_t>(lane_node[s])];
  }
  // The end of spring s that is not its lane node.
  const auto other_end = [&](size_t s) {
    return lane_node[s] == spring_i_[s] ? spring_j_[s] : spring_i_[s];
  };
  // Springs by lane node (CSR), in canonical order within a node.
  std::vector<size_t> start(n + 1, 0);
  for (size_t s = 0; s < m; ++s) ++start[static_cast<size_t>(lane_node[s]) + 1];
  for (size_t i = 0; i < n; ++i) start[i + 1] += start[i];
  std::vector<size_t> by_node(m);
  std::vector<size_t> fill(start.begin(), start.end() - 1);
  for (size_t s = 0; s < m; ++s) by_node[fill[static_cast<size_t>(lane_node[s])]++] = s;
  // Outgoing columns. A slice's springs with one offset Δ = other node − lane node (an edge kind
  // of a structured mesh) go into one run column when enough of its lanes have one: lane l's
  // other node is then 8 slice + l + Δ, and the pass loads the 8 other nodes' x and v as 24
  // consecutive values each instead of gathering them; lanes without such a spring hold none
  // (the pass stores F = 0 for them). The slice's other springs go into gathered columns,
  // column k holding each lane's k-th. How many lanes a run column needs is chosen per slice:
  // the least that costs the pass least (a gathered column costs kGatheredColumnCost run
  // columns).
  slice_column_start_.assign(1, 0);
  column_other3_.clear();
  column_rest_.clear();
  column_lanes_.clear();
  spring_slot_.assign(m, 0);
  slice_gathered_column_.clear();
  constexpr int64_t kNotInRun = std::numeric_limits<int64_t>::min();
  std::vector<int64_t> run_offset(m, kNotInRun);  // Δ of each spring in a run column
  // Each slice's run columns as (Δ, column), for the incoming columns below.
  std::vector<std::vector<std::pair<int64_t, int32_t>>> slice_runs(num_slices);
  const auto emit_column = [&](const std::array<size_t, 8>& spring,
                               const std::array<int32_t, 8>& other3, uint8_t lanes) {
    const auto index = static_cast<int32_t>(column_lanes_.size());
    for (size_t lane = 0; lane < 8; ++lane) {
      const size_t s = spring[lane];
      column_rest_.push_back(s < m ? rest_length_[s] : 0.0);
      if (s < m) spring_slot_[s] = 8 * index + static_cast<int32_t>(lane);
    }
    column_other3_.insert(column_other3_.end(), other3.begin(), other3.end());
    column_lanes_.push_back(lanes);
    return index;
  };
  struct Candidate {
    int64_t offset;  // Δ
    size_t lane;
    size_t spring;
  };
  struct Run {  // the candidates [begin, end) of one Δ
    size_t begin, end;
    uint8_t lanes;  // lanes with a spring of this Δ (their first one when a lane has two)
    int lane_count;
    bool loadable;  // the 8 other nodes 8 slice + Δ .. + 7 exist
  };
  std::vector<Candidate> candidates;
  std::vector<Run> runs;
  std::array<std::vector<size_t>, 8> rest_of_lane;
  for (size_t slice = 0; slice < num_slices; ++slice) {
    const size_t first = 8 * slice, last = std::min(n, first + 8);
    candidates.clear();
    for (size_t node = first; node < last; ++node) {
      for (size_t k = start[node]; k < start[node + 1]; ++k) {
        const size_t s = by_node[k];
        candidates.push_back({int64_t{other_end(s)} - static_cast<int64_t>(node), node - first, s});
      }
    }
    // By Δ; within one Δ by lane, and a lane's springs in canonical order.
    std::stable_sort(candidates.begin(), candidates.end(),
                     [](const Candidate& a, const Candidate& b) { return a.offset < b.offset; });
    runs.clear();
    for (size_t b = 0; b < candidates.size();) {
      size_t e = b;
      Run run{b, b, 0, 0, false};
      while (e < candidates.size() && candidates[e].offset == candidates[b].offset) {
        run.lanes = static_cast<uint8_t>(run.lanes | (1U << candidates[e].lane));
        ++e;
      }
      run.end = e;
      run.lane_count = std::popcount(run.lanes);
      const int64_t window = static_cast<int64_t>(first) + candidates[b].offset;
      run.loadable = window >= 0 && window + 8 <= static_cast<int64_t>(n);
      runs.push_back(run);
      b = e;
    }
    // The threshold: the number of run columns plus kGatheredColumnCost × the widest lane's
    // springs left for gathered columns, least over 1..8 lanes.
    int best_threshold = 9;
    double best_cost = std::numeric_limits<double>::infinity();
    for (int threshold = 1; threshold <= 8; ++threshold) {
      std::array<size_t, 8> left{};
      size_t run_columns = 0;
      for (const Run& run : runs) {
        const bool taken = run.loadable && run.lane_count >= threshold;
        run_columns += taken ? 1 : 0;
        for (size_t c = run.begin; c < run.end; ++c) ++left[candidates[c].lane];
        if (taken) {
          for (size_t lane = 0; lane < 8; ++lane) left[lane] -= (run.lanes >> lane) & 1U;
        }
      }
      const double cost =
          static_cast<double>(run_columns) +
          kGatheredColumnCost * static_cast<double>(*std::max_element(left.begin(), left.end()));
      if (cost < best_cost) {
        best_cost = cost;
        best_threshold = threshold;
      }
    }
    for (const Run& run : runs) {
      if (!run.loadable || run.lane_count < best_threshold) continue;
      std::array<size_t, 8> spring;
      spring.fill(m);
      std::array<int32_t, 8> other3{};
      const int64_t offset = candidates[run.begin].offset;
      for (size_t lane = 0; lane < 8; ++lane) {
        other3[lane] = static_cast<int32_t>(3 * (static_cast<int64_t>(first + lane) + offset));
      }
      for (size_t c = run.begin; c < run.end; ++c) {
        if (spring[candidates[c].lane] != m) continue;  // a lane's second spring of this Δ
        spring[candidates[c].lane] = candidates[c].spring;
        run_offset[candidates[c].spring] = offset;
      }
      slice_runs[slice].emplace_back(offset, emit_column(spring, other3, run.lanes));
    }
    slice_gathered_column_.push_back(static_cast<int32_t>(column_lanes_.size()));
    size_t width = 0;
    for (size_t node = first; node < last; ++node) {
      std::vector<size_t>& rest = rest_of_lane[node - first];
      rest.clear();
      for (size_t k = start[node]; k < start[node + 1]; ++k) {
        if (run_offset[by_node[k]] == kNotInRun) rest.push_back(by_node[k]);
      }
      width = std::max(width, rest.size());
    }
    for (size_t k = 0; k < width; ++k) {
      std::array<size_t, 8> spring;
      spring.fill(m);
      std::array<int32_t, 8> other3{};
      uint8_t lanes = 0;
      for (size_t lane = 0; lane < last - first; ++lane) {
        if (k >= rest_of_lane[lane].size()) continue;
        const size_t s = rest_of_lane[lane][k];
        spring[lane] = s;
        other3[lane] = 3 * other_end(s);
        lanes = static_cast<uint8_t>(lanes | (1U << lane));
      }
      emit_column(spring, other3, lanes);
    }
    slice_column_start_.push_back(static_cast<int32_t>(column_lanes_.size()));
  }
  // Incoming columns: a slice's nodes take -F of the springs ending on them. For each Δ of run
  // columns, one rotated column: lane l's spring of that Δ starts at node 8 slice + l - Δ =
  // 8 s_a + r + l, in lane r + l of the Δ run column of slice s_a (l < 8 - r), or lane
  // r + l - 8 of that of slice s_a + 1; the pass loads both columns' forces and rotates them.
  // Lanes without such a spring read a lane the run column left empty (F = 0 there), or the
  // ring's zero column where there is no run column (or one not yet computed: only a Δ < 0
  // within one slice reads beyond it, and only empty lanes). The other springs ending on a lane
  // are gathered from their ring places, column k holding each lane's k-th.
  std::vector<std::vector<size_t>> incoming(n);
  for (size_t s = 0; s < m; ++s) {
    incoming[static_cast<size_t>(other_end(s))].push_back(s);
  }
  struct IncomingColumn {
    // Rotated: {column of lanes r.., column of lanes ..r-1, r} (-1: the zero column); gathered:
    // each lane's 8 × column + lane.
    std::array<int32_t, 8> slot;
    uint8_t lanes;
    bool rotated;
  };
  std::vector<IncomingColumn> incoming_columns;
  std::vector<size_t> incoming_column_start(1, 0);
  std::vector<std::pair<int64_t, uint8_t>> rotated;  // Δ, lanes
  const auto run_column = [&](int64_t slice, int64_t offset) {
    if (slice < 0) return int32_t{-1};
    for (const auto& [o, column] : slice_runs[static_cast<size_t>(slice)]) {
      if (o == offset) return column;
    }
    return int32_t{-1};
  };
  for (size_t slice = 0; slice < num_slices; ++slice) {
    const size_t first = 8 * slice, last = std::min(n, first + 8);
    rotated.clear();
    size_t width = 0;
    for (size_t node = first; node < last; ++node) {
      std::vector<size_t>& rest = rest_of_lane[node - first];
      rest.clear();
      for (const size_t s : incoming[node]) {
        if (run_offset[s] == kNotInRun) {
          rest.push_back(s);
          continue;
        }
        auto it = std::find_if(rotated.begin(), rotated.end(),
                               [&](const auto& entry) { return entry.first == run_offset[s]; });
        if (it == rotated.end()) it = rotated.insert(rotated.end(), {run_offset[s], uint8_t{0}});
        it->second = static_cast<uint8_t>(it->second | (1U << (node - first)));
      }
      width = std::max(width, rest.size());
    }
    std::sort(rotated.begin(), rotated.end());
    for (const auto& [offset, lanes] : rotated) {
      const int64_t source = static_cast<int64_t>(first) - offset;  // lane 0's start node
      const int64_t source_slice = source >= 0 ? source / 8 : -((7 - source) / 8);
      const auto r = static_cast<int32_t>(source - 8 * source_slice);
      const int32_t a = source_slice <= static_cast<int64_t>(slice)
                            ? run_column(source_slice, offset)
                            : int32_t{-1};
      const int32_t b = r == 0 ? a
                        : source_slice + 1 <= static_cast<int64_t>(slice)
                            ? run_column(source_slice + 1, offset)
                            : int32_t{-1};
      incoming_columns.push_back({{a, b, r, 0, 0, 0, 0, 0}, lanes, true});
    }
    for (size_t k = 0; k < width; ++k) {
      IncomingColumn column{{}, 0, false};
      for (size_t lane = 0; lane < last - first; ++lane) {
        if (k >= rest_of_lane[lane].size()) continue;
        column.slot[lane] = spring_slot_[rest_of_lane[lane][k]];
        column.lanes = static_cast<uint8_t>(column.lanes | (1U << lane));
      }
      incoming_columns.push_back(column);
    }
    incoming_column_start.push_back(incoming_columns.size());
  }
  // The ring of column forces: every column an incoming column reads must not be overwritten
  // before the end of the reading slice's columns.
  size_t reach = 1;
  for (size_t slice = 0; slice < num_slices; ++slice) {
    const auto end = static_cast<int64_t>(slice_column_start_[slice + 1]);
    for (size_t c = incoming_column_start[slice]; c < incoming_column_start[slice + 1]; ++c) {
      const IncomingColumn& column = incoming_columns[c];
      for (size_t lane = 0; lane < 8; ++lane) {
        int64_t read = -1;
        if (column.rotated) {
          if (lane < 2) read = column.slot[lane];
        } else if (((column.lanes >> lane) & 1U) != 0) {
          read = column.slot[lane] / 8;
        }
        if (read >= 0) reach = std::max(reach, static_cast<size_t>(end - read));
      }
    }
  }
  size_t ring = 1;
  while (ring < reach) ring *= 2;
  ring_columns_ = static_cast<int32_t>(ring);
  const auto ring_place = [&](int32_t column) {
    return column < 0 ? 24 * ring_columns_ : 24 * (column % ring_columns_);
  };
  slice_incoming_start_.assign(1, 0);
  incoming_slot_.clear();
  incoming_lanes_.clear();
  slice_gathered_incoming_.clear();
  for (size_t slice = 0; slice < num_slices; ++slice) {
    slice_gathered_incoming_.push_back(static_cast<int32_t>(incoming_column_start[slice]));
    for (size_t c = incoming_column_start[slice]; c < incoming_column_start[slice + 1]; ++c) {
      IncomingColumn column = incoming_columns[c];
      if (column.rotated) {
        column.slot[0] = ring_place(column.slot[0]);
        column.slot[1] = ring_place(column.slot[1]);
        ++slice_gathered_incoming_.back();
      } else {
        for (size_t lane = 0; lane < 8; ++lane) {
          if (((column.lanes >> lane) & 1U) == 0) continue;
          column.slot[lane] = ring_place(column.slot[lane] / 8) + column.slot[lane] % 8;
        }
      }
      incoming_slot_.insert(incoming_slot_.end(), column.slot.begin(), column.slot.end());
      incoming_lanes_.push_back(column.lanes);
    }
    slice_incoming_start_.push_back(static_cast<int32_t>(incoming_lanes_.size()));
  }
  // The window of the AVX-512 pass (SlicePass::window): a run column of slice s reads the
  // nodes 8 s + Δ .. + 7, in slices s - 1 (Δ < 0) to s + (Δ + 7) / 8; the pass fills slice
  // s + lead at the start of slice s, so the window must hold lead + 2 slices.
  window_lead_ = 0;
  column_window_.assign(column_lanes_.size(), 0);
  for (size_t slice = 0; slice < num_slices; ++slice) {
    for (auto c = static_cast<size_t>(slice_column_start_[slice]);
         c < static_cast<size_t>(slice_gathered_column_[slice]); ++c) {
      const int64_t offset = column_other3_[8 * c] / 3 - static_cast<int64_t>(8 * slice);
      window_lead_ = std::max(window_lead_, static_cast<int32_t>((offset + 7) / 8));
    }
  }
  window_slices_ = 1;
  while (window_slices_ < window_lead_ + 2) window_slices_ *= 2;
  for (size_t c = 0; c < column_lanes_.size(); ++c) {
    column_window_[c] = (column_other3_[8 * c] / 3) & (8 * window_slices_ - 1);
  }
  // The distinct (k, d) pairs, exactly (after MergeNearlyEqual): when each is shared by 8 springs
  // or more on average (structured meshes: 20 pairs for the 1M springs of a 53³ grid) and the
  // table stays small, the state keeps a 2-byte index per spring instead of k and d (16 bytes).
  std::vector<std::array<double, 2>> pairs;
  pairs.reserve(m + 1);
  pairs.push_back({0.0, 0.0});
  for (size_t s = 0; s < m; ++s) pairs.push_back({stiffness_[s], damping_[s]});
  std::sort(pairs.begin(), pairs.end());
  pairs.erase(std::unique(pairs.begin(), pairs.end()), pairs.end());
  material_kd_.clear();
  spring_material_.clear();
  column_pair_.clear();
  if (pairs.size() <= kMaxMaterialPairs && 8 * pairs.size() <= m) {
    // Pair 0 must be (0, 0): stiffness and damping are >= 0, so it sorts first.
    assert(pairs[0][0] == 0.0 && pairs[0][1] == 0.0);
    for (const auto& pair : pairs)
      material_kd_.insert(material_kd_.end(), pair.begin(), pair.end());
    spring_material_.resize(m);
    for (size_t s = 0; s < m; ++s) {
      const std::array<double, 2> pair = {stiffness_[s], damping_[s]};
      spring_material_[s] =
          static_cast<uint16_t>(std::lower_bound(pairs.begin(), pairs.end(), pair) - pairs.begin());
    }
    // Each column's one pair, or 0 (several pairs: the pass gathers them per lane). Pair 0 is
    // only empty lanes' and cut springs': never a column's pair.
    constexpr uint32_t kSeveral = 0x10000;
    std::vector<uint32_t> column(column_lanes_.size(), 0);
    for (size_t s = 0; s < m; ++s) {
      uint32_t& pair = column[static_cast<size_t>(spring_slot_[s] / 8)];
      pair = pair == 0 || pair == spring_material_[s] ? spring_material_[s] : kSeveral;
    }
    column_pair_.resize(column.size());
    for (size_t c = 0; c < column.size(); ++c) {
      column_pair_[c] = column[c] == kSeveral ? 0 : static_cast<uint16_t>(column[c]);
    }
  }
}

std::unique_ptr<TissueState> MassSpringModel::MakeState() const {
  auto state = std::make_unique<MassSpringState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = rest_.cols();
  state->forces = mesh::Points::Zero(3, n);
  state->stiffness = stiffness_;
  state->damping = damping_;
  // The ring's columns and its zero column (never written).
  state->column_forces.assign(24 * (static_cast<size_t>(ring_columns_) + 1), 0.0);
  // The pass's window: 6 rows of 8 window_slices_ + 8 values, 64-byte aligned (+ 8 to align).
  state->window.assign(6 * (8 * static_cast<size_t>(window_slices_) + 8) + 8, 0.0);
  state->column_lanes = column_lanes_;
  if (!spring_material_.empty()) {
    state->column_material.assign(column_rest_.size(), 0);
    for (size_t s = 0; s < spring_slot_.size(); ++s) {
      state->column_material[static_cast<size_t>(spring_slot_[s])] = spring_material_[s];
    }
  } else {
    state->column_stiffness_damping.assign(2 * column_rest_.size(), 0.0);
    for (size_t s = 0; s < spring_slot_.size(); ++s) {
      const auto slot = static_cast<size_t>(spring_slot_[s]);
      state->column_stiffness_damping[2 * slot - slot % 8] = stiffness_[s];
      state->column_stiffness_damping[2 * slot - slot % 8 + 8] = damping_[s];
    }
  }
  if (integrator_ == MassSpringIntegrator::kImplicitEuler) {
    SizeImplicitScratch(state.get());
  } else {
    state->pending = mesh::Points::Zero(3, n);
  }
  return state;
}

void MassSpringModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  // Seed 002 eq. 1–3: f_i += K (l - l0) u + D ((v_j - v_i)·u) u, u = (x_j - x_i) / l; f_j -= ….
  forces->resize(3, rest_.cols());  // a no-op (no allocation) when already sized
  forces->setZero();
  const auto& ms = static_cast<const MassSpringState&>(state);
  SlicePass pass{};
  pass.x = state.positions.data();
  pass.v = state.velocities.data();
  pass.num_nodes = static_cast<size_t>(rest_.cols());
  pass.column_start = slice_column_start_.data();
  pass.other3 = column_other3_.data();
  pass.rest = column_rest_.data();
  pass.lanes = column_lanes_.data();
  pass.live_lanes = ms.column_lanes.data();
  SetSpringConstants(ms, material_kd_, column_pair_, &pass);
  pass.gathered_column = slice_gathered_column_.data();
  pass.incoming_start = slice_incoming_start_.data();
  pass.incoming_slot = incoming_slot_.data();
  pass.incoming_lanes = incoming_lanes_.data();
  pass.gathered_incoming = slice_gathered_incoming_.data();
  pass.ring = ms.column_forces.data();
  pass.ring_mask = static_cast<size_t>(ring_columns_) - 1;
  SetWindow(ms, window_slices_, window_lead_, column_window_, &pass);
  pass.pending = forces->data();
  pass.integrate = false;
  RunSlicePass(pass);
  AddAnchorForces(state, forces->data());
}

void MassSpringModel::AddAnchorForces(const TissueState& state, double* forces) const {
  // Seed 001 eq. 10: f_i = k_s (x0_i - x_i), plus its damping -d_i v_i.
  const double* __restrict x = state.positions.data();
  const double* __restrict v = state.velocities.data();
  const double* __restrict x0 = rest_.data();
  const double k = anchor_stiffness_;
  for (size_t a = 0; a < anchor_nodes_.size(); ++a) {
    const auto i = 3 * static_cast<size_t>(anchor_nodes_[a]);
    const double d = anchor_damping_[a];
    forces[i] += k * (x0[i] - x[i]) - d * v[i];
    forces[i + 1] += k * (x0[i + 1] - x[i + 1]) - d * v[i + 1];
    forces[i + 2] += k * (x0[i + 2] - x[i + 2]) - d * v[i + 2];
  }
}

void MassSpringModel::AddExternalForces(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<MassSpringState*>(base);
  const Eigen::Index n = rest_.cols();
  for (Eigen::Index i = 0; i < n; ++i) {
    state->forces.col(i) += mass_[static_cast<size_t>(i)] * inputs.gravity;
  }
  if (inputs.external_forces != nullptr) state->forces += *inputs.external_forces;
  for (const Attachment& a : inputs.attachments) {
    state->forces.col(a.node) += a.stiffness * (a.target - state->positions.col(a.node));
  }
}

void MassSpringModel::Advance(const StepInputs& inputs, TissueState* base) const {
  if (integrator_ == MassSpringIntegrator::kImplicitEuler) {
    AdvanceImplicit(inputs, base);
    return;
  }
  auto* state = static_cast<MassSpringState*>(base);
  // One pass: spring forces (seed 002 eq. 1–3) and, as soon as a node's force is complete,
  // symplectic Euler (seed 002 eq. 4–5) with gravity: v += dt (f/m + g), then x += dt v.
  // Massless nodes (inverse mass 0) do not move. state->pending is zero between steps: the
  // attachments and anchors go in first, each node's entry is reset once it is used.
  double* const pending = state->pending.data();
  AddAnchorForces(*state, pending);
  for (const Attachment& a : inputs.attachments) {
    const Eigen::Index i = a.node;
    const Vector3d pull = a.stiffness * (a.target - state->positions.col(i));
    pending[3 * i] += pull.x();
    pending[3 * i + 1] += pull.y();
    pending[3 * i + 2] += pull.z();
  }
  // SavesGoodStateItself: the state the step starts from becomes the last-good one by a swap of
  // buffers (no copy); the pass reads it and writes every node's new x and v into the others.
  SwapWithLastGood(state);
  SlicePass pass{};
  pass.x = LastGoodPositions(state);
  pass.v = LastGoodVelocities(state);
  pass.moved_x = state->positions.data();
  pass.moved_v = state->velocities.data();
  pass.num_nodes = static_cast<size_t>(rest_.cols());
  pass.column_start = slice_column_start_.data();
  pass.other3 = column_other3_.data();
  pass.rest = column_rest_.data();
  pass.lanes = column_lanes_.data();
  pass.live_lanes = state->column_lanes.data();
  SetSpringConstants(*state, material_kd_, column_pair_, &pass);
  pass.gathered_column = slice_gathered_column_.data();
  pass.incoming_start = slice_incoming_start_.data();
  pass.incoming_slot = incoming_slot_.data();
  pass.incoming_lanes = incoming_lanes_.data();
  pass.gathered_incoming = slice_gathered_incoming_.data();
  pass.ring = state->column_forces.data();
  pass.ring_mask = static_cast<size_t>(ring_columns_) - 1;
  SetWindow(*state, window_slices_, window_lead_, column_window_, &pass);
  pass.pending = anchor_nodes_.empty() && inputs.attachments.empty() ? nullptr : pending;
  pass.integrate = true;
  pass.external = inputs.external_forces != nullptr ? inputs.external_forces->data() : nullptr;
  pass.inverse_mass = inverse_mass_.data();
  pass.dt = inputs.dt;
  pass.gravity[0] = inputs.gravity.x();
  pass.gravity[1] = inputs.gravity.y();
  pass.gravity[2] = inputs.gravity.z();
  pass.component_limit = component_speed_limit();
  const StateCheck check = RunSlicePass(pass);
  ApplyFixedAndPrescribed(inputs, state);
  // ChecksStateItself: the pass checked every value it wrote, but fixed and prescribed nodes
  // have been given new ones since. When the pass found nothing, checking those nodes completes
  // the check of the final state; when it flagged something (a step about to be rejected, or
  // fast nodes to be measured exactly), Step's own pass over the final state decides, as for
  // any model.
  if (check.non_finite || check.maybe_too_fast) {
    CheckWholeState(state);
    return;
  }
  StateCheck moved;
  const auto check_node = [&](int32_t node) {
    for (Eigen::Index axis = 0; axis < 3; ++axis) {
      moved.Add(state->positions(axis, node), state->velocities(axis, node), pass.component_limit);
    }
  };
  for (const int32_t node : inputs.fixed_nodes) check_node(node);
  for (const int32_t node : inputs.prescribed_nodes) check_node(node);
  SetStateChecked(state, moved.non_finite, moved.maybe_too_fast);
}

Eigen::Matrix3d MassSpringModel::LocalStiffness(const TissueState& state, int32_t node) const {
  assert(node >= 0 && node < num_nodes());
  // -∂f_i/∂x_i of each incident spring: k [u uᵀ + (1 - l0/l)(I - u uᵀ)] (elastic part).
  const auto& ms = static_cast<const MassSpringState&>(state);
  Eigen::Matrix3d k_local = Eigen::Matrix3d::Zero();
  for (int32_t e = node_spring_start_[static_cast<size_t>(node)];
       e < node_spring_start_[static_cast<size_t>(node) + 1]; ++e) {
    const auto s = static_cast<size_t>(node_springs_[static_cast<size_t>(e)]);
    AddEdgeStiffness(state.positions.col(spring_j_[s]) - state.positions.col(spring_i_[s]),
                     rest_length_[s], ms.stiffness[s], &k_local);
  }
  if (anchor_stiffness_ > 0.0 && mass_[static_cast<size_t>(node)] > 0.0) {
    k_local += anchor_stiffness_ * Eigen::Matrix3d::Identity();
  }
  return k_local;
}

EnergyReport MassSpringModel::Energy(const TissueState& state,
                                     const Eigen::Vector3d& gravity) const {
  const auto& ms = static_cast<const MassSpringState&>(state);
  EnergyReport report;
  for (size_t s = 0; s < spring_i_.size(); ++s) {
    const double stretch =
        (state.positions.col(spring_j_[s]) - state.positions.col(spring_i_[s])).norm() -
        rest_length_[s];
    report.elastic += 0.5 * ms.stiffness[s] * stretch * stretch;
  }
  for (const int32_t node : anchor_nodes_) {  // seed 001: ½ k_s |x - x0|²
    report.elastic +=
        0.5 * anchor_stiffness_ * (state.positions.col(node) - rest_.col(node)).squaredNorm();
  }
  AddKineticAndGravity(mass_, state, gravity, &report);
  return report;
}

int32_t MassSpringModel::Cut(const SweptQuad& sweep, TissueState* base) const {
  auto* state = static_cast<MassSpringState*>(base);
  if (!sweep.AllFinite()) return 0;
  int32_t removed = 0;
  for (size_t s = 0; s < spring_i_.size(); ++s) {
    if (state->stiffness[s] == 0.0 && state->damping[s] == 0.0) continue;  // already cut
    if (SegmentCrossesSweep(state->positions.col(spring_i_[s]), state->positions.col(spring_j_[s]),
                            sweep)) {
      state->stiffness[s] = 0.0;
      state->damping[s] = 0.0;
      const auto slot = static_cast<size_t>(spring_slot_[s]);
      state->column_lanes[slot / 8] =
          static_cast<uint8_t>(state->column_lanes[slot / 8] & ~(1U << (slot % 8)));
      if (!state->column_material.empty()) {
        state->column_material[slot] = 0;  // the pair (0, 0)
      } else {
        state->column_stiffness_damping[2 * slot - slot % 8] = 0.0;
        state->column_stiffness_damping[2 * slot - slot % 8 + 8] = 0.0;
      }
      ++removed;
    }
  }
  return removed;
}

}  // namespace somasim::models
