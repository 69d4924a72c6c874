// Seed 001's generalised surface mesh (SPEC §4.1): the outer shell is the outer fraction of the
// organ's thickness, measured by exact distances to the boundary; only shell edges become
// springs and only shell nodes carry mass.
#include "server/models/generalised_surface.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <stdexcept>
#include <string>

#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"

namespace somasim::models {
namespace {

using Eigen::Vector3d;

TEST(PointTriangleDistance, MatchesDenseSamplingOfTheTriangle) {
  const Vector3d a(0.0, 0.0, 0.0), b(1.0, 0.0, 0.0), c(0.2, 0.8, 0.1);
  std::mt19937 random(7);
  std::uniform_real_distribution<double> coordinate(-1.0, 2.0);
  for (int trial = 0; trial < 200; ++trial) {
    const Vector3d p(coordinate(random), coordinate(random), coordinate(random));
    double sampled = 1e300;
    const int n = 200;
    for (int i = 0; i <= n; ++i) {
      for (int j = 0; i + j <= n; ++j) {
        const double u = double(i) / n, v = double(j) / n;
        sampled = std::min(sampled, (p - (a + u * (b - a) + v * (c - a))).norm());
      }
    }
    const double exact = PointTriangleDistance(p, a, b, c);
    EXPECT_LE(exact, sampled + 1e-12) << "point " << p.transpose();
    EXPECT_NEAR(exact, sampled, 1e-2) << "point " << p.transpose();  // sampling resolution
  }
}

TEST(PointTriangleDistance, CornerEdgeAndFaceRegions) {
  const Vector3d a(0.0, 0.0, 0.0), b(2.0, 0.0, 0.0), c(0.0, 2.0, 0.0);
  EXPECT_DOUBLE_EQ(PointTriangleDistance(Vector3d(0.5, 0.5, 3.0), a, b, c), 3.0);    // face
  EXPECT_DOUBLE_EQ(PointTriangleDistance(Vector3d(1.0, -4.0, 3.0), a, b, c), 5.0);   // edge ab
  EXPECT_DOUBLE_EQ(PointTriangleDistance(Vector3d(-3.0, -4.0, 0.0), a, b, c), 5.0);  // corner a
  EXPECT_DOUBLE_EQ(PointTriangleDistance(Vector3d(2.0, 2.0, 0.0), a, b, c), std::sqrt(2.0));
}

TEST(SelectOuterShell, DepthIsTheDistanceToTheNearestFaceOfABox) {
  // Unit cube, 11³ nodes, spacing 0.1: depth = distance to the nearest of the six faces.
  const mesh::TetMesh cube = mesh_gen::BoxGridTets(11, 11, 11, Vector3d::Zero(), Vector3d::Ones());
  const OuterShell shell = SelectOuterShell(cube, 0.25);
  EXPECT_NEAR(shell.thickness, 1.0, 1e-12);  // the centre node is 0.5 deep
  for (Eigen::Index i = 0; i < cube.vertices.cols(); ++i) {
    const Vector3d p = cube.vertices.col(i);
    const double expected = std::min({p.x(), p.y(), p.z(), 1.0 - p.x(), 1.0 - p.y(), 1.0 - p.z()});
    ASSERT_NEAR(shell.depth[static_cast<size_t>(i)], expected, 1e-12) << "node " << i;
  }
  // depth <= 0.25: the outer three layers on each side; the core is the 5³ nodes 0.3..0.7.
  EXPECT_EQ(shell.num_shell_nodes, 11 * 11 * 11 - 5 * 5 * 5);
}

TEST(SelectOuterShell, KeepsTheWholeBoundaryAndDropsTheCoreOfAnOrgan) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  const OuterShell shell = SelectOuterShell(liver, 0.2);
  const mesh::SurfaceMesh boundary = mesh::ExtractBoundarySurface(liver);
  for (Eigen::Index f = 0; f < boundary.triangles.cols(); ++f) {
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(shell.in_shell[static_cast<size_t>(boundary.triangles(k, f))], 1);
    }
  }
  EXPECT_GT(shell.num_shell_nodes, 0);
  EXPECT_LT(shell.num_shell_nodes, liver.vertices.cols());  // a core exists and is dropped
  for (size_t i = 0; i < shell.depth.size(); ++i) {
    EXPECT_EQ(shell.in_shell[i] != 0, shell.depth[i] <= 0.2 * shell.thickness) << "node " << i;
  }
}

TEST(ShellEdges, OnlyShellNodesCarrySpringsAndMass) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  const OuterShell shell = SelectOuterShell(liver, 0.2);
  const MeshEdges edges = ShellEdges(liver, shell);
  const MeshEdges all = TetMeshEdges(liver, "test");
  EXPECT_LT(edges.edges.size(), all.edges.size());
  for (const auto& [i, j] : edges.edges) {
    EXPECT_EQ(shell.in_shell[static_cast<size_t>(i)], 1);
    EXPECT_EQ(shell.in_shell[static_cast<size_t>(j)], 1);
  }
  for (size_t i = 0; i < edges.node_size.size(); ++i) {
    if (shell.in_shell[i] != 0) {
      EXPECT_DOUBLE_EQ(edges.node_size[i], all.node_size[i]);
    } else {
      EXPECT_EQ(edges.node_size[i], 0.0);
    }
  }
}

TEST(SelectOuterShell, RefusesBadFractionsAndBadMeshesWithAMessage) {
  const mesh::TetMesh cube = mesh_gen::BoxGridTets(3, 3, 3, Vector3d::Zero(), Vector3d::Ones());
  for (const double fraction : {0.0, -0.1, 0.6, std::nan("")}) {
    try {
      SelectOuterShell(cube, fraction);
      ADD_FAILURE() << "fraction " << fraction << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("shell fraction"), std::string::npos) << e.what();
    }
  }
  mesh::TetMesh broken = cube;
  broken.tetrahedra(2, 0) = 99;
  EXPECT_THROW(SelectOuterShell(broken, 0.2), std::invalid_argument);
  broken = cube;
  broken.vertices(0, 4) = std::nan("");
  EXPECT_THROW(SelectOuterShell(broken, 0.2), std::invalid_argument);
  OuterShell wrong = SelectOuterShell(cube, 0.2);
  wrong.in_shell.pop_back();
  EXPECT_THROW(ShellEdges(cube, wrong), std::invalid_argument);
}

}  // namespace
}  // namespace somasim::models
