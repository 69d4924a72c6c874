#include "server/models/position_based_model.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "server/models/particle_mesh.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_PBD_AVX512 1
#endif

namespace somasim::models {
namespace {

using Eigen::Vector3d;

constexpr double kDefaultDt = 1e-3;  // [s] seed-mode k_eff before the first step

// The state of a position-based model: the base state, the multipliers of the last step and the
// scratch of a step, all sized by MakeState so that stepping allocates nothing.
class PositionBasedState final : public TissueState {
 public:
  mesh::Points start;                // x at the start of the step [m], 3 × num_nodes
  mesh::Points predicted;            // x̃ after prediction and boundary conditions, 3 × num_nodes
  mesh::Points impulse;              // Σ ∇C λ per node [N s²] (XPBD), 3 × num_nodes
  std::vector<double> inverse_mass;  // w this step (0 for fixed, prescribed), num_nodes
  std::vector<double> lambda;        // multipliers [N s²], num_constraints, in sweep order
  // Per-constraint factors of the step, in sweep order (num_constraints), functions of Δt and w
  // only: recomputed when either changes (see PrepareSweep).
  std::vector<double> sweep_w1;     // w_i [1/kg]
  std::vector<double> sweep_w2;     // w_j [1/kg]
  std::vector<double> sweep_alpha;  // α̃ = compliance/Δt² [1/kg] (0 in seed mode)
  std::vector<double> sweep_gain;  // 1/(w_i + w_j + α̃) (seed: k/(w_i + w_j)); 0 if w_i + w_j = 0
  std::vector<double> prepared_w;  // the w the factors were computed with, num_nodes
  double prepared_dt = 0.0;        // and the Δt [s] (0: not yet)
  double last_dt = 0.0;            // [s] of the last accepted step, 0 before any
  // Attachments, merged per node: Σ_a k_a (t_a - x) = K (t̄ - x) with K = Σ k_a,
  // t̄ = Σ k_a t_a / K, projected as one compliant vector constraint (compliance 1/K).
  std::vector<double> attach_stiffness;  // K [N/m], num_nodes, 0 between steps
  mesh::Points attach_weighted_target;   // Σ k_a t_a [N], 3 × num_nodes
  mesh::Points attach_lambda;            // [N s²], 3 × num_nodes
  std::vector<int32_t> attached_nodes;   // the first num_attached are this step's, num_nodes
  size_t num_attached = 0;

 protected:
  void SaveGood() override {
    good_lambda_ = lambda;  // same size: no allocation
    good_last_dt_ = last_dt;
  }
  void RestoreGood() override {
    lambda = good_lambda_;
    last_dt = good_last_dt_;
  }

 private:
  friend class somasim::models::PositionBasedModel;
  std::vector<double> good_lambda_;
  mesh::Points volume_forces;  // [N], 3 × num_nodes when the volume reaction is on
  double good_last_dt_ = 0.0;
};

// The arrays one sweep reads, in sweep order. Projecting slot e: d = x_j - x_i, l = |d|,
// t = l - a + α̃ λ, Δλ = -t · gain, λ += Δλ, x_i -= w_i Δλ d/l, x_j += w_j Δλ d/l. In XPBD mode
// (gain = 1/(w_i + w_j + α̃)) that is Macklin et al. 2016 eq. 18; in seed mode (α̃ = 0,
// gain = k/(w_i + w_j)) seed 004 eq. 2–3, λ then being unused.
struct SweepArrays {
  const int32_t* i3;
  const int32_t* j3;
  const double* rest;
  const double* inverse_rest;
  const double* w1;
  const double* w2;
  const double* alpha;
  const double* gain;
  double* lambda;
};

// Projects slots [begin, end) in order onto x (3 × n, column-major); returns the largest
// relative residual |C + α̃ λ|/a seen before each projection (0 unless kResidual).
template <bool kResidual>
double ProjectScalar(const SweepArrays& s, size_t begin, size_t end, double* __restrict x) {
  double residual = 0.0;
  for (size_t e = begin; e < end; ++e) {
    double* __restrict xi = x + s.i3[e];
    double* __restrict xj = x + s.j3[e];
    const double dx = xj[0] - xi[0];
    const double dy = xj[1] - xi[1];
    const double dz = xj[2] - xi[2];
    const double l2 = dx * dx + dy * dy + dz * dz;
    const double length = std::sqrt(l2);
    const double t = (length - s.rest[e]) + s.alpha[e] * s.lambda[e];
    if constexpr (kResidual) residual = std::max(residual, std::abs(t) * s.inverse_rest[e]);
    if (!(l2 > 0.0)) continue;
    const double dlambda = -t * s.gain[e];
    s.lambda[e] += dlambda;
    const double f = dlambda / length;
    const double fi = s.w1[e] * f;
    const double fj = s.w2[e] * f;
    xi[0] -= fi * dx;
    xi[1] -= fi * dy;
    xi[2] -= fi * dz;
    xj[0] += fj * dx;
    xj[1] += fj * dy;
    xj[2] += fj * dz;
  }
  return residual;
}

#ifdef SOMASIM_PBD_AVX512
// ProjectScalar, 8 slots at a time (gathers, then scalar stores): valid only when no two slots
// of [begin, end) share a node (one colour), so that the order within a vector does not matter. 1/l
// comes from rsqrt14 and two Newton steps (relative error ~1e-16), so results differ from the
// scalar sweep by rounding.
template <bool kResidual>
__attribute__((target("avx512f"))) double ProjectAvx512(const SweepArrays& s, size_t begin,
                                                        size_t end, double* x) {
  const __m512d zero = _mm512_setzero_pd();
  const __m512d three_halves = _mm512_set1_pd(1.5);
  const __m512d half = _mm512_set1_pd(0.5);
  const __m512i sign_mask = _mm512_set1_epi64(INT64_MAX);
  __m512d worst = zero;
  for (size_t e = begin; e < end; e += 8) {
    const size_t left = end - e;
    const auto lanes =
        static_cast<__mmask8>(left >= 8 ? 0xFFU : (1U << static_cast<unsigned>(left)) - 1U);
    __m256i i3;
    __m256i j3;
    if (left >= 8) {
      i3 = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(s.i3 + e));
      j3 = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(s.j3 + e));
    } else {  // the colour's last, partial vector: masked lanes gather from node 0, unused
      alignas(32) int32_t tail_i[8] = {};
      alignas(32) int32_t tail_j[8] = {};
      std::copy(s.i3 + e, s.i3 + end, tail_i);
      std::copy(s.j3 + e, s.j3 + end, tail_j);
      i3 = _mm256_load_si256(reinterpret_cast<const __m256i*>(tail_i));
      j3 = _mm256_load_si256(reinterpret_cast<const __m256i*>(tail_j));
    }
    const __m512d xi = _mm512_mask_i32gather_pd(zero, lanes, i3, x, 8);
    const __m512d yi = _mm512_mask_i32gather_pd(zero, lanes, i3, x + 1, 8);
    const __m512d zi = _mm512_mask_i32gather_pd(zero, lanes, i3, x + 2, 8);
    const __m512d xj = _mm512_mask_i32gather_pd(zero, lanes, j3, x, 8);
    const __m512d yj = _mm512_mask_i32gather_pd(zero, lanes, j3, x + 1, 8);
    const __m512d zj = _mm512_mask_i32gather_pd(zero, lanes, j3, x + 2, 8);
    const __m512d dx = _mm512_sub_pd(xj, xi);
    const __m512d dy = _mm512_sub_pd(yj, yi);
    const __m512d dz = _mm512_sub_pd(zj, zi);
    const __m512d l2 = _mm512_fmadd_pd(dz, dz, _mm512_fmadd_pd(dy, dy, _mm512_mul_pd(dx, dx)));
    const __mmask8 ok = _mm512_mask_cmp_pd_mask(lanes, l2, zero, _CMP_GT_OQ);
    // 1/l: y ← y (3/2 - l²/2 y²), twice.
    const __m512d h = _mm512_mul_pd(half, l2);
    __m512d y = _mm512_maskz_rsqrt14_pd(ok, l2);
    y = _mm512_mul_pd(y, _mm512_fnmadd_pd(h, _mm512_mul_pd(y, y), three_halves));
    y = _mm512_mul_pd(y, _mm512_fnmadd_pd(h, _mm512_mul_pd(y, y), three_halves));
    const __m512d length = _mm512_mul_pd(l2, y);  // 0 where l = 0
    const __m512d lambda = _mm512_maskz_loadu_pd(lanes, s.lambda + e);
    const __m512d t =
        _mm512_fmadd_pd(_mm512_maskz_loadu_pd(lanes, s.alpha + e), lambda,
                        _mm512_sub_pd(length, _mm512_maskz_loadu_pd(lanes, s.rest + e)));
    if constexpr (kResidual) {
      const __m512d relative =
          _mm512_mul_pd(_mm512_castsi512_pd(_mm512_and_si512(_mm512_castpd_si512(t), sign_mask)),
                        _mm512_maskz_loadu_pd(lanes, s.inverse_rest + e));
      worst = _mm512_mask_max_pd(worst, lanes, relative, worst);
    }
    const __m512d dlambda =
        _mm512_maskz_mul_pd(ok, _mm512_sub_pd(zero, t), _mm512_maskz_loadu_pd(lanes, s.gain + e));
    _mm512_mask_storeu_pd(s.lambda + e, ok, _mm512_add_pd(lambda, dlambda));
    const __m512d f = _mm512_mul_pd(dlambda, y);
    const __m512d fi = _mm512_mul_pd(_mm512_maskz_loadu_pd(lanes, s.w1 + e), f);
    const __m512d fj = _mm512_mul_pd(_mm512_maskz_loadu_pd(lanes, s.w2 + e), f);
    // Scalar stores from a buffer beat six scatters (no two lanes share a node; a lane whose
    // length is 0 writes back the values it read).
    alignas(64) double updated[6][8];
    _mm512_store_pd(updated[0], _mm512_fnmadd_pd(fi, dx, xi));
    _mm512_store_pd(updated[1], _mm512_fnmadd_pd(fi, dy, yi));
    _mm512_store_pd(updated[2], _mm512_fnmadd_pd(fi, dz, zi));
    _mm512_store_pd(updated[3], _mm512_fmadd_pd(fj, dx, xj));
    _mm512_store_pd(updated[4], _mm512_fmadd_pd(fj, dy, yj));
    _mm512_store_pd(updated[5], _mm512_fmadd_pd(fj, dz, zj));
    const size_t count = std::min<size_t>(left, 8);
    for (size_t k = 0; k < count; ++k) {
      double* xi_k = x + s.i3[e + k];
      double* xj_k = x + s.j3[e + k];
      xi_k[0] = updated[0][k];
      xi_k[1] = updated[1][k];
      xi_k[2] = updated[2][k];
      xj_k[0] = updated[3][k];
      xj_k[1] = updated[4][k];
      xj_k[2] = updated[5][k];
    }
  }
  alignas(64) double lane_worst[8];
  _mm512_store_pd(lane_worst, worst);
  return *std::max_element(lane_worst, lane_worst + 8);
}

bool CpuHasAvx512() {
  static const bool has = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx512f") != 0;
  }();
  return has;
}
#else
bool CpuHasAvx512() { return false; }
#endif

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("position-based: " + what);
}

bool VolumeOn(const SolidAngleVolumeParameters& v) {
  return v.gamma_plus != 0.0 || v.sigma_plus != 0.0 || v.gamma_minus != 0.0 || v.sigma_minus != 0.0;
}

void CheckParameters(const PositionBasedParameters& p) {
  if (p.mode != PositionBasedMode::kSeedStiffness && p.mode != PositionBasedMode::kXpbd) {
    Refuse("mode must be kSeedStiffness or kXpbd");
  }
  if (!(p.iterations >= 1)) Refuse("iterations must be >= 1");
  if (!(p.stiffness > 0.0 && p.stiffness <= 1.0)) Refuse("stiffness k must lie in (0, 1]");
  if (!(p.compliance >= 0.0) || !std::isfinite(p.compliance)) {
    Refuse("compliance [m/N] must be finite and >= 0");
  }
  if (p.mode == PositionBasedMode::kXpbd && !(p.compliance > 0.0) &&
      (!(p.youngs_modulus > 0.0) || !std::isfinite(p.youngs_modulus))) {
    Refuse("youngs_modulus [Pa] must be a finite value > 0 (or give compliance > 0)");
  }
  if (!(p.node_mass >= 0.0) || !std::isfinite(p.node_mass)) {
    Refuse("node_mass [kg] must be finite and >= 0");
  }
  if (!(p.node_mass > 0.0) && (!(p.density > 0.0) || !std::isfinite(p.density))) {
    Refuse("density [kg/m^3] must be a finite value > 0 (or give node_mass > 0)");
  }
  if (!(p.thickness > 0.0) || !std::isfinite(p.thickness)) {
    Refuse("thickness [m] must be a finite value > 0");
  }
  if (!(p.tolerance >= 0.0) || !std::isfinite(p.tolerance)) {
    Refuse("tolerance must be finite and >= 0");
  }
  if (!(p.speed_limit > 0.0)) Refuse("speed_limit [m/s] must be > 0");
}

}  // namespace

std::unique_ptr<PositionBasedModel> PositionBasedModel::FromTetMesh(
    const mesh::TetMesh& mesh, const PositionBasedParameters& parameters) {
  CheckParameters(parameters);
  const MeshEdges edges = TetMeshEdges(mesh, "position-based");
  std::unique_ptr<PositionBasedModel> model(new PositionBasedModel());
  model->Build(mesh.vertices, edges.edges, edges.edge_size, edges.node_size, parameters);
  if (VolumeOn(parameters.volume)) {
    model->volume_ = std::make_unique<SolidAngleVolumeTerm>(SolidAngleVolumeTerm::Build(
        mesh.vertices, mesh::ExtractBoundarySurface(mesh).triangles, parameters.volume));
  }
  return model;
}

std::unique_ptr<PositionBasedModel> PositionBasedModel::FromSurface(
    const mesh::SurfaceMesh& surface, const PositionBasedParameters& parameters) {
  CheckParameters(parameters);
  const MeshEdges edges = SurfaceEdges(surface, parameters.thickness, "position-based");
  std::unique_ptr<PositionBasedModel> model(new PositionBasedModel());
  model->Build(surface.vertices, edges.edges, edges.edge_size, edges.node_size, parameters);
  if (VolumeOn(parameters.volume)) {
    model->volume_ = std::make_unique<SolidAngleVolumeTerm>(
        SolidAngleVolumeTerm::Build(surface, parameters.volume));
  }
  return model;
}

std::unique_ptr<PositionBasedModel> PositionBasedModel::FromEdges(
    const mesh::Points& rest, const std::vector<std::array<int32_t, 2>>& edges,
    const PositionBasedParameters& parameters) {
  CheckParameters(parameters);
  CheckFinitePoints(rest, "position-based");
  if (!(parameters.node_mass > 0.0)) Refuse("constraints given as edges need node_mass > 0");
  if (parameters.mode == PositionBasedMode::kXpbd && !(parameters.compliance > 0.0)) {
    Refuse("XPBD constraints given as edges need compliance > 0");
  }
  if (edges.empty()) Refuse("no constraints");
  if (VolumeOn(parameters.volume)) {
    Refuse("the volume reaction needs a closed surface; constraints given as edges have none");
  }
  std::vector<std::array<int32_t, 2>> ordered;
  ordered.reserve(edges.size());
  for (size_t e = 0; e < edges.size(); ++e) {
    const auto [a, b] = edges[e];
    if (a < 0 || b < 0 || a >= rest.cols() || b >= rest.cols() || a == b) {
      Refuse("constraint " + std::to_string(e) + " joins nodes " + std::to_string(a) + " and " +
             std::to_string(b) + ", not two distinct nodes of 0.." +
             std::to_string(rest.cols() - 1));
    }
    ordered.push_back({std::min(a, b), std::max(a, b)});
  }
  std::sort(ordered.begin(), ordered.end());
  ordered.erase(std::unique(ordered.begin(), ordered.end()), ordered.end());
  std::unique_ptr<PositionBasedModel> model(new PositionBasedModel());
  model->Build(rest, ordered, std::vector<double>(ordered.size(), 0.0),
               std::vector<double>(static_cast<size_t>(rest.cols()), 0.0), parameters);
  return model;
}

void PositionBasedModel::Build(const mesh::Points& rest,
                               const std::vector<std::array<int32_t, 2>>& edges,
                               const std::vector<double>& edge_size_sum,
                               const std::vector<double>& node_size,
                               const PositionBasedParameters& p) {
  parameters_ = p;
  rest_ = rest;
  const auto n = static_cast<size_t>(rest.cols());
  mass_.resize(n);
  inverse_mass_.resize(n);
  for (size_t i = 0; i < n; ++i) {
    // Lumped masses ρ · size / corners, as in the mass-spring model.
    mass_[i] = p.node_mass > 0.0 ? p.node_mass : p.density * node_size[i];
    // A node no element touches has no mass: it cannot move (inverse mass 0).
    inverse_mass_[i] = mass_[i] > 0.0 ? 1.0 / mass_[i] : 0.0;
  }
  const size_t m = edges.size();
  edge_i_.resize(m);
  edge_j_.resize(m);
  rest_length_.resize(m);
  const bool xpbd = p.mode == PositionBasedMode::kXpbd;
  edge_stiffness_.assign(xpbd ? m : 0, 0.0);
  edge_compliance_.assign(xpbd ? m : 0, 0.0);
  for (size_t e = 0; e < m; ++e) {
    const auto [i, j] = edges[e];
    edge_i_[e] = i;
    edge_j_[e] = j;
    const double length = (rest.col(j) - rest.col(i)).norm();
    if (!(length > 0.0)) {
      Refuse("nodes " + std::to_string(i) + " and " + std::to_string(j) +
             " coincide (a zero-length constraint)");
    }
    rest_length_[e] = length;
    if (xpbd) {
      // Van Gelder 1998: k_e = E Σ size / |e|²; compliance = 1/k_e.
      const double k = p.compliance > 0.0 ? 1.0 / p.compliance
                                          : p.youngs_modulus * edge_size_sum[e] / (length * length);
      if (!(k > 0.0) || !std::isfinite(k)) {
        Refuse("constraint " + std::to_string(e) + " (nodes " + std::to_string(i) + ", " +
               std::to_string(j) + ") gets no stiffness from the material");
      }
      edge_stiffness_[e] = k;
      edge_compliance_[e] = 1.0 / k;
    }
  }
  node_edge_start_.assign(n + 1, 0);
  for (size_t e = 0; e < m; ++e) {
    ++node_edge_start_[static_cast<size_t>(edge_i_[e]) + 1];
    ++node_edge_start_[static_cast<size_t>(edge_j_[e]) + 1];
  }
  for (size_t i = 0; i < n; ++i) node_edge_start_[i + 1] += node_edge_start_[i];
  node_edges_.resize(2 * m);
  std::vector<int32_t> fill(node_edge_start_.begin(), node_edge_start_.end() - 1);
  for (size_t e = 0; e < m; ++e) {
    node_edges_[static_cast<size_t>(fill[static_cast<size_t>(edge_i_[e])]++)] =
        static_cast<int32_t>(e);
    node_edges_[static_cast<size_t>(fill[static_cast<size_t>(edge_j_[e])]++)] =
        static_cast<int32_t>(e);
  }
  ColourConstraints();
  simd_ = p.vectorised && CpuHasAvx512();
  set_speed_limit(p.speed_limit);
}

void PositionBasedModel::ColourConstraints() {
  // Greedy colouring in sorted order: each constraint takes the lowest colour that neither of
  // its nodes has yet. At most 2 · (max degree) - 1 colours.
  const size_t n = mass_.size();
  const size_t m = edge_i_.size();
  int32_t max_degree = 0;
  for (size_t i = 0; i < n; ++i) {
    max_degree = std::max(max_degree, node_edge_start_[i + 1] - node_edge_start_[i]);
  }
  const size_t words = (2 * static_cast<size_t>(max_degree) + 63) / 64;
  std::vector<uint64_t> used(n * words, 0);  // bit c of node i: colour c touches i
  std::vector<int32_t> colour(m);
  int32_t num_colours = 0;
  for (size_t e = 0; e < m; ++e) {
    const uint64_t* ui = &used[static_cast<size_t>(edge_i_[e]) * words];
    const uint64_t* uj = &used[static_cast<size_t>(edge_j_[e]) * words];
    size_t c = 0;
    for (size_t w = 0; w < words; ++w) {
      const uint64_t taken = ui[w] | uj[w];
      if (taken != ~uint64_t{0}) {
        c = 64 * w + static_cast<size_t>(__builtin_ctzll(~taken));
        break;
      }
    }
    colour[e] = static_cast<int32_t>(c);
    num_colours = std::max(num_colours, static_cast<int32_t>(c) + 1);
    used[static_cast<size_t>(edge_i_[e]) * words + c / 64] |= uint64_t{1} << (c % 64);
    used[static_cast<size_t>(edge_j_[e]) * words + c / 64] |= uint64_t{1} << (c % 64);
  }
  // Slots by colour, sorted order within a colour (a counting sort).
  colour_start_.assign(static_cast<size_t>(num_colours) + 1, 0);
  for (size_t e = 0; e < m; ++e) ++colour_start_[static_cast<size_t>(colour[e]) + 1];
  for (size_t c = 0; c < static_cast<size_t>(num_colours); ++c) {
    colour_start_[c + 1] += colour_start_[c];
  }
  std::vector<int32_t> fill(colour_start_.begin(), colour_start_.end() - 1);
  sweep_edge_.resize(m);
  for (size_t e = 0; e < m; ++e) {
    sweep_edge_[static_cast<size_t>(fill[static_cast<size_t>(colour[e])]++)] =
        static_cast<int32_t>(e);
  }
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  sweep_i3_.resize(m);
  sweep_j3_.resize(m);
  sweep_rest_.resize(m);
  sweep_inv_rest_.resize(m);
  sweep_compliance_.resize(m);
  for (size_t s = 0; s < m; ++s) {
    const auto e = static_cast<size_t>(sweep_edge_[s]);
    sweep_i3_[s] = 3 * edge_i_[e];
    sweep_j3_[s] = 3 * edge_j_[e];
    sweep_rest_[s] = rest_length_[e];
    sweep_inv_rest_[s] = 1.0 / rest_length_[e];
    sweep_compliance_[s] = xpbd ? edge_compliance_[e] : 0.0;
  }
}

std::unique_ptr<TissueState> PositionBasedModel::MakeState() const {
  auto state = std::make_unique<PositionBasedState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = rest_.cols();
  const auto m = static_cast<size_t>(num_constraints());
  state->start = rest_;
  state->predicted = rest_;
  state->impulse = mesh::Points::Zero(3, n);
  state->inverse_mass = inverse_mass_;
  state->lambda.assign(m, 0.0);
  state->good_lambda_.assign(m, 0.0);
  state->sweep_w1.assign(m, 0.0);
  state->sweep_w2.assign(m, 0.0);
  state->sweep_alpha.assign(m, 0.0);
  state->sweep_gain.assign(m, 0.0);
  state->prepared_w.assign(static_cast<size_t>(n), 0.0);
  state->prepared_dt = 0.0;
  state->attach_stiffness.assign(static_cast<size_t>(n), 0.0);
  state->attach_weighted_target = mesh::Points::Zero(3, n);
  state->attach_lambda = mesh::Points::Zero(3, n);
  state->attached_nodes.assign(static_cast<size_t>(n), 0);
  if (volume_ != nullptr) state->volume_forces = mesh::Points::Zero(3, n);
  return state;
}

double PositionBasedModel::EffectiveStiffness(size_t e, double dt) const {
  if (parameters_.mode == PositionBasedMode::kXpbd) return edge_stiffness_[e];
  // Seed mode: `iterations` projections of one isolated constraint with factor k close the gap
  // by s = 1 - (1-k)^iterations; as a backward-Euler spring that is k_eff = s m_e / Δt².
  const double mi = mass_[static_cast<size_t>(edge_i_[e])];
  const double mj = mass_[static_cast<size_t>(edge_j_[e])];
  const double reduced = mi + mj > 0.0 ? mi * mj / (mi + mj) : 0.0;
  const double s = 1.0 - std::pow(1.0 - parameters_.stiffness, parameters_.iterations);
  const double h = dt > 0.0 ? dt : kDefaultDt;
  return s * reduced / (h * h);
}

void PositionBasedModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<PositionBasedState*>(base);
  const double dt = inputs.dt;
  const double dt2 = dt * dt;
  const auto n = static_cast<size_t>(rest_.cols());
  mesh::Points& x = state->positions;
  std::vector<double>& w = state->inverse_mass;
  state->start = x;
  std::copy(inverse_mass_.begin(), inverse_mass_.end(), w.begin());

  // Prediction, seed 004 eq. 1: x' = 2x - x* + a Δt² = x + Δt v + Δt² (g + f_ext/m), with
  // v = (x - x*)/Δt kept as the state's velocity. Massless nodes do not move. The volume
  // reaction (seed 004) joins f_ext, evaluated at the start of the step.
  const double* __restrict pf =
      inputs.external_forces != nullptr ? inputs.external_forces->data() : nullptr;
  if (volume_ != nullptr) {
    state->volume_forces.setZero();
    volume_->AddForces(x, &state->volume_forces);
    if (pf != nullptr) state->volume_forces += *inputs.external_forces;
    pf = state->volume_forces.data();
  }
  double* __restrict px = x.data();
  const double* __restrict pv = state->velocities.data();
  const Vector3d& g = inputs.gravity;
  for (size_t i = 0; i < n; ++i) {
    const double wi = w[i];
    if (!(wi > 0.0)) continue;
    for (size_t k = 0; k < 3; ++k) {
      const double a = pf != nullptr ? g[static_cast<Eigen::Index>(k)] + wi * pf[3 * i + k]
                                     : g[static_cast<Eigen::Index>(k)];
      px[3 * i + k] += dt * pv[3 * i + k] + dt2 * a;
    }
  }
  // Fixed nodes stay where they were; prescribed nodes go to their targets. Both get inverse
  // mass 0, so the projections never move them.
  for (const int32_t node : inputs.fixed_nodes) {
    x.col(node) = state->start.col(node);
    w[static_cast<size_t>(node)] = 0.0;
  }
  for (size_t k = 0; k < inputs.prescribed_nodes.size(); ++k) {
    const int32_t node = inputs.prescribed_nodes[k];
    x.col(node) = inputs.prescribed_positions->col(static_cast<Eigen::Index>(k));
    w[static_cast<size_t>(node)] = 0.0;
  }
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  const bool primal_correction = xpbd && parameters_.primal_correction;
  if (primal_correction) state->predicted = x;
  // Attachments, merged per node into one compliant constraint x - t̄ = 0 with compliance 1/K.
  state->num_attached = 0;
  for (const Attachment& a : inputs.attachments) {
    if (!(a.stiffness > 0.0)) continue;
    const auto node = static_cast<size_t>(a.node);
    if (state->attach_stiffness[node] == 0.0) {
      state->attached_nodes[state->num_attached++] = a.node;
      state->attach_weighted_target.col(a.node).setZero();
      state->attach_lambda.col(a.node).setZero();
    }
    state->attach_stiffness[node] += a.stiffness;
    state->attach_weighted_target.col(a.node) += a.stiffness * a.target;
  }

  // The per-constraint factors: they change only with Δt and the inverse masses (fixed and
  // prescribed nodes), so most steps reuse the last ones.
  const size_t m = sweep_edge_.size();
  const double inverse_dt2 = 1.0 / dt2;
  if (!(dt == state->prepared_dt) || !std::equal(w.begin(), w.end(), state->prepared_w.begin())) {
    const double k_seed = parameters_.stiffness;
    for (size_t s = 0; s < m; ++s) {
      const double w1 = w[static_cast<size_t>(sweep_i3_[s] / 3)];
      const double w2 = w[static_cast<size_t>(sweep_j3_[s] / 3)];
      const double alpha = sweep_compliance_[s] * inverse_dt2;  // α̃, 0 in seed mode
      const double w_sum = w1 + w2;
      state->sweep_w1[s] = w1;
      state->sweep_w2[s] = w2;
      state->sweep_alpha[s] = alpha;
      // A constraint between two immovable nodes is left alone (its λ stays 0).
      state->sweep_gain[s] = !(w_sum > 0.0) ? 0.0 : xpbd ? 1.0 / (w_sum + alpha) : k_seed / w_sum;
    }
    std::copy(w.begin(), w.end(), state->prepared_w.begin());
    state->prepared_dt = dt;
  }

  std::fill(state->lambda.begin(), state->lambda.end(), 0.0);
  const SweepArrays arrays{
      sweep_i3_.data(),          sweep_j3_.data(),         sweep_rest_.data(),
      sweep_inv_rest_.data(),    state->sweep_w1.data(),   state->sweep_w2.data(),
      state->sweep_alpha.data(), state->sweep_gain.data(), state->lambda.data()};
  const size_t num_colours = colour_start_.size() - 1;
  int iteration = 0;
  double residual = 0.0;  // computed only when a tolerance asks for it
  const double tolerance = parameters_.tolerance;
  while (iteration < parameters_.iterations) {
    ++iteration;
    residual = 0.0;
    // Distance constraints colour by colour (Gauss–Seidel; within a colour no two constraints
    // share a node, so their order there does not matter).
    for (size_t c = 0; c < num_colours; ++c) {
      const auto begin = static_cast<size_t>(colour_start_[c]);
      const auto end = static_cast<size_t>(colour_start_[c + 1]);
      double worst = 0.0;
#ifdef SOMASIM_PBD_AVX512
      if (simd_) {
        worst = tolerance > 0.0 ? ProjectAvx512<true>(arrays, begin, end, px)
                                : ProjectAvx512<false>(arrays, begin, end, px);
        residual = std::max(residual, worst);
        continue;
      }
#endif
      worst = tolerance > 0.0 ? ProjectScalar<true>(arrays, begin, end, px)
                              : ProjectScalar<false>(arrays, begin, end, px);
      residual = std::max(residual, worst);
    }
    // Attachments: the vector constraint C = x - t̄ with compliance 1/K, ∇C = I (XPBD).
    for (size_t k = 0; k < state->num_attached; ++k) {
      const int32_t node = state->attached_nodes[k];
      const double wi = w[static_cast<size_t>(node)];
      if (!(wi > 0.0)) continue;
      const double stiffness = state->attach_stiffness[static_cast<size_t>(node)];
      const double alpha = inverse_dt2 / stiffness;
      const Vector3d c = x.col(node) - state->attach_weighted_target.col(node) / stiffness;
      const Vector3d dlambda = (-c - alpha * state->attach_lambda.col(node)) / (wi + alpha);
      state->attach_lambda.col(node) += dlambda;
      x.col(node) += wi * dlambda;
    }
    // Further constraints of the whole body (e.g. a volume term) are projected here, once per
    // sweep, after the distance constraints and attachments.
    if (primal_correction) {
      // Primal correction: Gauss–Seidel moved each node along gradients taken at intermediate
      // positions, so x - x̃ drifts from M⁻¹ Σ ∇C(x) λ by O(|Δx|/l) (the g ≈ 0 assumption of
      // Macklin et al. §4). Re-anchoring x = x̃ + M⁻¹ (Σ_e ∇C_e(x) λ_e + λ_attach) makes a
      // converged step an exact backward-Euler step, whose rest state is the static solution
      // of springs 1/compliance, whatever Δt or the sweep count.
      state->impulse.setZero();
      double* __restrict impulse = state->impulse.data();
      const double* __restrict lambda = state->lambda.data();
      for (size_t s = 0; s < m; ++s) {
        const auto i = static_cast<size_t>(sweep_i3_[s]);
        const auto j = static_cast<size_t>(sweep_j3_[s]);
        const double dx = px[j] - px[i];
        const double dy = px[j + 1] - px[i + 1];
        const double dz = px[j + 2] - px[i + 2];
        const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
        if (!(length > 0.0)) continue;
        const double f = lambda[s] / length;  // ∇_{x_j} C λ = f d
        impulse[j] += f * dx;
        impulse[j + 1] += f * dy;
        impulse[j + 2] += f * dz;
        impulse[i] -= f * dx;
        impulse[i + 1] -= f * dy;
        impulse[i + 2] -= f * dz;
      }
      for (size_t k = 0; k < state->num_attached; ++k) {
        const int32_t node = state->attached_nodes[k];
        state->impulse.col(node) += state->attach_lambda.col(node);
      }
      const double* __restrict predicted = state->predicted.data();
      for (size_t i = 0; i < n; ++i) {
        for (size_t k = 0; k < 3; ++k) {
          px[3 * i + k] = predicted[3 * i + k] + w[i] * impulse[3 * i + k];
        }
      }
    }
    if (tolerance > 0.0 && residual < tolerance) break;
  }
  state->counters.solver_iterations += iteration;
  if (tolerance > 0.0 && !(residual < tolerance)) ++state->counters.solver_unconverged;
  for (size_t k = 0; k < state->num_attached; ++k) {
    state->attach_stiffness[static_cast<size_t>(state->attached_nodes[k])] = 0.0;
  }

  // Velocities consistent with the Verlet step: v = (x_new - x)/Δt (fixed nodes: 0).
  state->velocities = (x - state->start) * (1.0 / dt);
  state->last_dt = dt;
}

double PositionBasedModel::LastConstraintResidual(const TissueState& base) const {
  const auto& state = static_cast<const PositionBasedState&>(base);
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  const double inverse_dt2 = state.last_dt > 0.0 ? 1.0 / (state.last_dt * state.last_dt) : 0.0;
  const double* x = state.positions.data();
  double worst = 0.0;
  for (size_t s = 0; s < sweep_edge_.size(); ++s) {
    const auto i = static_cast<size_t>(sweep_i3_[s]);
    const auto j = static_cast<size_t>(sweep_j3_[s]);
    const double dx = x[j] - x[i];
    const double dy = x[j + 1] - x[i + 1];
    const double dz = x[j + 2] - x[i + 2];
    const double c = std::sqrt(dx * dx + dy * dy + dz * dz) - sweep_rest_[s];
    // λ is in sweep order, like the sweep arrays.
    const double h = xpbd ? c + sweep_compliance_[s] * inverse_dt2 * state.lambda[s] : c;
    worst = std::max(worst, std::abs(h) * sweep_inv_rest_[s]);
  }
  return worst;
}

Eigen::Matrix3d PositionBasedModel::LocalStiffness(const TissueState& base, int32_t node) const {
  assert(node >= 0 && node < num_nodes());
  const auto& state = static_cast<const PositionBasedState&>(base);
  // Hessian of ½ k_eff C² at node i: k_eff [u uᵀ + (1 - a/l)(I - u uᵀ)].
  Eigen::Matrix3d k_local = Eigen::Matrix3d::Zero();
  for (int32_t slot = node_edge_start_[static_cast<size_t>(node)];
       slot < node_edge_start_[static_cast<size_t>(node) + 1]; ++slot) {
    const auto e = static_cast<size_t>(node_edges_[static_cast<size_t>(slot)]);
    const Vector3d d = state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e]);
    const double length = d.norm();
    if (!(length > 0.0)) continue;
    const Vector3d u = d / length;
    const Eigen::Matrix3d uu = u * u.transpose();
    k_local += EffectiveStiffness(e, state.last_dt) *
               (uu + (1.0 - rest_length_[e] / length) * (Eigen::Matrix3d::Identity() - uu));
  }
  if (volume_ != nullptr) k_local += volume_->LocalStiffness(state.positions, node);
  return k_local;
}

void PositionBasedModel::InternalForces(const TissueState& base, mesh::Points* forces) const {
  const auto& state = static_cast<const PositionBasedState&>(base);
  forces->resize(3, rest_.cols());  // a no-op (no allocation) when already sized
  forces->setZero();
  for (size_t e = 0; e < edge_i_.size(); ++e) {
    const Vector3d d = state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e]);
    const double length = d.norm();
    if (!(length > 0.0)) continue;
    // f_i = k_eff C u, f_j = -k_eff C u (a stretched constraint pulls its ends together).
    const Vector3d f =
        (EffectiveStiffness(e, state.last_dt) * (length - rest_length_[e]) / length) * d;
    forces->col(edge_i_[e]) += f;
    forces->col(edge_j_[e]) -= f;
  }
  if (volume_ != nullptr) volume_->AddForces(state.positions, forces);
}

EnergyReport PositionBasedModel::Energy(const TissueState& base,
                                        const Eigen::Vector3d& gravity) const {
  const auto& state = static_cast<const PositionBasedState&>(base);
  EnergyReport report;
  for (size_t e = 0; e < edge_i_.size(); ++e) {
    const double c = (state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e])).norm() -
                     rest_length_[e];
    report.elastic += 0.5 * EffectiveStiffness(e, state.last_dt) * c * c;
  }
  if (volume_ != nullptr) report.elastic += volume_->Energy(state.positions);
  for (Eigen::Index i = 0; i < rest_.cols(); ++i) {
    const double m = mass_[static_cast<size_t>(i)];
    report.kinetic += 0.5 * m * state.velocities.col(i).squaredNorm();
    report.gravity -= m * gravity.dot(state.positions.col(i));
    report.momentum += m * state.velocities.col(i);
  }
  return report;
}

}  // namespace somasim::models
