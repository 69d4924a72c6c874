// The exact triangle queries: closest points in every Voronoi region against dense sampling,
// watertight segment crossings through shared edges and fan vertices, segment–triangle distances
// against sampling and analytic cases, degenerate triangles and segments.
#include "server/contact/triangle_queries.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <random>

namespace somasim::contact {
namespace {

using Eigen::Vector3d;

Vector3d RandomPoint(std::mt19937* rng, double half_width) {
  std::uniform_real_distribution<double> u(-half_width, half_width);
  return Vector3d(u(*rng), u(*rng), u(*rng));
}

Vector3d FromBarycentric(const Vector3d& w, const Vector3d& a, const Vector3d& b,
                         const Vector3d& c) {
  return w.x() * a + w.y() * b + w.z() * c;
}

void ExpectValidBarycentric(const Vector3d& w) {
  for (int i = 0; i < 3; ++i) {
    EXPECT_GE(w[i], 0.0);
    EXPECT_LE(w[i], 1.0);
  }
  EXPECT_NEAR(w.sum(), 1.0, 1e-12);
}

// Nearest sampled point of the triangle to p on a grid of n × n barycentric samples: the exact
// distance lies in [sampled - spacing, sampled].
double SampledTriangleDistance(const Vector3d& p, const Vector3d& a, const Vector3d& b,
                               const Vector3d& c, int n) {
  double best = std::numeric_limits<double>::infinity();
  for (int i = 0; i <= n; ++i) {
    for (int j = 0; i + j <= n; ++j) {
      const double v = static_cast<double>(i) / n;
      const double w = static_cast<double>(j) / n;
      best = std::min(best, (p - ((1.0 - v - w) * a + v * b + w * c)).norm());
    }
  }
  return best;
}

double Diameter(const Vector3d& a, const Vector3d& b, const Vector3d& c) {
  return std::max({(a - b).norm(), (b - c).norm(), (c - a).norm()});
}

TEST(TriangleQueries, ClosestPointFindsEveryVoronoiRegion) {
  const Vector3d a(0.0, 0.0, 0.0);
  const Vector3d b(1.0, 0.0, 0.0);
  const Vector3d c(0.0, 1.0, 0.0);
  struct Case {
    Vector3d p;
    Vector3d expected;
  };
  const Case cases[] = {
      {Vector3d(-1.0, -1.0, 0.3), Vector3d(1.0, 0.0, 0.0)},     // vertex a
      {Vector3d(2.0, -0.5, -0.2), Vector3d(0.0, 1.0, 0.0)},     // vertex b
      {Vector3d(-0.5, 2.0, 0.7), Vector3d(0.0, 0.0, 1.0)},      // vertex c
      {Vector3d(0.25, -1.0, 0.5), Vector3d(0.75, 0.25, 0.0)},   // edge ab
      {Vector3d(-1.0, 0.75, -0.5), Vector3d(0.25, 0.0, 0.75)},  // edge ac
      {Vector3d(1.0, 1.0, 0.1), Vector3d(0.0, 0.5, 0.5)},       // edge bc
      {Vector3d(0.2, 0.3, 2.0), Vector3d(0.5, 0.2, 0.3)},       // face
      {Vector3d(0.2, 0.3, 0.0), Vector3d(0.5, 0.2, 0.3)},       // in the face
  };
  for (const Case& k : cases) {
    const Vector3d w = ClosestPointBarycentric(k.p, a, b, c);
    EXPECT_LT((w - k.expected).norm(), 1e-14) << k.p.transpose() << " -> " << w.transpose();
    ExpectValidBarycentric(w);
  }
}

TEST(TriangleQueries, ClosestPointMatchesDenseSamplingOfRandomTriangles) {
  std::mt19937 rng(1);
  constexpr int kSamples = 120;
  for (int trial = 0; trial < 300; ++trial) {
    const Vector3d a = RandomPoint(&rng, 1.0);
    const Vector3d b = RandomPoint(&rng, 1.0);
    const Vector3d c = RandomPoint(&rng, 1.0);
    const Vector3d p = RandomPoint(&rng, 2.0);
    Vector3d w;
    const double d2 = PointTriangleDistanceSquared(p, a, b, c, &w);
    ExpectValidBarycentric(w);
    EXPECT_EQ(w, ClosestPointBarycentric(p, a, b, c));
    EXPECT_NEAR(std::sqrt(d2), (p - FromBarycentric(w, a, b, c)).norm(), 1e-14);
    const double sampled = SampledTriangleDistance(p, a, b, c, kSamples);
    EXPECT_LE(std::sqrt(d2), sampled + 1e-12);
    EXPECT_GE(std::sqrt(d2), sampled - Diameter(a, b, c) / kSamples);
  }
}

TEST(TriangleQueries, DegenerateTrianglesGiveNearestPointOfTheirLongestEdge) {
  // Collinear: c between a and b; the longest edge is ab.
  const Vector3d a(0.0, 0.0, 0.0);
  const Vector3d b(2.0, 0.0, 0.0);
  const Vector3d c(0.5, 0.0, 0.0);
  for (const Vector3d& p : {Vector3d(1.5, 1.0, 0.0), Vector3d(-1.0, 0.5, 0.5),
                            Vector3d(3.0, 0.0, -1.0), Vector3d(0.5, 0.0, 2.0)}) {
    const Vector3d w = ClosestPointBarycentric(p, a, b, c);
    ExpectValidBarycentric(w);
    const Vector3d expected(std::clamp(p.x(), 0.0, 2.0), 0.0, 0.0);
    EXPECT_LT((FromBarycentric(w, a, b, c) - expected).norm(), 1e-14) << p.transpose();
  }
  // Two coincident vertices, and all three.
  const Vector3d w2 = ClosestPointBarycentric(Vector3d(0.5, 1.0, 0.0), a, b, a);
  ExpectValidBarycentric(w2);
  EXPECT_LT((FromBarycentric(w2, a, b, a) - Vector3d(0.5, 0.0, 0.0)).norm(), 1e-14);
  const Vector3d w3 = ClosestPointBarycentric(Vector3d(0.5, 1.0, 0.0), b, b, b);
  ExpectValidBarycentric(w3);
  EXPECT_LT((FromBarycentric(w3, b, b, b) - b).norm(), 1e-14);
  // A segment crossing the degenerate triangle's line is at distance 0 from it.
  double s = -1.0;
  Vector3d bary;
  EXPECT_NEAR(SegmentTriangleDistanceSquared(Vector3d(1.0, -1.0, 0.0), Vector3d(1.0, 1.0, 0.0), a,
                                             b, c, &s, &bary),
              0.0, 1e-28);
  EXPECT_NEAR(s, 0.5, 1e-14);
  ExpectValidBarycentric(bary);
}

TEST(TriangleQueries, SegmentCrossingCountsEdgesCornersAndEndsButNotThePlane) {
  const Vector3d a(0.0, 0.0, 0.0);
  const Vector3d b(1.0, 0.0, 0.0);
  const Vector3d c(0.0, 1.0, 0.0);
  double t = -1.0;
  Vector3d w;
  // Interior.
  ASSERT_TRUE(SegmentTriangleIntersection(Vector3d(0.25, 0.25, 1.0), Vector3d(0.25, 0.25, -3.0), a,
                                          b, c, &t, &w));
  EXPECT_DOUBLE_EQ(t, 0.25);
  EXPECT_LT((w - Vector3d(0.5, 0.25, 0.25)).norm(), 1e-15);
  // Edge, corner, from either side.
  EXPECT_TRUE(SegmentTriangleIntersection(Vector3d(0.5, 0.0, 1.0), Vector3d(0.5, 0.0, -1.0), a, b,
                                          c, &t, &w));
  EXPECT_TRUE(SegmentTriangleIntersection(Vector3d(0.5, 0.5, -1.0), Vector3d(0.5, 0.5, 1.0), a, b,
                                          c, &t, &w));
  EXPECT_TRUE(SegmentTriangleIntersection(Vector3d(0.0, 1.0, 1.0), Vector3d(0.0, 1.0, -1.0), a, b,
                                          c, &t, &w));
  EXPECT_LT((w - Vector3d(0.0, 0.0, 1.0)).norm(), 1e-15);
  // An end on the triangle.
  ASSERT_TRUE(SegmentTriangleIntersection(Vector3d(0.2, 0.2, 1.0), Vector3d(0.2, 0.2, 0.0), a, b, c,
                                          &t, &w));
  EXPECT_EQ(t, 1.0);
  ASSERT_TRUE(SegmentTriangleIntersection(Vector3d(0.2, 0.2, 0.0), Vector3d(0.3, 0.1, 2.0), a, b, c,
                                          &t, &w));
  EXPECT_EQ(t, 0.0);
  // Misses: beyond an edge, short of the plane, in the plane, a point.
  EXPECT_FALSE(SegmentTriangleIntersection(Vector3d(0.6, 0.6, 1.0), Vector3d(0.6, 0.6, -1.0), a, b,
                                           c, &t, &w));
  EXPECT_FALSE(SegmentTriangleIntersection(Vector3d(0.2, 0.2, 1.0), Vector3d(0.2, 0.2, 0.01), a, b,
                                           c, &t, &w));
  EXPECT_FALSE(SegmentTriangleIntersection(Vector3d(-1.0, 0.2, 0.0), Vector3d(2.0, 0.2, 0.0), a, b,
                                           c, &t, &w));
  EXPECT_FALSE(SegmentTriangleIntersection(Vector3d(0.2, 0.2, 0.0), Vector3d(0.2, 0.2, 0.0), a, b,
                                           c, &t, &w));
  // Non-finite input: no crossing, no crash.
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_FALSE(SegmentTriangleIntersection(Vector3d(nan, 0.2, 1.0), Vector3d(0.2, 0.2, -1.0), a, b,
                                           c, &t, &w));
}

TEST(TriangleQueries, SegmentCrossingReproducesItsPointOnRandomTriangles) {
  std::mt19937 rng(2);
  int hits = 0;
  for (int trial = 0; trial < 5000; ++trial) {
    const Vector3d a = RandomPoint(&rng, 1.0);
    const Vector3d b = RandomPoint(&rng, 1.0);
    const Vector3d c = RandomPoint(&rng, 1.0);
    const Vector3d p = RandomPoint(&rng, 1.5);
    const Vector3d q = RandomPoint(&rng, 1.5);
    double t = -1.0;
    Vector3d w;
    const bool hit = SegmentTriangleIntersection(p, q, a, b, c, &t, &w);
    // The segment crosses iff its ends lie on opposite sides of the plane and the crossing point
    // of the plane is inside the triangle (checked away from the boundaries).
    const Vector3d n = (b - a).cross(c - a);
    const double sp = n.dot(p - a);
    const double sq = n.dot(q - a);
    if (hit) {
      ++hits;
      EXPECT_GE(t, 0.0);
      EXPECT_LE(t, 1.0);
      ExpectValidBarycentric(w);
      EXPECT_LT((p + t * (q - p) - FromBarycentric(w, a, b, c)).norm(), 1e-9);
      double s = -1.0;
      Vector3d w2;
      EXPECT_EQ(SegmentTriangleDistanceSquared(p, q, a, b, c, &s, &w2), 0.0);
    } else if (sp * sq < 0.0) {
      const Vector3d x = p + sp / (sp - sq) * (q - p);
      const Vector3d wx = ClosestPointBarycentric(x, a, b, c);
      EXPECT_TRUE(wx.minCoeff() < 1e-9 || wx.maxCoeff() > 1.0 - 1e-9 ||
                  (x - FromBarycentric(wx, a, b, c)).norm() > 1e-9)
          << "missed a crossing inside the triangle";
    }
  }
  EXPECT_GT(hits, 200);
}

// Segments through points of a shared edge never slip between its two triangles, whatever the
// rounding: at least one of the two reports the crossing.
TEST(TriangleQueries, SegmentThroughASharedEdgeHitsAtLeastOneTriangle) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  int tested = 0;
  for (int trial = 0; trial < 20000; ++trial) {
    const Vector3d e0 = RandomPoint(&rng, 0.1);
    const Vector3d e1 = RandomPoint(&rng, 0.1);
    const Vector3d side = RandomPoint(&rng, 0.1);
    // The second triangle folds around the edge by up to ~90° but stays on the other side.
    const Vector3d normal = (e1 - e0).cross(side - e0);
    const Vector3d other = e0 + (e1 - e0) * unit(rng) - (side - e0) * (0.2 + unit(rng)) +
                           normal.normalized() * 0.1 * (unit(rng) - 0.5);
    const Vector3d x = e0 + unit(rng) * (e1 - e0);  // on the edge, to rounding
    Vector3d dir = RandomPoint(&rng, 1.0);
    if (trial % 4 == 0) dir = normal;  // head-on
    const Vector3d p = x + dir * 0.05;
    const Vector3d q = x - dir * 0.05;
    double t = 0.0;
    Vector3d w;
    const bool hit1 = SegmentTriangleIntersection(p, q, e0, e1, side, &t, &w);
    const bool hit2 = SegmentTriangleIntersection(p, q, e1, e0, other, &t, &w);
    // The segment crosses the surface at x unless the pair, seen along pq, folds onto one side
    // of the edge (then it only grazes the fold): both triangles must face pq the same way.
    const Vector3d d = q - p;
    const Vector3d n1 = (e1 - e0).cross(side - e0);
    const Vector3d n2 = (e0 - e1).cross(other - e1);
    const double f1 = d.dot(n1) / (d.norm() * n1.norm());
    const double f2 = d.dot(n2) / (d.norm() * n2.norm());
    if (!(f1 * f2 > 1e-6)) continue;
    ++tested;
    EXPECT_TRUE(hit1 || hit2) << "trial " << trial;
  }
  EXPECT_GT(tested, 10000);
}

// A fan of triangles around a vertex (a closed ring, like any vertex of a closed surface): a
// segment through the vertex crosses at least one of them.
TEST(TriangleQueries, SegmentThroughAFanVertexHitsAtLeastOneTriangle) {
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  int tested = 0;
  for (int trial = 0; trial < 5000; ++trial) {
    const Vector3d v = RandomPoint(&rng, 0.1);
    const int n = 3 + trial % 6;
    // Ring of n neighbours around v in a random frame, with some height jitter.
    const Vector3d axis = RandomPoint(&rng, 1.0).normalized();
    const Vector3d u1 = axis.unitOrthogonal();
    const Vector3d u2 = axis.cross(u1);
    std::vector<Vector3d> ring;
    for (int k = 0; k < n; ++k) {
      const double angle = 2.0 * std::numbers::pi * (k + 0.4 * unit(rng)) / n;
      ring.push_back(v + 0.01 * (std::cos(angle) * u1 + std::sin(angle) * u2 +
                                 0.3 * (unit(rng) - 0.5) * axis));
    }
    // Directions mostly across the fan; exact vertex through x = v: p, q symmetric around v.
    Vector3d dir = axis + 0.8 * RandomPoint(&rng, 1.0);
    const double scale = trial % 2 == 0 ? 0.003 : 0.1;
    const Vector3d p = v + scale * dir;
    const Vector3d q = v - scale * dir;
    // The line crosses the fan at v when every triangle faces it the same way (the fan seen
    // along pq is then a star around v); otherwise it may only graze it.
    int towards = 0;
    int away = 0;
    for (int k = 0; k < n; ++k) {
      const Vector3d& r0 = ring[static_cast<size_t>(k)];
      const Vector3d& r1 = ring[static_cast<size_t>((k + 1) % n)];
      const Vector3d normal = (r0 - v).cross(r1 - v);
      const double f = (q - p).dot(normal) / ((q - p).norm() * normal.norm());
      towards += f < -1e-6 ? 1 : 0;
      away += f > 1e-6 ? 1 : 0;
    }
    if (towards != n && away != n) continue;
    ++tested;
    bool any = false;
    for (int k = 0; k < n; ++k) {
      double t = 0.0;
      Vector3d w;
      any = any || SegmentTriangleIntersection(p, q, v, ring[static_cast<size_t>(k)],
                                               ring[static_cast<size_t>((k + 1) % n)], &t, &w);
    }
    EXPECT_TRUE(any) << "trial " << trial;
  }
  EXPECT_GT(tested, 1000);
}

// Minimum over dense samples s of the (exact) point–triangle distance: the exact segment
// distance lies in [sampled - |pq| / n, sampled].
double SampledSegmentDistance(const Vector3d& p, const Vector3d& q, const Vector3d& a,
                              const Vector3d& b, const Vector3d& c, int n) {
  double best = std::numeric_limits<double>::infinity();
  for (int i = 0; i <= n; ++i) {
    const Vector3d x = p + (static_cast<double>(i) / n) * (q - p);
    Vector3d w;
    best = std::min(best, std::sqrt(PointTriangleDistanceSquared(x, a, b, c, &w)));
  }
  return best;
}

TEST(TriangleQueries, SegmentDistanceMatchesDenseSampling) {
  std::mt19937 rng(5);
  constexpr int kSamples = 4000;
  for (int trial = 0; trial < 400; ++trial) {
    const Vector3d a = RandomPoint(&rng, 1.0);
    const Vector3d b = RandomPoint(&rng, 1.0);
    // Every fifth triangle degenerate (collinear), every seventh segment a point.
    const Vector3d c = trial % 5 == 0 ? Vector3d(a + 0.3 * (b - a)) : RandomPoint(&rng, 1.0);
    const Vector3d p = RandomPoint(&rng, 2.0);
    const Vector3d q = trial % 7 == 0 ? p : RandomPoint(&rng, 2.0);
    double s = -1.0;
    Vector3d w;
    const double d2 = SegmentTriangleDistanceSquared(p, q, a, b, c, &s, &w);
    EXPECT_GE(s, 0.0);
    EXPECT_LE(s, 1.0);
    ExpectValidBarycentric(w);
    const double d = std::sqrt(d2);
    EXPECT_NEAR(d, (p + s * (q - p) - FromBarycentric(w, a, b, c)).norm(), 1e-12);
    const double sampled = SampledSegmentDistance(p, q, a, b, c, kSamples);
    EXPECT_LE(d, sampled + 1e-12);
    EXPECT_GE(d, sampled - (q - p).norm() / kSamples - 1e-12);
  }
}

TEST(TriangleQueries, SegmentDistanceAnalyticCases) {
  const Vector3d a(0.0, 0.0, 0.0);
  const Vector3d b(1.0, 0.0, 0.0);
  const Vector3d c(0.0, 1.0, 0.0);
  double s = -1.0;
  Vector3d w;
  // Parallel to the plane, over the face at height 0.3.
  EXPECT_NEAR(SegmentTriangleDistanceSquared(Vector3d(0.1, 0.1, 0.3), Vector3d(0.4, 0.2, 0.3), a, b,
                                             c, &s, &w),
              0.09, 1e-15);
  // Parallel to edge ab, beside it (y = -0.5) and above (z = 0.5): distance² 0.5.
  EXPECT_NEAR(SegmentTriangleDistanceSquared(Vector3d(0.2, -0.5, 0.5), Vector3d(0.7, -0.5, 0.5), a,
                                             b, c, &s, &w),
              0.5, 1e-15);
  EXPECT_NEAR(w.z(), 0.0, 1e-15);
  // Parallel to edge ab, overlapping beyond b: nearest is vertex b to the segment's line.
  EXPECT_NEAR(SegmentTriangleDistanceSquared(Vector3d(1.5, -0.5, 0.0), Vector3d(3.0, -0.5, 0.0), a,
                                             b, c, &s, &w),
              0.25 + 0.25, 1e-15);
  EXPECT_EQ(s, 0.0);
  // Skew to edge bc outside the triangle: the line x = y = 0.75 (beyond the hypotenuse, whose
  // nearest point is (0.5, 0.5, 0)), vertical: distance² = 2 · 0.25².
  EXPECT_NEAR(SegmentTriangleDistanceSquared(Vector3d(0.75, 0.75, -1.0), Vector3d(0.75, 0.75, 1.0),
                                             a, b, c, &s, &w),
              0.125, 1e-15);
  EXPECT_NEAR(s, 0.5, 1e-15);
  EXPECT_LT((w - Vector3d(0.0, 0.5, 0.5)).norm(), 1e-15);
  // In the plane, crossing the triangle: distance 0 though the crossing test says no.
  EXPECT_NEAR(SegmentTriangleDistanceSquared(Vector3d(-1.0, 0.2, 0.0), Vector3d(2.0, 0.2, 0.0), a,
                                             b, c, &s, &w),
              0.0, 1e-30);
  // Crossing: 0 with the crossing's parameters.
  EXPECT_EQ(SegmentTriangleDistanceSquared(Vector3d(0.2, 0.2, 1.0), Vector3d(0.2, 0.2, -1.0), a, b,
                                           c, &s, &w),
            0.0);
  EXPECT_DOUBLE_EQ(s, 0.5);
  // A zero-length segment is a point.
  EXPECT_NEAR(SegmentTriangleDistanceSquared(Vector3d(2.0, 0.0, 0.0), Vector3d(2.0, 0.0, 0.0), a, b,
                                             c, &s, &w),
              1.0, 1e-15);
}

}  // namespace
}  // namespace somasim::contact

namespace somasim::contact {
namespace {

TEST(TriangleQueries, ClosestPointOnSegmentClampsToItsEnds) {
  const Eigen::Vector3d p(0.0, 0.0, 0.0), q(2.0, 0.0, 0.0);
  EXPECT_EQ(ClosestPointOnSegment(Eigen::Vector3d(0.5, 1.0, -3.0), p, q),
            Eigen::Vector3d(0.5, 0.0, 0.0));
  EXPECT_EQ(ClosestPointOnSegment(Eigen::Vector3d(-1.0, 1.0, 0.0), p, q), p);
  EXPECT_EQ(ClosestPointOnSegment(Eigen::Vector3d(5.0, -1.0, 0.0), p, q), q);
  EXPECT_EQ(ClosestPointOnSegment(Eigen::Vector3d(5.0, -1.0, 0.0), p, p), p);  // no length
}

}  // namespace
}  // namespace somasim::contact
