#include "server/models/mass_spring_slice_pass.h"

#include <algorithm>
#include <cmath>

#include "server/models/cpu_features.h"

namespace somasim::models {
namespace {

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

// Tests switch the AVX-512 pass off to compare it with the scalar one
// (SetMassSpringAvx512ForTesting, declared where the tests use it).
bool g_use_avx512 = true;

}  // namespace

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

StateCheck RunSlicePass(const SlicePass& p) {
  if (g_use_avx512 && CpuHasAvx512()) return SlicePassAvx512(p);
  return SlicePassScalar(p);
}

void SetMassSpringAvx512ForTesting(bool enabled) { g_use_avx512 = enabled; }

}  // namespace somasim::models
