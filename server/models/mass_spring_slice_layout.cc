#include "server/models/mass_spring_slice_layout.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cassert>
#include <limits>
#include <utility>

namespace somasim::models {
namespace {

// What a gathered column (its other nodes' x and v gathered) costs the pass, counted in run
// columns (theirs loaded): the rate at which each slice trades one for the other. The value is
// the fastest measured on the benchmark organs (docs/benchmarks.md).
constexpr double kGatheredColumnCost = 2.0;
// The most (k, d) pairs a table may hold (64 KiB): the pass gathers from it, so it must stay in
// L1/L2.
constexpr size_t kMaxMaterialPairs = 4096;
constexpr int64_t kNotInRun = std::numeric_limits<int64_t>::min();

// One of a slice's springs, by the offset Δ = other node − lane node of its lane node.
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

struct IncomingColumn {
  // Rotated: {column of lanes r.., column of lanes ..r-1, r} (-1: the zero column); gathered:
  // each lane's 8 × column + lane.
  std::array<int32_t, 8> slot;
  uint8_t lanes;
  bool rotated;
};

// The stages of BuildSliceLayout, in the order they run, and what each leaves for the next.
class SliceLayoutBuilder {
 public:
  SliceLayoutBuilder(size_t num_nodes, const std::vector<int32_t>& spring_i,
                     const std::vector<int32_t>& spring_j, const std::vector<double>& rest_length,
                     MassSpringSliceLayout* layout)
      : n_(num_nodes),
        m_(spring_i.size()),
        num_slices_((num_nodes + 7) / 8),
        spring_i_(spring_i),
        spring_j_(spring_j),
        rest_length_(rest_length),
        out_(*layout) {}

  // Each spring's lane node: the end in the earlier slice, which lets the pass move a slice's
  // nodes at its end (every spring touching them is done, none still to come reads them).
  // Springs within one slice go to the end with fewer springs so far, to keep slices narrow.
  // Then the springs by lane node (CSR), in canonical order within a node.
  void AssignLanes() {
    lane_node_.assign(m_, 0);
    std::vector<int32_t> per_node(n_, 0);
    std::vector<size_t> inner;
    for (size_t s = 0; s < m_; ++s) {
      const int32_t i = spring_i_[s], j = spring_j_[s];
      if (i / 8 == j / 8) {
        inner.push_back(s);
      } else {
        lane_node_[s] = i;
        ++per_node[static_cast<size_t>(i)];
      }
    }
    for (const size_t s : inner) {
      const int32_t i = spring_i_[s], j = spring_j_[s];
      lane_node_[s] = per_node[static_cast<size_t>(j)] < per_node[static_cast<size_t>(i)] ? j : i;
      ++per_node[static_cast<size_t>(lane_node_[s])];
    }
    start_.assign(n_ + 1, 0);
    for (size_t s = 0; s < m_; ++s) ++start_[static_cast<size_t>(lane_node_[s]) + 1];
    for (size_t i = 0; i < n_; ++i) start_[i + 1] += start_[i];
    by_node_.resize(m_);
    std::vector<size_t> fill(start_.begin(), start_.end() - 1);
    for (size_t s = 0; s < m_; ++s) by_node_[fill[static_cast<size_t>(lane_node_[s])]++] = s;
  }

  // Outgoing columns. A slice's springs with one offset Δ = other node − lane node (an edge kind
  // of a structured mesh) go into one run column when enough of its lanes have one: lane l's
  // other node is then 8 slice + l + Δ, and the pass loads the 8 other nodes' x and v as 24
  // consecutive values each instead of gathering them; lanes without such a spring hold none
  // (the pass stores F = 0 for them). The slice's other springs go into gathered columns,
  // column k holding each lane's k-th. How many lanes a run column needs is chosen per slice:
  // the least that costs the pass least (a gathered column costs kGatheredColumnCost run
  // columns).
  void OutgoingColumns() {
    out_.slice_column_start.assign(1, 0);
    out_.column_other3.clear();
    out_.column_rest.clear();
    out_.column_lanes.clear();
    out_.spring_slot.assign(m_, 0);
    out_.slice_gathered_column.clear();
    run_offset_.assign(m_, kNotInRun);
    slice_runs_.assign(num_slices_, {});
    for (size_t slice = 0; slice < num_slices_; ++slice) {
      CollectRuns(slice);
      EmitRunColumns(slice, BestThreshold());
      out_.slice_gathered_column.push_back(static_cast<int32_t>(out_.column_lanes.size()));
      EmitGatheredColumns(slice);
      out_.slice_column_start.push_back(static_cast<int32_t>(out_.column_lanes.size()));
    }
  }

  // Incoming columns: a slice's nodes take -F of the springs ending on them. For each Δ of run
  // columns, one rotated column: lane l's spring of that Δ starts at node 8 slice + l - Δ =
  // 8 s_a + r + l, in lane r + l of the Δ run column of slice s_a (l < 8 - r), or lane
  // r + l - 8 of that of slice s_a + 1; the pass loads both columns' forces and rotates them.
  // Lanes without such a spring read a lane the run column left empty (F = 0 there), or the
  // ring's zero column where there is no run column (or one not yet computed: only a Δ < 0
  // within one slice reads beyond it, and only empty lanes). The other springs ending on a lane
  // are gathered from their ring places, column k holding each lane's k-th.
  void IncomingColumns() {
    incoming_.assign(n_, {});
    for (size_t s = 0; s < m_; ++s) {
      incoming_[static_cast<size_t>(OtherEnd(s))].push_back(s);
    }
    incoming_columns_.clear();
    incoming_column_start_.assign(1, 0);
    for (size_t slice = 0; slice < num_slices_; ++slice) {
      IncomingColumnsOf(slice);
      incoming_column_start_.push_back(incoming_columns_.size());
    }
  }

  // The ring of column forces: every column an incoming column reads must not be overwritten
  // before the end of the reading slice's columns. Then the incoming columns' slots as places in
  // the ring.
  void PlaceIncomingColumns() {
    size_t reach = 1;
    for (size_t slice = 0; slice < num_slices_; ++slice) {
      const auto end = static_cast<int64_t>(out_.slice_column_start[slice + 1]);
      for (size_t c = incoming_column_start_[slice]; c < incoming_column_start_[slice + 1]; ++c) {
        const IncomingColumn& column = incoming_columns_[c];
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
    out_.ring_columns = static_cast<int32_t>(ring);
    const int32_t ring_columns = out_.ring_columns;
    const auto ring_place = [ring_columns](int32_t column) {
      return column < 0 ? 24 * ring_columns : 24 * (column % ring_columns);
    };
    out_.slice_incoming_start.assign(1, 0);
    out_.incoming_slot.clear();
    out_.incoming_lanes.clear();
    out_.slice_gathered_incoming.clear();
    for (size_t slice = 0; slice < num_slices_; ++slice) {
      out_.slice_gathered_incoming.push_back(static_cast<int32_t>(incoming_column_start_[slice]));
      for (size_t c = incoming_column_start_[slice]; c < incoming_column_start_[slice + 1]; ++c) {
        IncomingColumn column = incoming_columns_[c];
        if (column.rotated) {
          column.slot[0] = ring_place(column.slot[0]);
          column.slot[1] = ring_place(column.slot[1]);
          ++out_.slice_gathered_incoming.back();
        } else {
          for (size_t lane = 0; lane < 8; ++lane) {
            if (((column.lanes >> lane) & 1U) == 0) continue;
            column.slot[lane] = ring_place(column.slot[lane] / 8) + column.slot[lane] % 8;
          }
        }
        out_.incoming_slot.insert(out_.incoming_slot.end(), column.slot.begin(), column.slot.end());
        out_.incoming_lanes.push_back(column.lanes);
      }
      out_.slice_incoming_start.push_back(static_cast<int32_t>(out_.incoming_lanes.size()));
    }
  }

  // The window of the AVX-512 pass (SlicePass::window): a run column of slice s reads the
  // nodes 8 s + Δ .. + 7, in slices s - 1 (Δ < 0) to s + (Δ + 7) / 8; the pass fills slice
  // s + lead at the start of slice s, so the window must hold lead + 2 slices.
  void SizeWindow() {
    out_.window_lead = 0;
    out_.column_window.assign(out_.column_lanes.size(), 0);
    for (size_t slice = 0; slice < num_slices_; ++slice) {
      for (auto c = static_cast<size_t>(out_.slice_column_start[slice]);
           c < static_cast<size_t>(out_.slice_gathered_column[slice]); ++c) {
        const int64_t offset = out_.column_other3[8 * c] / 3 - static_cast<int64_t>(8 * slice);
        out_.window_lead = std::max(out_.window_lead, static_cast<int32_t>((offset + 7) / 8));
      }
    }
    out_.window_slices = 1;
    while (out_.window_slices < out_.window_lead + 2) out_.window_slices *= 2;
    for (size_t c = 0; c < out_.column_lanes.size(); ++c) {
      out_.column_window[c] = (out_.column_other3[8 * c] / 3) & (8 * out_.window_slices - 1);
    }
  }

 private:
  // The end of spring s that is not its lane node.
  int32_t OtherEnd(size_t s) const {
    return lane_node_[s] == spring_i_[s] ? spring_j_[s] : spring_i_[s];
  }

  // Appends a column (spring[lane] = m_ for an empty lane) and returns its index.
  int32_t EmitColumn(const std::array<size_t, 8>& spring, const std::array<int32_t, 8>& other3,
                     uint8_t lanes) {
    const auto index = static_cast<int32_t>(out_.column_lanes.size());
    for (size_t lane = 0; lane < 8; ++lane) {
      const size_t s = spring[lane];
      out_.column_rest.push_back(s < m_ ? rest_length_[s] : 0.0);
      if (s < m_) out_.spring_slot[s] = 8 * index + static_cast<int32_t>(lane);
    }
    out_.column_other3.insert(out_.column_other3.end(), other3.begin(), other3.end());
    out_.column_lanes.push_back(lanes);
    return index;
  }

  // The slice's springs as candidates_, by Δ (within one Δ by lane, and a lane's springs in
  // canonical order), and the runs_ of one Δ each.
  void CollectRuns(size_t slice) {
    const size_t first = 8 * slice, last = std::min(n_, first + 8);
    candidates_.clear();
    for (size_t node = first; node < last; ++node) {
      for (size_t k = start_[node]; k < start_[node + 1]; ++k) {
        const size_t s = by_node_[k];
        candidates_.push_back({int64_t{OtherEnd(s)} - static_cast<int64_t>(node), node - first, s});
      }
    }
    std::stable_sort(candidates_.begin(), candidates_.end(),
                     [](const Candidate& a, const Candidate& b) { return a.offset < b.offset; });
    runs_.clear();
    for (size_t b = 0; b < candidates_.size();) {
      size_t e = b;
      Run run{b, b, 0, 0, false};
      while (e < candidates_.size() && candidates_[e].offset == candidates_[b].offset) {
        run.lanes = static_cast<uint8_t>(run.lanes | (1U << candidates_[e].lane));
        ++e;
      }
      run.end = e;
      run.lane_count = std::popcount(run.lanes);
      const int64_t window = static_cast<int64_t>(first) + candidates_[b].offset;
      run.loadable = window >= 0 && window + 8 <= static_cast<int64_t>(n_);
      runs_.push_back(run);
      b = e;
    }
  }

  // The threshold (lanes a run needs to get a column): the number of run columns plus
  // kGatheredColumnCost × the widest lane's springs left for gathered columns, least over 1..8
  // lanes.
  int BestThreshold() const {
    int best_threshold = 9;
    double best_cost = std::numeric_limits<double>::infinity();
    for (int threshold = 1; threshold <= 8; ++threshold) {
      std::array<size_t, 8> left{};
      size_t run_columns = 0;
      for (const Run& run : runs_) {
        const bool taken = run.loadable && run.lane_count >= threshold;
        run_columns += taken ? 1 : 0;
        for (size_t c = run.begin; c < run.end; ++c) ++left[candidates_[c].lane];
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
    return best_threshold;
  }

  // A run column for each run of `threshold` lanes or more whose other nodes exist.
  void EmitRunColumns(size_t slice, int threshold) {
    const size_t first = 8 * slice;
    for (const Run& run : runs_) {
      if (!run.loadable || run.lane_count < threshold) continue;
      std::array<size_t, 8> spring;
      spring.fill(m_);
      std::array<int32_t, 8> other3{};
      const int64_t offset = candidates_[run.begin].offset;
      for (size_t lane = 0; lane < 8; ++lane) {
        other3[lane] = static_cast<int32_t>(3 * (static_cast<int64_t>(first + lane) + offset));
      }
      for (size_t c = run.begin; c < run.end; ++c) {
        if (spring[candidates_[c].lane] != m_) continue;  // a lane's second spring of this Δ
        spring[candidates_[c].lane] = candidates_[c].spring;
        run_offset_[candidates_[c].spring] = offset;
      }
      slice_runs_[slice].emplace_back(offset, EmitColumn(spring, other3, run.lanes));
    }
  }

  // The slice's springs in no run column, column k holding each lane's k-th.
  void EmitGatheredColumns(size_t slice) {
    const size_t first = 8 * slice, last = std::min(n_, first + 8);
    size_t width = 0;
    for (size_t node = first; node < last; ++node) {
      std::vector<size_t>& rest = rest_of_lane_[node - first];
      rest.clear();
      for (size_t k = start_[node]; k < start_[node + 1]; ++k) {
        if (run_offset_[by_node_[k]] == kNotInRun) rest.push_back(by_node_[k]);
      }
      width = std::max(width, rest.size());
    }
    for (size_t k = 0; k < width; ++k) {
      std::array<size_t, 8> spring;
      spring.fill(m_);
      std::array<int32_t, 8> other3{};
      uint8_t lanes = 0;
      for (size_t lane = 0; lane < last - first; ++lane) {
        if (k >= rest_of_lane_[lane].size()) continue;
        const size_t s = rest_of_lane_[lane][k];
        spring[lane] = s;
        other3[lane] = 3 * OtherEnd(s);
        lanes = static_cast<uint8_t>(lanes | (1U << lane));
      }
      EmitColumn(spring, other3, lanes);
    }
  }

  // The run column of offset Δ in `slice`, or -1 (none, or no such slice).
  int32_t RunColumn(int64_t slice, int64_t offset) const {
    if (slice < 0) return int32_t{-1};
    for (const auto& [o, column] : slice_runs_[static_cast<size_t>(slice)]) {
      if (o == offset) return column;
    }
    return int32_t{-1};
  }

  // The slice's rotated incoming columns (one per Δ, by Δ), then its gathered ones.
  void IncomingColumnsOf(size_t slice) {
    const size_t first = 8 * slice, last = std::min(n_, first + 8);
    rotated_.clear();
    size_t width = 0;
    for (size_t node = first; node < last; ++node) {
      std::vector<size_t>& rest = rest_of_lane_[node - first];
      rest.clear();
      for (const size_t s : incoming_[node]) {
        if (run_offset_[s] == kNotInRun) {
          rest.push_back(s);
          continue;
        }
        auto it = std::find_if(rotated_.begin(), rotated_.end(),
                               [&](const auto& entry) { return entry.first == run_offset_[s]; });
        if (it == rotated_.end()) {
          it = rotated_.insert(rotated_.end(), {run_offset_[s], uint8_t{0}});
        }
        it->second = static_cast<uint8_t>(it->second | (1U << (node - first)));
      }
      width = std::max(width, rest.size());
    }
    std::sort(rotated_.begin(), rotated_.end());
    for (const auto& [offset, lanes] : rotated_) {
      const int64_t source = static_cast<int64_t>(first) - offset;  // lane 0's start node
      const int64_t source_slice = source >= 0 ? source / 8 : -((7 - source) / 8);
      const auto r = static_cast<int32_t>(source - 8 * source_slice);
      const int32_t a = source_slice <= static_cast<int64_t>(slice)
                            ? RunColumn(source_slice, offset)
                            : int32_t{-1};
      const int32_t b = r == 0 ? a
                        : source_slice + 1 <= static_cast<int64_t>(slice)
                            ? RunColumn(source_slice + 1, offset)
                            : int32_t{-1};
      incoming_columns_.push_back({{a, b, r, 0, 0, 0, 0, 0}, lanes, true});
    }
    for (size_t k = 0; k < width; ++k) {
      IncomingColumn column{{}, 0, false};
      for (size_t lane = 0; lane < last - first; ++lane) {
        if (k >= rest_of_lane_[lane].size()) continue;
        column.slot[lane] = out_.spring_slot[rest_of_lane_[lane][k]];
        column.lanes = static_cast<uint8_t>(column.lanes | (1U << lane));
      }
      incoming_columns_.push_back(column);
    }
  }

  const size_t n_, m_, num_slices_;
  const std::vector<int32_t>& spring_i_;
  const std::vector<int32_t>& spring_j_;
  const std::vector<double>& rest_length_;
  MassSpringSliceLayout& out_;
  // AssignLanes: each spring's lane node, and the springs by lane node (CSR).
  std::vector<int32_t> lane_node_;
  std::vector<size_t> start_, by_node_;
  // OutgoingColumns: Δ of each spring in a run column (kNotInRun for the others), and each
  // slice's run columns as (Δ, column).
  std::vector<int64_t> run_offset_;
  std::vector<std::vector<std::pair<int64_t, int32_t>>> slice_runs_;
  // IncomingColumns: the springs ending on each node, and the incoming columns (with their ring
  // columns, not yet places) and where each slice's start.
  std::vector<std::vector<size_t>> incoming_;
  std::vector<IncomingColumn> incoming_columns_;
  std::vector<size_t> incoming_column_start_;
  // Scratch of one slice.
  std::vector<Candidate> candidates_;
  std::vector<Run> runs_;
  std::array<std::vector<size_t>, 8> rest_of_lane_;
  std::vector<std::pair<int64_t, uint8_t>> rotated_;  // Δ, lanes
};

// The distinct (k, d) pairs, exactly (the model merged constants that differ by rounding): when
// each is shared by 8 springs or more on average (structured meshes) and the table stays small,
// the state keeps a 2-byte index per spring instead of k and d (16 bytes).
void BuildPairTable(const std::vector<double>& stiffness, const std::vector<double>& damping,
                    MassSpringSliceLayout* out) {
  const size_t m = stiffness.size();
  std::vector<std::array<double, 2>> pairs;
  pairs.reserve(m + 1);
  pairs.push_back({0.0, 0.0});
  for (size_t s = 0; s < m; ++s) pairs.push_back({stiffness[s], damping[s]});
  std::sort(pairs.begin(), pairs.end());
  pairs.erase(std::unique(pairs.begin(), pairs.end()), pairs.end());
  out->material_kd.clear();
  out->spring_material.clear();
  out->column_pair.clear();
  if (pairs.size() > kMaxMaterialPairs || 8 * pairs.size() > m) return;
  // Pair 0 must be (0, 0): stiffness and damping are >= 0, so it sorts first.
  assert(pairs[0][0] == 0.0 && pairs[0][1] == 0.0);
  for (const auto& pair : pairs) {
    out->material_kd.insert(out->material_kd.end(), pair.begin(), pair.end());
  }
  out->spring_material.resize(m);
  for (size_t s = 0; s < m; ++s) {
    const std::array<double, 2> pair = {stiffness[s], damping[s]};
    out->spring_material[s] =
        static_cast<uint16_t>(std::lower_bound(pairs.begin(), pairs.end(), pair) - pairs.begin());
  }
  // Each column's one pair, or 0 (several pairs: the pass gathers them per lane). Pair 0 is only
  // empty lanes' and cut springs': never a column's pair.
  constexpr uint32_t kSeveral = 0x10000;
  std::vector<uint32_t> column(out->column_lanes.size(), 0);
  for (size_t s = 0; s < m; ++s) {
    uint32_t& pair = column[static_cast<size_t>(out->spring_slot[s] / 8)];
    pair = pair == 0 || pair == out->spring_material[s] ? out->spring_material[s] : kSeveral;
  }
  out->column_pair.resize(column.size());
  for (size_t c = 0; c < column.size(); ++c) {
    out->column_pair[c] = column[c] == kSeveral ? 0 : static_cast<uint16_t>(column[c]);
  }
}

}  // namespace

MassSpringSliceLayout BuildSliceLayout(size_t num_nodes, const std::vector<int32_t>& spring_i,
                                       const std::vector<int32_t>& spring_j,
                                       const std::vector<double>& rest_length,
                                       const std::vector<double>& stiffness,
                                       const std::vector<double>& damping) {
  MassSpringSliceLayout layout;
  SliceLayoutBuilder builder(num_nodes, spring_i, spring_j, rest_length, &layout);
  builder.AssignLanes();
  builder.OutgoingColumns();
  builder.IncomingColumns();
  builder.PlaceIncomingColumns();
  builder.SizeWindow();
  BuildPairTable(stiffness, damping, &layout);
  return layout;
}

}  // namespace somasim::models
