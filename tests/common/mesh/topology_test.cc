#include "common/mesh/topology.h"

#include <gtest/gtest.h>

#include <set>

#include "common/mesh/geometry.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh {
namespace {

TEST(Topology, BoundaryOfBoxIsWatertightSphereTopology) {
  const mesh_io::MeshData box = testing::BoxTets(3, 2, 2);
  const SurfaceMesh surface = ExtractBoundarySurface({box.vertices, box.tetrahedra});
  // Each face of an a×b grid of squares gives 2ab triangles.
  EXPECT_EQ(surface.triangles.cols(), 2 * 2 * (3 * 2 + 3 * 2 + 2 * 2));
  const SurfaceTopology topo = AnalyseSurfaceTopology(surface);
  EXPECT_TRUE(topo.watertight);
  EXPECT_TRUE(topo.manifold);
  EXPECT_EQ(topo.num_components, 1);
  EXPECT_EQ(topo.euler_characteristic, 2);
}

TEST(Topology, BoundaryTrianglesFaceOutwards) {
  const mesh_io::MeshData box = testing::BoxTets(2, 2, 2);
  const SurfaceMesh s = ExtractBoundarySurface({box.vertices, box.tetrahedra});
  const Eigen::Vector3d centre(0.5, 0.5, 0.5);
  for (Eigen::Index t = 0; t < s.triangles.cols(); ++t) {
    const Eigen::Vector3d a = s.vertices.col(s.triangles(0, t));
    const Eigen::Vector3d b = s.vertices.col(s.triangles(1, t));
    const Eigen::Vector3d c = s.vertices.col(s.triangles(2, t));
    EXPECT_GT((b - a).cross(c - a).dot((a + b + c) / 3 - centre), 0) << "triangle " << t;
  }
}

TEST(Topology, UnreferencedNodesAreThoseNoElementUses) {
  Triangles triangles(3, 1);
  triangles << 0, 2, 5;
  Tetrahedra tets(4, 1);
  tets << 1, 2, 3, 9;  // 9 is out of range for 7 nodes: ignored
  EXPECT_EQ(UnreferencedNodes(7, triangles, tets), (std::vector<int32_t>{4, 6}));
  EXPECT_EQ(UnreferencedNodes(3, Triangles(3, 0), Tetrahedra(4, 0)),
            (std::vector<int32_t>{0, 1, 2}));
}

TEST(Topology, OpenPatchIsManifoldButNotWatertight) {
  const mesh_io::MeshData patch = testing::SquarePatch(3);
  const SurfaceTopology topo = AnalyseSurfaceTopology({patch.vertices, patch.triangles});
  EXPECT_FALSE(topo.watertight);
  EXPECT_TRUE(topo.manifold);
  EXPECT_EQ(topo.num_boundary_edges, 4 * 3);
  EXPECT_EQ(topo.euler_characteristic, 1);  // a disc
}

TEST(Topology, FlippedTriangleIsMisoriented) {
  mesh_io::MeshData box = testing::BoxSurface(1, 1, 1);
  std::swap(box.triangles(1, 0), box.triangles(2, 0));
  const SurfaceTopology topo = AnalyseSurfaceTopology({box.vertices, box.triangles});
  EXPECT_EQ(topo.num_misoriented_edges, 3);
  EXPECT_FALSE(topo.watertight);
  EXPECT_TRUE(topo.manifold);
}

TEST(Topology, ThreeTrianglesOnOneEdgeAreNonManifold) {
  SurfaceMesh s;
  s.vertices.resize(3, 5);
  s.vertices << 0, 1, 0, 0, 1,  //
      0, 0, 1, -1, 1,           //
      0, 0, 0, 0, 1;
  s.triangles.resize(3, 3);
  s.triangles << 0, 1, 0,  //
      1, 0, 1,             //
      2, 3, 4;
  const SurfaceTopology topo = AnalyseSurfaceTopology(s);
  EXPECT_EQ(topo.num_nonmanifold_edges, 1);
  EXPECT_FALSE(topo.manifold);
}

TEST(Topology, TwoCubesSharingAVertexMakeANonManifoldVertex) {
  const mesh_io::MeshData a = testing::BoxSurface(1, 1, 1);
  SurfaceMesh s;
  const Eigen::Index n = a.vertices.cols();
  s.vertices.resize(3, 2 * n);
  s.vertices.leftCols(n) = a.vertices;
  s.vertices.rightCols(n) = a.vertices.array() + 1.0;  // corner (1,1,1) of a = corner 0 of b
  s.triangles.resize(3, 2 * a.triangles.cols());
  s.triangles.leftCols(a.triangles.cols()) = a.triangles;
  s.triangles.rightCols(a.triangles.cols()) = a.triangles.array() + static_cast<int32_t>(n);
  // Merge b's corner at (1,1,1) into a's.
  Eigen::Index a_corner = -1, b_corner = -1;
  for (Eigen::Index i = 0; i < n; ++i) {
    if (a.vertices.col(i) == Eigen::Vector3d(1, 1, 1)) a_corner = i;
    if (a.vertices.col(i) == Eigen::Vector3d(0, 0, 0)) b_corner = i + n;
  }
  ASSERT_GE(a_corner, 0);
  ASSERT_GE(b_corner, 0);
  for (Eigen::Index i = 0; i < s.triangles.size(); ++i) {
    if (s.triangles.data()[i] == b_corner) s.triangles.data()[i] = static_cast<int32_t>(a_corner);
  }
  const SurfaceTopology topo = AnalyseSurfaceTopology(s);
  EXPECT_EQ(topo.num_nonmanifold_vertices, 1);
  EXPECT_EQ(topo.num_nonmanifold_edges, 0);
  EXPECT_FALSE(topo.manifold);
  EXPECT_TRUE(topo.watertight);  // every edge still has two consistently oriented triangles
  EXPECT_EQ(topo.num_components, 2);
}

TEST(Topology, FaceNeighboursAreSymmetric) {
  const mesh_io::MeshData box = testing::BoxTets(2, 3, 2);
  const auto nb = TetFaceNeighbours(static_cast<int32_t>(box.vertices.cols()), box.tetrahedra);
  int64_t boundary = 0;
  for (Eigen::Index t = 0; t < nb.cols(); ++t) {
    for (int f = 0; f < 4; ++f) {
      const int32_t o = nb(f, t);
      if (o == -1) {
        ++boundary;
        continue;
      }
      ASSERT_GE(o, 0);
      int back = 0;
      for (int g = 0; g < 4; ++g) back += nb(g, o) == t ? 1 : 0;
      EXPECT_EQ(back, 1);
    }
  }
  EXPECT_EQ(boundary, ExtractBoundarySurface({box.vertices, box.tetrahedra}).triangles.cols());
}

TEST(Topology, NodeToTetsListsEachIncidence) {
  const mesh_io::MeshData box = testing::BoxTets(2, 2, 2);
  const Adjacency adj = NodeToTets(static_cast<int32_t>(box.vertices.cols()), box.tetrahedra);
  EXPECT_EQ(adj.entries.size(), static_cast<size_t>(4 * box.tetrahedra.cols()));
  for (size_t v = 0; v + 1 < adj.offsets.size(); ++v) {
    for (int32_t k = adj.offsets[v]; k < adj.offsets[v + 1]; ++k) {
      const int32_t t = adj.entries[static_cast<size_t>(k)];
      EXPECT_TRUE((box.tetrahedra.col(t).array() == static_cast<int32_t>(v)).any());
    }
  }
  // The centre node of a 2×2×2 Kuhn grid: all 6 tets of the two cells whose diagonal ends at
  // it, and 2 of each other cell's 6 (the monotone paths through a mixed corner): 24 in all.
  EXPECT_EQ(adj.Count(static_cast<size_t>(1 + 3 * (1 + 3 * 1))), 24);
}

TEST(Topology, CompactSurfaceDropsInteriorNodes) {
  const mesh_io::MeshData box = testing::BoxTets(2, 2, 2);
  std::vector<int32_t> map;
  const SurfaceMesh s =
      CompactSurface(ExtractBoundarySurface({box.vertices, box.tetrahedra}), &map);
  EXPECT_EQ(s.vertices.cols(), 27 - 1);
  EXPECT_EQ(map[13], -1);  // the centre node
  EXPECT_NEAR(SurfaceEnclosedVolume(s), 1.0, 1e-12);
}

}  // namespace
}  // namespace somasim::mesh
