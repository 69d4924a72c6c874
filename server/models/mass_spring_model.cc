#include "server/models/mass_spring_model.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "server/models/generalised_surface.h"
#include "server/models/mass_spring_state.h"
#include "server/models/particle_mesh.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_MSS_AVX512 1
#endif

namespace somasim::models {
namespace {

using Eigen::Vector3d;

// The explicit force pass runs over the springs in blocks: a block's spring forces are computed
// (8 at a time where the CPU has AVX-512) into a buffer on the stack, then summed into the nodes.
constexpr size_t kBlock = 256;  // springs; the buffer (3 × kBlock doubles, 6 KiB) stays in L1

// What the spring-force kernels read. Springs are sorted by (i, j).
struct SpringArrays {
  const double* x;            // [m], positions, 3 × num_nodes
  const double* v;            // [m/s], velocities, 3 × num_nodes
  size_t num_values;          // 3 × num_nodes
  const int32_t* i;           // num_springs, first node
  const int32_t* j;           // num_springs, second node (> i)
  const double* rest_length;  // [m], num_springs
  const double* stiffness;    // [N/m]
  const double* damping;      // [N s/m]
};

// Seed 002 eq. 1–3, the force F_s [N] each spring s of [begin, end) puts on its first node i
// (its second node j gets -F_s): F = (K (l - l0) + D ((v_j - v_i)·u)) u, l = |x_j - x_i|,
// u = (x_j - x_i) / l (u = 0 for a spring of zero length). Written to fx/fy/fz[s - begin].
void SpringForcesScalar(const SpringArrays& a, size_t begin, size_t end, double* fx, double* fy,
                        double* fz) {
  for (size_t s = begin; s < end; ++s) {
    const size_t i = 3 * static_cast<size_t>(a.i[s]);
    const size_t j = 3 * static_cast<size_t>(a.j[s]);
    const double dx = a.x[j] - a.x[i];
    const double dy = a.x[j + 1] - a.x[i + 1];
    const double dz = a.x[j + 2] - a.x[i + 2];
    const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
    const double inv = length > 0.0 ? 1.0 / length : 0.0;
    const double ux = dx * inv, uy = dy * inv, uz = dz * inv;
    const double closing =
        (a.v[j] - a.v[i]) * ux + (a.v[j + 1] - a.v[i + 1]) * uy + (a.v[j + 2] - a.v[i + 2]) * uz;
    const double magnitude = a.stiffness[s] * (length - a.rest_length[s]) + a.damping[s] * closing;
    fx[s - begin] = magnitude * ux;
    fy[s - begin] = magnitude * uy;
    fz[s - begin] = magnitude * uz;
  }
}

#ifdef SOMASIM_MSS_AVX512
// The 8 doubles base[index[k]] (the masked form: the unmasked one reads an uninitialised source).
__attribute__((target("avx512f"))) inline __m512d Gather(__m256i index, const double* base) {
  return _mm512_mask_i32gather_pd(_mm512_setzero_pd(), 0xFF, index, base, 8);
}

// SpringForcesScalar, 8 springs at a time (gathers of x and v, fused multiply-adds, 1/l by
// Newton's method instead of a square root and a division, which would bound the throughput),
// so results differ from it by rounding only (a few units in the last place of l and u).
__attribute__((target("avx512f,avx2,fma"))) void SpringForcesAvx512(const SpringArrays& a,
                                                                    size_t begin, size_t end,
                                                                    double* fx, double* fy,
                                                                    double* fz) {
  const __m512d tiny = _mm512_set1_pd(1e-200);  // [m²]
  const __m512d half = _mm512_set1_pd(0.5);
  const __m512d three_halves = _mm512_set1_pd(1.5);
  size_t s = begin;
  for (; s + 8 <= end; s += 8) {
    const __m256i j = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(a.j + s));
    const __m256i j3 = _mm256_add_epi32(j, _mm256_add_epi32(j, j));
    // The first nodes are sorted: when the 8 springs' first nodes lie within 5 nodes of the
    // first one, their x and v come from two 16-double loads and permutes instead of gathers.
    __m512d xi, yi, zi, vxi, vyi, vzi;
    const auto base = static_cast<size_t>(a.i[s]);
    if (a.i[s + 7] - a.i[s] < 5 && 3 * base + 16 <= a.num_values) {
      const __m256i i =
          _mm256_sub_epi32(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(a.i + s)),
                           _mm256_set1_epi32(static_cast<int32_t>(base)));
      const __m512i i3 =
          _mm512_maskz_cvtepi32_epi64(0xFF, _mm256_add_epi32(i, _mm256_add_epi32(i, i)));
      const __m512i i3y = _mm512_add_epi64(i3, _mm512_set1_epi64(1));
      const __m512i i3z = _mm512_add_epi64(i3, _mm512_set1_epi64(2));
      const double* xb = a.x + 3 * base;
      const double* vb = a.v + 3 * base;
      const __m512d x0 = _mm512_loadu_pd(xb), x1 = _mm512_loadu_pd(xb + 8);
      const __m512d v0 = _mm512_loadu_pd(vb), v1 = _mm512_loadu_pd(vb + 8);
      xi = _mm512_permutex2var_pd(x0, i3, x1);
      yi = _mm512_permutex2var_pd(x0, i3y, x1);
      zi = _mm512_permutex2var_pd(x0, i3z, x1);
      vxi = _mm512_permutex2var_pd(v0, i3, v1);
      vyi = _mm512_permutex2var_pd(v0, i3y, v1);
      vzi = _mm512_permutex2var_pd(v0, i3z, v1);
    } else {
      const __m256i i = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(a.i + s));
      const __m256i i3 = _mm256_add_epi32(i, _mm256_add_epi32(i, i));
      xi = Gather(i3, a.x);
      yi = Gather(i3, a.x + 1);
      zi = Gather(i3, a.x + 2);
      vxi = Gather(i3, a.v);
      vyi = Gather(i3, a.v + 1);
      vzi = Gather(i3, a.v + 2);
    }
    const __m512d dx = _mm512_sub_pd(Gather(j3, a.x), xi);
    const __m512d dy = _mm512_sub_pd(Gather(j3, a.x + 1), yi);
    const __m512d dz = _mm512_sub_pd(Gather(j3, a.x + 2), zi);
    const __m512d dvx = _mm512_sub_pd(Gather(j3, a.v), vxi);
    const __m512d dvy = _mm512_sub_pd(Gather(j3, a.v + 1), vyi);
    const __m512d dvz = _mm512_sub_pd(Gather(j3, a.v + 2), vzi);
    const __m512d l2 = _mm512_fmadd_pd(dz, dz, _mm512_fmadd_pd(dy, dy, _mm512_mul_pd(dx, dx)));
    // 1/l from rsqrt14 and two Newton steps y ← y (3/2 - l²/2 y²) (14 → 28 → 56 bits), l = l² y;
    // both 0 for a spring shorter than 1e-100 m (as good as zero length: no direction).
    const __m512d h = _mm512_mul_pd(half, l2);
    __m512d inv = _mm512_maskz_rsqrt14_pd(_mm512_cmp_pd_mask(l2, tiny, _CMP_GT_OQ), l2);
    inv = _mm512_mul_pd(inv, _mm512_fnmadd_pd(h, _mm512_mul_pd(inv, inv), three_halves));
    inv = _mm512_mul_pd(inv, _mm512_fnmadd_pd(h, _mm512_mul_pd(inv, inv), three_halves));
    const __m512d length = _mm512_mul_pd(l2, inv);
    const __m512d ux = _mm512_mul_pd(dx, inv);
    const __m512d uy = _mm512_mul_pd(dy, inv);
    const __m512d uz = _mm512_mul_pd(dz, inv);
    const __m512d closing =
        _mm512_fmadd_pd(dvz, uz, _mm512_fmadd_pd(dvy, uy, _mm512_mul_pd(dvx, ux)));
    const __m512d magnitude = _mm512_fmadd_pd(
        _mm512_loadu_pd(a.stiffness + s), _mm512_sub_pd(length, _mm512_loadu_pd(a.rest_length + s)),
        _mm512_mul_pd(_mm512_loadu_pd(a.damping + s), closing));
    _mm512_storeu_pd(fx + (s - begin), _mm512_mul_pd(magnitude, ux));
    _mm512_storeu_pd(fy + (s - begin), _mm512_mul_pd(magnitude, uy));
    _mm512_storeu_pd(fz + (s - begin), _mm512_mul_pd(magnitude, uz));
  }
  if (s < end) {
    SpringForcesScalar(a, s, end, fx + (s - begin), fy + (s - begin), fz + (s - begin));
  }
}

bool CpuHasAvx512() {
  static const bool has = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx512f") != 0;
  }();
  return has;
}
#else
void SpringForcesAvx512(const SpringArrays& a, size_t begin, size_t end, double* fx, double* fy,
                        double* fz) {
  SpringForcesScalar(a, begin, end, fx, fy, fz);
}
bool CpuHasAvx512() { return false; }
#endif

// The spring pass shared by InternalForces and the explicit step. Adds each spring's force into
// `pending` (3 × num_nodes) at its second node j, sums the forces of each node's own run (the
// springs whose first node it is) in registers, and calls finish(node, fx, fy, fz) once per node
// in increasing order with that sum, as soon as the node's total is known: every spring touching
// a node has been added by then (springs with j = node come from runs of smaller nodes), and no
// later spring reads the node (later springs have both nodes above it), so `finish` may move it.
template <class Finish>
void SpringPass(const SpringArrays& a, const int32_t* first_start, size_t num_nodes,
                size_t num_springs, bool use_avx512, double* pending, Finish&& finish) {
  alignas(64) double buffer[3 * kBlock];
  double* const bx = buffer;
  double* const by = buffer + kBlock;
  double* const bz = buffer + 2 * kBlock;
  size_t node = 0;
  double fx = 0.0, fy = 0.0, fz = 0.0;
  for (size_t begin = 0; begin < num_springs; begin += kBlock) {
    const size_t end = std::min(begin + kBlock, num_springs);
    if (use_avx512) {
      SpringForcesAvx512(a, begin, end, bx, by, bz);
    } else {
      SpringForcesScalar(a, begin, end, bx, by, bz);
    }
    size_t s = begin;
    while (s < end) {
      const auto run_end = static_cast<size_t>(first_start[node + 1]);
      const size_t stop = std::min(run_end, end);
      for (; s < stop; ++s) {
        const size_t k = s - begin;
        const size_t j = 3 * static_cast<size_t>(a.j[s]);
        fx += bx[k];
        fy += by[k];
        fz += bz[k];
        pending[j] -= bx[k];
        pending[j + 1] -= by[k];
        pending[j + 2] -= bz[k];
      }
      if (s == run_end) {
        finish(node, fx, fy, fz);
        fx = fy = fz = 0.0;
        ++node;
      }
    }
  }
  for (; node < num_nodes; ++node) finish(node, 0.0, 0.0, 0.0);
}

void CheckParameters(const MassSpringParameters& p) {
  const auto positive_or_raw = [](double physical, double raw, const char* what) {
    if (raw > 0.0) return;
    if (!(physical > 0.0) || !std::isfinite(physical)) {
      throw std::invalid_argument(std::string("mass-spring: ") + what +
                                  " must be a finite value > 0");
    }
  };
  positive_or_raw(p.youngs_modulus, p.spring_stiffness, "youngs_modulus [Pa]");
  positive_or_raw(p.density, p.node_mass, "density [kg/m^3]");
  if (!(p.damping_ratio >= 0.0) || !std::isfinite(p.damping_ratio)) {
    throw std::invalid_argument("mass-spring: damping_ratio must be a finite value >= 0");
  }
  if (!(p.thickness > 0.0) || !std::isfinite(p.thickness)) {
    throw std::invalid_argument("mass-spring: thickness [m] must be a finite value > 0");
  }
  if (!(p.spring_stiffness >= 0.0) || !std::isfinite(p.spring_stiffness)) {
    throw std::invalid_argument("mass-spring: spring_stiffness [N/m] must be finite and >= 0");
  }
  if (!(p.node_mass >= 0.0) || !std::isfinite(p.node_mass)) {
    throw std::invalid_argument("mass-spring: node_mass [kg] must be finite and >= 0");
  }
  if (!(p.cg_tolerance > 0.0) || !(p.cg_max_iterations > 0)) {
    throw std::invalid_argument("mass-spring: cg_tolerance and cg_max_iterations must be > 0");
  }
  if (!(p.speed_limit > 0.0)) {
    throw std::invalid_argument("mass-spring: speed_limit [m/s] must be > 0");
  }
  if (!(p.anchor_stiffness >= 0.0) || !std::isfinite(p.anchor_stiffness)) {
    throw std::invalid_argument("mass-spring: anchor_stiffness [N/m] must be finite and >= 0");
  }
}

}  // namespace

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
  std::vector<std::array<int32_t, 2>> ordered;
  ordered.reserve(edges.size());
  for (size_t e = 0; e < edges.size(); ++e) {
    const auto [a, b] = edges[e];
    if (a < 0 || b < 0 || a >= rest.cols() || b >= rest.cols() || a == b) {
      throw std::invalid_argument("mass-spring: spring " + std::to_string(e) + " joins nodes " +
                                  std::to_string(a) + " and " + std::to_string(b) +
                                  ", not two distinct nodes of 0.." +
                                  std::to_string(rest.cols() - 1));
    }
    ordered.push_back({std::min(a, b), std::max(a, b)});
  }
  std::sort(ordered.begin(), ordered.end());  // the force loop runs over springs by first node
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
  mass_.resize(n);
  inverse_mass_.resize(n);
  for (size_t i = 0; i < n; ++i) {
    mass_[i] = p.node_mass > 0.0 ? p.node_mass : p.density * node_size[i];
    // A node no element touches has no mass: it cannot move (inverse mass 0).
    inverse_mass_[i] = mass_[i] > 0.0 ? 1.0 / mass_[i] : 0.0;
  }
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
    const double length = (rest.col(j) - rest.col(i)).norm();
    if (!(length > 0.0)) {
      throw std::invalid_argument("mass-spring: nodes " + std::to_string(i) + " and " +
                                  std::to_string(j) + " coincide (a zero-length spring)");
    }
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
  // Springs come sorted by (i, j): the springs whose first node is i are one run.
  first_node_start_.assign(n + 1, 0);
  for (size_t s = 0; s < m; ++s) ++first_node_start_[static_cast<size_t>(spring_i_[s]) + 1];
  for (size_t i = 0; i < n; ++i) first_node_start_[i + 1] += first_node_start_[i];
  node_spring_start_.assign(n + 1, 0);
  for (size_t s = 0; s < m; ++s) {
    ++node_spring_start_[static_cast<size_t>(spring_i_[s]) + 1];
    ++node_spring_start_[static_cast<size_t>(spring_j_[s]) + 1];
  }
  for (size_t i = 0; i < n; ++i) node_spring_start_[i + 1] += node_spring_start_[i];
  node_springs_.resize(2 * m);
  std::vector<int32_t> fill(node_spring_start_.begin(), node_spring_start_.end() - 1);
  for (size_t s = 0; s < m; ++s) {
    node_springs_[static_cast<size_t>(fill[static_cast<size_t>(spring_i_[s])]++)] =
        static_cast<int32_t>(s);
    node_springs_[static_cast<size_t>(fill[static_cast<size_t>(spring_j_[s])]++)] =
        static_cast<int32_t>(s);
  }
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
  if (integrator_ == MassSpringIntegrator::kImplicitEuler) BuildImplicitData();
}

std::unique_ptr<TissueState> MassSpringModel::MakeState() const {
  auto state = std::make_unique<MassSpringState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = rest_.cols();
  state->forces = mesh::Points::Zero(3, n);
  state->stiffness = stiffness_;
  state->damping = damping_;
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
  double* const f = forces->data();
  const auto& ms = static_cast<const MassSpringState&>(state);
  const SpringArrays springs{
      state.positions.data(), state.velocities.data(), static_cast<size_t>(state.positions.size()),
      spring_i_.data(),       spring_j_.data(),        rest_length_.data(),
      ms.stiffness.data(),    ms.damping.data()};
  SpringPass(springs, first_node_start_.data(), static_cast<size_t>(rest_.cols()), spring_j_.size(),
             CpuHasAvx512(), f, [f](size_t node, double fx, double fy, double fz) {
               f[3 * node] += fx;
               f[3 * node + 1] += fy;
               f[3 * node + 2] += fz;
             });
  AddAnchorForces(state, f);
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
  const double dt = inputs.dt;
  const double* const external =
      inputs.external_forces != nullptr ? inputs.external_forces->data() : nullptr;
  const double* const inverse_mass = inverse_mass_.data();
  double* const x = state->positions.data();
  double* const v = state->velocities.data();
  const double gx = inputs.gravity.x(), gy = inputs.gravity.y(), gz = inputs.gravity.z();
  // SavesGoodStateItself: each node's x and v go to the last-good buffers before they change.
  double* const good_x = LastGoodPositions(state);
  double* const good_v = LastGoodVelocities(state);
  const SpringArrays springs{x,
                             v,
                             static_cast<size_t>(state->positions.size()),
                             spring_i_.data(),
                             spring_j_.data(),
                             rest_length_.data(),
                             state->stiffness.data(),
                             state->damping.data()};
  SpringPass(springs, first_node_start_.data(), static_cast<size_t>(rest_.cols()), spring_j_.size(),
             CpuHasAvx512(), pending,
             [pending, external, inverse_mass, x, v, good_x, good_v, dt, gx, gy, gz](
                 size_t node, double fx, double fy, double fz) {
               const size_t i = 3 * node;
               fx += pending[i];
               fy += pending[i + 1];
               fz += pending[i + 2];
               pending[i] = pending[i + 1] = pending[i + 2] = 0.0;
               if (external != nullptr) {
                 fx += external[i];
                 fy += external[i + 1];
                 fz += external[i + 2];
               }
               const double w = inverse_mass[node];
               const double moves = w > 0.0 ? 1.0 : 0.0;
               const double vx = v[i], vy = v[i + 1], vz = v[i + 2];
               const double px = x[i], py = x[i + 1], pz = x[i + 2];
               good_v[i] = vx;
               good_v[i + 1] = vy;
               good_v[i + 2] = vz;
               good_x[i] = px;
               good_x[i + 1] = py;
               good_x[i + 2] = pz;
               const double nvx = vx + dt * (w * fx + moves * gx);
               const double nvy = vy + dt * (w * fy + moves * gy);
               const double nvz = vz + dt * (w * fz + moves * gz);
               v[i] = nvx;
               v[i + 1] = nvy;
               v[i + 2] = nvz;
               x[i] = px + dt * nvx;
               x[i + 1] = py + dt * nvy;
               x[i + 2] = pz + dt * nvz;
             });
  ApplyFixedAndPrescribed(inputs, state);
}

Eigen::Matrix3d MassSpringModel::LocalStiffness(const TissueState& state, int32_t node) const {
  assert(node >= 0 && node < num_nodes());
  // -∂f_i/∂x_i of each incident spring: k [u uᵀ + (1 - l0/l)(I - u uᵀ)] (elastic part).
  const auto& ms = static_cast<const MassSpringState&>(state);
  Eigen::Matrix3d k_local = Eigen::Matrix3d::Zero();
  for (int32_t e = node_spring_start_[static_cast<size_t>(node)];
       e < node_spring_start_[static_cast<size_t>(node) + 1]; ++e) {
    const auto s = static_cast<size_t>(node_springs_[static_cast<size_t>(e)]);
    const Vector3d d = state.positions.col(spring_j_[s]) - state.positions.col(spring_i_[s]);
    const double length = d.norm();
    if (!(length > 0.0)) continue;
    const Vector3d u = d / length;
    const Eigen::Matrix3d uu = u * u.transpose();
    k_local += ms.stiffness[s] *
               (uu + (1.0 - rest_length_[s] / length) * (Eigen::Matrix3d::Identity() - uu));
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
      ++removed;
    }
  }
  return removed;
}

}  // namespace somasim::models
