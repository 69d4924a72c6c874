#include "server/models/position_based_model.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/checks/finite.h"
#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "server/models/cpu_features.h"
#include "server/models/particle_edges.h"
#include "server/models/particle_mesh.h"
#include "server/models/position_based_state.h"

namespace somasim::models {
namespace {

using Eigen::Vector3d;

constexpr double kDefaultDt = 1e-3;  // [s] seed-mode k_eff before the first step

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
  checks::RequireFiniteNonNegative("position-based", "compliance [m/N]", p.compliance);
  if (p.mode == PositionBasedMode::kXpbd && !(p.compliance > 0.0) &&
      !checks::FinitePositive(p.youngs_modulus)) {
    Refuse("youngs_modulus [Pa] must be a finite value > 0 (or give compliance > 0)");
  }
  checks::RequireFiniteNonNegative("position-based", "node_mass [kg]", p.node_mass);
  if (!(p.node_mass > 0.0) && !checks::FinitePositive(p.density)) {
    Refuse("density [kg/m^3] must be a finite value > 0 (or give node_mass > 0)");
  }
  if (!checks::FinitePositive(p.thickness)) Refuse("thickness [m] must be a finite value > 0");
  checks::RequireFiniteNonNegative("position-based", "tolerance", p.tolerance);
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
  std::vector<std::array<int32_t, 2>> ordered =
      SortedEdges(edges, rest.cols(), "position-based", "constraint");
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
  LumpMasses(node_size, p.density, p.node_mass, &mass_, &inverse_mass_);
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
    const double length = EdgeRestLength(rest, i, j, "position-based", "constraint");
    rest_length_[e] = length;
    if (xpbd) {
      // Van Gelder 1998: k_e = E Σ size / |e|²; compliance = 1/k_e.
      const double k = p.compliance > 0.0 ? 1.0 / p.compliance
                                          : p.youngs_modulus * edge_size_sum[e] / (length * length);
      if (!checks::FinitePositive(k)) {
        Refuse("constraint " + std::to_string(e) + " (nodes " + std::to_string(i) + ", " +
               std::to_string(j) + ") gets no stiffness from the material");
      }
      edge_stiffness_[e] = k;
      edge_compliance_[e] = 1.0 / k;
    }
  }
  NodeEdgeLists(n, edge_i_, edge_j_, &node_edge_start_, &node_edges_);
  OrderNodes();
  ColourConstraints();
  simd_ = p.vectorised && CpuHasAvx512();
  set_speed_limit(p.speed_limit);
}

void PositionBasedModel::OrderNodes() {
  // Reverse Cuthill–McKee on the constraint graph (breadth first from a node of least degree,
  // neighbours by increasing degree, then reversed; component by component), so that the
  // records a sweep touches in turn lie close together in memory.
  const size_t n = mass_.size();
  const auto degree = [this](size_t i) { return node_edge_start_[i + 1] - node_edge_start_[i]; };
  const auto by_degree = [&degree](int32_t a, int32_t b) {
    const int32_t da = degree(static_cast<size_t>(a));
    const int32_t db = degree(static_cast<size_t>(b));
    return da != db ? da < db : a < b;
  };
  std::vector<int32_t> starts(n);
  for (size_t i = 0; i < n; ++i) starts[i] = static_cast<int32_t>(i);
  std::sort(starts.begin(), starts.end(), by_degree);
  std::vector<char> seen(n, 0);
  std::vector<int32_t> order;
  order.reserve(n);
  for (const int32_t start : starts) {
    if (seen[static_cast<size_t>(start)] != 0) continue;
    seen[static_cast<size_t>(start)] = 1;
    size_t head = order.size();
    order.push_back(start);
    while (head < order.size()) {
      const auto node = static_cast<size_t>(order[head++]);
      const size_t first = order.size();
      for (int32_t slot = node_edge_start_[node]; slot < node_edge_start_[node + 1]; ++slot) {
        const auto e = static_cast<size_t>(node_edges_[static_cast<size_t>(slot)]);
        const int32_t other = static_cast<size_t>(edge_i_[e]) == node ? edge_j_[e] : edge_i_[e];
        if (seen[static_cast<size_t>(other)] != 0) continue;
        seen[static_cast<size_t>(other)] = 1;
        order.push_back(other);
      }
      std::sort(order.begin() + static_cast<std::ptrdiff_t>(first), order.end(), by_degree);
    }
  }
  std::reverse(order.begin(), order.end());
  node_order_ = std::move(order);
  node_slot_.resize(n);
  for (size_t p = 0; p < n; ++p)
    node_slot_[static_cast<size_t>(node_order_[p])] = static_cast<int32_t>(p);
}

void PositionBasedModel::ColourConstraints() {
  // Greedy colouring, constraints taken by their internal node slots (lower, then upper): each
  // takes the lowest colour that neither of its nodes has yet. At most 2 · (max degree) - 1
  // colours. Within a colour the same order, so consecutive slots touch nearby records.
  const size_t n = mass_.size();
  const size_t m = edge_i_.size();
  int32_t max_degree = 0;
  for (size_t i = 0; i < n; ++i) {
    max_degree = std::max(max_degree, node_edge_start_[i + 1] - node_edge_start_[i]);
  }
  std::vector<std::array<int32_t, 3>> by_slot(m);  // lower slot, upper slot, constraint
  for (size_t e = 0; e < m; ++e) {
    const int32_t a = node_slot_[static_cast<size_t>(edge_i_[e])];
    const int32_t b = node_slot_[static_cast<size_t>(edge_j_[e])];
    by_slot[e] = {std::min(a, b), std::max(a, b), static_cast<int32_t>(e)};
  }
  std::sort(by_slot.begin(), by_slot.end());
  const size_t words = (2 * static_cast<size_t>(max_degree) + 63) / 64;
  std::vector<uint64_t> used(n * words, 0);  // bit c of node i: colour c touches i
  std::vector<int32_t> colour(m);            // of by_slot[k]
  int32_t num_colours = 0;
  for (size_t k = 0; k < m; ++k) {
    const auto e = static_cast<size_t>(by_slot[k][2]);
    uint64_t* ui = &used[static_cast<size_t>(edge_i_[e]) * words];
    uint64_t* uj = &used[static_cast<size_t>(edge_j_[e]) * words];
    size_t c = 0;
    for (size_t w = 0; w < words; ++w) {
      const uint64_t taken = ui[w] | uj[w];
      if (taken != ~uint64_t{0}) {
        c = 64 * w + static_cast<size_t>(__builtin_ctzll(~taken));
        break;
      }
    }
    colour[k] = static_cast<int32_t>(c);
    num_colours = std::max(num_colours, static_cast<int32_t>(c) + 1);
    ui[c / 64] |= uint64_t{1} << (c % 64);
    uj[c / 64] |= uint64_t{1} << (c % 64);
  }
  // Slots by colour, in by_slot order within a colour (a counting sort).
  colour_start_.assign(static_cast<size_t>(num_colours) + 1, 0);
  for (size_t k = 0; k < m; ++k) ++colour_start_[static_cast<size_t>(colour[k]) + 1];
  for (size_t c = 0; c < static_cast<size_t>(num_colours); ++c) {
    colour_start_[c + 1] += colour_start_[c];
  }
  std::vector<int32_t> fill(colour_start_.begin(), colour_start_.end() - 1);
  sweep_edge_.resize(m);
  for (size_t k = 0; k < m; ++k) {
    sweep_edge_[static_cast<size_t>(fill[static_cast<size_t>(colour[k])]++)] = by_slot[k][2];
  }
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  sweep_i4_.resize(m);
  sweep_j4_.resize(m);
  sweep_rest_.resize(m);
  sweep_inv_rest_.resize(m);
  sweep_compliance_.resize(m);
  for (size_t s = 0; s < m; ++s) {
    const auto e = static_cast<size_t>(sweep_edge_[s]);
    sweep_i4_[s] = 4 * node_slot_[static_cast<size_t>(edge_i_[e])];
    sweep_j4_[s] = 4 * node_slot_[static_cast<size_t>(edge_j_[e])];
    sweep_rest_[s] = rest_length_[e];
    sweep_inv_rest_[s] = 1.0 / rest_length_[e];
    sweep_compliance_[s] = xpbd ? edge_compliance_[e] : 0.0;
  }
}

std::unique_ptr<TissueState> PositionBasedModel::MakeState() const {
  auto state = std::make_unique<PositionBasedState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = rest_.cols();
  const auto nn = static_cast<size_t>(n);
  const auto m = static_cast<size_t>(num_constraints());
  state->node_buffer.assign(4 * nn + 8, 0.0);
  void* first = state->node_buffer.data();
  size_t space = state->node_buffer.size() * sizeof(double);
  std::align(64, 4 * nn * sizeof(double), first, space);
  state->node_offset = static_cast<size_t>(static_cast<double*>(first) - state->node_buffer.data());
  state->predicted.assign(4 * nn, 0.0);
  state->impulse.assign(4 * nn, 0.0);
  state->inverse_mass.assign(nn, 0.0);
  state->lambda.assign(m, 0.0);
  state->good_lambda_.assign(m, 0.0);
  state->sweep_alpha.assign(m, 0.0);
  state->sweep_gain.assign(m, 0.0);
  state->sweep_wi_gain.assign(m, 0.0);
  state->sweep_wj_gain.assign(m, 0.0);
  state->cut.assign(m, 0);
  state->prepared_w.assign(nn, 0.0);
  state->prepared_dt = 0.0;
  state->attach_stiffness.assign(nn, 0.0);
  state->attach_weighted_target = mesh::Points::Zero(3, n);
  state->attach_lambda = mesh::Points::Zero(3, n);
  state->attached_nodes.assign(nn, 0);
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

double PositionBasedModel::LastConstraintResidual(const TissueState& base) const {
  const auto& state = static_cast<const PositionBasedState&>(base);
  const bool xpbd = parameters_.mode == PositionBasedMode::kXpbd;
  const double inverse_dt2 = state.last_dt > 0.0 ? 1.0 / (state.last_dt * state.last_dt) : 0.0;
  double worst = 0.0;
  for (size_t s = 0; s < sweep_edge_.size(); ++s) {
    const auto e = static_cast<size_t>(sweep_edge_[s]);
    if (state.cut[e] != 0) continue;
    const double c =
        (state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e])).norm() - sweep_rest_[s];
    // λ (of the last accepted step) is in sweep order, like the sweep arrays.
    const double h = xpbd ? c + sweep_compliance_[s] * inverse_dt2 * state.good_lambda_[s] : c;
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
    if (state.cut[e] != 0) continue;
    AddEdgeStiffness(state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e]),
                     rest_length_[e], EffectiveStiffness(e, state.last_dt), &k_local);
  }
  if (volume_ != nullptr) k_local += volume_->LocalStiffness(state.positions, node);
  return k_local;
}

void PositionBasedModel::InternalForces(const TissueState& base, mesh::Points* forces) const {
  const auto& state = static_cast<const PositionBasedState&>(base);
  forces->resize(3, rest_.cols());  // a no-op (no allocation) when already sized
  forces->setZero();
  for (size_t e = 0; e < edge_i_.size(); ++e) {
    if (state.cut[e] != 0) continue;
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
    if (state.cut[e] != 0) continue;
    const double c = (state.positions.col(edge_j_[e]) - state.positions.col(edge_i_[e])).norm() -
                     rest_length_[e];
    report.elastic += 0.5 * EffectiveStiffness(e, state.last_dt) * c * c;
  }
  if (volume_ != nullptr) report.elastic += volume_->Energy(state.positions);
  AddKineticAndGravity(mass_, state, gravity, &report);
  return report;
}

int32_t PositionBasedModel::Cut(const SweptQuad& sweep, TissueState* base) const {
  auto* state = static_cast<PositionBasedState*>(base);
  if (!sweep.AllFinite()) return 0;
  int32_t removed = 0;
  for (size_t e = 0; e < edge_i_.size(); ++e) {
    if (state->cut[e] != 0) continue;
    if (SegmentCrossesSweep(state->positions.col(edge_i_[e]), state->positions.col(edge_j_[e]),
                            sweep)) {
      state->cut[e] = 1;
      ++removed;
    }
  }
  if (removed > 0) state->prepared_dt = 0.0;  // the sweep factors are recomputed next step
  return removed;
}

}  // namespace somasim::models
