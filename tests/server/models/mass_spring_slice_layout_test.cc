// Tests of the explicit mass-spring pass's layout (BuildSliceLayout): every spring sits in
// exactly one lane of one column of the slice of its earlier end, with its other end and rest
// length; run columns' other ends are consecutive; the ring, the window and the pair table are
// sized and filled as the pass expects. On an organ's irregular surface and on a structured grid.
#include "server/models/mass_spring_slice_layout.h"

#include <gtest/gtest.h>

#include <array>
#include <bit>
#include <cstdint>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {
namespace {

struct Springs {
  size_t num_nodes = 0;
  std::vector<int32_t> i, j;
  std::vector<double> rest, stiffness, damping;
};

// The mesh's edges as springs; `kinds` distinct (k, d) pairs, assigned in turn.
Springs FromEdges(const mesh::Points& x, const MeshEdges& edges, size_t kinds) {
  Springs s;
  s.num_nodes = static_cast<size_t>(x.cols());
  for (size_t e = 0; e < edges.edges.size(); ++e) {
    const auto [a, b] = edges.edges[e];
    s.i.push_back(a);
    s.j.push_back(b);
    s.rest.push_back((x.col(b) - x.col(a)).norm());
    s.stiffness.push_back(10.0 + static_cast<double>(e % kinds));
    s.damping.push_back(0.5 + 0.25 * static_cast<double>(e % kinds));
  }
  return s;
}

void ExpectConsistent(const Springs& s, const MassSpringSliceLayout& layout) {
  const size_t m = s.i.size();
  const size_t num_slices = (s.num_nodes + 7) / 8;
  ASSERT_EQ(layout.slice_column_start.size(), num_slices + 1);
  ASSERT_EQ(layout.slice_gathered_column.size(), num_slices);
  ASSERT_EQ(layout.spring_slot.size(), m);
  const size_t columns = layout.column_lanes.size();
  ASSERT_EQ(layout.column_other3.size(), 8 * columns);
  ASSERT_EQ(layout.column_rest.size(), 8 * columns);
  // The slice of each column.
  std::vector<size_t> slice_of(columns, num_slices);
  for (size_t slice = 0; slice < num_slices; ++slice) {
    const auto begin = static_cast<size_t>(layout.slice_column_start[slice]);
    const auto end = static_cast<size_t>(layout.slice_column_start[slice + 1]);
    ASSERT_LE(begin, static_cast<size_t>(layout.slice_gathered_column[slice]));
    ASSERT_LE(static_cast<size_t>(layout.slice_gathered_column[slice]), end);
    for (size_t c = begin; c < end; ++c) slice_of[c] = slice;
    // Run columns: lane l's other node is lane 0's + l.
    for (auto c = begin; c < static_cast<size_t>(layout.slice_gathered_column[slice]); ++c) {
      for (size_t lane = 0; lane < 8; ++lane) {
        EXPECT_EQ(layout.column_other3[8 * c + lane],
                  layout.column_other3[8 * c] + 3 * static_cast<int32_t>(lane));
      }
    }
  }
  // Every spring in one occupied lane, of the slice of its earlier end, and nothing else there.
  size_t occupied = 0;
  for (size_t c = 0; c < columns; ++c) occupied += std::popcount(layout.column_lanes[c]);
  EXPECT_EQ(occupied, m);
  std::vector<int> seen(8 * columns, 0);
  for (size_t k = 0; k < m; ++k) {
    const auto slot = static_cast<size_t>(layout.spring_slot[k]);
    const size_t c = slot / 8, lane = slot % 8;
    ASSERT_LT(c, columns);
    EXPECT_EQ(++seen[slot], 1);
    EXPECT_NE((layout.column_lanes[c] >> lane) & 1U, 0U);
    const auto lane_node = static_cast<int32_t>(8 * slice_of[c] + lane);
    const int32_t other = layout.column_other3[slot] / 3;
    EXPECT_TRUE((lane_node == s.i[k] && other == s.j[k]) ||
                (lane_node == s.j[k] && other == s.i[k]));
    EXPECT_LE(lane_node / 8, other / 8);
    EXPECT_EQ(layout.column_rest[slot], s.rest[k]);
  }
  // The ring and the window: powers of two, the window holding its lead and two slices.
  EXPECT_EQ(std::popcount(static_cast<uint32_t>(layout.ring_columns)), 1);
  EXPECT_EQ(std::popcount(static_cast<uint32_t>(layout.window_slices)), 1);
  EXPECT_GE(layout.window_slices, layout.window_lead + 2);
  ASSERT_EQ(layout.column_window.size(), columns);
  ASSERT_EQ(layout.slice_incoming_start.size(), num_slices + 1);
  EXPECT_EQ(layout.incoming_slot.size(), 8 * layout.incoming_lanes.size());
}

TEST(MassSpringSliceLayout, EverySpringSitsOnceInItsEarlierEndsSliceOnAnOrgan) {
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan("spleen600");
  const Springs s =
      FromEdges(organ.surface.vertices, SurfaceEdges(organ.surface, 0.005, "test"), 1000);
  const MassSpringSliceLayout layout =
      BuildSliceLayout(s.num_nodes, s.i, s.j, s.rest, s.stiffness, s.damping);
  ExpectConsistent(s, layout);
  EXPECT_TRUE(layout.material_kd.empty());  // too many distinct pairs for a table
  EXPECT_TRUE(layout.spring_material.empty());
}

TEST(MassSpringSliceLayout, GridGetsRunColumnsAndAPairTable) {
  const mesh::TetMesh grid =
      mesh_gen::BoxGridTets(9, 7, 6, Eigen::Vector3d::Zero(), Eigen::Vector3d(0.08, 0.06, 0.05));
  const Springs s = FromEdges(grid.vertices, TetMeshEdges(grid, "test"), 3);
  const MassSpringSliceLayout layout =
      BuildSliceLayout(s.num_nodes, s.i, s.j, s.rest, s.stiffness, s.damping);
  ExpectConsistent(s, layout);
  size_t runs = 0;
  for (size_t slice = 0; slice + 1 < layout.slice_column_start.size(); ++slice) {
    runs +=
        static_cast<size_t>(layout.slice_gathered_column[slice] - layout.slice_column_start[slice]);
  }
  EXPECT_GT(runs, layout.column_lanes.size() / 2);  // a structured numbering is mostly runs
  // The table: pair 0 is (0, 0), then each spring's own (k, d).
  ASSERT_EQ(layout.material_kd.size(), 2 * 4U);
  EXPECT_EQ(layout.material_kd[0], 0.0);
  EXPECT_EQ(layout.material_kd[1], 0.0);
  ASSERT_EQ(layout.spring_material.size(), s.i.size());
  for (size_t k = 0; k < s.i.size(); ++k) {
    EXPECT_EQ(layout.material_kd[2 * size_t{layout.spring_material[k]}], s.stiffness[k]);
    EXPECT_EQ(layout.material_kd[2 * size_t{layout.spring_material[k]} + 1], s.damping[k]);
  }
  ASSERT_EQ(layout.column_pair.size(), layout.column_lanes.size());
  for (size_t k = 0; k < s.i.size(); ++k) {
    const uint16_t pair = layout.column_pair[static_cast<size_t>(layout.spring_slot[k] / 8)];
    if (pair != 0) {
      EXPECT_EQ(pair, layout.spring_material[k]);
    }
  }
}

}  // namespace
}  // namespace somasim::models
