// The mass-spring slice pass with AVX-512 (see mass_spring_slice_pass.h): the 8 nodes of a slice
// in the 8 lanes of a register.
#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <utility>

#include "server/models/mass_spring_slice_pass.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_MSS_AVX512 1
#endif

namespace somasim::models {

#ifdef SOMASIM_MSS_AVX512
#define SOMASIM_MSS_TARGET __attribute__((target("avx512f,avx2,fma")))

namespace {

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

}  // namespace

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

}  // namespace somasim::models
