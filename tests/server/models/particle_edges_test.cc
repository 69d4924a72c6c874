// Tests of the edge helpers the mass-spring and position-based models share: pairs are checked,
// ordered and sorted, coincident ends and bad indices are refused by name, masses follow the
// lumping rule, every edge is listed at both its nodes, and an edge's stiffness block is the
// Jacobian of its spring force.
#include "server/models/particle_edges.h"

#include <gtest/gtest.h>

#include <array>
#include <cstdint>
#include <functional>
#include <stdexcept>
#include <string>
#include <vector>

namespace somasim::models {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

std::string MessageOf(const std::function<void()>& call) {
  try {
    call();
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

TEST(ParticleEdges, SortedEdgesOrdersEachPairAndSortsThem) {
  const std::vector<std::array<int32_t, 2>> edges = {{3, 1}, {0, 2}, {2, 1}, {1, 3}};
  const std::vector<std::array<int32_t, 2>> sorted = SortedEdges(edges, 4, "model", "edge");
  const std::vector<std::array<int32_t, 2>> expected = {{0, 2}, {1, 2}, {1, 3}, {1, 3}};
  EXPECT_EQ(sorted, expected);
}

TEST(ParticleEdges, SortedEdgesRefusesTheFirstBadPairByName) {
  const std::vector<std::array<int32_t, 2>> edges = {{0, 1}, {2, 2}, {0, 9}};
  EXPECT_EQ(MessageOf([&] { SortedEdges(edges, 4, "mass-spring", "spring"); }),
            "mass-spring: spring 1 joins nodes 2 and 2, not two distinct nodes of 0..3");
  const std::vector<std::array<int32_t, 2>> out_of_range = {{0, 1}, {-1, 2}};
  EXPECT_EQ(MessageOf([&] { SortedEdges(out_of_range, 4, "position-based", "constraint"); }),
            "position-based: constraint 1 joins nodes -1 and 2, not two distinct nodes of 0..3");
}

TEST(ParticleEdges, RestLengthIsTheDistanceAndCoincidentEndsAreRefused) {
  mesh::Points rest(3, 3);
  rest.col(0) = Vector3d(0.0, 0.0, 0.0);
  rest.col(1) = Vector3d(3.0, 4.0, 0.0);
  rest.col(2) = Vector3d(3.0, 4.0, 0.0);
  EXPECT_DOUBLE_EQ(EdgeRestLength(rest, 0, 1, "model", "edge"), 5.0);
  EXPECT_EQ(MessageOf([&] { EdgeRestLength(rest, 1, 2, "mass-spring", "spring"); }),
            "mass-spring: nodes 1 and 2 coincide (a zero-length spring)");
}

TEST(ParticleEdges, MassesFollowTheLumpingRule) {
  const std::vector<double> node_size = {2e-6, 0.0, 5e-7};  // [m³]
  std::vector<double> mass, inverse_mass;
  LumpMasses(node_size, 1000.0, 0.0, &mass, &inverse_mass);
  ASSERT_EQ(mass.size(), 3U);
  EXPECT_DOUBLE_EQ(mass[0], 2e-3);
  EXPECT_DOUBLE_EQ(inverse_mass[0], 500.0);
  EXPECT_EQ(mass[1], 0.0);  // untouched by any element: no mass, and it cannot move
  EXPECT_EQ(inverse_mass[1], 0.0);
  LumpMasses(node_size, 1000.0, 0.25, &mass, &inverse_mass);  // the raw constant wins
  for (size_t i = 0; i < 3; ++i) {
    EXPECT_EQ(mass[i], 0.25);
    EXPECT_EQ(inverse_mass[i], 4.0);
  }
}

TEST(ParticleEdges, EveryEdgeIsListedAtBothItsNodesInEdgeOrder) {
  const std::vector<int32_t> edge_i = {0, 0, 1, 2};
  const std::vector<int32_t> edge_j = {1, 3, 3, 3};
  std::vector<int32_t> start, edges;
  NodeEdgeLists(5, edge_i, edge_j, &start, &edges);
  EXPECT_EQ(start, (std::vector<int32_t>{0, 2, 4, 5, 8, 8}));
  EXPECT_EQ(edges, (std::vector<int32_t>{0, 1, 0, 2, 3, 1, 2, 3}));
}

TEST(ParticleEdges, EdgeStiffnessIsTheSpringForceJacobian) {
  // f_i = k (l - l0) u for d = x_j - x_i: -∂f_i/∂x_i by central differences.
  const Vector3d xj(0.3, -0.2, 0.9);
  const Vector3d xi(0.1, 0.2, 0.05);
  const double l0 = 0.7, k = 40.0;
  const auto force = [&](const Vector3d& x) {
    const Vector3d d = xj - x;
    return Vector3d(k * (d.norm() - l0) * d / d.norm());
  };
  Matrix3d numeric;
  const double h = 1e-6;
  for (int c = 0; c < 3; ++c) {
    Vector3d step = Vector3d::Zero();
    step[c] = h;
    numeric.col(c) = -(force(xi + step) - force(xi - step)) / (2.0 * h);
  }
  Matrix3d analytic = Matrix3d::Zero();
  AddEdgeStiffness(xj - xi, l0, k, &analytic);
  EXPECT_LT((analytic - numeric).norm(), 1e-6 * analytic.norm());
  Matrix3d none = Matrix3d::Identity();
  AddEdgeStiffness(Vector3d::Zero(), l0, k, &none);  // zero length: nothing added
  EXPECT_EQ(none, Matrix3d::Identity());
}

}  // namespace
}  // namespace somasim::models
