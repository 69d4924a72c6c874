// The multicolour layout of the mass-spring implicit step's Gauss-Seidel preconditioner
// (MassSpringModel's implicit-step data), built once, and the scratch it sizes in a state.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <numeric>
#include <vector>

#include "server/models/mass_spring_implicit_cg.h"
#include "server/models/mass_spring_model.h"
#include "server/models/mass_spring_state.h"

namespace somasim::models {

void MassSpringModel::BuildImplicitData() {
  const auto n = static_cast<size_t>(rest_.cols());
  const size_t m = spring_i_.size();
  // Greedy colouring in node order: the smallest colour no neighbour has.
  std::vector<int32_t> colour(n, -1);
  int32_t colours = 0;
  std::vector<uint8_t> taken;
  for (size_t i = 0; i < n; ++i) {
    taken.assign(static_cast<size_t>(colours) + 1, 0);
    for (auto e = static_cast<size_t>(node_spring_start_[i]);
         e < static_cast<size_t>(node_spring_start_[i + 1]); ++e) {
      const auto s = static_cast<size_t>(node_springs_[e]);
      const auto other = static_cast<size_t>(
          spring_i_[s] == static_cast<int32_t>(i) ? spring_j_[s] : spring_i_[s]);
      if (colour[other] >= 0) taken[static_cast<size_t>(colour[other])] = 1;
    }
    int32_t c = 0;
    while (taken[static_cast<size_t>(c)] != 0) ++c;
    colour[i] = c;
    colours = std::max(colours, c + 1);
  }
  // Per node: its springs to lower and to higher colours.
  std::vector<int32_t> lower_count(n, 0), upper_count(n, 0);
  for (size_t s = 0; s < m; ++s) {
    const auto i = static_cast<size_t>(spring_i_[s]), j = static_cast<size_t>(spring_j_[s]);
    ++(colour[j] < colour[i] ? lower_count[i] : upper_count[i]);
    ++(colour[i] < colour[j] ? lower_count[j] : upper_count[j]);
  }
  // Lanes: colour by colour; within a colour by (lower, upper) counts so that a group's lanes
  // need about the same number of rows, then by node.
  std::vector<int32_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(), [&](int32_t a, int32_t b) {
    const auto ua = static_cast<size_t>(a), ub = static_cast<size_t>(b);
    if (colour[ua] != colour[ub]) return colour[ua] < colour[ub];
    if (lower_count[ua] != lower_count[ub]) return lower_count[ua] < lower_count[ub];
    if (upper_count[ua] != upper_count[ub]) return upper_count[ua] < upper_count[ub];
    return a < b;
  });
  implicit_node_.clear();
  implicit_colour_start_.assign(1, 0);
  for (size_t k = 0; k < n;) {
    const int32_t c = colour[static_cast<size_t>(order[k])];
    while (k < n && colour[static_cast<size_t>(order[k])] == c)
      implicit_node_.push_back(order[k++]);
    while (implicit_node_.size() % kImplicitLanes != 0) implicit_node_.push_back(-1);
    implicit_colour_start_.push_back(static_cast<int32_t>(implicit_node_.size() / kImplicitLanes));
  }
  implicit_padded_ = implicit_node_.size();
  const size_t p = implicit_padded_;
  const size_t groups = p / kImplicitLanes;
  implicit_lane_.assign(n, 0);
  implicit_massless_group_.assign(groups, 0);
  implicit_mass_.assign(p, 0.0);
  implicit_real_.assign(p, 0.0);
  for (size_t i = 0; i < p; ++i) {
    if (implicit_node_[i] < 0) continue;
    const auto node = static_cast<size_t>(implicit_node_[i]);
    implicit_lane_[node] = static_cast<int32_t>(i);
    implicit_mass_[i] = mass_[node];
    implicit_real_[i] = 1.0;
    if (!(mass_[node] > 0.0)) implicit_massless_group_[i / kImplicitLanes] = 1;
  }
  // Rows: per group, max lower count, then max upper count, rows of 8 slots.
  implicit_row_start_.assign(groups + 1, 0);
  implicit_lower_rows_.assign(groups, 0);
  std::vector<int32_t> upper_rows(groups, 0);
  for (size_t g = 0; g < groups; ++g) {
    for (size_t lane = 0; lane < kImplicitLanes; ++lane) {
      const int32_t node = implicit_node_[kImplicitLanes * g + lane];
      if (node < 0) continue;
      const auto u = static_cast<size_t>(node);
      implicit_lower_rows_[g] = std::max(implicit_lower_rows_[g], lower_count[u]);
      upper_rows[g] = std::max(upper_rows[g], upper_count[u]);
    }
    implicit_row_start_[g + 1] = implicit_row_start_[g] + implicit_lower_rows_[g] + upper_rows[g];
  }
  const size_t slots = kImplicitLanes * static_cast<size_t>(implicit_row_start_[groups]);
  implicit_neighbour_.assign(slots, 0);
  implicit_spring_.assign(slots, static_cast<int32_t>(m));
  implicit_sign_.assign(slots, 0.0);
  for (size_t g = 0; g < groups; ++g) {
    for (size_t lane = 0; lane < kImplicitLanes; ++lane) {
      const size_t i = kImplicitLanes * g + lane;
      size_t lower = static_cast<size_t>(implicit_row_start_[g]);
      size_t upper = lower + static_cast<size_t>(implicit_lower_rows_[g]);
      for (size_t row = lower; row < static_cast<size_t>(implicit_row_start_[g + 1]); ++row) {
        implicit_neighbour_[kImplicitLanes * row + lane] = static_cast<int32_t>(i);
      }
      const int32_t node = implicit_node_[i];
      if (node < 0) continue;
      const auto u = static_cast<size_t>(node);
      for (auto e = static_cast<size_t>(node_spring_start_[u]);
           e < static_cast<size_t>(node_spring_start_[u + 1]); ++e) {
        const auto s = static_cast<size_t>(node_springs_[e]);
        const bool first = spring_i_[s] == node;
        const auto other = static_cast<size_t>(first ? spring_j_[s] : spring_i_[s]);
        size_t& row = colour[other] < colour[u] ? lower : upper;
        implicit_neighbour_[kImplicitLanes * row + lane] = implicit_lane_[other];
        implicit_spring_[kImplicitLanes * row + lane] = static_cast<int32_t>(s);
        implicit_sign_[kImplicitLanes * row + lane] = first ? 1.0 : -1.0;
        ++row;
      }
    }
  }
}

void MassSpringModel::SizeImplicitScratch(MassSpringState* state) const {
  const size_t p = implicit_padded_;
  state->implicit_springs.assign(kImplicitRecord * (spring_i_.size() + 1), 0.0);
  state->implicit_gather.assign(4 * p, 0.0);
  state->implicit_rows.assign(4 * implicit_neighbour_.size(), 0.0);
  state->implicit_diagonal.assign(6 * p, 0.0);
  state->implicit_inverse.assign(6 * p, 0.0);
  state->implicit_keep.assign(p, 0.0);
  for (std::vector<double>* v :
       {&state->implicit_rhs, &state->implicit_dv, &state->implicit_residual, &state->implicit_z,
        &state->implicit_search, &state->implicit_product, &state->implicit_az, &state->implicit_dy,
        &state->implicit_dv_previous}) {
    v->assign(3 * p, 0.0);
  }
}

}  // namespace somasim::models
