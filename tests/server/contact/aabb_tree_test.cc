// The AABB tree against brute force over every triangle (random soups, a sphere-like closed
// surface, the gallbladder5400 surface, kidney424's boundary), before and after deformation and
// refit; watertight segment crossings of closed surfaces; allocation-free refit and queries; bad
// inputs.
#include "server/contact/aabb_tree.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "server/contact/triangle_queries.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::contact {
namespace {

using Eigen::Vector3d;
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// ---------------------------------------------------------------- meshes

// Random triangle soup: `count` triangles over count / 2 + 3 random vertices in a cube of side
// `size` [m], shared at random; `small` makes each triangle a local one (vertices near a centre).
mesh::SurfaceMesh RandomSoup(uint32_t seed, int count, double size, bool small) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, size);
  std::normal_distribution<double> jitter(0.0, 0.02 * size);
  mesh::SurfaceMesh m;
  if (small) {
    m.vertices.resize(3, 3 * count);
    m.triangles.resize(3, count);
    for (int j = 0; j < count; ++j) {
      const Vector3d centre(u(rng), u(rng), u(rng));
      for (int k = 0; k < 3; ++k) {
        m.vertices.col(3 * j + k) = centre + Vector3d(jitter(rng), jitter(rng), jitter(rng));
        m.triangles(k, j) = 3 * j + k;
      }
    }
    return m;
  }
  const int n = count / 2 + 3;
  m.vertices.resize(3, n);
  for (int i = 0; i < n; ++i) m.vertices.col(i) = Vector3d(u(rng), u(rng), u(rng));
  std::uniform_int_distribution<int32_t> index(0, n - 1);
  m.triangles.resize(3, count);
  for (int j = 0; j < count; ++j) {
    for (int k = 0; k < 3; ++k) m.triangles(k, j) = index(rng);
  }
  return m;
}

// Icosphere of radius `radius` [m] around `centre`, `levels` subdivisions (20 · 4^levels
// triangles, outward), each vertex's radius scaled by 1 + bump · (smooth function): closed and
// manifold.
mesh::SurfaceMesh Icosphere(int levels, double radius, const Vector3d& centre, double bump) {
  const double g = (1.0 + std::sqrt(5.0)) / 2.0;
  std::vector<Vector3d> v = {{-1, g, 0}, {1, g, 0}, {-1, -g, 0}, {1, -g, 0},
                             {0, -1, g}, {0, 1, g}, {0, -1, -g}, {0, 1, -g},
                             {g, 0, -1}, {g, 0, 1}, {-g, 0, -1}, {-g, 0, 1}};
  std::vector<std::array<int32_t, 3>> f = {
      {0, 11, 5},  {0, 5, 1},  {0, 1, 7},  {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
      {11, 10, 2}, {10, 7, 6}, {7, 1, 8},  {3, 9, 4},  {3, 4, 2},   {3, 2, 6}, {3, 6, 8},
      {3, 8, 9},   {4, 9, 5},  {2, 4, 11}, {6, 2, 10}, {8, 6, 7},   {9, 8, 1}};
  for (Vector3d& x : v) x.normalize();
  for (int level = 0; level < levels; ++level) {
    std::map<std::pair<int32_t, int32_t>, int32_t> midpoints;
    auto midpoint = [&](int32_t i, int32_t j) {
      const auto key = std::minmax(i, j);
      const auto it = midpoints.find(key);
      if (it != midpoints.end()) return it->second;
      v.push_back((v[static_cast<size_t>(i)] + v[static_cast<size_t>(j)]).normalized());
      const auto id = static_cast<int32_t>(v.size() - 1);
      midpoints.emplace(key, id);
      return id;
    };
    std::vector<std::array<int32_t, 3>> next;
    for (const auto& t : f) {
      const int32_t a = midpoint(t[0], t[1]);
      const int32_t b = midpoint(t[1], t[2]);
      const int32_t c = midpoint(t[2], t[0]);
      next.push_back({t[0], a, c});
      next.push_back({t[1], b, a});
      next.push_back({t[2], c, b});
      next.push_back({a, b, c});
    }
    f = std::move(next);
  }
  mesh::SurfaceMesh m;
  m.vertices.resize(3, static_cast<Eigen::Index>(v.size()));
  for (size_t i = 0; i < v.size(); ++i) {
    const Vector3d& x = v[i];
    const double r = radius * (1.0 + bump * std::sin(3.0 * x.x() + 1.0) * std::cos(2.0 * x.y()));
    m.vertices.col(static_cast<Eigen::Index>(i)) = centre + r * x;
  }
  m.triangles.resize(3, static_cast<Eigen::Index>(f.size()));
  for (size_t j = 0; j < f.size(); ++j) {
    for (int k = 0; k < 3; ++k)
      m.triangles(k, static_cast<Eigen::Index>(j)) = f[j][static_cast<size_t>(k)];
  }
  return m;
}

mesh::SurfaceMesh Gallbladder() {
  return mesh_gen::GenerateBuiltinOrgan("gallbladder5400").surface;
}

// kidney424's boundary in the volume's numbering (interior vertices unreferenced), as the
// contact pipeline sees an FEM organ.
mesh::SurfaceMesh KidneyBoundary() {
  return mesh::ExtractBoundarySurface(mesh_gen::GenerateBuiltinOrgan("kidney424").volume);
}

struct Bounds {
  Vector3d lo;
  Vector3d hi;
  double size() const { return (hi - lo).maxCoeff(); }
};
Bounds BoundsOf(const mesh::Points& x) {
  return Bounds{x.rowwise().minCoeff(), x.rowwise().maxCoeff()};
}

// A smooth random displacement field (three sine modes), amplitude ~ `amplitude` [m].
mesh::Points Deformed(const mesh::Points& x, uint32_t seed, double amplitude) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const double size = BoundsOf(x).size();
  mesh::Points y = x;
  for (int mode = 0; mode < 3; ++mode) {
    const Vector3d k = Vector3d(u(rng), u(rng), u(rng)) * (2.0 * std::numbers::pi / size);
    const Vector3d a = Vector3d(u(rng), u(rng), u(rng)) * amplitude;
    const double phase = 3.0 * u(rng);
    for (Eigen::Index i = 0; i < x.cols(); ++i) {
      y.col(i) += a * std::sin(k.dot(x.col(i)) + phase);
    }
  }
  return y;
}

// ---------------------------------------------------------------- brute force

struct Tri {
  Vector3d a, b, c;
};
Tri TriangleAt(const mesh::Points& x, const mesh::Triangles& t, int32_t j) {
  return Tri{x.col(t(0, j)), x.col(t(1, j)), x.col(t(2, j))};
}

SegmentHit BruteFirstHit(const mesh::Points& x, const mesh::Triangles& tris, const Vector3d& p,
                         const Vector3d& q) {
  SegmentHit best;
  best.t = kInf;
  for (int32_t j = 0; j < tris.cols(); ++j) {
    const Tri k = TriangleAt(x, tris, j);
    double t = 0.0;
    Vector3d w;
    if (SegmentTriangleIntersection(p, q, k.a, k.b, k.c, &t, &w) && t < best.t) {
      best.triangle = j;
      best.t = t;
      best.barycentric = w;
    }
  }
  return best;
}

SurfacePoint BruteNearest(const mesh::Points& x, const mesh::Triangles& tris, const Vector3d& y,
                          double max_distance) {
  SurfacePoint best;
  double best_d2 = max_distance * max_distance;
  for (int32_t j = 0; j < tris.cols(); ++j) {
    const Tri k = TriangleAt(x, tris, j);
    Vector3d w;
    const double d2 = PointTriangleDistanceSquared(y, k.a, k.b, k.c, &w);
    if (d2 < best_d2 || (d2 == best_d2 && best.triangle < 0)) {
      best_d2 = d2;
      best.triangle = j;
      best.barycentric = w;
      best.distance = std::sqrt(d2);
    }
  }
  return best;
}

SurfacePoint BruteNearestToSegment(const mesh::Points& x, const mesh::Triangles& tris,
                                   const Vector3d& p, const Vector3d& q, double radius) {
  SurfacePoint best;
  double best_d2 = radius * radius;
  for (int32_t j = 0; j < tris.cols(); ++j) {
    const Tri k = TriangleAt(x, tris, j);
    double s = 0.0;
    Vector3d w;
    const double d2 = SegmentTriangleDistanceSquared(p, q, k.a, k.b, k.c, &s, &w);
    if (d2 < best_d2 || (d2 == best_d2 && best.triangle < 0)) {
      best_d2 = d2;
      best.triangle = j;
      best.barycentric = w;
      best.distance = std::sqrt(d2);
    }
  }
  return best;
}

std::vector<int32_t> BruteSphere(const mesh::Points& x, const mesh::Triangles& tris,
                                 const Vector3d& c, double r) {
  std::vector<int32_t> found;
  for (int32_t j = 0; j < tris.cols(); ++j) {
    const Tri k = TriangleAt(x, tris, j);
    Vector3d w;
    if (PointTriangleDistanceSquared(c, k.a, k.b, k.c, &w) <= r * r) found.push_back(j);
  }
  return found;
}

std::vector<int32_t> BruteCapsule(const mesh::Points& x, const mesh::Triangles& tris,
                                  const Vector3d& p, const Vector3d& q, double r) {
  std::vector<int32_t> found;
  for (int32_t j = 0; j < tris.cols(); ++j) {
    const Tri k = TriangleAt(x, tris, j);
    double s = 0.0;
    Vector3d w;
    if (SegmentTriangleDistanceSquared(p, q, k.a, k.b, k.c, &s, &w) <= r * r) found.push_back(j);
  }
  return found;
}

std::vector<int32_t> Sorted(std::vector<int32_t> v) {
  std::sort(v.begin(), v.end());
  return v;
}

// Every query of `tree` against brute force over `x` at `count` random poses: long and short
// segments, points inside and around the bounds, radii from 0 to 20 % of the size.
void ExpectQueriesEqualBruteForce(const AabbTree& tree, const mesh::Points& x,
                                  const mesh::Triangles& tris, uint32_t seed, int count) {
  // Fewer poses in the (slow) sanitizer build; the Release build runs them all.
  if (testing::kUnderSanitizer) count = std::max(20, count / 6);
  std::mt19937 rng(seed);
  const Bounds box = BoundsOf(x);
  const double size = box.size();
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  auto point = [&] {
    const Vector3d f(unit(rng), unit(rng), unit(rng));
    return Vector3d(box.lo + (box.hi - box.lo).cwiseProduct(1.4 * f - Vector3d::Constant(0.2)));
  };
  auto near_surface = [&] {
    const auto j = static_cast<int32_t>(unit(rng) * static_cast<double>(tris.cols() - 1));
    const Tri k = TriangleAt(x, tris, j);
    const Vector3d offset(unit(rng) - 0.5, unit(rng) - 0.5, unit(rng) - 0.5);
    return Vector3d((k.a + k.b + k.c) / 3.0 + 0.05 * size * offset);
  };
  std::vector<int32_t> out(static_cast<size_t>(tris.cols()));
  int hits = 0;
  for (int trial = 0; trial < count; ++trial) {
    const double length = trial % 3 == 0 ? size : 0.05 * size;
    const Vector3d dir(unit(rng) - 0.5, unit(rng) - 0.5, unit(rng) - 0.5);
    Vector3d p = trial % 2 == 0 ? point() : near_surface();
    if (trial % 4 == 1) {
      // Through a random point of a random triangle, so small triangles get crossed too.
      const auto j = static_cast<int32_t>(unit(rng) * static_cast<double>(tris.cols() - 1));
      const Tri k = TriangleAt(x, tris, j);
      const double v = unit(rng);
      const double w = (1.0 - v) * unit(rng);
      p = (1.0 - v - w) * k.a + v * k.b + w * k.c - (0.3 + 0.4 * unit(rng)) * length * dir;
    }
    const Vector3d q = p + length * dir;
    const double radius = 0.2 * size * unit(rng) * unit(rng);

    SegmentHit hit;
    const SegmentHit expected_hit = BruteFirstHit(x, tris, p, q);
    ASSERT_EQ(tree.FirstHit(p, q, &hit), expected_hit.triangle >= 0) << "trial " << trial;
    if (expected_hit.triangle >= 0) {
      ++hits;
      EXPECT_EQ(hit.triangle, expected_hit.triangle);
      EXPECT_EQ(hit.t, expected_hit.t);
      EXPECT_EQ(hit.barycentric, expected_hit.barycentric);
      EXPECT_LT((hit.point - (p + hit.t * (q - p))).norm(), 1e-15);
    }

    for (const double max_distance : {kInf, radius}) {
      SurfacePoint nearest;
      const SurfacePoint expected = BruteNearest(x, tris, p, max_distance);
      ASSERT_EQ(tree.Nearest(p, &nearest, max_distance), expected.triangle >= 0);
      if (expected.triangle >= 0) {
        EXPECT_EQ(nearest.triangle, expected.triangle);
        EXPECT_EQ(nearest.distance, expected.distance);
        EXPECT_EQ(nearest.barycentric, expected.barycentric);
        const Tri k = TriangleAt(x, tris, nearest.triangle);
        const Vector3d& w = nearest.barycentric;
        EXPECT_GE(w.minCoeff(), 0.0);
        EXPECT_LE(w.maxCoeff(), 1.0);
        EXPECT_NEAR(w.sum(), 1.0, 1e-12);
        EXPECT_LT((nearest.point - (w.x() * k.a + w.y() * k.b + w.z() * k.c)).norm(), 1e-15);
        EXPECT_NEAR((nearest.point - p).norm(), nearest.distance, 1e-12 * size);
      }
    }

    SurfacePoint nearest;
    const SurfacePoint expected = BruteNearestToSegment(x, tris, p, q, radius);
    ASSERT_EQ(tree.NearestToSegment(p, q, radius, &nearest), expected.triangle >= 0);
    if (expected.triangle >= 0) {
      EXPECT_EQ(nearest.triangle, expected.triangle);
      EXPECT_EQ(nearest.distance, expected.distance);
      EXPECT_EQ(nearest.barycentric, expected.barycentric);
      EXPECT_LE(nearest.distance, radius);
    }

    const int32_t in_sphere = tree.SphereQuery(p, radius, out);
    ASSERT_LE(in_sphere, static_cast<int32_t>(out.size()));
    EXPECT_EQ(Sorted({out.begin(), out.begin() + in_sphere}), BruteSphere(x, tris, p, radius));
    const int32_t in_capsule = tree.CapsuleQuery(p, q, radius, out);
    ASSERT_LE(in_capsule, static_cast<int32_t>(out.size()));
    EXPECT_EQ(Sorted({out.begin(), out.begin() + in_capsule}), BruteCapsule(x, tris, p, q, radius));
  }
  EXPECT_GT(hits, count / 20) << "too few segment hits to test FirstHit";
}

void ExpectEqualBruteForceBeforeAndAfterRefit(const mesh::SurfaceMesh& m, int count,
                                              int max_leaf = 4) {
  AabbTree tree(m.vertices, m.triangles, max_leaf);
  EXPECT_EQ(tree.num_triangles(), m.triangles.cols());
  EXPECT_LT(tree.max_depth(), AabbTree::kMaxDepth);
  ExpectQueriesEqualBruteForce(tree, m.vertices, m.triangles, 10, count);
  const double size = BoundsOf(m.vertices).size();
  for (uint32_t step = 0; step < 2; ++step) {
    const mesh::Points moved = Deformed(m.vertices, 100 + step, 0.05 * size);
    tree.Refit(moved);
    EXPECT_EQ(&tree.positions(), &moved);  // referenced, not copied
    ExpectQueriesEqualBruteForce(tree, moved, m.triangles, 20 + step, count);
  }
}

// ---------------------------------------------------------------- tests

TEST(AabbTree, QueriesEqualBruteForceOnRandomSoups) {
  ExpectEqualBruteForceBeforeAndAfterRefit(RandomSoup(1, 300, 0.1, false), 150);
  ExpectEqualBruteForceBeforeAndAfterRefit(RandomSoup(2, 2000, 0.1, true), 150);
  ExpectEqualBruteForceBeforeAndAfterRefit(RandomSoup(3, 500, 0.1, true), 100, 1);
  ExpectEqualBruteForceBeforeAndAfterRefit(RandomSoup(4, 500, 0.1, true), 100, 9);
}

TEST(AabbTree, QueriesEqualBruteForceOnASphereLikeClosedSurface) {
  // Long under the sanitizer (10-35 s): the Release build runs it (CI tiers).
  if (testing::kUnderSanitizer) GTEST_SKIP() << "long: Release only";
  ExpectEqualBruteForceBeforeAndAfterRefit(Icosphere(4, 0.04, Vector3d(0.01, -0.02, 0.03), 0.2),
                                           150);
}

TEST(AabbTree, QueriesEqualBruteForceOnGallbladder5400) {
  // Long under the sanitizer (10-35 s): the Release build runs it (CI tiers).
  if (testing::kUnderSanitizer) GTEST_SKIP() << "long: Release only";
  ExpectEqualBruteForceBeforeAndAfterRefit(Gallbladder(), 80);
}

TEST(AabbTree, QueriesEqualBruteForceOnKidney424Boundary) {
  ExpectEqualBruteForceBeforeAndAfterRefit(KidneyBoundary(), 150);
}

// Meshes that defeat the midpoint split (every centroid equal; centroids at 2^-k, which halves
// one side per level) still build with a bounded depth and answer like brute force.
// Refit's portable leaf pass (taken on CPUs without AVX2) answers like brute force too.
TEST(AabbTree, PortableRefitPathAnswersExactly) {
  const mesh::SurfaceMesh m = KidneyBoundary();
  AabbTree tree(m.vertices, m.triangles);
  const mesh::Points moved = Deformed(m.vertices, 7, 0.004);
  SetAabbRefitAvx2ForTesting(false);
  tree.Refit(moved);
  SetAabbRefitAvx2ForTesting(true);
  ExpectQueriesEqualBruteForce(tree, moved, m.triangles, 30, 100);
}

// Every node's single-precision box is exactly its triangles' box computed afresh (the double
// min / max of their vertices rounded outwards), so it contains them, after the build and after
// refits by either leaf pass (AVX2: leaves in pairs padded with repeated vertices, the parents of
// leaf pairs fitted there too, the last vertex loaded masked; portable: leaf by leaf). Meshes
// with odd numbers of leaves, single-triangle leaves, degenerate triangles, a lone triangle, and
// coordinates from 1e-20 m to 1e20 m of both signs (the outward rounding).
TEST(AabbTree, EveryBoxIsItsTrianglesBoxRoundedOutwardsAfterBuildAndRefit) {
  auto expect_exact_boxes = [](const mesh::SurfaceMesh& m, int max_leaf, const std::string& name) {
    SCOPED_TRACE(name + ", leaves of " + std::to_string(max_leaf));
    AabbTree tree(m.vertices, m.triangles, max_leaf);
    EXPECT_EQ(tree.CountBoxMismatchesForTesting(), 0);
    const double size = BoundsOf(m.vertices).size();
    const mesh::Points moved = Deformed(m.vertices, 11, 0.05 * size);
    tree.Refit(moved);
    EXPECT_EQ(tree.CountBoxMismatchesForTesting(), 0);
    SetAabbRefitAvx2ForTesting(false);
    tree.Refit(m.vertices);
    EXPECT_EQ(tree.CountBoxMismatchesForTesting(), 0);
    tree.Refit(moved);
    SetAabbRefitAvx2ForTesting(true);
    EXPECT_EQ(tree.CountBoxMismatchesForTesting(), 0);
    tree.Refit(m.vertices);
    EXPECT_EQ(tree.CountBoxMismatchesForTesting(), 0);
  };
  expect_exact_boxes(KidneyBoundary(), 8, "kidney424");
  expect_exact_boxes(KidneyBoundary(), 3, "kidney424");
  expect_exact_boxes(Gallbladder(), 8, "gallbladder5400");
  for (const int max_leaf : {1, 2, 5, 8}) {
    expect_exact_boxes(RandomSoup(21, 301, 0.1, true), max_leaf, "soup");
    expect_exact_boxes(RandomSoup(22, 77, 0.1, false), max_leaf, "loose soup");
  }
  // Degenerate triangles (a point, a segment) among ordinary ones.
  mesh::SurfaceMesh degenerate = RandomSoup(23, 100, 0.1, true);
  for (int j = 0; j < 100; j += 7)
    degenerate.triangles.col(j).setConstant(degenerate.triangles(0, j));
  for (int j = 3; j < 100; j += 11) degenerate.triangles(2, j) = degenerate.triangles(1, j);
  expect_exact_boxes(degenerate, 8, "degenerate");
  expect_exact_boxes(degenerate, 1, "degenerate");
  mesh::SurfaceMesh lone = RandomSoup(24, 1, 0.1, false);
  expect_exact_boxes(lone, 8, "one triangle");
  // Scales where float rounding is coarse or fine, zeros and both signs.
  for (const double scale : {1e-20, 1e-3, 1e20}) {
    mesh::SurfaceMesh scaled = RandomSoup(25, 200, 2.0, false);
    scaled.vertices = (scaled.vertices.array() - 1.0) * scale;
    scaled.vertices.col(0).setZero();
    scaled.vertices(1, 1) = 0.0;
    expect_exact_boxes(scaled, 4, "scale " + std::to_string(scale));
  }
}

// FirstHit's pruning (the segment's grown box against node and triangle boxes, then slabs)
// never drops a crossing at the very end of a segment: segments that start or end exactly on a
// vertex or an edge midpoint, along random and axis directions, at scales from 1e-20 m to
// 1e20 m, answer like brute force.
TEST(AabbTree, FirstHitFindsCrossingsAtTheSegmentsEnds) {
  const mesh::SurfaceMesh kidney = KidneyBoundary();
  std::mt19937 rng(31);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::uniform_int_distribution<int32_t> pick(0, static_cast<int32_t>(kidney.triangles.cols()) - 1);
  for (const double scale : {1e-20, 1.0, 1e20}) {
    const mesh::Points x = kidney.vertices * scale;
    const AabbTree tree(x, kidney.triangles);
    const double size = BoundsOf(x).size();
    int hits = 0;
    for (int i = 0; i < 300; ++i) {
      const auto tri = kidney.triangles.col(pick(rng));
      const Vector3d end =
          i % 2 == 0 ? Vector3d(x.col(tri[0])) : Vector3d(0.5 * (x.col(tri[0]) + x.col(tri[1])));
      Vector3d dir = i % 3 == 0 ? Vector3d::Unit(i % 9 / 3) : Vector3d(u(rng), u(rng), u(rng));
      dir *= 1e-3 * size * (u(rng) < 0.0 ? -1.0 : 1.0);
      for (const bool ends_there : {true, false}) {
        const Vector3d p = ends_there ? Vector3d(end + dir) : end;
        const Vector3d q = ends_there ? end : Vector3d(end + dir);
        const SegmentHit expected = BruteFirstHit(x, kidney.triangles, p, q);
        SegmentHit hit;
        ASSERT_EQ(tree.FirstHit(p, q, &hit), expected.triangle >= 0) << scale << " " << i;
        if (expected.triangle < 0) continue;
        ++hits;
        EXPECT_EQ(hit.triangle, expected.triangle);
        EXPECT_EQ(hit.t, expected.t);
      }
    }
    EXPECT_GT(hits, 300) << "too few end crossings at scale " << scale;
  }
}

TEST(AabbTree, DegenerateMeshesKeepTheDepthBoundAndAnswerExactly) {
  mesh::SurfaceMesh same;
  same.vertices.resize(3, 3);
  same.vertices << 0.0, 0.01, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 0.0;
  same.triangles.resize(3, 500);
  for (int j = 0; j < 500; ++j) same.triangles.col(j) << 0, 1, 2;
  {
    const AabbTree tree(same.vertices, same.triangles);
    EXPECT_LT(tree.max_depth(), AabbTree::kMaxDepth);
    ExpectQueriesEqualBruteForce(tree, same.vertices, same.triangles, 5, 20);
  }
  mesh::SurfaceMesh geometric;
  const int n = 400;
  geometric.vertices.resize(3, 3 * n);
  geometric.triangles.resize(3, n);
  for (int j = 0; j < n; ++j) {
    const double x = std::ldexp(1.0, -j / 4);  // repeated 2^-k: midpoint splits peel one by one
    geometric.vertices.col(3 * j) = Vector3d(x, 0.0, 0.0);
    geometric.vertices.col(3 * j + 1) = Vector3d(x, 1e-3, 0.0);
    geometric.vertices.col(3 * j + 2) = Vector3d(x, 0.0, 1e-3);
    geometric.triangles.col(j) << 3 * j, 3 * j + 1, 3 * j + 2;
  }
  const AabbTree tree(geometric.vertices, geometric.triangles, 1);
  EXPECT_LT(tree.max_depth(), AabbTree::kMaxDepth);
  EXPECT_GE(tree.max_depth(), AabbTree::kMaxMidpointDepth);  // the fallback did engage
  ExpectQueriesEqualBruteForce(tree, geometric.vertices, geometric.triangles, 6, 100);
}

TEST(AabbTree, FirstHitIsTheSmallestParameterOfAllCrossings) {
  const mesh::SurfaceMesh m = Icosphere(3, 0.05, Vector3d::Zero(), 0.3);
  const AabbTree tree(m.vertices, m.triangles);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-0.1, 0.1);
  int multiple = 0;
  for (int trial = 0; trial < 500; ++trial) {
    const Vector3d p(u(rng), u(rng), u(rng));
    const Vector3d q(u(rng), u(rng), u(rng));
    SegmentHit hit;
    const bool found = tree.FirstHit(p, q, &hit);
    int crossings = 0;
    for (int32_t j = 0; j < m.triangles.cols(); ++j) {
      const Tri k = TriangleAt(m.vertices, m.triangles, j);
      double t = 0.0;
      Vector3d w;
      if (SegmentTriangleIntersection(p, q, k.a, k.b, k.c, &t, &w)) {
        ++crossings;
        ASSERT_TRUE(found);
        EXPECT_LE(hit.t, t);
      }
    }
    if (crossings > 1) ++multiple;
    EXPECT_EQ(found, crossings > 0);
  }
  EXPECT_GT(multiple, 50);
}

// Segments from inside a closed surface to outside always report a crossing: random ones, ones
// aimed through vertices and through edge midpoints.
void ExpectClosedSurfaceIsWatertight(const mesh::SurfaceMesh& m, const Vector3d& inside,
                                     double inner_radius, uint32_t seed) {
  const AabbTree tree(m.vertices, m.triangles);
  const Bounds box = BoundsOf(m.vertices);
  const double far = 2.0 * box.size();
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  int misses = 0;
  auto check = [&](const Vector3d& from, const Vector3d& through, double beyond) {
    const Vector3d to = from + (through - from) * beyond;
    SegmentHit hit;
    if (!tree.FirstHit(from, to, &hit)) ++misses;
    if (!tree.FirstHit(to, from, &hit)) ++misses;
  };
  for (int trial = 0; trial < 3000; ++trial) {
    const Vector3d from = inside + inner_radius * Vector3d(u(rng), u(rng), u(rng)) / 2.0;
    const Vector3d dir = Vector3d(u(rng), u(rng), u(rng)).normalized();
    check(from, from + far * dir, 1.0);
  }
  for (int32_t j = 0; j < m.triangles.cols(); ++j) {
    const Vector3d a = m.vertices.col(m.triangles(0, j));
    const Vector3d b = m.vertices.col(m.triangles(1, j));
    check(inside, a, 3.0);
    check(inside, 0.5 * (a + b), 3.0);
    check(inside, a, 1.0 + 1e-12);  // ending just past the vertex
  }
  EXPECT_EQ(misses, 0);
}

TEST(AabbTree, SegmentsCrossingAClosedIcosphereAlwaysHit) {
  ExpectClosedSurfaceIsWatertight(Icosphere(3, 0.05, Vector3d(0.003, -0.001, 0.002), 0.0),
                                  Vector3d(0.003, -0.001, 0.002), 0.02, 8);
  ExpectClosedSurfaceIsWatertight(Icosphere(2, 1.0, Vector3d::Zero(), 0.0), Vector3d::Zero(), 0.4,
                                  9);
}

// A cube of 4 × 4 squares a side with dyadic coordinates: segments exactly through its vertices
// and edges (axis-aligned and oblique, exactly representable) always hit.
TEST(AabbTree, SegmentsExactlyThroughVerticesAndEdgesOfACubeAlwaysHit) {
  const int n = 4;
  std::map<std::array<int, 3>, int32_t> index;
  std::vector<Vector3d> vertices;
  std::vector<std::array<int32_t, 3>> faces;
  auto vertex = [&](const std::array<int, 3>& g) {
    const auto it = index.find(g);
    if (it != index.end()) return it->second;
    vertices.emplace_back(0.25 * g[0], 0.25 * g[1], 0.25 * g[2]);
    const auto id = static_cast<int32_t>(vertices.size() - 1);
    index.emplace(g, id);
    return id;
  };
  for (int axis = 0; axis < 3; ++axis) {
    for (int side = 0; side <= n; side += n) {
      for (int i = 0; i < n; ++i) {
        for (int j = 0; j < n; ++j) {
          auto at = [&](int di, int dj) {
            std::array<int, 3> g{};
            g[static_cast<size_t>(axis)] = side;
            g[static_cast<size_t>((axis + 1) % 3)] = i + di;
            g[static_cast<size_t>((axis + 2) % 3)] = j + dj;
            return vertex(g);
          };
          // Alternate the diagonals so vertices have different fans.
          if ((i + j) % 2 == 0) {
            faces.push_back({at(0, 0), at(1, 0), at(1, 1)});
            faces.push_back({at(0, 0), at(1, 1), at(0, 1)});
          } else {
            faces.push_back({at(0, 0), at(1, 0), at(0, 1)});
            faces.push_back({at(1, 0), at(1, 1), at(0, 1)});
          }
        }
      }
    }
  }
  mesh::SurfaceMesh m;
  m.vertices.resize(3, static_cast<Eigen::Index>(vertices.size()));
  for (size_t i = 0; i < vertices.size(); ++i)
    m.vertices.col(static_cast<Eigen::Index>(i)) = vertices[i];
  m.triangles.resize(3, static_cast<Eigen::Index>(faces.size()));
  for (size_t j = 0; j < faces.size(); ++j) {
    for (int k = 0; k < 3; ++k)
      m.triangles(k, static_cast<Eigen::Index>(j)) = faces[j][static_cast<size_t>(k)];
  }
  const AabbTree tree(m.vertices, m.triangles);
  int tested = 0;
  int misses = 0;
  // Through every point of the bottom face's grid at half-steps (vertices, edge midpoints, face
  // centres), in directions with dyadic components so the lines are exact.
  const std::array<Vector3d, 5> dirs = {Vector3d(0, 0, 1), Vector3d(0.25, 0.5, 1),
                                        Vector3d(-0.5, 0.25, 1), Vector3d(0.5, 0.5, 1),
                                        Vector3d(-0.25, -0.75, 1)};
  for (int i = 1; i < 2 * n; ++i) {
    for (int j = 1; j < 2 * n; ++j) {
      const Vector3d x(0.125 * i, 0.125 * j, 0.0);
      for (const Vector3d& d : dirs) {
        SegmentHit hit;
        ++tested;
        if (!tree.FirstHit(x - 0.25 * d, x + 0.25 * d, &hit)) ++misses;
        if (!tree.FirstHit(x + 0.25 * d, x - 0.25 * d, &hit)) ++misses;
        if (tree.FirstHit(x - 0.25 * d, x + 0.25 * d, &hit)) {
          EXPECT_LT((hit.point - x).norm(), 1e-15);
        }
      }
    }
  }
  EXPECT_GT(tested, 200);
  EXPECT_EQ(misses, 0);
}

TEST(AabbTree, SegmentsCrossingTheGallbladderSurfaceThroughVerticesAlwaysHit) {
  const mesh::SurfaceMesh m = Gallbladder();
  const AabbTree tree(m.vertices, m.triangles);
  // Vertex normals (area-weighted, outward): a point 0.05 mm inside each vertex and one 2 mm
  // outside on the line through the vertex.
  mesh::Points normals = mesh::Points::Zero(3, m.vertices.cols());
  for (int32_t j = 0; j < m.triangles.cols(); ++j) {
    const Tri k = TriangleAt(m.vertices, m.triangles, j);
    const Vector3d n = (k.b - k.a).cross(k.c - k.a);
    for (int i = 0; i < 3; ++i) normals.col(m.triangles(i, j)) += n;
  }
  int misses = 0;
  std::mt19937 rng(12);
  std::uniform_real_distribution<double> u(-0.5, 0.5);
  for (Eigen::Index i = 0; i < m.vertices.cols(); ++i) {
    const Vector3d v = m.vertices.col(i);
    const Vector3d n = normals.col(i).normalized();
    const Vector3d tilt = (n + Vector3d(u(rng), u(rng), u(rng))).normalized();
    const Vector3d inner = v - 5e-5 * tilt;
    const Vector3d outer = inner + (v - inner) * 40.0;
    SegmentHit hit;
    if (!tree.FirstHit(outer, inner, &hit)) ++misses;
    if (!tree.FirstHit(inner, outer, &hit)) ++misses;
  }
  EXPECT_EQ(misses, 0);
}

TEST(AabbTree, RefitAndQueriesAllocateNothing) {
  const mesh::SurfaceMesh m = Gallbladder();
  AabbTree tree(m.vertices, m.triangles);
  const mesh::Points moved = Deformed(m.vertices, 3, 0.003);
  const Vector3d c = m.vertices.col(17);
  const Vector3d p = c + Vector3d(0.002, 0.001, 0.003);
  std::array<int32_t, 64> out{};
  SegmentHit hit;
  SurfacePoint nearest;
  int64_t allocations = 0;
  int32_t found = 0;
  {
    const testing::AllocationCounter counter;
    tree.Refit(moved);
    tree.FirstHit(p, c - (p - c), &hit);
    tree.Nearest(p, &nearest);
    tree.Nearest(p, &nearest, 0.001);
    tree.NearestToSegment(c, p, 0.002, &nearest);
    found += tree.SphereQuery(c, 0.003, out);
    found += tree.CapsuleQuery(c, p, 0.002, out);
    tree.Refit(m.vertices);
    allocations = counter.count();
  }
  EXPECT_EQ(allocations, 0);
  EXPECT_GT(found, 0);
}

TEST(AabbTree, ConstructorRejectsBadInputs) {
  const mesh::SurfaceMesh m = Icosphere(1, 0.05, Vector3d::Zero(), 0.0);
  EXPECT_THROW(AabbTree(m.vertices, m.triangles, 0), std::invalid_argument);
  mesh::Triangles bad = m.triangles;
  bad(1, 5) = -1;
  EXPECT_THROW(AabbTree(m.vertices, bad), std::invalid_argument);
  bad(1, 5) = static_cast<int32_t>(m.vertices.cols());
  EXPECT_THROW(AabbTree(m.vertices, bad), std::invalid_argument);
  mesh::Points nan = m.vertices;
  nan(2, 3) = kNaN;
  EXPECT_THROW(AabbTree(nan, m.triangles), std::invalid_argument);
  mesh::Points inf = m.vertices;
  inf(0, 7) = kInf;
  EXPECT_THROW(AabbTree(inf, m.triangles), std::invalid_argument);
  mesh::Points huge = m.vertices;
  huge(1, 2) = 1e31;  // beyond what single-precision boxes hold
  EXPECT_THROW(AabbTree(huge, m.triangles), std::invalid_argument);
  AabbTree tree(m.vertices, m.triangles);
  const mesh::Points fewer = m.vertices.leftCols(m.vertices.cols() - 1);
  EXPECT_THROW(tree.Refit(fewer), std::invalid_argument);
  try {
    AabbTree(m.vertices, bad);
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("triangle 5"), std::string::npos) << e.what();
  }
}

TEST(AabbTree, QueriesWithNonFiniteArgumentsFindNothing) {
  const mesh::SurfaceMesh m = Icosphere(2, 0.05, Vector3d::Zero(), 0.0);
  const AabbTree tree(m.vertices, m.triangles);
  const Vector3d good(0.0, 0.0, 0.0);
  const Vector3d far(0.2, 0.0, 0.0);
  SegmentHit hit;
  SurfacePoint nearest;
  std::array<int32_t, 8> out{};
  out.fill(-7);
  ASSERT_TRUE(tree.FirstHit(good, far, &hit));  // the good arguments do find something
  ASSERT_TRUE(tree.Nearest(good, &nearest));
  ASSERT_GT(tree.SphereQuery(far, 0.2, out), 0);
  out.fill(-7);
  for (const Vector3d& bad :
       {Vector3d(kNaN, 0.0, 0.0), Vector3d(0.0, kInf, 0.0), Vector3d(0.0, 0.0, -kInf)}) {
    EXPECT_FALSE(tree.FirstHit(bad, far, &hit));
    EXPECT_FALSE(tree.FirstHit(good, bad, &hit));
    EXPECT_FALSE(tree.Nearest(bad, &nearest));
    EXPECT_FALSE(tree.NearestToSegment(bad, far, 0.1, &nearest));
    EXPECT_FALSE(tree.NearestToSegment(good, bad, 0.1, &nearest));
    EXPECT_EQ(tree.SphereQuery(bad, 0.1, out), 0);
    EXPECT_EQ(tree.CapsuleQuery(bad, far, 0.1, out), 0);
    EXPECT_EQ(tree.CapsuleQuery(good, bad, 0.1, out), 0);
  }
  for (const double r : {kNaN, -0.01, kInf}) {
    EXPECT_FALSE(tree.NearestToSegment(good, far, r, &nearest));
    EXPECT_EQ(tree.SphereQuery(far, r, out), 0);
    EXPECT_EQ(tree.CapsuleQuery(good, far, r, out), 0);
  }
  EXPECT_FALSE(tree.Nearest(good, &nearest, kNaN));
  EXPECT_FALSE(tree.Nearest(good, &nearest, -1.0));
  for (const int32_t v : out) EXPECT_EQ(v, -7);  // nothing written
  // An empty tree finds nothing.
  const AabbTree empty;
  EXPECT_FALSE(empty.FirstHit(good, far, &hit));
  EXPECT_FALSE(empty.Nearest(good, &nearest));
  EXPECT_EQ(empty.SphereQuery(good, 1.0, out), 0);
  EXPECT_EQ(empty.num_nodes(), 0);
}

TEST(AabbTree, CountsOverflowingTheOutputSpanAreReportedAndTheSpanFilled) {
  const mesh::SurfaceMesh m = Icosphere(2, 0.05, Vector3d::Zero(), 0.0);
  const AabbTree tree(m.vertices, m.triangles);
  std::array<int32_t, 4> out{};
  const int32_t all = tree.SphereQuery(Vector3d::Zero(), 1.0, out);
  EXPECT_EQ(all, m.triangles.cols());
  for (const int32_t v : out) {
    EXPECT_GE(v, 0);
    EXPECT_LT(v, m.triangles.cols());
  }
  EXPECT_EQ(tree.CapsuleQuery(Vector3d::Zero(), Vector3d(0.01, 0, 0), 1.0, std::span<int32_t>()),
            m.triangles.cols());
}

}  // namespace
}  // namespace somasim::contact
