#include "server/models/position_based_model.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "server/models/particle_mesh.h"

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
  std::vector<double> lambda;        // XPBD multipliers [N s²], num_constraints
  double last_dt = 0.0;              // [s] of the last accepted step, 0 before any
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
  double good_last_dt_ = 0.0;
};

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("position-based: " + what);
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
  return model;
}

std::unique_ptr<PositionBasedModel> PositionBasedModel::FromSurface(
    const mesh::SurfaceMesh& surface, const PositionBasedParameters& parameters) {
  CheckParameters(parameters);
  const MeshEdges edges = SurfaceEdges(surface, parameters.thickness, "position-based");
  std::unique_ptr<PositionBasedModel> model(new PositionBasedModel());
  model->Build(surface.vertices, edges.edges, edges.edge_size, edges.node_size, parameters);
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
  set_speed_limit(p.speed_limit);
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
  state->attach_stiffness.assign(static_cast<size_t>(n), 0.0);
  state->attach_weighted_target = mesh::Points::Zero(3, n);
  state->attach_lambda = mesh::Points::Zero(3, n);
  state->attached_nodes.assign(static_cast<size_t>(n), 0);
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
  const Eigen::Index n = rest_.cols();
  mesh::Points& x = state->positions;
  std::vector<double>& w = state->inverse_mass;
  state->start = x;
  std::copy(inverse_mass_.begin(), inverse_mass_.end(), w.begin());

  // Prediction, seed 004 eq. 1: x' = 2x - x* + a Δt² = x + Δt v + Δt² (g + f_ext/m), with
  // v = (x - x*)/Δt kept as the state's velocity. Massless nodes do not move.
  for (Eigen::Index i = 0; i < n; ++i) {
    const double wi = w[static_cast<size_t>(i)];
    if (!(wi > 0.0)) continue;
    Vector3d a = inputs.gravity;
    if (inputs.external_forces != nullptr) a += wi * inputs.external_forces->col(i);
    x.col(i) += dt * state->velocities.col(i) + dt2 * a;
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
  state->predicted = x;
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

  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  const double k_seed = parameters_.stiffness;
  const size_t m = edge_i_.size();
  std::fill(state->lambda.begin(), state->lambda.end(), 0.0);
  double* __restrict px = x.data();
  const double* __restrict pw = w.data();
  double* __restrict lambda = state->lambda.data();
  const double inverse_dt2 = 1.0 / dt2;

  int iteration = 0;
  double residual = 0.0;
  const double tolerance = parameters_.tolerance;
  while (iteration < parameters_.iterations) {
    ++iteration;
    residual = 0.0;
    // Distance constraints in a fixed order (sorted edges): Gauss–Seidel.
    for (size_t e = 0; e < m; ++e) {
      const auto i = 3 * static_cast<size_t>(edge_i_[e]);
      const auto j = 3 * static_cast<size_t>(edge_j_[e]);
      const double w1 = pw[i / 3];
      const double w2 = pw[j / 3];
      const double w_sum = w1 + w2;
      const double dx = px[j] - px[i];
      const double dy = px[j + 1] - px[i + 1];
      const double dz = px[j + 2] - px[i + 2];
      const double length = std::sqrt(dx * dx + dy * dy + dz * dz);
      const double a = rest_length_[e];
      const double c = length - a;  // C = |d| - a
      if (xpbd) {
        // XPBD (Macklin et al. 2016 eq. 18): Δλ = (-C - α̃ λ)/(w1 + w2 + α̃), α̃ = compliance/Δt²;
        // Δx1 = -w1 Δλ u, Δx2 = w2 Δλ u with u = d/|d| = ∇_{x2} C.
        const double alpha = edge_compliance_[e] * inverse_dt2;
        residual = std::max(residual, std::abs(c + alpha * lambda[e]) / a);
        if (!(w_sum > 0.0) || !(length > 0.0)) continue;
        const double dlambda = (-c - alpha * lambda[e]) / (w_sum + alpha);
        lambda[e] += dlambda;
        const double s = dlambda / length;
        px[i] -= w1 * s * dx;
        px[i + 1] -= w1 * s * dy;
        px[i + 2] -= w1 * s * dz;
        px[j] += w2 * s * dx;
        px[j + 1] += w2 * s * dy;
        px[j + 2] += w2 * s * dz;
      } else {
        // Seed 004 eq. 2–3: x1 += k w1/(w1+w2) (|d|-a)/|d| d, x2 -= k w2/(w1+w2) (|d|-a)/|d| d.
        residual = std::max(residual, std::abs(c) / a);
        if (!(w_sum > 0.0) || !(length > 0.0)) continue;
        const double s = k_seed * c / (length * w_sum);
        px[i] += w1 * s * dx;
        px[i + 1] += w1 * s * dy;
        px[i + 2] += w1 * s * dz;
        px[j] -= w2 * s * dx;
        px[j + 1] -= w2 * s * dy;
        px[j + 2] -= w2 * s * dz;
      }
    }
    // Attachments: the vector constraint C = x - t̄ with compliance 1/K, ∇C = I (XPBD).
    for (size_t k = 0; k < state->num_attached; ++k) {
      const int32_t node = state->attached_nodes[k];
      const double wi = pw[static_cast<size_t>(node)];
      if (!(wi > 0.0)) continue;
      const double stiffness = state->attach_stiffness[static_cast<size_t>(node)];
      const double alpha = inverse_dt2 / stiffness;
      const Vector3d c = x.col(node) - state->attach_weighted_target.col(node) / stiffness;
      const Vector3d dlambda = (-c - alpha * state->attach_lambda.col(node)) / (wi + alpha);
      state->attach_lambda.col(node) += dlambda;
      x.col(node) += wi * dlambda;
    }
    if (xpbd && parameters_.primal_correction) {
      // Primal correction: Gauss–Seidel moved each node along gradients taken at intermediate
      // positions, so x - x̃ drifts from M⁻¹ Σ ∇C(x) λ by O(|Δx|/l) (the g ≈ 0 assumption of
      // Macklin et al. §4). Re-anchoring x = x̃ + M⁻¹ (Σ_e ∇C_e(x) λ_e + λ_attach) makes a
      // converged step an exact backward-Euler step, whose rest state is the static solution
      // of springs 1/compliance, whatever Δt or the sweep count.
      state->impulse.setZero();
      for (size_t e = 0; e < m; ++e) {
        const Vector3d d = x.col(edge_j_[e]) - x.col(edge_i_[e]);
        const double length = d.norm();
        if (!(length > 0.0)) continue;
        const Vector3d push = (lambda[e] / length) * d;  // ∇_{x_j} C λ
        state->impulse.col(edge_j_[e]) += push;
        state->impulse.col(edge_i_[e]) -= push;
      }
      for (size_t k = 0; k < state->num_attached; ++k) {
        const int32_t node = state->attached_nodes[k];
        state->impulse.col(node) += state->attach_lambda.col(node);
      }
      for (Eigen::Index i = 0; i < n; ++i) {
        x.col(i) = state->predicted.col(i) + pw[static_cast<size_t>(i)] * state->impulse.col(i);
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
  double worst = 0.0;
  for (size_t e = 0; e < edge_i_.size(); ++e) {
    const double c = (state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e])).norm() -
                     rest_length_[e];
    const double h = xpbd ? c + edge_compliance_[e] * inverse_dt2 * state.lambda[e] : c;
    worst = std::max(worst, std::abs(h) / rest_length_[e]);
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
  for (Eigen::Index i = 0; i < rest_.cols(); ++i) {
    const double m = mass_[static_cast<size_t>(i)];
    report.kinetic += 0.5 * m * state.velocities.col(i).squaredNorm();
    report.gravity -= m * gravity.dot(state.positions.col(i));
    report.momentum += m * state.velocities.col(i);
  }
  return report;
}

}  // namespace somasim::models
