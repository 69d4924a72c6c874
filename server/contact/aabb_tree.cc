// The AABB tree's build: the input checked, the nodes split top-down, Refit's order of leaves
// and internal nodes fixed once; and what the tests ask of the tree's layout.
#include "server/contact/aabb_tree.h"

#include <algorithm>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <string>
#include <tuple>
#include <vector>

#include "server/contact/aabb_tree_internal.h"

namespace somasim::contact {
namespace {

using aabb_internal::kInf;
using aabb_internal::RoundDown;
using aabb_internal::RoundUp;
using Eigen::Vector3d;

void CheckBuildInput(const mesh::Points& positions, const mesh::Triangles& triangles,
                     int max_leaf_triangles) {
  if (max_leaf_triangles < 1) {
    throw std::invalid_argument("AabbTree: max_leaf_triangles must be >= 1, got " +
                                std::to_string(max_leaf_triangles));
  }
  const Eigen::Index num_vertices = positions.cols();
  const Eigen::Index num_triangles = triangles.cols();
  if (num_vertices > std::numeric_limits<int32_t>::max() ||
      num_triangles > std::numeric_limits<int32_t>::max() / 3) {
    throw std::invalid_argument("AabbTree: too many vertices or triangles");
  }
  for (Eigen::Index j = 0; j < num_vertices; ++j) {
    // Finite and within ±1e30 m, so the single-precision boxes can hold them.
    if (!positions.col(j).allFinite() || !(positions.col(j).cwiseAbs().maxCoeff() <= 1e30)) {
      throw std::invalid_argument("AabbTree: position " + std::to_string(j) +
                                  " is not finite (or beyond 1e30 m)");
    }
  }
  for (Eigen::Index j = 0; j < num_triangles; ++j) {
    for (int k = 0; k < 3; ++k) {
      const int32_t v = triangles(k, j);
      if (v < 0 || v >= num_vertices) {
        throw std::invalid_argument("AabbTree: triangle " + std::to_string(j) + " vertex " +
                                    std::to_string(k) + " index " + std::to_string(v) +
                                    " is out of range [0, " + std::to_string(num_vertices) + ")");
      }
    }
  }
}

}  // namespace

AabbTree::AabbTree(const mesh::Points& positions, const mesh::Triangles& triangles,
                   int max_leaf_triangles) {
  CheckBuildInput(positions, triangles, max_leaf_triangles);
  positions_ = positions;
  triangles_ = triangles;
  const auto t_count = static_cast<int32_t>(triangles.cols());
  if (t_count == 0) return;
  BuildNodes(positions, max_leaf_triangles);
  if (max_depth_ >= kMaxDepth) {
    throw std::logic_error("AabbTree: depth bound broken");  // unreachable by construction
  }
  OrderForRefit(positions.cols());
  order_vertices_.resize(3 * static_cast<size_t>(t_count));
  for (size_t k = 0; k < order_.size(); ++k) {
    for (int i = 0; i < 3; ++i) {
      order_vertices_[3 * k + static_cast<size_t>(i)] = triangles(i, order_[k]);
    }
  }
  Refit(positions_);
  external_ = nullptr;  // the tree's own copy, so a temporary `positions` may go
}

void AabbTree::BuildNodes(const mesh::Points& positions, int max_leaf_triangles) {
  const Eigen::Index num_triangles = triangles_.cols();
  const auto t_count = static_cast<int32_t>(num_triangles);
  const mesh::Triangles& triangles = triangles_;
  // Centroids of the triangles, 3 × T: what the splits sort.
  Eigen::Matrix3Xd centroids(3, num_triangles);
  for (Eigen::Index j = 0; j < num_triangles; ++j) {
    centroids.col(j) = (positions.col(triangles(0, j)) + positions.col(triangles(1, j)) +
                        positions.col(triangles(2, j))) /
                       3.0;
  }
  order_.resize(static_cast<size_t>(t_count));
  std::iota(order_.begin(), order_.end(), 0);
  nodes_.reserve(2 * static_cast<size_t>(t_count / max_leaf_triangles + 1));
  std::vector<int32_t> scratch;  // a leaf's vertices before sorting

  // Top-down (SPEC §5.1): split at the middle of the longest axis of the centroids' box; when
  // that leaves a side empty (or every centroid is the same point), or the tree is already
  // kMaxMidpointDepth deep, split evenly by count along that axis (a total order on (centroid,
  // index), so the build is deterministic), which bounds the depth.
  auto build = [&](auto& self, int32_t begin, int32_t end, int depth) -> void {
    const auto node = static_cast<int32_t>(nodes_.size());
    nodes_.push_back(Node{});
    max_depth_ = std::max(max_depth_, depth);
    if (end - begin <= max_leaf_triangles) {
      nodes_.back().index = begin;
      nodes_.back().count = end - begin;
      leaves_.push_back(
          Leaf{node, static_cast<int32_t>(leaf_vertices_.size()), 0, begin, end - begin, -1, 0});
      scratch.clear();
      for (int32_t k = begin; k < end; ++k) {
        for (int i = 0; i < 3; ++i) scratch.push_back(triangles(i, order_[static_cast<size_t>(k)]));
      }
      std::sort(scratch.begin(), scratch.end());
      scratch.erase(std::unique(scratch.begin(), scratch.end()), scratch.end());
      leaf_vertices_.insert(leaf_vertices_.end(), scratch.begin(), scratch.end());
      return;
    }
    Vector3d lo = Vector3d::Constant(kInf);
    Vector3d hi = Vector3d::Constant(-kInf);
    for (int32_t k = begin; k < end; ++k) {
      const auto c = centroids.col(order_[static_cast<size_t>(k)]);
      lo = lo.cwiseMin(c);
      hi = hi.cwiseMax(c);
    }
    int axis = 0;
    (hi - lo).maxCoeff(&axis);
    const auto first = order_.begin() + begin;
    const auto last = order_.begin() + end;
    auto mid = first;
    if (depth < kMaxMidpointDepth && hi[axis] > lo[axis]) {
      const double split = 0.5 * (lo[axis] + hi[axis]);
      mid = std::partition(first, last, [&](int32_t tri) { return centroids(axis, tri) < split; });
    }
    if (mid == first || mid == last) {
      mid = first + (end - begin) / 2;
      std::nth_element(first, mid, last, [&](int32_t x, int32_t y) {
        const double cx = centroids(axis, x);
        const double cy = centroids(axis, y);
        return cx < cy || (cx == cy && x < y);
      });
    }
    const auto split_at = static_cast<int32_t>(mid - order_.begin());
    self(self, begin, split_at, depth + 1);
    const auto right = static_cast<int32_t>(nodes_.size());
    self(self, split_at, end, depth + 1);
    nodes_[static_cast<size_t>(node)].index = right;
    nodes_[static_cast<size_t>(node)].count = 0;
  };
  build(build, 0, t_count, 0);
}

// Refit's order. Internal nodes by height (a node after its children), ties in reverse
// depth-first order: consecutive nodes rarely depend on each other, so their refits overlap.
// Leaves in pairs (Refit's AVX2 pass takes two at a time): first the two children of each
// node of height 1, whose box that pass then writes too (so its internal pass starts after
// them), then the other leaves by vertex count (an odd one out pairs with itself); pairs
// sorted by count, so the inner loop's trip count repeats and its exit branch is predicted.
void AabbTree::OrderForRefit(Eigen::Index num_vertices) {
  std::vector<int32_t> leaf_of(nodes_.size(), -1);
  for (size_t l = 0; l < leaves_.size(); ++l) {
    const int32_t end = l + 1 < leaves_.size() ? leaves_[l + 1].vertex_begin
                                               : static_cast<int32_t>(leaf_vertices_.size());
    leaves_[l].vertex_count = end - leaves_[l].vertex_begin;
    leaf_of[static_cast<size_t>(leaves_[l].node)] = static_cast<int32_t>(l);
  }
  const std::vector<int32_t> height = OrderInternalByHeight();
  PairLeaves(height, leaf_of, num_vertices);
}

// Fills internal_ with the internal nodes, children before parents; returns every node's height.
std::vector<int32_t> AabbTree::OrderInternalByHeight() {
  std::vector<int32_t> height(nodes_.size(), 0);
  for (size_t i = nodes_.size(); i-- > 0;) {
    if (nodes_[i].count != 0) continue;
    height[i] = 1 + std::max(height[i + 1], height[static_cast<size_t>(nodes_[i].index)]);
    internal_.push_back(static_cast<int32_t>(i));
  }
  // Total orders throughout (ties by node), so plain sort is deterministic; no stable_sort,
  // whose temporary buffer comes from nothrow new.
  std::sort(internal_.begin(), internal_.end(), [&](int32_t x, int32_t y) {
    const int32_t hx = height[static_cast<size_t>(x)];
    const int32_t hy = height[static_cast<size_t>(y)];
    return hx < hy || (hx == hy && x > y);
  });
  return height;
}

void AabbTree::PairLeaves(const std::vector<int32_t>& height, const std::vector<int32_t>& leaf_of,
                          Eigen::Index num_vertices) {
  struct Pair {
    int32_t first;  // leaves_ indices
    int32_t second;
    int32_t parent;  // the node of height 1 whose children they are, or -1
    int32_t count;   // the larger vertex count, rounded up to even
  };
  auto count_of = [&](int32_t x, int32_t y) {
    const int32_t c = std::max(leaves_[static_cast<size_t>(x)].vertex_count,
                               leaves_[static_cast<size_t>(y)].vertex_count);
    return c + c % 2;
  };
  std::vector<Pair> pairs;
  std::vector<bool> paired(leaves_.size(), false);
  for (const int32_t i : internal_) {
    if (height[static_cast<size_t>(i)] != 1) break;
    const int32_t x = leaf_of[static_cast<size_t>(i) + 1];
    const int32_t y = leaf_of[static_cast<size_t>(nodes_[static_cast<size_t>(i)].index)];
    pairs.push_back(Pair{x, y, i, count_of(x, y)});
    paired[static_cast<size_t>(x)] = true;
    paired[static_cast<size_t>(y)] = true;
    ++num_leaf_parents_;
  }
  std::vector<int32_t> rest;
  for (size_t l = 0; l < leaves_.size(); ++l) {
    if (!paired[l]) rest.push_back(static_cast<int32_t>(l));
  }
  std::sort(rest.begin(), rest.end(), [&](int32_t x, int32_t y) {
    const Leaf& lx = leaves_[static_cast<size_t>(x)];
    const Leaf& ly = leaves_[static_cast<size_t>(y)];
    return lx.vertex_count < ly.vertex_count ||
           (lx.vertex_count == ly.vertex_count && lx.node < ly.node);
  });
  for (size_t k = 0; k < rest.size(); k += 2) {
    const int32_t x = rest[k];
    const int32_t y = rest[std::min(k + 1, rest.size() - 1)];
    pairs.push_back(Pair{x, y, -1, count_of(x, y)});
  }
  // Pairs holding the last vertex go at the very end: the AVX2 pass loads 4 doubles per
  // vertex and masks the fourth only for them (past the last vertex is outside the matrix).
  auto holds_last = [&](const Pair& pair) {
    for (const int32_t l : {pair.first, pair.second}) {
      const Leaf& leaf = leaves_[static_cast<size_t>(l)];
      const auto first = leaf_vertices_.begin() + leaf.vertex_begin;
      const auto last = first + leaf.vertex_count;
      if (std::find(first, last, static_cast<int32_t>(num_vertices - 1)) != last) return true;
    }
    return false;
  };
  auto key = [&](const Pair& pair) {
    return std::make_tuple(holds_last(pair), pair.parent < 0, pair.count, pair.first);
  };
  std::sort(pairs.begin(), pairs.end(),
            [&](const Pair& x, const Pair& y) { return key(x) < key(y); });
  num_unmasked_leaves_ = 0;
  while (num_unmasked_leaves_ / 2 < pairs.size() && !holds_last(pairs[num_unmasked_leaves_ / 2])) {
    num_unmasked_leaves_ += 2;
  }
  // Each pair's vertex lists padded to its count by repeating their last vertex (which
  // changes no min or max).
  std::vector<Leaf> ordered;
  std::vector<int32_t> vertices;
  for (const Pair& pair : pairs) {
    for (const int32_t l : {pair.first, pair.second}) {
      Leaf leaf = leaves_[static_cast<size_t>(l)];
      const auto first = leaf_vertices_.begin() + leaf.vertex_begin;
      const auto last = first + leaf.vertex_count;
      leaf.vertex_begin = static_cast<int32_t>(vertices.size());
      vertices.insert(vertices.end(), first, last);
      vertices.insert(vertices.end(), static_cast<size_t>(pair.count - leaf.vertex_count),
                      *(last - 1));
      leaf.vertex_count = pair.count;
      leaf.parent = pair.parent;
      leaf.parent_index = pair.parent >= 0 ? nodes_[static_cast<size_t>(pair.parent)].index : 0;
      ordered.push_back(leaf);
    }
  }
  leaves_ = std::move(ordered);
  leaf_vertices_ = std::move(vertices);
}

int32_t AabbTree::CountBoxMismatchesForTesting() const {
  const mesh::Points& xs = positions();
  // Each node's triangle slots [first, last): a leaf's own; an internal node's span its
  // children's (children follow their parent, so a reverse pass sees them first).
  std::vector<int32_t> first(nodes_.size());
  std::vector<int32_t> last(nodes_.size());
  for (size_t i = nodes_.size(); i-- > 0;) {
    const Node& node = nodes_[i];
    if (node.count > 0) {
      first[i] = node.index;
      last[i] = node.index + node.count;
    } else {
      first[i] = first[i + 1];
      last[i] = last[static_cast<size_t>(node.index)];
    }
  }
  int32_t mismatches = 0;
  for (size_t i = 0; i < nodes_.size(); ++i) {
    Vector3d lo = Vector3d::Constant(kInf);
    Vector3d hi = Vector3d::Constant(-kInf);
    for (int32_t k = first[i]; k < last[i]; ++k) {
      for (int c = 0; c < 3; ++c) {
        const auto v = xs.col(triangles_(c, order_[static_cast<size_t>(k)]));
        lo = lo.cwiseMin(v);
        hi = hi.cwiseMax(v);
      }
    }
    bool ok = true;
    for (size_t k = 0; k < 3; ++k) {
      const auto e = static_cast<Eigen::Index>(k);
      const Node& node = nodes_[i];
      ok = ok && node.lo[k] == RoundDown(lo[e]) && node.hi[k] == RoundUp(hi[e]) &&
           static_cast<double>(node.lo[k]) <= lo[e] && static_cast<double>(node.hi[k]) >= hi[e];
    }
    mismatches += ok ? 0 : 1;
  }
  return mismatches;
}

int32_t AabbTree::num_triangles() const { return static_cast<int32_t>(triangles_.cols()); }
int32_t AabbTree::num_nodes() const { return static_cast<int32_t>(nodes_.size()); }

}  // namespace somasim::contact
