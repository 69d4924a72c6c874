// Mass-spring model, seed 002 §2.1 eq. 1–5: construction (the material rule, the springs, their
// layouts), the state, the explicit step around its slice pass (mass_spring_slice_pass.h),
// forces, energy, stiffness and cutting.
#include "server/models/mass_spring_model.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cassert>
#include <cmath>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
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

// Points the pass at the state's spring constants in whichever form it holds them.
void SetSpringConstants(const MassSpringState& state, const std::vector<double>& material_kd,
                        const HugePageVector<uint16_t>& column_pair, SlicePass* pass) {
  if (!state.column_material.empty()) {
    pass->material = state.column_material.data();
    pass->material_kd = material_kd.data();
    pass->column_pair = column_pair.data();
  } else {
    pass->stiffness_damping = state.column_stiffness_damping.data();
  }
}

// Points the pass at the state's window (MassSpringModel::window_slices_), 64-byte aligned.
void SetWindow(const MassSpringState& state, int32_t window_slices, int32_t window_lead,
               const HugePageVector<int32_t>& column_window, SlicePass* pass) {
  const size_t span = 8 * static_cast<size_t>(window_slices);
  void* start = state.window.data();
  size_t space = state.window.size() * sizeof(double);
  pass->window =
      static_cast<double*>(std::align(64, 6 * (span + 8) * sizeof(double), start, space));
  pass->window_stride = span + 8;
  pass->window_mask = span - 1;
  pass->window_lead = static_cast<size_t>(window_lead);
  pass->column_window = column_window.data();
}

// Values (>= 0) that agree to kMergeTolerance relative become one: each group of values sorted
// within the tolerance of its least takes that least. Rounding makes the constants of congruent
// springs differ in their last bits (the 53³ grid: 2,103 distinct (k, d) pairs, 20 once merged),
// which would keep the explicit pass from treating a column of them as one material; 1e-12 of a
// tissue's stiffness is far below anything measured of it.
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
  BuildExplicitLayout();
  if (integrator_ == MassSpringIntegrator::kImplicitEuler) BuildImplicitData();
}

void MassSpringModel::BuildExplicitLayout() {
  const auto n = static_cast<size_t>(rest_.cols());
  const size_t m = spring_i_.size();
  const size_t num_slices = (n + 7) / 8;
  // Each spring's lane node: the end in the earlier slice, which lets the pass move a slice's
  // nodes at its end (every spring touching them is done, none still to come reads them).
  // Springs within one slice go to the end with fewer springs so far, to keep slices narrow.
  std::vector<int32_t> lane_node(m), per_node(n, 0);
  std::vector<size_t> inner;
  for (size_t s = 0; s < m; ++s) {
    const int32_t i = spring_i_[s], j = spring_j_[s];
    if (i / 8 == j / 8) {
      inner.push_back(s);
    } else {
      lane_node[s] = i;
      ++per_node[static_cast<size_t>(i)];
    }
  }
  for (const size_t s : inner) {
    const int32_t i = spring_i_[s], j = spring_j_[s];
    lane_node[s] = per_node[static_cast<size_t>(j)] < per_node[static_cast<size_t>(i)] ? j : i;
    ++per_node[static_cast<size_t>(lane_node[s])];
  }
  // The end of spring s that is not its lane node.
  const auto other_end = [&](size_t s) {
    return lane_node[s] == spring_i_[s] ? spring_j_[s] : spring_i_[s];
  };
  // Springs by lane node (CSR), in canonical order within a node.
  std::vector<size_t> start(n + 1, 0);
  for (size_t s = 0; s < m; ++s) ++start[static_cast<size_t>(lane_node[s]) + 1];
  for (size_t i = 0; i < n; ++i) start[i + 1] += start[i];
  std::vector<size_t> by_node(m);
  std::vector<size_t> fill(start.begin(), start.end() - 1);
  for (size_t s = 0; s < m; ++s) by_node[fill[static_cast<size_t>(lane_node[s])]++] = s;
  // Outgoing columns. A slice's springs with one offset Δ = other node − lane node (an edge kind
  // of a structured mesh) go into one run column when enough of its lanes have one: lane l's
  // other node is then 8 slice + l + Δ, and the pass loads the 8 other nodes' x and v as 24
  // consecutive values each instead of gathering them; lanes without such a spring hold none
  // (the pass stores F = 0 for them). The slice's other springs go into gathered columns,
  // column k holding each lane's k-th. How many lanes a run column needs is chosen per slice:
  // the least that costs the pass least (a gathered column costs kGatheredColumnCost run
  // columns).
  slice_column_start_.assign(1, 0);
  column_other3_.clear();
  column_rest_.clear();
  column_lanes_.clear();
  spring_slot_.assign(m, 0);
  slice_gathered_column_.clear();
  constexpr int64_t kNotInRun = std::numeric_limits<int64_t>::min();
  std::vector<int64_t> run_offset(m, kNotInRun);  // Δ of each spring in a run column
  // Each slice's run columns as (Δ, column), for the incoming columns below.
  std::vector<std::vector<std::pair<int64_t, int32_t>>> slice_runs(num_slices);
  const auto emit_column = [&](const std::array<size_t, 8>& spring,
                               const std::array<int32_t, 8>& other3, uint8_t lanes) {
    const auto index = static_cast<int32_t>(column_lanes_.size());
    for (size_t lane = 0; lane < 8; ++lane) {
      const size_t s = spring[lane];
      column_rest_.push_back(s < m ? rest_length_[s] : 0.0);
      if (s < m) spring_slot_[s] = 8 * index + static_cast<int32_t>(lane);
    }
    column_other3_.insert(column_other3_.end(), other3.begin(), other3.end());
    column_lanes_.push_back(lanes);
    return index;
  };
  struct Candidate {
    int64_t offset;  // Δ
    size_t lane;
    size_t spring;
  };
  struct Run {  // the candidates [begin, end) of one Δ
    size_t begin, end;
    uint8_t lanes;  // lanes with a spring of this Δ (their first one when a lane has two)
    int lane_count;
    bool loadable;  // the 8 other nodes 8 slice + Δ .. + 7 exist
  };
  std::vector<Candidate> candidates;
  std::vector<Run> runs;
  std::array<std::vector<size_t>, 8> rest_of_lane;
  for (size_t slice = 0; slice < num_slices; ++slice) {
    const size_t first = 8 * slice, last = std::min(n, first + 8);
    candidates.clear();
    for (size_t node = first; node < last; ++node) {
      for (size_t k = start[node]; k < start[node + 1]; ++k) {
        const size_t s = by_node[k];
        candidates.push_back({int64_t{other_end(s)} - static_cast<int64_t>(node), node - first, s});
      }
    }
    // By Δ; within one Δ by lane, and a lane's springs in canonical order.
    std::stable_sort(candidates.begin(), candidates.end(),
                     [](const Candidate& a, const Candidate& b) { return a.offset < b.offset; });
    runs.clear();
    for (size_t b = 0; b < candidates.size();) {
      size_t e = b;
      Run run{b, b, 0, 0, false};
      while (e < candidates.size() && candidates[e].offset == candidates[b].offset) {
        run.lanes = static_cast<uint8_t>(run.lanes | (1U << candidates[e].lane));
        ++e;
      }
      run.end = e;
      run.lane_count = std::popcount(run.lanes);
      const int64_t window = static_cast<int64_t>(first) + candidates[b].offset;
      run.loadable = window >= 0 && window + 8 <= static_cast<int64_t>(n);
      runs.push_back(run);
      b = e;
    }
    // The threshold: the number of run columns plus kGatheredColumnCost × the widest lane's
    // springs left for gathered columns, least over 1..8 lanes.
    int best_threshold = 9;
    double best_cost = std::numeric_limits<double>::infinity();
    for (int threshold = 1; threshold <= 8; ++threshold) {
      std::array<size_t, 8> left{};
      size_t run_columns = 0;
      for (const Run& run : runs) {
        const bool taken = run.loadable && run.lane_count >= threshold;
        run_columns += taken ? 1 : 0;
        for (size_t c = run.begin; c < run.end; ++c) ++left[candidates[c].lane];
        if (taken) {
          for (size_t lane = 0; lane < 8; ++lane) left[lane] -= (run.lanes >> lane) & 1U;
        }
      }
      const double cost =
          static_cast<double>(run_columns) +
          kGatheredColumnCost * static_cast<double>(*std::max_element(left.begin(), left.end()));
      if (cost < best_cost) {
        best_cost = cost;
        best_threshold = threshold;
      }
    }
    for (const Run& run : runs) {
      if (!run.loadable || run.lane_count < best_threshold) continue;
      std::array<size_t, 8> spring;
      spring.fill(m);
      std::array<int32_t, 8> other3{};
      const int64_t offset = candidates[run.begin].offset;
      for (size_t lane = 0; lane < 8; ++lane) {
        other3[lane] = static_cast<int32_t>(3 * (static_cast<int64_t>(first + lane) + offset));
      }
      for (size_t c = run.begin; c < run.end; ++c) {
        if (spring[candidates[c].lane] != m) continue;  // a lane's second spring of this Δ
        spring[candidates[c].lane] = candidates[c].spring;
        run_offset[candidates[c].spring] = offset;
      }
      slice_runs[slice].emplace_back(offset, emit_column(spring, other3, run.lanes));
    }
    slice_gathered_column_.push_back(static_cast<int32_t>(column_lanes_.size()));
    size_t width = 0;
    for (size_t node = first; node < last; ++node) {
      std::vector<size_t>& rest = rest_of_lane[node - first];
      rest.clear();
      for (size_t k = start[node]; k < start[node + 1]; ++k) {
        if (run_offset[by_node[k]] == kNotInRun) rest.push_back(by_node[k]);
      }
      width = std::max(width, rest.size());
    }
    for (size_t k = 0; k < width; ++k) {
      std::array<size_t, 8> spring;
      spring.fill(m);
      std::array<int32_t, 8> other3{};
      uint8_t lanes = 0;
      for (size_t lane = 0; lane < last - first; ++lane) {
        if (k >= rest_of_lane[lane].size()) continue;
        const size_t s = rest_of_lane[lane][k];
        spring[lane] = s;
        other3[lane] = 3 * other_end(s);
        lanes = static_cast<uint8_t>(lanes | (1U << lane));
      }
      emit_column(spring, other3, lanes);
    }
    slice_column_start_.push_back(static_cast<int32_t>(column_lanes_.size()));
  }
  // Incoming columns: a slice's nodes take -F of the springs ending on them. For each Δ of run
  // columns, one rotated column: lane l's spring of that Δ starts at node 8 slice + l - Δ =
  // 8 s_a + r + l, in lane r + l of the Δ run column of slice s_a (l < 8 - r), or lane
  // r + l - 8 of that of slice s_a + 1; the pass loads both columns' forces and rotates them.
  // Lanes without such a spring read a lane the run column left empty (F = 0 there), or the
  // ring's zero column where there is no run column (or one not yet computed: only a Δ < 0
  // within one slice reads beyond it, and only empty lanes). The other springs ending on a lane
  // are gathered from their ring places, column k holding each lane's k-th.
  std::vector<std::vector<size_t>> incoming(n);
  for (size_t s = 0; s < m; ++s) {
    incoming[static_cast<size_t>(other_end(s))].push_back(s);
  }
  struct IncomingColumn {
    // Rotated: {column of lanes r.., column of lanes ..r-1, r} (-1: the zero column); gathered:
    // each lane's 8 × column + lane.
    std::array<int32_t, 8> slot;
    uint8_t lanes;
    bool rotated;
  };
  std::vector<IncomingColumn> incoming_columns;
  std::vector<size_t> incoming_column_start(1, 0);
  std::vector<std::pair<int64_t, uint8_t>> rotated;  // Δ, lanes
  const auto run_column = [&](int64_t slice, int64_t offset) {
    if (slice < 0) return int32_t{-1};
    for (const auto& [o, column] : slice_runs[static_cast<size_t>(slice)]) {
      if (o == offset) return column;
    }
    return int32_t{-1};
  };
  for (size_t slice = 0; slice < num_slices; ++slice) {
    const size_t first = 8 * slice, last = std::min(n, first + 8);
    rotated.clear();
    size_t width = 0;
    for (size_t node = first; node < last; ++node) {
      std::vector<size_t>& rest = rest_of_lane[node - first];
      rest.clear();
      for (const size_t s : incoming[node]) {
        if (run_offset[s] == kNotInRun) {
          rest.push_back(s);
          continue;
        }
        auto it = std::find_if(rotated.begin(), rotated.end(),
                               [&](const auto& entry) { return entry.first == run_offset[s]; });
        if (it == rotated.end()) it = rotated.insert(rotated.end(), {run_offset[s], uint8_t{0}});
        it->second = static_cast<uint8_t>(it->second | (1U << (node - first)));
      }
      width = std::max(width, rest.size());
    }
    std::sort(rotated.begin(), rotated.end());
    for (const auto& [offset, lanes] : rotated) {
      const int64_t source = static_cast<int64_t>(first) - offset;  // lane 0's start node
      const int64_t source_slice = source >= 0 ? source / 8 : -((7 - source) / 8);
      const auto r = static_cast<int32_t>(source - 8 * source_slice);
      const int32_t a = source_slice <= static_cast<int64_t>(slice)
                            ? run_column(source_slice, offset)
                            : int32_t{-1};
      const int32_t b = r == 0 ? a
                        : source_slice + 1 <= static_cast<int64_t>(slice)
                            ? run_column(source_slice + 1, offset)
                            : int32_t{-1};
      incoming_columns.push_back({{a, b, r, 0, 0, 0, 0, 0}, lanes, true});
    }
    for (size_t k = 0; k < width; ++k) {
      IncomingColumn column{{}, 0, false};
      for (size_t lane = 0; lane < last - first; ++lane) {
        if (k >= rest_of_lane[lane].size()) continue;
        column.slot[lane] = spring_slot_[rest_of_lane[lane][k]];
        column.lanes = static_cast<uint8_t>(column.lanes | (1U << lane));
      }
      incoming_columns.push_back(column);
    }
    incoming_column_start.push_back(incoming_columns.size());
  }
  // The ring of column forces: every column an incoming column reads must not be overwritten
  // before the end of the reading slice's columns.
  size_t reach = 1;
  for (size_t slice = 0; slice < num_slices; ++slice) {
    const auto end = static_cast<int64_t>(slice_column_start_[slice + 1]);
    for (size_t c = incoming_column_start[slice]; c < incoming_column_start[slice + 1]; ++c) {
      const IncomingColumn& column = incoming_columns[c];
      for (size_t lane = 0; lane < 8; ++lane) {
        int64_t read = -1;
        if (column.rotated) {
          if (lane < 2) read = column.slot[lane];
        } else if (((column.lanes >> lane) & 1U) != 0) {
          read = column.slot[lane] / 8;
        }
        if (read >= 0) reach = std::max(reach, static_cast<size_t>(end - read));
      }
    }
  }
  size_t ring = 1;
  while (ring < reach) ring *= 2;
  ring_columns_ = static_cast<int32_t>(ring);
  const auto ring_place = [&](int32_t column) {
    return column < 0 ? 24 * ring_columns_ : 24 * (column % ring_columns_);
  };
  slice_incoming_start_.assign(1, 0);
  incoming_slot_.clear();
  incoming_lanes_.clear();
  slice_gathered_incoming_.clear();
  for (size_t slice = 0; slice < num_slices; ++slice) {
    slice_gathered_incoming_.push_back(static_cast<int32_t>(incoming_column_start[slice]));
    for (size_t c = incoming_column_start[slice]; c < incoming_column_start[slice + 1]; ++c) {
      IncomingColumn column = incoming_columns[c];
      if (column.rotated) {
        column.slot[0] = ring_place(column.slot[0]);
        column.slot[1] = ring_place(column.slot[1]);
        ++slice_gathered_incoming_.back();
      } else {
        for (size_t lane = 0; lane < 8; ++lane) {
          if (((column.lanes >> lane) & 1U) == 0) continue;
          column.slot[lane] = ring_place(column.slot[lane] / 8) + column.slot[lane] % 8;
        }
      }
      incoming_slot_.insert(incoming_slot_.end(), column.slot.begin(), column.slot.end());
      incoming_lanes_.push_back(column.lanes);
    }
    slice_incoming_start_.push_back(static_cast<int32_t>(incoming_lanes_.size()));
  }
  // The window of the AVX-512 pass (SlicePass::window): a run column of slice s reads the
  // nodes 8 s + Δ .. + 7, in slices s - 1 (Δ < 0) to s + (Δ + 7) / 8; the pass fills slice
  // s + lead at the start of slice s, so the window must hold lead + 2 slices.
  window_lead_ = 0;
  column_window_.assign(column_lanes_.size(), 0);
  for (size_t slice = 0; slice < num_slices; ++slice) {
    for (auto c = static_cast<size_t>(slice_column_start_[slice]);
         c < static_cast<size_t>(slice_gathered_column_[slice]); ++c) {
      const int64_t offset = column_other3_[8 * c] / 3 - static_cast<int64_t>(8 * slice);
      window_lead_ = std::max(window_lead_, static_cast<int32_t>((offset + 7) / 8));
    }
  }
  window_slices_ = 1;
  while (window_slices_ < window_lead_ + 2) window_slices_ *= 2;
  for (size_t c = 0; c < column_lanes_.size(); ++c) {
    column_window_[c] = (column_other3_[8 * c] / 3) & (8 * window_slices_ - 1);
  }
  // The distinct (k, d) pairs, exactly (after MergeNearlyEqual): when each is shared by 8 springs
  // or more on average (structured meshes: 20 pairs for the 1M springs of a 53³ grid) and the
  // table stays small, the state keeps a 2-byte index per spring instead of k and d (16 bytes).
  std::vector<std::array<double, 2>> pairs;
  pairs.reserve(m + 1);
  pairs.push_back({0.0, 0.0});
  for (size_t s = 0; s < m; ++s) pairs.push_back({stiffness_[s], damping_[s]});
  std::sort(pairs.begin(), pairs.end());
  pairs.erase(std::unique(pairs.begin(), pairs.end()), pairs.end());
  material_kd_.clear();
  spring_material_.clear();
  column_pair_.clear();
  if (pairs.size() <= kMaxMaterialPairs && 8 * pairs.size() <= m) {
    // Pair 0 must be (0, 0): stiffness and damping are >= 0, so it sorts first.
    assert(pairs[0][0] == 0.0 && pairs[0][1] == 0.0);
    for (const auto& pair : pairs)
      material_kd_.insert(material_kd_.end(), pair.begin(), pair.end());
    spring_material_.resize(m);
    for (size_t s = 0; s < m; ++s) {
      const std::array<double, 2> pair = {stiffness_[s], damping_[s]};
      spring_material_[s] =
          static_cast<uint16_t>(std::lower_bound(pairs.begin(), pairs.end(), pair) - pairs.begin());
    }
    // Each column's one pair, or 0 (several pairs: the pass gathers them per lane). Pair 0 is
    // only empty lanes' and cut springs': never a column's pair.
    constexpr uint32_t kSeveral = 0x10000;
    std::vector<uint32_t> column(column_lanes_.size(), 0);
    for (size_t s = 0; s < m; ++s) {
      uint32_t& pair = column[static_cast<size_t>(spring_slot_[s] / 8)];
      pair = pair == 0 || pair == spring_material_[s] ? spring_material_[s] : kSeveral;
    }
    column_pair_.resize(column.size());
    for (size_t c = 0; c < column.size(); ++c) {
      column_pair_[c] = column[c] == kSeveral ? 0 : static_cast<uint16_t>(column[c]);
    }
  }
}

std::unique_ptr<TissueState> MassSpringModel::MakeState() const {
  auto state = std::make_unique<MassSpringState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = rest_.cols();
  state->forces = mesh::Points::Zero(3, n);
  state->stiffness = stiffness_;
  state->damping = damping_;
  // The ring's columns and its zero column (never written).
  state->column_forces.assign(24 * (static_cast<size_t>(ring_columns_) + 1), 0.0);
  // The pass's window: 6 rows of 8 window_slices_ + 8 values, 64-byte aligned (+ 8 to align).
  state->window.assign(6 * (8 * static_cast<size_t>(window_slices_) + 8) + 8, 0.0);
  state->column_lanes = column_lanes_;
  if (!spring_material_.empty()) {
    state->column_material.assign(column_rest_.size(), 0);
    for (size_t s = 0; s < spring_slot_.size(); ++s) {
      state->column_material[static_cast<size_t>(spring_slot_[s])] = spring_material_[s];
    }
  } else {
    state->column_stiffness_damping.assign(2 * column_rest_.size(), 0.0);
    for (size_t s = 0; s < spring_slot_.size(); ++s) {
      const auto slot = static_cast<size_t>(spring_slot_[s]);
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
  SlicePass pass{};
  pass.x = state.positions.data();
  pass.v = state.velocities.data();
  pass.num_nodes = static_cast<size_t>(rest_.cols());
  pass.column_start = slice_column_start_.data();
  pass.other3 = column_other3_.data();
  pass.rest = column_rest_.data();
  pass.lanes = column_lanes_.data();
  pass.live_lanes = ms.column_lanes.data();
  SetSpringConstants(ms, material_kd_, column_pair_, &pass);
  pass.gathered_column = slice_gathered_column_.data();
  pass.incoming_start = slice_incoming_start_.data();
  pass.incoming_slot = incoming_slot_.data();
  pass.incoming_lanes = incoming_lanes_.data();
  pass.gathered_incoming = slice_gathered_incoming_.data();
  pass.ring = ms.column_forces.data();
  pass.ring_mask = static_cast<size_t>(ring_columns_) - 1;
  SetWindow(ms, window_slices_, window_lead_, column_window_, &pass);
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
  SlicePass pass{};
  pass.x = LastGoodPositions(state);
  pass.v = LastGoodVelocities(state);
  pass.moved_x = state->positions.data();
  pass.moved_v = state->velocities.data();
  pass.num_nodes = static_cast<size_t>(rest_.cols());
  pass.column_start = slice_column_start_.data();
  pass.other3 = column_other3_.data();
  pass.rest = column_rest_.data();
  pass.lanes = column_lanes_.data();
  pass.live_lanes = state->column_lanes.data();
  SetSpringConstants(*state, material_kd_, column_pair_, &pass);
  pass.gathered_column = slice_gathered_column_.data();
  pass.incoming_start = slice_incoming_start_.data();
  pass.incoming_slot = incoming_slot_.data();
  pass.incoming_lanes = incoming_lanes_.data();
  pass.gathered_incoming = slice_gathered_incoming_.data();
  pass.ring = state->column_forces.data();
  pass.ring_mask = static_cast<size_t>(ring_columns_) - 1;
  SetWindow(*state, window_slices_, window_lead_, column_window_, &pass);
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
      const auto slot = static_cast<size_t>(spring_slot_[s]);
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
