// Vertex-preserving cutting (server/cutting/tet_cutter.h, seed 003 §3–4) on the built-in
// organs: the seed's plate scenarios (a straight cut from an edge opens a slit on the blade's
// plane and keeps the surface closed; a complete cut separates two pieces, each closed; an
// oblique partial-depth cut from mid-face leaves one piece), the relocation rules (eq. 1 onto
// the sweep, eq. 2 onto its boundary), and random blade paths on every volume organ that never
// break the mesh: vertex count constant, no inverted or degenerate element, no vertex in no
// element, the alive counts consistent, the surface manifold, and inner faces only where
// something was removed. Steps allocate nothing; bad input is refused.
#include "server/cutting/tet_cutter.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <limits>
#include <numeric>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::cutting {
namespace {

using Eigen::Vector3d;
using models::SweptQuad;

struct Organ {
  mesh::TetMesh mesh;
  mesh::BoundingBox box;
};

Organ Load(const std::string& name) {
  Organ o;
  o.mesh = mesh_gen::GenerateBuiltinOrganVolume(name);
  o.box = mesh::ComputeBoundingBox(o.mesh.vertices);
  return o;
}

// Connected components of the alive tetrahedra across shared faces.
int Components(const TetCutter& cutter, const mesh::Tetrahedra& tets) {
  const auto nb = mesh::TetFaceNeighbours(cutter.num_nodes(), tets);
  std::vector<int> label(static_cast<size_t>(tets.cols()), -1);
  int count = 0;
  std::vector<int32_t> stack;
  for (Eigen::Index t = 0; t < tets.cols(); ++t) {
    if (!cutter.alive(static_cast<int32_t>(t)) || label[static_cast<size_t>(t)] >= 0) continue;
    stack.push_back(static_cast<int32_t>(t));
    label[static_cast<size_t>(t)] = count;
    while (!stack.empty()) {
      const int32_t u = stack.back();
      stack.pop_back();
      for (int f = 0; f < 4; ++f) {
        const int32_t w = nb(f, u);
        if (w < 0 || !cutter.alive(w) || label[static_cast<size_t>(w)] >= 0) continue;
        label[static_cast<size_t>(w)] = count;
        stack.push_back(w);
      }
    }
    ++count;
  }
  return count;
}

// Everything a cut must never break; `what` names the moment in failures.
void ExpectSound(const TetCutter& cutter, const mesh::Tetrahedra& tets, const mesh::Points& x,
                 int32_t num_nodes, const std::string& what) {
  ASSERT_EQ(x.cols(), num_nodes) << what;
  std::vector<int32_t> alive_per_node(static_cast<size_t>(num_nodes), 0);
  int32_t alive = 0;
  for (Eigen::Index t = 0; t < tets.cols(); ++t) {
    if (!cutter.alive(static_cast<int32_t>(t))) continue;
    ++alive;
    for (int k = 0; k < 4; ++k) ++alive_per_node[static_cast<size_t>(tets(k, t))];
    const double v = mesh::TetSignedVolume(x.col(tets(0, t)), x.col(tets(1, t)), x.col(tets(2, t)),
                                           x.col(tets(3, t)));
    ASSERT_GT(v, 0.0) << what << ": tetrahedron " << t << " inverted or flat";
  }
  EXPECT_EQ(alive, cutter.num_alive()) << what;
  for (int32_t v = 0; v < num_nodes; ++v) {
    ASSERT_GT(alive_per_node[static_cast<size_t>(v)], 0) << what << ": node " << v << " orphaned";
  }
  ASSERT_TRUE(x.allFinite()) << what;
  mesh::SurfaceMesh surface;
  surface.vertices = x;
  std::vector<uint8_t> inner;
  cutter.ExtractSurface(&surface.triangles, &inner);
  const mesh::SurfaceTopology topo = mesh::AnalyseSurfaceTopology(surface);
  EXPECT_EQ(topo.num_misoriented_edges, 0) << what;
  EXPECT_EQ(topo.num_degenerate_triangles, 0) << what;
  EXPECT_EQ(topo.num_boundary_edges, 0) << what << ": the surface of a solid is closed";
  EXPECT_EQ(topo.num_nonmanifold_edges, 0) << what;
  EXPECT_EQ(topo.num_nonmanifold_vertices, 0) << what;
}

// The plate's blade: vertical, through the whole thickness, at (x, y).
SweptQuad Vertical(const Organ& o, double x0, double y0, double x1, double y1) {
  const double below = o.box.min.z() - 0.002, above = o.box.max.z() + 0.002;
  return {Vector3d(x0, y0, below), Vector3d(x0, y0, above), Vector3d(x1, y1, below),
          Vector3d(x1, y1, above)};
}

TEST(TetCutter, AStraightCutFromAnEdgeOpensASlitOnTheBladesPlaneKeepingEveryVertex) {
  const Organ plate = Load("plate192");
  mesh::Points x = plate.mesh.vertices;
  TetCutter cutter(plate.mesh.tetrahedra, x);
  const double y = plate.box.min.y() + 0.5 * (plate.box.max.y() - plate.box.min.y()) + 0.0013;
  const double x_start = plate.box.min.x() - 0.005;
  const double x_end = plate.box.min.x() + 0.5 * (plate.box.max.x() - plate.box.min.x());
  int removed = 0;
  for (double a = x_start; a < x_end; a += 0.004) {  // 4 mm per step
    const CutStepResult r = cutter.Step(Vertical(plate, a, y, a + 0.004, y), &x);
    removed += r.removed;
    ExpectSound(cutter, plate.mesh.tetrahedra, x, 192, "step at x " + std::to_string(a));
  }
  EXPECT_GT(removed, 5);
  EXPECT_EQ(cutter.topology_version() > 0, true);
  EXPECT_EQ(Components(cutter, plate.mesh.tetrahedra), 1);  // cut half-way: one piece
  // The inner faces lie on the blade's plane (their vertices were projected by eq. 1).
  mesh::Triangles triangles;
  std::vector<uint8_t> inner;
  cutter.ExtractSurface(&triangles, &inner);
  int inner_faces = 0, on_plane = 0;
  for (Eigen::Index i = 0; i < triangles.cols(); ++i) {
    if (inner[static_cast<size_t>(i)] == 0) continue;
    ++inner_faces;
    bool all = true;
    for (int k = 0; k < 3; ++k) all = all && std::abs(x(1, triangles(k, i)) - y) < 1e-9;
    on_plane += all ? 1 : 0;
  }
  EXPECT_GT(inner_faces, 10);
  // Most: a move the inversion guard shortened leaves its faces near the plane, not on it.
  EXPECT_GE(on_plane, inner_faces * 8 / 10) << "inner faces off the blade's plane";
  // Nothing moved beyond where the blade went (eq. 2): no relocated vertex past the tip's end.
  for (Eigen::Index v = 0; v < x.cols(); ++v) {
    if ((x.col(v) - plate.mesh.vertices.col(v)).norm() > 0.0) {
      EXPECT_LE(x(0, v), x_end + 0.004 + 1e-9) << v;
    }
  }
}

TEST(TetCutter, ACompleteCutSeparatesThePlateIntoTwoClosedPieces) {
  const Organ plate = Load("plate192");
  mesh::Points x = plate.mesh.vertices;
  TetCutter cutter(plate.mesh.tetrahedra, x);
  const double y = plate.box.min.y() + 0.37 * (plate.box.max.y() - plate.box.min.y());
  for (double a = plate.box.min.x() - 0.005; a < plate.box.max.x() + 0.005; a += 0.004) {
    cutter.Step(Vertical(plate, a, y, a + 0.004, y), &x);
  }
  ExpectSound(cutter, plate.mesh.tetrahedra, x, 192, "after the complete cut");
  EXPECT_EQ(Components(cutter, plate.mesh.tetrahedra), 2);
}

TEST(TetCutter, AnObliquePartialDepthCutFromMidFaceLeavesOnePiece) {
  const Organ plate = Load("plate192");
  mesh::Points x = plate.mesh.vertices;
  TetCutter cutter(plate.mesh.tetrahedra, x);
  const double cx = 0.5 * (plate.box.min.x() + plate.box.max.x());
  const double cy = 0.5 * (plate.box.min.y() + plate.box.max.y());
  const double depth = 0.6 * (plate.box.max.z() - plate.box.min.z());
  // The blade tilted 30° from vertical, its tip 60 % of the thickness deep, from the middle of
  // the top face towards +x for 6 cm.
  const Vector3d up(0.5, 0.0, std::sqrt(3.0) / 2.0);
  int removed = 0;
  for (double a = 0.0; a < 0.06; a += 0.003) {
    const Vector3d p0(cx + a, cy, plate.box.max.z() - depth);
    const Vector3d p1(cx + a + 0.003, cy, plate.box.max.z() - depth);
    removed += cutter.Step({p0, p0 + 0.02 * up, p1, p1 + 0.02 * up}, &x).removed;
    ExpectSound(cutter, plate.mesh.tetrahedra, x, 192, "oblique step " + std::to_string(a));
  }
  EXPECT_GT(removed, 0);
  EXPECT_EQ(Components(cutter, plate.mesh.tetrahedra), 1);
}

TEST(TetCutter, RelocatesOntoTheSweepAndOntoItsBoundaryOutsideIt) {
  // One tetrahedron's worth of mesh: a cube of 5 × 6 tetrahedra... simpler: the plate, one step
  // whose blade stops inside it: every moved interior vertex is on the sweep's plane (eq. 1) and
  // within the swept quad or on its boundary (eq. 2).
  const Organ plate = Load("plate192");
  mesh::Points x = plate.mesh.vertices;
  TetCutter cutter(plate.mesh.tetrahedra, x);
  const double cx = 0.5 * (plate.box.min.x() + plate.box.max.x());
  const double cy = 0.5 * (plate.box.min.y() + plate.box.max.y()) + 0.0021;
  const SweptQuad s = Vertical(plate, cx - 0.02, cy, cx + 0.01, cy);
  const CutStepResult r = cutter.Step(s, &x);
  ASSERT_GT(r.removed, 0);
  ASSERT_GT(r.relocated, 0);
  for (const int32_t v : cutter.moved_nodes()) {
    if (cutter.on_surface(v)) continue;
    EXPECT_NEAR(x(1, v), cy, 1e-12) << v;        // eq. 1: on the plane y = cy
    EXPECT_GE(x(0, v), cx - 0.02 - 1e-12) << v;  // eq. 2: within the sweep
    EXPECT_LE(x(0, v), cx + 0.01 + 1e-12) << v;
  }
}

TEST(TetCutter, RandomBladePathsNeverBreakAnyVolumeOrgan) {
  // Every built-in volume organ: the small ones with 400 paths each, the 19k-element liver and
  // beam with 60 (the sanitizer build: the two smallest, 40 paths each).
  const std::vector<std::string> organs =
      testing::kUnderSanitizer
          ? std::vector<std::string>{"plate192", "liver288"}
          : std::vector<std::string>{"plate192", "liver288", "kidney424", "liver4055", "beam19k"};
  std::mt19937_64 rng(20261123);
  for (const std::string& name : organs) {
    const int paths = testing::kUnderSanitizer                     ? 40
                      : (name == "liver4055" || name == "beam19k") ? 60
                                                                   : 400;
    const Organ o = Load(name);
    const Vector3d lo = o.box.min, hi = o.box.max;
    const Vector3d size = hi - lo;
    // Blades in proportion to the organ (the beam is 16 m long, the organs 5–25 cm).
    const double scale = std::max(1.0, size.maxCoeff() / 0.25);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    const auto random_point = [&] {
      return Vector3d(lo.x() + u(rng) * size.x(), lo.y() + u(rng) * size.y(),
                      lo.z() + u(rng) * size.z());
    };
    int total_removed = 0;
    int undone_steps = 0, total_steps = 0;
    for (int path = 0; path < paths; ++path) {
      mesh::Points x = o.mesh.vertices;
      TetCutter cutter(o.mesh.tetrahedra, x);
      // A blade of 1–4 cm moving 5–15 steps of up to 5 mm, turning as it goes.
      Vector3d p = random_point();
      Vector3d dir = Vector3d::Random().normalized();
      const double length = scale * (0.01 + 0.03 * u(rng));
      Vector3d heading = Vector3d::Random().normalized();
      const int steps = 5 + static_cast<int>(u(rng) * 10);
      int unresolved = 0;
      for (int k = 0; k < steps; ++k) {
        const Vector3d p1 = p + scale * 0.005 * u(rng) * heading;
        const Vector3d dir1 = (dir + 0.2 * Vector3d::Random()).normalized();
        const CutStepResult r = cutter.Step({p, p + length * dir, p1, p1 + length * dir1}, &x);
        total_removed += r.removed;
        unresolved += r.undone ? 1 : 0;
        p = p1;
        dir = dir1;
        heading = (heading + 0.3 * Vector3d::Random()).normalized();
      }
      ExpectSound(cutter, o.mesh.tetrahedra, x, static_cast<int32_t>(o.mesh.vertices.cols()),
                  name + " path " + std::to_string(path) + " (" + std::to_string(unresolved) +
                      " steps undone)");
      undone_steps += unresolved;
      total_steps += steps;
      if (::testing::Test::HasFatalFailure()) return;
    }
    EXPECT_GT(total_removed, paths) << name << ": the blades cut little";
    // A step is undone only where no removal keeps the boundary a manifold: rarely.
    EXPECT_LT(undone_steps, total_steps / 20) << name;
    std::printf("%s: %d paths, %d steps, %d tetrahedra removed, %d steps undone\n", name.c_str(),
                paths, total_steps, total_removed, undone_steps);
  }
}

TEST(TetCutter, BladeStepsAllocateNothing) {
  const Organ plate = Load("plate192");
  mesh::Points x = plate.mesh.vertices;
  TetCutter cutter(plate.mesh.tetrahedra, x);
  const double y = 0.5 * (plate.box.min.y() + plate.box.max.y()) + 0.0007;
  cutter.Step(Vertical(plate, plate.box.min.x() - 0.01, y, plate.box.min.x(), y), &x);
  int removed = 0;
  {
    testing::AllocationCounter counter;
    for (double a = plate.box.min.x(); a < plate.box.max.x(); a += 0.004) {
      removed += cutter.Step(Vertical(plate, a, y, a + 0.004, y), &x).removed;
    }
    EXPECT_EQ(counter.count(), 0);
  }
  EXPECT_GT(removed, 10);
}

TEST(TetCutter, RefusesBadMeshesAndIgnoresBadSweeps) {
  const Organ plate = Load("plate192");
  mesh::Tetrahedra bad = plate.mesh.tetrahedra;
  bad(2, 5) = 192;
  EXPECT_THROW(TetCutter(bad, plate.mesh.vertices), std::invalid_argument);
  bad(2, 5) = -1;
  EXPECT_THROW(TetCutter(bad, plate.mesh.vertices), std::invalid_argument);
  EXPECT_THROW(TetCutter(plate.mesh.tetrahedra, plate.mesh.vertices, CutSettings{1.5}),
               std::invalid_argument);
  mesh::Points x = plate.mesh.vertices;
  TetCutter cutter(plate.mesh.tetrahedra, x);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  SweptQuad s = Vertical(plate, 0, 0, 0.01, 0);
  s.q1.x() = nan;
  EXPECT_EQ(cutter.Step(s, &x).cut, 0);
  // A blade that did not move sweeps nothing.
  const SweptQuad still = Vertical(plate, 0.0, 0.0, 0.0, 0.0);
  EXPECT_EQ(cutter.Step(still, &x).cut, 0);
  mesh::Points wrong(3, 10);
  wrong.setZero();
  EXPECT_EQ(cutter.Step(Vertical(plate, -1, 0, 1, 0), &wrong).cut, 0);
  EXPECT_EQ(cutter.num_alive(), plate.mesh.tetrahedra.cols());
  EXPECT_TRUE(x == plate.mesh.vertices);
}

}  // namespace
}  // namespace somasim::cutting
