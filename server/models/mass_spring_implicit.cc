// Implicit Euler for the mass-spring model (MassSpringIntegrator::kImplicitEuler): linearised
// backward Euler (Baraff & Witkin 1998) solved by conjugate gradients, matrix-free over the
// springs, preconditioned by symmetric block Gauss-Seidel.
//
// Speed (issue 4, BM_MassSpringImplicit): each step first linearises every spring once, storing
// its 3×3 block of A = M + dt C + dt² K in factored form (see Linearise), so that a CG product is
// a tight loop over the springs without square roots; the preconditioner is one forward and one
// backward Gauss-Seidel sweep over the same springs (about 2.5× fewer iterations than block
// Jacobi on the built-in organs, for two more passes over the springs that cost less than the
// iterations they save); the backward sweep also yields A z, so that CG updates A p = A z + β A p
// instead of running a separate product pass per iteration (the backward sweep reads each
// node's springs twice while they are in L1); the vector updates are fused into passes over the
// nodes; and CG starts from the previous step's Δv (a warm start, kept only when it beats the zero
// guess).
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <span>

#include "server/models/mass_spring_model.h"
#include "server/models/mass_spring_state.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {

// The pieces of one implicit step; a friend of MassSpringModel to read its spring arrays.
//
// Each spring s (nodes i, j, unit direction u from i to j, length l) contributes the block
//   B_s = (dt D_s + dt² k_s) u uᵀ + dt² k_s c_s (I - u uᵀ),   c_s = (1 - l0/l)₊ ∈ [0, 1),
// to A = M + dt C + dt² K (Baraff & Witkin 1998 eq. 18, with the spring Jacobian of seed 002
// eq. 1–3 keeping only the non-negative transverse stiffness), added on the diagonal blocks ii
// and jj and subtracted on ij and ji. Written as B_s = a_s I + w_s w_sᵀ with
//   a_s = dt² k_s c_s,   w_s = √(dt D_s + dt² k_s (1 - c_s)) u
// (the root's argument is >= 0 because c_s < 1), B_s d costs 3 products, one dot and 3 FMAs.
class MassSpringImplicitStep {
 public:
  // a b + c (keeps the 3×3 products below readable).
  static double Madd(double a, double b, double c) { return a * b + c; }

  // Per spring: w_s into state->spring_direction and a_s into state->spring_transverse. Also
  // accumulates K v into state->product (for the right-hand side) and the upper triangle of each
  // node's diagonal block Σ_s B_s into rows 0..5 of state->inverse_diagonal (xx, xy, xz, yy, yz,
  // zz), both of which must be zero on entry.
  static void Linearise(const MassSpringModel& model, double dt, MassSpringState* state) {
    const double* __restrict x = state->positions.data();
    const double* __restrict v = state->velocities.data();
    double* __restrict w_out = state->spring_direction.data();
    double* __restrict a_out = state->spring_transverse.data();
    double* __restrict kv = state->product.data();
    double* __restrict diagonal = state->inverse_diagonal.data();
    const int32_t* __restrict spring_j = model.spring_j_.data();
    const double* __restrict rest_length = model.rest_length_.data();
    const double* __restrict stiffness = state->stiffness.data();
    const double* __restrict damping = state->damping.data();
    const int32_t* __restrict first_start = model.first_node_start_.data();
    const auto n = static_cast<size_t>(model.rest_.cols());
    const double dt2 = dt * dt;
    // Springs are sorted by their first node i: each node's run is summed in registers.
    for (size_t node = 0; node < n; ++node) {
      const size_t i = 3 * node;
      const double xi = x[i], yi = x[i + 1], zi = x[i + 2];
      const double vxi = v[i], vyi = v[i + 1], vzi = v[i + 2];
      double kx = 0.0, ky = 0.0, kz = 0.0;
      double bxx = 0.0, bxy = 0.0, bxz = 0.0, byy = 0.0, byz = 0.0, bzz = 0.0;
      const auto end = static_cast<size_t>(first_start[node + 1]);
      for (auto s = static_cast<size_t>(first_start[node]); s < end; ++s) {
        const auto node_j = static_cast<size_t>(spring_j[s]);
        const size_t j = 3 * node_j;
        const double dx = x[j] - xi, dy = x[j + 1] - yi, dz = x[j + 2] - zi;
        const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
        const double inv = length > 0.0 ? 1.0 / length : 0.0;
        const double ux = dx * inv, uy = dy * inv, uz = dz * inv;
        const double c = length > 0.0 ? std::max(0.0, 1.0 - rest_length[s] * inv) : 0.0;
        const double k = stiffness[s];
        // K v on i: K_s (v_i - v_j), K_s = k (c I + (1 - c) u uᵀ); minus that on j.
        const double ex = vxi - v[j], ey = vyi - v[j + 1], ez = vzi - v[j + 2];
        const double kc = k * c;
        const double kt = k * (1.0 - c) * (ux * ex + uy * ey + uz * ez);
        const double fx = kc * ex + kt * ux, fy = kc * ey + kt * uy, fz = kc * ez + kt * uz;
        kx += fx;
        ky += fy;
        kz += fz;
        kv[j] -= fx;
        kv[j + 1] -= fy;
        kv[j + 2] -= fz;
        // B_s = a I + w wᵀ.
        const double a = dt2 * kc;
        const double scale = std::sqrt(dt * damping[s] + dt2 * (k - kc));
        const double wx = scale * ux, wy = scale * uy, wz = scale * uz;
        w_out[3 * s] = wx;
        w_out[3 * s + 1] = wy;
        w_out[3 * s + 2] = wz;
        a_out[s] = a;
        const double b[6] = {a + wx * wx, wx * wy, wx * wz, a + wy * wy, wy * wz, a + wz * wz};
        double* __restrict dj = diagonal + 9 * node_j;
        for (int e = 0; e < 6; ++e) dj[e] += b[e];
        bxx += b[0];
        bxy += b[1];
        bxz += b[2];
        byy += b[3];
        byz += b[4];
        bzz += b[5];
      }
      kv[i] += kx;
      kv[i + 1] += ky;
      kv[i + 2] += kz;
      double* __restrict di = diagonal + 9 * node;
      di[0] += bxx;
      di[1] += bxy;
      di[2] += bxz;
      di[3] += byy;
      di[4] += byz;
      di[5] += bzz;
    }
  }

  // q += (stiffness_coeff k_s + damping_coeff d_i) p on every anchored node (seed 001's
  // generalised springs: their part of A p, or of K v); returns their part of p · q.
  static double AddAnchors(const MassSpringModel& model, double stiffness_coeff,
                           double damping_coeff, const double* p, double* q) {
    double pq = 0.0;
    for (size_t a = 0; a < model.anchor_nodes_.size(); ++a) {
      const auto i = 3 * static_cast<size_t>(model.anchor_nodes_[a]);
      const double k =
          stiffness_coeff * model.anchor_stiffness_ + damping_coeff * model.anchor_damping_[a];
      q[i] += k * p[i];
      q[i + 1] += k * p[i + 1];
      q[i + 2] += k * p[i + 2];
      pq += k * (p[i] * p[i] + p[i + 1] * p[i + 1] + p[i + 2] * p[i + 2]);
    }
    return pq;
  }

  // q = A p over the springs and masses (attachments and constraints are the caller's); returns
  // p · q. Nodes whose p is zero (the constrained ones) add nothing to the dot product.
  static double Multiply(const MassSpringModel& model, const MassSpringState& state,
                         const double* __restrict p, double* __restrict q) {
    const double* __restrict w = state.spring_direction.data();
    const double* __restrict a = state.spring_transverse.data();
    const double* __restrict mass = model.mass_.data();
    const int32_t* __restrict spring_j = model.spring_j_.data();
    const int32_t* __restrict first_start = model.first_node_start_.data();
    const auto n = static_cast<size_t>(model.rest_.cols());
    for (size_t node = 0; node < n; ++node) {
      const double m = mass[node];
      q[3 * node] = m * p[3 * node];
      q[3 * node + 1] = m * p[3 * node + 1];
      q[3 * node + 2] = m * p[3 * node + 2];
    }
    double pq = 0.0;
    for (size_t node = 0; node < n; ++node) {
      const size_t i = 3 * node;
      const double pxi = p[i], pyi = p[i + 1], pzi = p[i + 2];
      double qx = 0.0, qy = 0.0, qz = 0.0;
      const auto end = static_cast<size_t>(first_start[node + 1]);
      for (auto s = static_cast<size_t>(first_start[node]); s < end; ++s) {
        const size_t j = 3 * static_cast<size_t>(spring_j[s]);
        const double dx = pxi - p[j], dy = pyi - p[j + 1], dz = pzi - p[j + 2];
        const double wx = w[3 * s], wy = w[3 * s + 1], wz = w[3 * s + 2];
        const double t = wx * dx + wy * dy + wz * dz;
        const double as = a[s];
        const double bx = as * dx + t * wx, by = as * dy + t * wy, bz = as * dz + t * wz;
        qx += bx;
        qy += by;
        qz += bz;
        q[j] -= bx;
        q[j + 1] -= by;
        q[j + 2] -= bz;
      }
      // Springs run from lower to higher node: every spring touching this node is done.
      const double qxi = q[i] + qx, qyi = q[i + 1] + qy, qzi = q[i + 2] + qz;
      q[i] = qxi;
      q[i + 1] = qyi;
      q[i + 2] = qzi;
      pq += pxi * qxi + pyi * qyi + pzi * qzi;
    }
    return pq;
  }

  // z = (D + Lᵀ)⁻¹ D (D + L)⁻¹ r: the symmetric block Gauss-Seidel preconditioner of A = L + D + Lᵀ
  // (D its diagonal blocks, given inverted, zero on constrained nodes; L its strictly lower blocks,
  // -B_s between the nodes of spring s). `scratch` (3 × num_nodes) is overwritten. Also writes
  // az = A z (zero on constrained nodes), which the backward sweep gets nearly for free: with
  // U = Lᵀ, (A z)_i = D_i z_i - (U z)_i - (L z)_i, where the sweep sums (U z)_i anyway and pushes
  // each finished z_i along its springs to the later nodes for (L z)_j; those nodes are done
  // already (the sweep runs backwards), so az_j is complete when the sweep ends. CG then updates
  // A p = A z + β A p_old without a separate product pass. Returns r · z.
  static double SymmetricGaussSeidel(const MassSpringModel& model, const MassSpringState& state,
                                     const double* __restrict r, double* __restrict scratch,
                                     double* __restrict z, double* __restrict az) {
    const double* __restrict diagonal = state.diagonal.data();
    const double* __restrict mass = model.mass_.data();
    const double* __restrict w = state.spring_direction.data();
    const double* __restrict a = state.spring_transverse.data();
    const double* __restrict inverse = state.inverse_diagonal.data();
    const int32_t* __restrict spring_j = model.spring_j_.data();
    const int32_t* __restrict first_start = model.first_node_start_.data();
    const auto n = static_cast<size_t>(model.rest_.cols());
    std::copy(r, r + 3 * n, scratch);
    // Forward: D_i y_i = r_i + Σ_{j<i} B_s y_j; then (D y)_i = r_i + Σ_{j<i} B_s y_j is kept in
    // scratch. Each y_i is pushed to the later nodes of its springs.
    for (size_t node = 0; node < n; ++node) {
      const size_t i = 3 * node;
      const double* b = inverse + 9 * node;
      const double sx = scratch[i], sy = scratch[i + 1], sz = scratch[i + 2];
      const double yx = Madd(b[0], sx, Madd(b[3], sy, b[6] * sz));
      const double yy = Madd(b[1], sx, Madd(b[4], sy, b[7] * sz));
      const double yz = Madd(b[2], sx, Madd(b[5], sy, b[8] * sz));
      const auto end = static_cast<size_t>(first_start[node + 1]);
      for (auto s = static_cast<size_t>(first_start[node]); s < end; ++s) {
        const size_t j = 3 * static_cast<size_t>(spring_j[s]);
        const double wx = w[3 * s], wy = w[3 * s + 1], wz = w[3 * s + 2];
        const double t = Madd(wx, yx, Madd(wy, yy, wz * yz));
        const double as = a[s];
        scratch[j] += Madd(as, yx, t * wx);
        scratch[j + 1] += Madd(as, yy, t * wy);
        scratch[j + 2] += Madd(as, yz, t * wz);
      }
    }
    // Backward: D_i z_i = (D y)_i + Σ_{j>i} B_s z_j.
    double rz = 0.0;
    for (size_t node = n; node-- > 0;) {
      const size_t i = 3 * node;
      const double dyx = scratch[i], dyy = scratch[i + 1], dyz = scratch[i + 2];
      double sx = dyx, sy = dyy, sz = dyz;
      const auto begin = static_cast<size_t>(first_start[node]);
      const auto end = static_cast<size_t>(first_start[node + 1]);
      for (size_t s = begin; s < end; ++s) {
        const size_t j = 3 * static_cast<size_t>(spring_j[s]);
        const double wx = w[3 * s], wy = w[3 * s + 1], wz = w[3 * s + 2];
        const double zx = z[j], zy = z[j + 1], zz = z[j + 2];
        const double t = Madd(wx, zx, Madd(wy, zy, wz * zz));
        const double as = a[s];
        sx += Madd(as, zx, t * wx);
        sy += Madd(as, zy, t * wy);
        sz += Madd(as, zz, t * wz);
      }
      const double* b = inverse + 9 * node;
      const double zx = Madd(b[0], sx, Madd(b[3], sy, b[6] * sz));
      const double zy = Madd(b[1], sx, Madd(b[4], sy, b[7] * sz));
      const double zz = Madd(b[2], sx, Madd(b[5], sy, b[8] * sz));
      z[i] = zx;
      z[i + 1] = zy;
      z[i + 2] = zz;
      rz = Madd(r[i], zx, Madd(r[i + 1], zy, Madd(r[i + 2], zz, rz)));
      // (A z)_i = D_i z_i - (U z)_i, with (U z)_i = s - (D y)_i, which is (D y)_i where D_i z_i =
      // s (up to rounding) on every node with mass; a massless node's inverse block is a stand-in
      // (the identity), so there D_i z_i is formed from D_i itself. (L z) follows from the earlier
      // nodes' pushes.
      if (mass[node] > 0.0) {
        az[i] = dyx;
        az[i + 1] = dyy;
        az[i + 2] = dyz;
      } else {
        const double* d = diagonal + 6 * node;
        az[i] = Madd(d[0], zx, Madd(d[1], zy, d[2] * zz)) - (sx - dyx);
        az[i + 1] = Madd(d[1], zx, Madd(d[3], zy, d[4] * zz)) - (sy - dyy);
        az[i + 2] = Madd(d[2], zx, Madd(d[4], zy, d[5] * zz)) - (sz - dyz);
      }
      for (size_t s = begin; s < end; ++s) {
        const size_t j = 3 * static_cast<size_t>(spring_j[s]);
        const double wx = w[3 * s], wy = w[3 * s + 1], wz = w[3 * s + 2];
        const double t = Madd(wx, zx, Madd(wy, zy, wz * zz));
        const double as = a[s];
        az[j] -= Madd(as, zx, t * wx);
        az[j + 1] -= Madd(as, zy, t * wy);
        az[j + 2] -= Madd(as, zz, t * wz);
      }
    }
    return rz;
  }
};

namespace {

// Zeroes the columns of `v` (3 × num_nodes) of the fixed and prescribed nodes.
void ZeroConstrained(const StepInputs& inputs, double* v) {
  for (const std::span<const int32_t> nodes : {inputs.fixed_nodes, inputs.prescribed_nodes}) {
    for (const int32_t node : nodes) {
      const auto i = 3 * static_cast<size_t>(node);
      v[i] = v[i + 1] = v[i + 2] = 0.0;
    }
  }
}

// q += stiffness_coeff k_a p on every attached node (the attachments' part of A p).
void AddAttachments(const StepInputs& inputs, double stiffness_coeff, const double* p, double* q) {
  for (const Attachment& attachment : inputs.attachments) {
    const auto i = 3 * static_cast<size_t>(attachment.node);
    const double k = stiffness_coeff * attachment.stiffness;
    q[i] += k * p[i];
    q[i + 1] += k * p[i + 1];
    q[i + 2] += k * p[i + 2];
  }
}

}  // namespace

void MassSpringModel::BuildImplicitData() {}

void MassSpringModel::SizeImplicitScratch(MassSpringState* state) const {
  const Eigen::Index n = rest_.cols();
  state->spring_direction = mesh::Points::Zero(3, num_springs());
  state->spring_transverse.assign(static_cast<size_t>(num_springs()), 0.0);
  state->constrained.assign(static_cast<size_t>(n), 0);
  for (mesh::Points* v : {&state->rhs, &state->dv, &state->residual, &state->preconditioned,
                          &state->search, &state->product, &state->preconditioned_product}) {
    *v = mesh::Points::Zero(3, n);
  }
  state->inverse_diagonal = Eigen::Matrix<double, 9, Eigen::Dynamic>::Zero(9, n);
  state->diagonal = Eigen::Matrix<double, 6, Eigen::Dynamic>::Zero(6, n);
}

void MassSpringModel::AdvanceImplicit(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<MassSpringState*>(base);
  const double dt = inputs.dt;
  const double dt2 = dt * dt;
  const auto n = static_cast<size_t>(rest_.cols());
  InternalForces(*state, &state->forces);
  AddExternalForces(inputs, state);

  // Linearise every spring at the current state: its block of A, K v and the diagonal blocks.
  state->product.setZero();
  state->inverse_diagonal.setZero();
  MassSpringImplicitStep::Linearise(*this, dt, state);
  AddAttachments(inputs, 1.0, state->velocities.data(), state->product.data());
  MassSpringImplicitStep::AddAnchors(*this, 1.0, 0.0, state->velocities.data(),
                                     state->product.data());
  for (size_t a = 0; a < anchor_nodes_.size(); ++a) {
    double* block = state->inverse_diagonal.col(anchor_nodes_[a]).data();
    const double k = dt2 * anchor_stiffness_ + dt * anchor_damping_[a];
    block[0] += k;
    block[3] += k;
    block[5] += k;
  }

  std::fill(state->constrained.begin(), state->constrained.end(), uint8_t{0});
  for (const std::span<const int32_t> nodes : {inputs.fixed_nodes, inputs.prescribed_nodes}) {
    for (const int32_t node : nodes) state->constrained[static_cast<size_t>(node)] = 1;
  }
  for (const Attachment& a : inputs.attachments) {
    double* block = state->inverse_diagonal.col(a.node).data();
    block[0] += dt2 * a.stiffness;
    block[3] += dt2 * a.stiffness;
    block[5] += dt2 * a.stiffness;
  }

  // rhs = dt f - dt² K v, and the inverse of each node's 3×3 diagonal block of A (M + Σ B_s) for
  // the preconditioner, zero on constrained nodes so that the preconditioned residual, and with
  // it every search direction and Δv, stays zero there.
  {
    const double* __restrict f = state->forces.data();
    const double* __restrict kv = state->product.data();
    double* __restrict rhs = state->rhs.data();
    for (size_t i = 0; i < n; ++i) {
      const bool held = state->constrained[i] != 0;
      for (size_t c = 3 * i; c < 3 * i + 3; ++c) rhs[c] = held ? 0.0 : dt * f[c] - dt2 * kv[c];
      double* block = state->inverse_diagonal.col(static_cast<Eigen::Index>(i)).data();
      if (!(mass_[i] > 0.0)) {  // SymmetricGaussSeidel reads D_i only on massless nodes
        double* d = state->diagonal.col(static_cast<Eigen::Index>(i)).data();
        for (int e = 0; e < 6; ++e) d[e] = held ? 0.0 : block[e];
      }
      Eigen::Map<Eigen::Matrix3d> inverse(block);
      if (held) {
        inverse.setZero();
      } else if (mass_[i] > 0.0) {
        const double m = mass_[i];
        Eigen::Matrix3d a;
        a << m + block[0], block[1], block[2],  //
            block[1], m + block[3], block[4],   //
            block[2], block[4], m + block[5];
        inverse = a.inverse();
      } else {
        inverse.setIdentity();
      }
    }
  }

  // Preconditioned conjugate gradients on (M + dt C + dt² K) Δv = rhs, constrained rows held at
  // 0, from the previous step's Δv when that is closer than 0 (it differs from this step's by
  // O(dt) in smooth motion; a rejected or non-finite guess fails the test and is dropped).
  double* __restrict dv = state->dv.data();
  double* __restrict r = state->residual.data();
  double* __restrict z = state->preconditioned.data();
  double* __restrict p = state->search.data();
  double* __restrict q = state->product.data();
  const double* rhs = state->rhs.data();
  const size_t size = 3 * n;
  double rhs_norm2 = 0.0;
  for (size_t c = 0; c < size; ++c) rhs_norm2 += rhs[c] * rhs[c];
  int iterations = 0;
  bool converged = !(rhs_norm2 > 0.0);
  if (converged) {
    std::fill(dv, dv + size, 0.0);
  } else {
    ZeroConstrained(inputs, dv);
    MassSpringImplicitStep::Multiply(*this, *state, dv, q);
    MassSpringImplicitStep::AddAnchors(*this, dt2, dt, dv, q);
    AddAttachments(inputs, dt2, dv, q);
    ZeroConstrained(inputs, q);
    double warm_norm2 = 0.0;
    for (size_t c = 0; c < size; ++c) {
      r[c] = rhs[c] - q[c];
      warm_norm2 += r[c] * r[c];
    }
    if (!(warm_norm2 < rhs_norm2)) {  // also false for a non-finite guess
      std::fill(dv, dv + size, 0.0);
      std::copy(rhs, rhs + size, r);
      warm_norm2 = rhs_norm2;
    }
    const double threshold2 = cg_tolerance_ * cg_tolerance_ * rhs_norm2;
    double* __restrict scratch = state->rhs.data();  // rhs is not read after this point
    double* __restrict az = state->preconditioned_product.data();
    const auto precondition = [&]() {  // z = P r and az = A z; returns r · z
      const double result =
          MassSpringImplicitStep::SymmetricGaussSeidel(*this, *state, r, scratch, z, az);
      ZeroConstrained(inputs, az);
      return result;
    };
    double rz = precondition();
    double curvature = 0.0;  // p · A p
    for (size_t c = 0; c < size; ++c) {
      p[c] = z[c];
      q[c] = az[c];
      curvature += p[c] * q[c];
    }
    double residual_norm2 = warm_norm2;
    converged = residual_norm2 <= threshold2;
    while (!converged && iterations < cg_max_iterations_) {
      if (!(curvature > 0.0)) break;
      const double alpha = rz / curvature;
      residual_norm2 = 0.0;
      for (size_t c = 0; c < size; ++c) {
        dv[c] += alpha * p[c];
        r[c] -= alpha * q[c];
        residual_norm2 += r[c] * r[c];
      }
      ++iterations;
      if (residual_norm2 <= threshold2) {
        converged = true;
        break;
      }
      const double rz_next = precondition();
      const double beta = rz_next / rz;
      // p = z + β p, and with it A p = A z + β A p (q holds A p; exact up to rounding).
      curvature = 0.0;
      for (size_t c = 0; c < size; ++c) {
        p[c] = z[c] + beta * p[c];
        q[c] = az[c] + beta * q[c];
        curvature += p[c] * q[c];
      }
      rz = rz_next;
    }
  }
  state->counters.solver_iterations += iterations;
  if (!converged) ++state->counters.solver_unconverged;

  state->velocities += state->dv;
  state->positions += dt * state->velocities;
  ApplyFixedAndPrescribed(inputs, state);
}

}  // namespace somasim::models
