// The sweep kernel of the position-based model: the projection of one colour's distance
// constraints onto the node records, scalar or with AVX-512 (position_based_sweep.cc). Internal to
// server/models.
#pragma once

#include <cstddef>
#include <cstdint>

namespace somasim::models {

// The arrays one sweep reads, in sweep order. Projecting slot e: d = x_j - x_i, l = |d|,
// t = l - a + α̃ λ, Δλ = -t · gain, λ += Δλ, x_i -= w_i Δλ d/l, x_j += w_j Δλ d/l. In XPBD mode
// (gain = 1/(w_i + w_j + α̃)) that is Macklin et al. 2016 eq. 18; in seed mode (α̃ = 0,
// gain = k/(w_i + w_j)) seed 004 eq. 2–3, λ then being unused. Positions and inverse masses come
// from the internal node records (x, y, z, w).
struct SweepArrays {
  const int32_t* i4;  // offset 4 p of node i's record
  const int32_t* j4;
  const double* rest;
  const double* inverse_rest;
  const double* alpha;
  const double* gain;
  const double* wi_gain;  // w_i gain: the vector sweep's
  const double* wj_gain;  // w_j gain
  double* lambda;
};

// Projects slots [begin, end) of one colour (no two of its constraints share a node) onto the
// node records x (4 × num_nodes); returns the largest relative residual |C + α̃ λ|/a seen before
// each projection when `residual`, else 0. `first`: the first sweep of a step, where every λ is
// 0 (so neither α̃ nor λ is read, and λ is written rather than updated: the step needs no zeroing
// pass over λ). `simd`: the AVX-512 kernel (the CPU must have AVX-512 F and VL), whose results
// differ from the scalar one's by rounding only.
double ProjectColour(const SweepArrays& arrays, size_t begin, size_t end, double* x, bool simd,
                     bool residual, bool first);

}  // namespace somasim::models
