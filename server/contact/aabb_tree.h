// Bounding-volume hierarchy of axis-aligned boxes over a triangle surface (SPEC §5.1, seed 002
// §3.1): built top-down once (each node split at the middle of the longest axis of its triangles'
// centroids, a few triangles per leaf), refitted bottom-up each step as the mesh deforms (the
// tree's shape stays, its boxes follow the vertices). Queries find what a tool touches: the first
// crossing of a segment, every triangle within a capsule or sphere, the nearest surface point
// with barycentric coordinates. Pure physics: no I/O; Refit and every query allocate nothing.
//
// Exactness: boxes are stored in single precision rounded outwards (they always contain their
// triangles), the triangle tests are exact double-precision ones (triangle_queries.h), so every
// query answers exactly what a brute-force loop over all triangles answers.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <limits>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"

namespace somasim::contact {

// A point on the surface: triangle index, barycentric weights (of the triangle's three vertices
// in order, summing to 1), the point [m] and its distance [m] from the query.
struct SurfacePoint {
  int32_t triangle = -1;  // -1: none
  Eigen::Vector3d barycentric = Eigen::Vector3d::Zero();
  Eigen::Vector3d point = Eigen::Vector3d::Zero();
  double distance = 0.0;
};

// Where a segment pq crosses the surface: t in [0, 1] along pq.
struct SegmentHit {
  int32_t triangle = -1;  // -1: none
  double t = 0.0;
  Eigen::Vector3d barycentric = Eigen::Vector3d::Zero();
  Eigen::Vector3d point = Eigen::Vector3d::Zero();
};

class AabbTree {
 public:
  AabbTree() = default;  // an empty tree: every query finds nothing
  // Builds the tree over `triangles` (3 × T indices into positions' columns) at `positions`
  // (3 × N) [m], leaves of at most max_leaf_triangles (>= 1). Throws std::invalid_argument on an
  // index out of range, a non-finite position or max_leaf_triangles < 1. Allocates.
  AabbTree(const mesh::Points& positions, const mesh::Triangles& triangles,
           int max_leaf_triangles = 4);

  int32_t num_triangles() const;
  int32_t num_nodes() const;  // tree nodes (for tests and benchmarks)

  // Moves every box to the vertices' new positions (same N and triangles as at build).
  // Allocation-free. Positions must be finite (the models never publish NaN).
  void Refit(const mesh::Points& positions);

  // The crossing of segment pq with the surface nearest to p (smallest t), using the positions
  // of the last build or refit. False when pq crosses nothing.
  bool FirstHit(const Eigen::Vector3d& p, const Eigen::Vector3d& q, SegmentHit* hit) const;
  // The surface point nearest to x no farther than max_distance [m]. False when there is none.
  bool Nearest(const Eigen::Vector3d& x, SurfacePoint* nearest,
               double max_distance = std::numeric_limits<double>::infinity()) const;
  // The triangles within `radius` [m] of segment pq (a capsule) or of point c (a sphere), in no
  // particular order: the first out.size() are written to `out`; the return value is how many
  // there are (may exceed out.size(), then the rest are dropped).
  int32_t CapsuleQuery(const Eigen::Vector3d& p, const Eigen::Vector3d& q, double radius,
                       std::span<int32_t> out) const;
  int32_t SphereQuery(const Eigen::Vector3d& c, double radius, std::span<int32_t> out) const;
  // The surface point nearest to segment pq within `radius` [m] (distance = segment-to-surface
  // distance; point on the surface). False when there is none.
  bool NearestToSegment(const Eigen::Vector3d& p, const Eigen::Vector3d& q, double radius,
                        SurfacePoint* nearest) const;

  // Positions of the last build or refit (what the queries test against).
  const mesh::Points& positions() const { return positions_; }
  const mesh::Triangles& triangles() const { return triangles_; }

 private:
  mesh::Points positions_;     // 3 × N: the last build's or refit's copy
  mesh::Triangles triangles_;  // 3 × T
  // The implementation's layout (nodes, boxes, leaf ranges, per-leaf vertex lists...) is
  // private to aabb_tree.cc.
  struct Node;
  std::vector<Node> nodes_;
  std::vector<int32_t> leaf_triangles_;
  std::vector<int32_t> leaf_vertices_;
};

}  // namespace somasim::contact
