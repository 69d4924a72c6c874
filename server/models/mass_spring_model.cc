// Mass-spring model, seed 002 §2.1 eq. 1–5: construction (the material rule, the springs, their
// layouts), the state, the explicit step around its slice pass (mass_spring_slice_pass.h),
// forces, energy, stiffness and cutting.
#include "server/models/mass_spring_model.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/checks/finite.h"
#include "server/models/generalised_surface.h"
#include "server/models/mass_spring_slice_pass.h"
#include "server/models/mass_spring_state.h"
#include "server/models/particle_edges.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {
namespace {

using Eigen::Vector3d;

// The slice pass over `layout` with the state's spring constants (in whichever form it holds
// them), live lanes, ring and window (64-byte aligned). What it reads as x and v, writes, and
// integrates with are the caller's to set.
SlicePass PassOver(const MassSpringSliceLayout& layout, const MassSpringState& state,
                   size_t num_nodes) {
  SlicePass pass{};
  pass.num_nodes = num_nodes;
  pass.column_start = layout.slice_column_start.data();
  pass.other3 = layout.column_other3.data();
  pass.rest = layout.column_rest.data();
  pass.lanes = layout.column_lanes.data();
  pass.live_lanes = state.column_lanes.data();
  if (!state.column_material.empty()) {
    pass.material = state.column_material.data();
    pass.material_kd = layout.material_kd.data();
    pass.column_pair = layout.column_pair.data();
  } else {
    pass.stiffness_damping = state.column_stiffness_damping.data();
  }
  pass.gathered_column = layout.slice_gathered_column.data();
  pass.incoming_start = layout.slice_incoming_start.data();
  pass.incoming_slot = layout.incoming_slot.data();
  pass.incoming_lanes = layout.incoming_lanes.data();
  pass.gathered_incoming = layout.slice_gathered_incoming.data();
  pass.ring = state.column_forces.data();
  pass.ring_mask = static_cast<size_t>(layout.ring_columns) - 1;
  const size_t span = 8 * static_cast<size_t>(layout.window_slices);
  void* start = state.window.data();
  size_t space = state.window.size() * sizeof(double);
  pass.window = static_cast<double*>(std::align(64, 6 * (span + 8) * sizeof(double), start, space));
  pass.window_stride = span + 8;
  pass.window_mask = span - 1;
  pass.window_lead = static_cast<size_t>(layout.window_lead);
  pass.column_window = layout.column_window.data();
  return pass;
}

// Values (>= 0) that agree to kMergeTolerance relative become one: each group of values sorted
// within the tolerance of its least takes that least. Rounding makes the constants of congruent
// springs differ in their last bits (a structured grid's thousands of distinct (k, d) pairs are a
// few tens once merged: docs/benchmarks.md), which would keep the explicit pass from treating a
// column of them as one material; 1e-12 of a tissue's stiffness is far below anything measured
// of it.
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
  layout_ = BuildSliceLayout(n, spring_i_, spring_j_, rest_length_, stiffness_, damping_);
  if (integrator_ == MassSpringIntegrator::kImplicitEuler) BuildImplicitData();
}

std::unique_ptr<TissueState> MassSpringModel::MakeState() const {
  auto state = std::make_unique<MassSpringState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = rest_.cols();
  state->forces = mesh::Points::Zero(3, n);
  state->stiffness = stiffness_;
  state->damping = damping_;
  // The ring's columns and its zero column (never written).
  state->column_forces.assign(24 * (static_cast<size_t>(layout_.ring_columns) + 1), 0.0);
  // The pass's window: 6 rows of 8 window_slices + 8 values, 64-byte aligned (+ 8 to align).
  state->window.assign(6 * (8 * static_cast<size_t>(layout_.window_slices) + 8) + 8, 0.0);
  state->column_lanes = layout_.column_lanes;
  const std::vector<int32_t>& spring_slot = layout_.spring_slot;
  if (!layout_.spring_material.empty()) {
    state->column_material.assign(layout_.column_rest.size(), 0);
    for (size_t s = 0; s < spring_slot.size(); ++s) {
      state->column_material[static_cast<size_t>(spring_slot[s])] = layout_.spring_material[s];
    }
  } else {
    state->column_stiffness_damping.assign(2 * layout_.column_rest.size(), 0.0);
    for (size_t s = 0; s < spring_slot.size(); ++s) {
      const auto slot = static_cast<size_t>(spring_slot[s]);
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
  SlicePass pass = PassOver(layout_, ms, static_cast<size_t>(rest_.cols()));
  pass.x = state.positions.data();
  pass.v = state.velocities.data();
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
  SlicePass pass = PassOver(layout_, *state, static_cast<size_t>(rest_.cols()));
  pass.x = LastGoodPositions(state);
  pass.v = LastGoodVelocities(state);
  pass.moved_x = state->positions.data();
  pass.moved_v = state->velocities.data();
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
      const auto slot = static_cast<size_t>(layout_.spring_slot[s]);
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
