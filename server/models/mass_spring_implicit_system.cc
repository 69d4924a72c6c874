// The linear system of the mass-spring implicit step, A Δv = b with A = M + dt C + dt² K: each
// spring linearised at the current state, the blocks gathered per node on the multicolour layout
// (scalar and AVX-512), then anchors, attachments, held nodes, the right-hand side and the
// inverse diagonal blocks.
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <span>

#include "server/models/mass_spring_implicit_cg.h"
#include "server/models/mass_spring_implicit_simd.h"
#include "server/models/mass_spring_model.h"
#include "server/models/mass_spring_state.h"

namespace somasim::models {

// The kernels of the system; a friend of MassSpringModel to read its spring arrays. Each spring s
// adds the block B_s = a_s I + w_s w_sᵀ of A (Baraff & Witkin 1998 eq. 18) on the diagonal blocks
// ii and jj and subtracts it on ij and ji, with a_s = dt² k_s c_s, w_s = √(dt D_s + dt² k_s
// (1 - c_s)) u and c_s = (1 - l0/l)₊ (the derivation: docs/models.md).
class MassSpringImplicitStep {
 public:
  // Per spring s (state->implicit_springs, records of kImplicitRecord = 8 doubles): w_s, a_s, h_s =
  // K_s (v_i - v_j), K_s = k (c I + (1 - c) u uᵀ) (the spring's part of K v: +h_s on i, -h_s on
  // j) and 0.
  static void LineariseScalar(const MassSpringModel& model, double dt, MassSpringState* state,
                              size_t begin) {
    const double* __restrict x = state->positions.data();
    const double* __restrict v = state->velocities.data();
    double* __restrict out = state->implicit_springs.data();
    const double dt2 = dt * dt;
    for (size_t s = begin; s < model.spring_i_.size(); ++s) {
      const size_t i = 3 * static_cast<size_t>(model.spring_i_[s]);
      const size_t j = 3 * static_cast<size_t>(model.spring_j_[s]);
      const double dx = x[j] - x[i], dy = x[j + 1] - x[i + 1], dz = x[j + 2] - x[i + 2];
      const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
      const double inv = length > 0.0 ? 1.0 / length : 0.0;
      const double ux = dx * inv, uy = dy * inv, uz = dz * inv;
      const double c = length > 0.0 ? std::max(0.0, 1.0 - model.rest_length_[s] * inv) : 0.0;
      const double k = state->stiffness[s];
      const double ex = v[i] - v[j], ey = v[i + 1] - v[j + 1], ez = v[i + 2] - v[j + 2];
      const double kc = k * c;
      const double kt = k * (1.0 - c) * (ux * ex + uy * ey + uz * ez);
      const double scale = std::sqrt(dt * state->damping[s] + dt2 * (k - kc));
      double* o = out + kImplicitRecord * s;
      o[0] = scale * ux;
      o[1] = scale * uy;
      o[2] = scale * uz;
      o[3] = dt2 * kc;
      o[4] = kc * ex + kt * ux;
      o[5] = kc * ey + kt * uy;
      o[6] = kc * ez + kt * uz;
    }
  }

  SOMASIM_MSI_TARGET static void LineariseAvx512(const MassSpringModel& model, double dt,
                                                 MassSpringState* state) {
    const double* x = state->positions.data();
    const double* v = state->velocities.data();
    double* out = state->implicit_springs.data();
    const __m512d vdt = _mm512_set1_pd(dt), vdt2 = _mm512_set1_pd(dt * dt);
    const __m512d zero = _mm512_setzero_pd(), one = _mm512_set1_pd(1.0);
    const size_t m = model.spring_i_.size();
    const size_t full = m / kImplicitLanes * kImplicitLanes;
    for (size_t s = 0; s < full; s += kImplicitLanes) {
      const int32_t* si = model.spring_i_.data() + s;
      const int32_t* sj = model.spring_j_.data() + s;
      __m512d xi[4], xj[4], vi[4], vj[4];
      LoadPoints(x, si, xi);
      LoadPoints(x, sj, xj);
      LoadPoints(v, si, vi);
      LoadPoints(v, sj, vj);
      const __m512d dx = _mm512_sub_pd(xj[0], xi[0]), dy = _mm512_sub_pd(xj[1], xi[1]),
                    dz = _mm512_sub_pd(xj[2], xi[2]);
      const __m512d length = _mm512_maskz_sqrt_pd(
          kAll, _mm512_fmadd_pd(dx, dx, _mm512_fmadd_pd(dy, dy, _mm512_mul_pd(dz, dz))));
      const __mmask8 positive = _mm512_cmp_pd_mask(length, zero, _CMP_GT_OQ);
      const __m512d inv = _mm512_maskz_div_pd(positive, one, length);
      const __m512d ux = _mm512_mul_pd(dx, inv), uy = _mm512_mul_pd(dy, inv),
                    uz = _mm512_mul_pd(dz, inv);
      const __m512d c = _mm512_maskz_max_pd(
          positive, zero,
          _mm512_fnmadd_pd(_mm512_loadu_pd(model.rest_length_.data() + s), inv, one));
      const __m512d k = _mm512_loadu_pd(state->stiffness.data() + s);
      const __m512d ex = _mm512_sub_pd(vi[0], vj[0]), ey = _mm512_sub_pd(vi[1], vj[1]),
                    ez = _mm512_sub_pd(vi[2], vj[2]);
      const __m512d kc = _mm512_mul_pd(k, c);
      const __m512d kt =
          _mm512_mul_pd(_mm512_mul_pd(k, _mm512_sub_pd(one, c)),
                        _mm512_fmadd_pd(ux, ex, _mm512_fmadd_pd(uy, ey, _mm512_mul_pd(uz, ez))));
      const __m512d scale = _mm512_maskz_sqrt_pd(
          kAll, _mm512_fmadd_pd(vdt, _mm512_loadu_pd(state->damping.data() + s),
                                _mm512_mul_pd(vdt2, _mm512_sub_pd(k, kc))));
      // Records of 8 per spring: w, a, then h = K_s (v_i - v_j) and 0.
      double* o = out + kImplicitRecord * s;
      StoreRecords(o, kImplicitRecord, _mm512_mul_pd(scale, ux), _mm512_mul_pd(scale, uy),
                   _mm512_mul_pd(scale, uz), _mm512_mul_pd(vdt2, kc));
      StoreRecords(o + 4, kImplicitRecord, _mm512_fmadd_pd(kc, ex, _mm512_mul_pd(kt, ux)),
                   _mm512_fmadd_pd(kc, ey, _mm512_mul_pd(kt, uy)),
                   _mm512_fmadd_pd(kc, ez, _mm512_mul_pd(kt, uz)), zero);
    }
    LineariseScalar(model, dt, state, full);
  }

  // Per group: the slot rows (w, a of each lane's springs), each lane's diagonal block
  // Σ B_s + m I (6 × P) and K v over its springs (3 × P, into implicit_dy).
  static void AssembleScalar(const MassSpringModel& model, MassSpringState* state) {
    const size_t p = model.implicit_padded_;
    const double* sp = state->implicit_springs.data();
    double* rows = state->implicit_rows.data();
    double* diag = state->implicit_diagonal.data();
    double* kv = state->implicit_dy.data();
    const size_t groups = p / kImplicitLanes;
    for (size_t g = 0; g < groups; ++g) {
      for (size_t lane = 0; lane < kImplicitLanes; ++lane) {
        double d[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        double h[3] = {0.0, 0.0, 0.0};
        for (auto row = static_cast<size_t>(model.implicit_row_start_[g]);
             row < static_cast<size_t>(model.implicit_row_start_[g + 1]); ++row) {
          const size_t slot = kImplicitLanes * row + lane;
          const auto s = static_cast<size_t>(model.implicit_spring_[slot]);
          const double* o = sp + kImplicitRecord * s;
          const double wx = o[0], wy = o[1], wz = o[2], a = o[3];
          double* r = rows + 4 * kImplicitLanes * row + lane;
          r[0] = wx;
          r[kImplicitLanes] = wy;
          r[2 * kImplicitLanes] = wz;
          r[3 * kImplicitLanes] = a;
          d[0] += a + wx * wx;
          d[1] += wx * wy;
          d[2] += wx * wz;
          d[3] += a + wy * wy;
          d[4] += wy * wz;
          d[5] += a + wz * wz;
          const double sign = model.implicit_sign_[slot];
          for (size_t k = 0; k < 3; ++k) h[k] += sign * o[4 + k];
        }
        const size_t i = kImplicitLanes * g + lane;
        const double mass = model.implicit_mass_[i];
        d[0] += mass;
        d[3] += mass;
        d[5] += mass;
        for (size_t e = 0; e < 6; ++e) diag[e * p + i] = d[e];
        for (size_t k = 0; k < 3; ++k) kv[k * p + i] = h[k];
      }
    }
  }

  SOMASIM_MSI_TARGET static void AssembleAvx512(const MassSpringModel& model,
                                                MassSpringState* state) {
    const size_t p = model.implicit_padded_;
    const double* sp = state->implicit_springs.data();
    double* rows = state->implicit_rows.data();
    double* diag = state->implicit_diagonal.data();
    double* kv = state->implicit_dy.data();
    const size_t groups = p / kImplicitLanes;
    for (size_t g = 0; g < groups; ++g) {
      __m512d d0 = _mm512_setzero_pd(), d1 = d0, d2 = d0, d3 = d0, d4 = d0, d5 = d0;
      __m512d hx = d0, hy = d0, hz = d0;
      for (auto row = static_cast<size_t>(model.implicit_row_start_[g]);
           row < static_cast<size_t>(model.implicit_row_start_[g + 1]); ++row) {
        const int32_t* s = model.implicit_spring_.data() + kImplicitLanes * row;
        __m512d w[4], h[4];
        LoadRecords<true>(sp, s, kImplicitRecord, w);
        LoadRecords<false>(sp + 4, s, kImplicitRecord, h);
        double* r = rows + 4 * kImplicitLanes * row;
        _mm512_storeu_pd(r, w[0]);
        _mm512_storeu_pd(r + kImplicitLanes, w[1]);
        _mm512_storeu_pd(r + 2 * kImplicitLanes, w[2]);
        _mm512_storeu_pd(r + 3 * kImplicitLanes, w[3]);
        d0 = _mm512_add_pd(d0, _mm512_fmadd_pd(w[0], w[0], w[3]));
        d1 = _mm512_fmadd_pd(w[0], w[1], d1);
        d2 = _mm512_fmadd_pd(w[0], w[2], d2);
        d3 = _mm512_add_pd(d3, _mm512_fmadd_pd(w[1], w[1], w[3]));
        d4 = _mm512_fmadd_pd(w[1], w[2], d4);
        d5 = _mm512_add_pd(d5, _mm512_fmadd_pd(w[2], w[2], w[3]));
        const __m512d sign = _mm512_loadu_pd(model.implicit_sign_.data() + kImplicitLanes * row);
        hx = _mm512_fmadd_pd(sign, h[0], hx);
        hy = _mm512_fmadd_pd(sign, h[1], hy);
        hz = _mm512_fmadd_pd(sign, h[2], hz);
      }
      const size_t i = kImplicitLanes * g;
      const __m512d mass = _mm512_loadu_pd(model.implicit_mass_.data() + i);
      _mm512_storeu_pd(diag + i, _mm512_add_pd(d0, mass));
      _mm512_storeu_pd(diag + p + i, d1);
      _mm512_storeu_pd(diag + 2 * p + i, d2);
      _mm512_storeu_pd(diag + 3 * p + i, _mm512_add_pd(d3, mass));
      _mm512_storeu_pd(diag + 4 * p + i, d4);
      _mm512_storeu_pd(diag + 5 * p + i, _mm512_add_pd(d5, mass));
      Store3(kv, p, i, {hx, hy, hz});
    }
  }

  // rhs = keep (dt f - dt² K v) per lane (f from state->forces, K v in implicit_dy), and the
  // inverse diagonal blocks: D_i⁻¹ on lanes with mass, the identity as a stand-in on massless
  // ones, zero on held lanes and padding (so that z, every search direction and Δv stay zero
  // there).
  static void Finalise(const MassSpringModel& model, double dt, MassSpringState* state) {
    const size_t p = model.implicit_padded_;
    const double* f = state->forces.data();
    const double* kv = state->implicit_dy.data();
    const double* d = state->implicit_diagonal.data();
    const double* keep = state->implicit_keep.data();
    double* rhs = state->implicit_rhs.data();
    double* inv = state->implicit_inverse.data();
    const double dt2 = dt * dt;
    for (size_t i = 0; i < p; ++i) {
      const int32_t node = model.implicit_node_[i];
      if (node < 0 || keep[i] == 0.0) {
        for (size_t k = 0; k < 3; ++k) rhs[k * p + i] = 0.0;
        for (size_t e = 0; e < 6; ++e) inv[e * p + i] = 0.0;
        continue;
      }
      const auto n3 = 3 * static_cast<size_t>(node);
      for (size_t k = 0; k < 3; ++k) rhs[k * p + i] = dt * f[n3 + k] - dt2 * kv[k * p + i];
      if (!(model.implicit_mass_[i] > 0.0)) {
        const double identity[6] = {1.0, 0.0, 0.0, 1.0, 0.0, 0.0};
        for (size_t e = 0; e < 6; ++e) inv[e * p + i] = identity[e];
        continue;
      }
      const double xx = d[i], xy = d[p + i], xz = d[2 * p + i], yy = d[3 * p + i],
                   yz = d[4 * p + i], zz = d[5 * p + i];
      const double cxx = yy * zz - yz * yz, cxy = xz * yz - xy * zz, cxz = xy * yz - xz * yy;
      const double cyy = xx * zz - xz * xz, cyz = xy * xz - xx * yz, czz = xx * yy - xy * xy;
      const double r = 1.0 / (xx * cxx + xy * cxy + xz * cxz);
      const double cof[6] = {cxx, cxy, cxz, cyy, cyz, czz};
      for (size_t e = 0; e < 6; ++e) inv[e * p + i] = r * cof[e];
    }
  }
};

void MassSpringModel::BuildImplicitSystem(const StepInputs& inputs, bool avx512,
                                          MassSpringState* state) const {
  const double dt = inputs.dt;
  const double dt2 = dt * dt;
  const size_t p = implicit_padded_;
  // Linearise every spring at the current state, then gather each node's blocks.
  if (avx512) {
    MassSpringImplicitStep::LineariseAvx512(*this, dt, state);
    MassSpringImplicitStep::AssembleAvx512(*this, state);
  } else {
    MassSpringImplicitStep::LineariseScalar(*this, dt, state, 0);
    MassSpringImplicitStep::AssembleScalar(*this, state);
  }
  // Anchors (seed 001's generalised springs) and attachments: k I in K and dt² k + dt d on the
  // diagonal of A.
  double* diag = state->implicit_diagonal.data();
  double* kv = state->implicit_dy.data();
  const double* v = state->velocities.data();
  const auto add_diagonal = [&](int32_t node, double stiffness, double block) {
    const auto i = static_cast<size_t>(implicit_lane_[static_cast<size_t>(node)]);
    const auto n3 = 3 * static_cast<size_t>(node);
    for (size_t k = 0; k < 3; ++k) kv[k * p + i] += stiffness * v[n3 + k];
    diag[i] += block;
    diag[3 * p + i] += block;
    diag[5 * p + i] += block;
  };
  for (size_t a = 0; a < anchor_nodes_.size(); ++a) {
    add_diagonal(anchor_nodes_[a], anchor_stiffness_,
                 dt2 * anchor_stiffness_ + dt * anchor_damping_[a]);
  }
  for (const Attachment& a : inputs.attachments)
    add_diagonal(a.node, a.stiffness, dt2 * a.stiffness);
  std::copy(implicit_real_.begin(), implicit_real_.end(), state->implicit_keep.begin());
  for (const std::span<const int32_t> nodes : {inputs.fixed_nodes, inputs.prescribed_nodes}) {
    for (const int32_t node : nodes) {
      state->implicit_keep[static_cast<size_t>(implicit_lane_[static_cast<size_t>(node)])] = 0.0;
    }
  }
  MassSpringImplicitStep::Finalise(*this, dt, state);
}

}  // namespace somasim::models
