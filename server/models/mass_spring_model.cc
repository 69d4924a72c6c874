#include "server/models/mass_spring_model.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "server/models/mass_spring_state.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {
namespace {

using Eigen::Vector3d;

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
  set_speed_limit(p.speed_limit);
  integrator_ = p.integrator;
  cg_tolerance_ = p.cg_tolerance;
  cg_max_iterations_ = p.cg_max_iterations;
}

std::unique_ptr<TissueState> MassSpringModel::MakeState() const {
  auto state = std::make_unique<MassSpringState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = rest_.cols();
  state->forces = mesh::Points::Zero(3, n);
  if (integrator_ == MassSpringIntegrator::kImplicitEuler) {
    state->spring_direction = mesh::Points::Zero(3, num_springs());
    state->spring_transverse.assign(static_cast<size_t>(num_springs()), 0.0);
    state->constrained.assign(static_cast<size_t>(n), 0);
    for (mesh::Points* v : {&state->rhs, &state->dv, &state->residual, &state->preconditioned,
                            &state->search, &state->product}) {
      *v = mesh::Points::Zero(3, n);
    }
    state->inverse_diagonal = Eigen::Matrix<double, 9, Eigen::Dynamic>::Zero(9, n);
  }
  return state;
}

void MassSpringModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  // Seed 002 eq. 1–3: f_i += K (l - l0) u + D ((v_j - v_i)·u) u, u = (x_j - x_i) / l; f_j -= ….
  forces->resize(3, rest_.cols());  // a no-op (no allocation) when already sized
  forces->setZero();
  // Raw pointers hoisted out of the loop and marked non-aliasing, so that stores to f do not make
  // the compiler reload the member vectors' data pointers.
  const double* __restrict x = state.positions.data();
  const double* __restrict v = state.velocities.data();
  double* __restrict f = forces->data();
  const int32_t* __restrict spring_j = spring_j_.data();
  const double* __restrict rest_length = rest_length_.data();
  const double* __restrict stiffness = stiffness_.data();
  const double* __restrict damping = damping_.data();
  const int32_t* __restrict first_start = first_node_start_.data();
  const auto n = static_cast<size_t>(rest_.cols());
  // Springs are sorted by their first node i: for each i, its springs form one run, whose force
  // on i is summed in registers and stored once (a read-modify-write of f[i] per spring would
  // chain every spring behind the last).
  for (size_t node = 0; node < n; ++node) {
    const size_t i = 3 * node;
    const double xi = x[i], yi = x[i + 1], zi = x[i + 2];
    const double vxi = v[i], vyi = v[i + 1], vzi = v[i + 2];
    double fx = 0.0, fy = 0.0, fz = 0.0;
    const auto end = static_cast<size_t>(first_start[node + 1]);
    for (auto s = static_cast<size_t>(first_start[node]); s < end; ++s) {
      const size_t j = 3 * static_cast<size_t>(spring_j[s]);
      const double dx = x[j] - xi;
      const double dy = x[j + 1] - yi;
      const double dz = x[j + 2] - zi;
      const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
      const double inv = length > 0.0 ? 1.0 / length : 0.0;
      const double ux = dx * inv, uy = dy * inv, uz = dz * inv;
      const double closing = (v[j] - vxi) * ux + (v[j + 1] - vyi) * uy + (v[j + 2] - vzi) * uz;
      const double magnitude = stiffness[s] * (length - rest_length[s]) + damping[s] * closing;
      fx += magnitude * ux;
      fy += magnitude * uy;
      fz += magnitude * uz;
      f[j] -= magnitude * ux;
      f[j + 1] -= magnitude * uy;
      f[j + 2] -= magnitude * uz;
    }
    f[i] += fx;
    f[i + 1] += fy;
    f[i + 2] += fz;
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
  InternalForces(*state, &state->forces);
  if (inputs.external_forces != nullptr) state->forces += *inputs.external_forces;
  for (const Attachment& a : inputs.attachments) {
    state->forces.col(a.node) += a.stiffness * (a.target - state->positions.col(a.node));
  }
  // Symplectic Euler (seed 002 eq. 4–5) with gravity: v += dt (f/m + g), then x += dt v.
  // Massless nodes (inverse mass 0) do not move.
  const double dt = inputs.dt;
  const auto n = static_cast<size_t>(rest_.cols());
  const double* __restrict f = state->forces.data();
  const double* __restrict inverse_mass = inverse_mass_.data();
  double* __restrict x = state->positions.data();
  double* __restrict v = state->velocities.data();
  const double gx = inputs.gravity.x(), gy = inputs.gravity.y(), gz = inputs.gravity.z();
  for (size_t i = 0; i < n; ++i) {
    const double w = inverse_mass[i];
    const double moves = w > 0.0 ? 1.0 : 0.0;
    v[3 * i] += dt * (w * f[3 * i] + moves * gx);
    v[3 * i + 1] += dt * (w * f[3 * i + 1] + moves * gy);
    v[3 * i + 2] += dt * (w * f[3 * i + 2] + moves * gz);
    x[3 * i] += dt * v[3 * i];
    x[3 * i + 1] += dt * v[3 * i + 1];
    x[3 * i + 2] += dt * v[3 * i + 2];
  }
  ApplyFixedAndPrescribed(inputs, state);
}

Eigen::Matrix3d MassSpringModel::LocalStiffness(const TissueState& state, int32_t node) const {
  assert(node >= 0 && node < num_nodes());
  // -∂f_i/∂x_i of each incident spring: k [u uᵀ + (1 - l0/l)(I - u uᵀ)] (elastic part).
  Eigen::Matrix3d k_local = Eigen::Matrix3d::Zero();
  for (int32_t e = node_spring_start_[static_cast<size_t>(node)];
       e < node_spring_start_[static_cast<size_t>(node) + 1]; ++e) {
    const auto s = static_cast<size_t>(node_springs_[static_cast<size_t>(e)]);
    const Vector3d d = state.positions.col(spring_j_[s]) - state.positions.col(spring_i_[s]);
    const double length = d.norm();
    if (!(length > 0.0)) continue;
    const Vector3d u = d / length;
    const Eigen::Matrix3d uu = u * u.transpose();
    k_local += stiffness_[s] *
               (uu + (1.0 - rest_length_[s] / length) * (Eigen::Matrix3d::Identity() - uu));
  }
  return k_local;
}

EnergyReport MassSpringModel::Energy(const TissueState& state,
                                     const Eigen::Vector3d& gravity) const {
  EnergyReport report;
  for (size_t s = 0; s < spring_i_.size(); ++s) {
    const double stretch =
        (state.positions.col(spring_j_[s]) - state.positions.col(spring_i_[s])).norm() -
        rest_length_[s];
    report.elastic += 0.5 * stiffness_[s] * stretch * stretch;
  }
  for (Eigen::Index i = 0; i < rest_.cols(); ++i) {
    const double m = mass_[static_cast<size_t>(i)];
    report.kinetic += 0.5 * m * state.velocities.col(i).squaredNorm();
    report.gravity -= m * gravity.dot(state.positions.col(i));
    report.momentum += m * state.velocities.col(i);
  }
  return report;
}

}  // namespace somasim::models
