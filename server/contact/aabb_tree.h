// Bounding-volume hierarchy of axis-aligned boxes over a triangle surface (SPEC §5.1, seed 002
// §3.1): built top-down once (each node split at the middle of the longest axis of its triangles'
// centroids, a few triangles per leaf), refitted bottom-up each step as the mesh deforms (the
// tree's shape stays, its boxes follow the vertices). Queries find what a tool touches: the first
// crossing of a segment, every triangle within a capsule or sphere, the nearest surface point
// with barycentric coordinates. Pure physics: no I/O; Refit and every query allocate nothing.
//
// Exactness: boxes are stored in single precision rounded outwards (they always contain their
// triangles) and only prune, with a margin; the triangle tests are the double-precision ones of
// triangle_queries.h (FirstHit's is watertight: a segment crossing a closed surface always hits),
// so every query answers exactly what a brute-force loop over all triangles with those functions
// answers (ties go to the smallest triangle index).
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
  // index out of range, a non-finite position or max_leaf_triangles < 1. Allocates. Leaves of 8
  // by default: against leaves of 4 the refit gathers a third fewer vertices (neighbouring
  // triangles share them) and visits half the nodes, while the queries cost the same (the
  // figures are in docs/benchmarks.md, "Leaves of 8 instead of 4").
  AabbTree(const mesh::Points& positions, const mesh::Triangles& triangles,
           int max_leaf_triangles = 8);

  int32_t num_triangles() const;
  int32_t num_nodes() const;  // tree nodes (for tests and benchmarks)

  // Moves every box to the vertices' new positions (same N and triangles as at build; throws
  // std::invalid_argument on another N). Allocation-free and copy-free: the tree keeps a
  // reference to `positions`, which the queries read, so that matrix must stay alive and
  // unchanged until the next Refit or the tree's end (refit again after changing it). Passing a
  // temporary does not compile. Positions must be finite (the models never publish NaN).
  void Refit(const mesh::Points& positions);
  void Refit(const mesh::Points&& positions) = delete;

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

  // Positions of the last build or refit (what the queries test against): the tree's own copy
  // made at build, or the matrix the last Refit was given (not copied: copying 3 × N doubles
  // would be a pass over every vertex on top of the leaves' gathers).
  const mesh::Points& positions() const { return external_ != nullptr ? *external_ : positions_; }
  // How many times the tree has been refitted: a caller that saw the same count last time
  // knows the surface has not moved since (GodObject skips its swallowed-proxy check then).
  uint64_t refits() const { return refits_; }
  const mesh::Triangles& triangles() const { return triangles_; }

  // Traversal stacks hold this many nodes; the build guarantees depth < kMaxDepth (midpoint
  // splits stop at depth kMaxMidpointDepth, below it every split is an even split by count,
  // which adds at most log2(T) < 32 levels), so a degenerate mesh cannot overflow them.
  static constexpr int kMaxMidpointDepth = 48;
  static constexpr int kMaxDepth = 96;
  int max_depth() const { return max_depth_; }  // deepest leaf (root = 0), for tests
  // For tests: how many nodes' boxes are not exactly their triangles' box computed afresh from
  // positions() (per axis, the double min / max over the vertices of the node's triangles,
  // rounded outwards to float as the build does), or do not contain one of those vertices.
  // 0 after every build and refit, whichever pass computed the boxes.
  int32_t CountBoxMismatchesForTesting() const;

 private:
  // Layout: 32-byte nodes in depth-first order (first child next, second child by index),
  // leaves holding a range of a triangle permutation with the triangles' vertex indices copied
  // alongside; for Refit each leaf's distinct vertices (one pass over leaves: box in double,
  // SSE2 or AVX2, rounded outwards to float once; the AVX2 pass takes leaves in pairs, sibling
  // leaves first, and fits their parent too) and the internal nodes by height (one pass, float
  // min/max). Depth is bounded (kMaxDepth), so traversals use a fixed stack. The build is in
  // aabb_tree.cc, Refit in aabb_tree_refit.cc, the queries in aabb_tree_queries.cc.
  //
  // A node: its box in single precision rounded outwards (it always contains its triangles),
  // 32 bytes so two share a cache line. Nodes are in depth-first order: an internal node's
  // first child is the next node, `index` is its second child; a leaf (count > 0) holds the
  // triangles order_[index .. index + count).
  // Layout lo, index, hi, count: Refit's SSE2 pass loads lo or hi with the next int as one
  // 16-byte vector and stores back only the three box lanes.
  struct alignas(32) Node {
    float lo[3];
    int32_t index;
    float hi[3];
    int32_t count;  // 0: internal
  };
  // A leaf for Refit: its node and its distinct vertices leaf_vertices_[vertex_begin ..
  // vertex_begin + vertex_count) (an even count >= 2, equal within each pair of leaves 2m,
  // 2m + 1: padded by repeating one).
  struct Leaf {
    int32_t node;
    int32_t vertex_begin;
    int32_t vertex_count;
    int32_t triangle_begin;  // the node's index and count, so Refit writes whole nodes
    int32_t triangle_count;
    int32_t parent;        // the node whose children are this leaf and its mate, or -1
    int32_t parent_index;  // that node's index (its second child)
  };
  // Build stages (aabb_tree.cc): the nodes split top-down; Refit's order of the internal nodes
  // (by height; returns each node's height) and of the leaves (in pairs).
  void BuildNodes(const mesh::Points& positions, int max_leaf_triangles);
  void OrderForRefit(Eigen::Index num_vertices);
  std::vector<int32_t> OrderInternalByHeight();
  void PairLeaves(const std::vector<int32_t>& height, const std::vector<int32_t>& leaf_of,
                  Eigen::Index num_vertices);

  mesh::Points positions_;                  // 3 × N: the build's copy
  const mesh::Points* external_ = nullptr;  // 3 × N: the last Refit's positions, if any
  mesh::Triangles triangles_;               // 3 × T, as given
  std::vector<Node> nodes_;
  std::vector<Leaf> leaves_;             // in Refit's order: in pairs, by vertex_count
  std::vector<int32_t> leaf_vertices_;   // each leaf's distinct vertices, leaf after leaf
  std::vector<int32_t> internal_;        // internal nodes, children before parents
  size_t num_leaf_parents_ = 0;          // internal_'s first, which Refit's AVX2 leaf pass fits
  size_t num_unmasked_leaves_ = 0;       // leaves_'s first, not holding the last vertex
  std::vector<int32_t> order_;           // T: triangle index at each leaf slot
  std::vector<int32_t> order_vertices_;  // 3 × T: the vertex indices of order_'s triangles
  double scale_ = 0.0;                   // max |coordinate| of the root box [m], for margins
  int max_depth_ = 0;
  uint64_t refits_ = 0;
};

// For tests: false makes Refit take its portable (SSE2 / scalar) leaf pass even where AVX2 is
// available; both give identical boxes. Default true. Set it only while no tree is refitting.
void SetAabbRefitAvx2ForTesting(bool enabled);

}  // namespace somasim::contact
