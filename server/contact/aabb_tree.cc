#include "server/contact/aabb_tree.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <numeric>
#include <stdexcept>
#include <string>
#include <tuple>

#include "server/contact/triangle_queries.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace somasim::contact {
namespace {

using Eigen::Vector3d;

constexpr double kInf = std::numeric_limits<double>::infinity();
// Slack of the box tests. Boxes only prune, so they may be generous: each is grown by
// kRelativeMargin × (scene scale + query scale) [m] (far above the ~1e-16 relative rounding of
// the exact triangle tests, far below any geometric size), so a triangle the exact test accepts
// is never pruned by rounding (the single-precision slab test below has its own, larger margin).
constexpr double kRelativeMargin = 1e-12;

// Double to float rounded down / up, whatever the rounding mode, without branches: move x
// outwards by 2^-22 |x| + 1e-37 first (in double), then convert. A conversion errs by less than
// one float ulp <= 2^-23 |y| + 2^-149 in any rounding mode, which that step exceeds, so the result
// is <= x (>= x). Costs at most ~3 float ulps (3.6e-7 relative) of looseness.
constexpr double kOutwardRelative = 0x1p-22;
constexpr double kOutwardAbsolute = 1e-37;
[[maybe_unused]] float RoundDown(double x) {
  return static_cast<float>(x - (std::abs(x) * kOutwardRelative + kOutwardAbsolute));
}
[[maybe_unused]] float RoundUp(double x) {
  return static_cast<float>(x + (std::abs(x) * kOutwardRelative + kOutwardAbsolute));
}

double MaxAbs(const Vector3d& v) { return v.cwiseAbs().maxCoeff(); }

// A segment p + t d, t in [0, 1], prepared for slab tests in single precision (boxes are floats):
// 1/d with tiny components replaced by a huge finite value, so no 0 × inf makes a NaN (the slab
// of a component that does not move is then everything or nothing, as it should be). Single
// precision rounding (~1e-7 relative) is covered by growing every box by kSlabRelativeMargin ×
// (scene scale + |p| + |q|) and the parameters by kSlabTSlack: the test only prunes, so it may
// be loose, never tight.
constexpr double kSlabRelativeMargin = 1e-6;
constexpr float kSlabTSlack = 1e-5f;

struct Slab {
  alignas(16) std::array<float, 4> p;  // x, y, z, x (the fourth lane repeats x)
  alignas(16) std::array<float, 4> inv;
};

Slab MakeSlab(const Vector3d& p, const Vector3d& q) {
  Slab s{};
  for (size_t i = 0; i < 4; ++i) {
    const auto k = static_cast<Eigen::Index>(i % 3);
    const double d = q[k] - p[k];
    s.p[i] = static_cast<float>(std::clamp(p[k], -1e30, 1e30));  // no out-of-range conversion
    s.inv[i] = std::abs(d) > 1e-30 ? static_cast<float>(1.0 / d) : 1e30f;
  }
  return s;
}

// The box of a segment (or of anything) grown by `grow` [m], in single precision rounded
// outwards: a node's box overlaps it only if the float comparisons say so, exactly (no rounding
// in the test itself). Lane 3 is not compared (a node keeps its index / count there).
struct GrownBox {
  alignas(16) std::array<float, 4> lo;
  alignas(16) std::array<float, 4> hi;
};

GrownBox MakeGrownBox(const Vector3d& p, const Vector3d& q, double grow) {
  GrownBox b{};
  for (size_t i = 0; i < 3; ++i) {
    const auto k = static_cast<Eigen::Index>(i);
    // Clamped to ±1e30 (positions are within it): no out-of-range conversion.
    b.lo[i] = RoundDown(std::clamp(std::min(p[k], q[k]) - grow, -1e30, 1e30));
    b.hi[i] = RoundUp(std::clamp(std::max(p[k], q[k]) + grow, -1e30, 1e30));
  }
  return b;
}

}  // namespace

AabbTree::AabbTree(const mesh::Points& positions, const mesh::Triangles& triangles,
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
  positions_ = positions;
  triangles_ = triangles;
  const auto t_count = static_cast<int32_t>(num_triangles);
  if (t_count == 0) return;

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
  if (max_depth_ >= kMaxDepth) {
    throw std::logic_error("AabbTree: depth bound broken");  // unreachable by construction
  }
  // Refit's order. Internal nodes by height (a node after its children), ties in reverse
  // depth-first order: consecutive nodes rarely depend on each other, so their refits overlap.
  // Leaves in pairs (Refit's AVX2 pass takes two at a time): first the two children of each
  // node of height 1, whose box that pass then writes too (so its internal pass starts after
  // them), then the other leaves by vertex count (an odd one out pairs with itself); pairs
  // sorted by count, so the inner loop's trip count repeats and its exit branch is predicted.
  {
    std::vector<int32_t> leaf_of(nodes_.size(), -1);
    for (size_t l = 0; l < leaves_.size(); ++l) {
      const int32_t end = l + 1 < leaves_.size() ? leaves_[l + 1].vertex_begin
                                                 : static_cast<int32_t>(leaf_vertices_.size());
      leaves_[l].vertex_count = end - leaves_[l].vertex_begin;
      leaf_of[static_cast<size_t>(leaves_[l].node)] = static_cast<int32_t>(l);
    }
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
    while (num_unmasked_leaves_ / 2 < pairs.size() &&
           !holds_last(pairs[num_unmasked_leaves_ / 2])) {
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
  order_vertices_.resize(3 * static_cast<size_t>(t_count));
  for (size_t k = 0; k < order_.size(); ++k) {
    for (int i = 0; i < 3; ++i) {
      order_vertices_[3 * k + static_cast<size_t>(i)] = triangles(i, order_[k]);
    }
  }
  Refit(positions_);
  external_ = nullptr;  // the tree's own copy, so a temporary `positions` may go
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

namespace {

std::atomic<bool> g_refit_avx2_enabled{true};

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define SOMASIM_AABB_AVX2 1
bool CpuHasAvx2() {
  static const bool has = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") != 0;
  }();
  return has;
}

// Refit's leaf pass with AVX2: a vertex's xyz in lanes 0-2 of one 4-lane register, the same
// arithmetic as the SSE2 / scalar pass (exact min / max, then outwards by
// 2^-22 |v| + 1e-37 and converted), so both give identical boxes. Leaves go in pairs of equal,
// even vertex counts (see the build): four independent min / max chains, so the loop waits on
// a quarter of the latencies of one. When the pair are a node's two children, that node's box
// is the float min / max of theirs, as in the internal pass. Nodes are written whole, 32 bytes
// from registers (index and count come with the leaf), never read: leaves are visited in
// Refit's order, not the nodes', and a read-modify-write would wait on each node's line.
// Templated so that it can take the tree's private Leaf and Node types.
template <bool kMasked, typename LeafT, typename NodeT>
__attribute__((target("avx2"))) void RefitLeavesAvx2(const double* x, const LeafT* leaves,
                                                     size_t num_leaves, const int32_t* vertices,
                                                     NodeT* nodes) {
  const __m256i xyz = _mm256_set_epi64x(0, -1, -1, -1);
  // Vertex v's xyz in lanes 0-2. Unmasked, lane 3 is the next vertex's x (never stored), which
  // is why the build puts the pairs holding the last vertex at the end, for the masked call.
  auto load = [ x, xyz ](int32_t v) __attribute__((target("avx2"))) {
    const double* at = x + 3 * static_cast<ptrdiff_t>(v);
    return kMasked ? _mm256_maskload_pd(at, xyz) : _mm256_loadu_pd(at);
  };
  const __m256d sign = _mm256_set1_pd(-0.0);
  const __m256d rel = _mm256_set1_pd(kOutwardRelative);
  const __m256d abs_ = _mm256_set1_pd(kOutwardAbsolute);
  for (size_t l = 0; l < num_leaves; l += 2) {
    const LeafT& leaf_a = leaves[l];
    const LeafT& leaf_b = leaves[l + 1];
    const int32_t* ka = vertices + leaf_a.vertex_begin;
    const int32_t* kb = vertices + leaf_b.vertex_begin;
    const int32_t count = leaf_a.vertex_count;
    __m256d lo[4];
    lo[0] = load(ka[0]);
    lo[1] = load(ka[1]);
    lo[2] = load(kb[0]);
    lo[3] = load(kb[1]);
    __m256d hi[4] = {lo[0], lo[1], lo[2], lo[3]};
    for (int32_t j = 2; j < count; j += 2) {
      const __m256d a0 = load(ka[j]);
      const __m256d a1 = load(ka[j + 1]);
      const __m256d b0 = load(kb[j]);
      const __m256d b1 = load(kb[j + 1]);
      lo[0] = _mm256_min_pd(lo[0], a0);
      hi[0] = _mm256_max_pd(hi[0], a0);
      lo[1] = _mm256_min_pd(lo[1], a1);
      hi[1] = _mm256_max_pd(hi[1], a1);
      lo[2] = _mm256_min_pd(lo[2], b0);
      hi[2] = _mm256_max_pd(hi[2], b0);
      lo[3] = _mm256_min_pd(lo[3], b1);
      hi[3] = _mm256_max_pd(hi[3], b1);
    }
    __m128 flo[2];
    __m128 fhi[2];
    for (size_t s = 0; s < 2; ++s) {
      __m256d box_lo = _mm256_min_pd(lo[2 * s], lo[2 * s + 1]);
      __m256d box_hi = _mm256_max_pd(hi[2 * s], hi[2 * s + 1]);
      box_lo = _mm256_sub_pd(
          box_lo, _mm256_add_pd(_mm256_mul_pd(_mm256_andnot_pd(sign, box_lo), rel), abs_));
      box_hi = _mm256_add_pd(
          box_hi, _mm256_add_pd(_mm256_mul_pd(_mm256_andnot_pd(sign, box_hi), rel), abs_));
      flo[s] = _mm256_cvtpd_ps(box_lo);
      fhi[s] = _mm256_cvtpd_ps(box_hi);
      const LeafT& leaf = s == 0 ? leaf_a : leaf_b;
      const __m128i node_lo = _mm_insert_epi32(_mm_castps_si128(flo[s]), leaf.triangle_begin, 3);
      const __m128i node_hi = _mm_insert_epi32(_mm_castps_si128(fhi[s]), leaf.triangle_count, 3);
      _mm256_store_si256(reinterpret_cast<__m256i*>(nodes + leaf.node),
                         _mm256_set_m128i(node_hi, node_lo));
    }
    if (leaf_a.parent >= 0) {  // the pairs with a parent come first: predicted
      const __m128i node_lo =
          _mm_insert_epi32(_mm_castps_si128(_mm_min_ps(flo[0], flo[1])), leaf_a.parent_index, 3);
      const __m128i node_hi = _mm_insert_epi32(_mm_castps_si128(_mm_max_ps(fhi[0], fhi[1])), 0, 3);
      _mm256_store_si256(reinterpret_cast<__m256i*>(nodes + leaf_a.parent),
                         _mm256_set_m128i(node_hi, node_lo));
    }
  }
}

// Refit's internal pass with AVX2: each child's whole node in one register (lo[3], index,
// hi[3], count), their min in the low half and max in the high half, the node's own index
// and count (0) in lanes 3 and 7, one 32-byte store. Float min / max as in the portable pass.
template <typename NodeT>
__attribute__((target("avx2"))) void RefitInternalAvx2(NodeT* nodes, const int32_t* internal,
                                                       size_t count) {
  for (size_t n = 0; n < count; ++n) {
    const int32_t i = internal[n];
    NodeT& node = nodes[i];
    const int32_t right = node.index;
    const __m256 a = _mm256_load_ps(nodes[i + 1].lo);
    const __m256 b = _mm256_load_ps(nodes[right].lo);
    const __m256 box = _mm256_blend_ps(_mm256_min_ps(a, b), _mm256_max_ps(a, b), 0xF0);
    const __m256 own = _mm256_castsi256_ps(_mm256_set_epi32(0, 0, 0, 0, right, 0, 0, 0));
    _mm256_store_ps(node.lo, _mm256_blend_ps(box, own, 0x88));
  }
}
#endif

}  // namespace

void SetAabbRefitAvx2ForTesting(bool enabled) { g_refit_avx2_enabled.store(enabled); }

void AabbTree::Refit(const mesh::Points& positions) {
  if (positions.cols() != positions_.cols()) {
    throw std::invalid_argument("AabbTree::Refit: " + std::to_string(positions.cols()) +
                                " positions, the tree was built over " +
                                std::to_string(positions_.cols()));
  }
  external_ = &positions;  // no copy (see the header's lifetime rule)
  ++refits_;
  if (nodes_.empty()) return;
  // Leaves: the box of their distinct vertices in double, then rounded outwards once.
  const double* x = positions.data();
#if defined(SOMASIM_AABB_AVX2)
  const bool avx2 = CpuHasAvx2() && g_refit_avx2_enabled.load(std::memory_order_relaxed);
  if (avx2) {
    RefitLeavesAvx2<false>(x, leaves_.data(), num_unmasked_leaves_, leaf_vertices_.data(),
                           nodes_.data());
    RefitLeavesAvx2<true>(x, leaves_.data() + num_unmasked_leaves_,
                          leaves_.size() - num_unmasked_leaves_, leaf_vertices_.data(),
                          nodes_.data());
  }
#else
  constexpr bool avx2 = false;
#endif
  for (const Leaf& leaf : leaves_) {
    if (avx2) break;
    const int32_t* begin = leaf_vertices_.data() + leaf.vertex_begin;
    const int32_t* end = begin + leaf.vertex_count;
    Node& node = nodes_[static_cast<size_t>(leaf.node)];
#if defined(__SSE2__)
    // SSE2 (every x86-64): xy in one register, z in another.
    __m128d lo_xy = _mm_set1_pd(kInf);
    __m128d hi_xy = _mm_set1_pd(-kInf);
    __m128d lo_z = lo_xy;
    __m128d hi_z = hi_xy;
    for (const int32_t* k = begin; k != end; ++k) {
      const double* v = x + 3 * static_cast<ptrdiff_t>(*k);
      const __m128d xy = _mm_loadu_pd(v);
      const __m128d z = _mm_load_sd(v + 2);
      lo_xy = _mm_min_pd(lo_xy, xy);
      hi_xy = _mm_max_pd(hi_xy, xy);
      lo_z = _mm_min_sd(lo_z, z);
      hi_z = _mm_max_sd(hi_z, z);
    }
    // Outwards by 2^-22 |v| + 1e-37, then to float (see RoundDown).
    const __m128d sign = _mm_set1_pd(-0.0);
    const __m128d rel = _mm_set1_pd(kOutwardRelative);
    const __m128d abs_ = _mm_set1_pd(kOutwardAbsolute);
    auto pad = [&](__m128d v) { return _mm_add_pd(_mm_mul_pd(_mm_andnot_pd(sign, v), rel), abs_); };
    const __m128 flo_xy = _mm_cvtpd_ps(_mm_sub_pd(lo_xy, pad(lo_xy)));
    const __m128 fhi_xy = _mm_cvtpd_ps(_mm_add_pd(hi_xy, pad(hi_xy)));
    const __m128 flo_z = _mm_cvtpd_ps(_mm_sub_pd(lo_z, pad(lo_z)));
    const __m128 fhi_z = _mm_cvtpd_ps(_mm_add_pd(hi_z, pad(hi_z)));
    _mm_storel_pi(reinterpret_cast<__m64*>(node.lo), flo_xy);
    _mm_store_ss(node.lo + 2, flo_z);
    _mm_storel_pi(reinterpret_cast<__m64*>(node.hi), fhi_xy);
    _mm_store_ss(node.hi + 2, fhi_z);
#else
    double lo[3] = {kInf, kInf, kInf};
    double hi[3] = {-kInf, -kInf, -kInf};
    for (const int32_t* k = begin; k != end; ++k) {
      const double* v = x + 3 * static_cast<ptrdiff_t>(*k);
      for (int i = 0; i < 3; ++i) {
        lo[i] = std::min(lo[i], v[i]);
        hi[i] = std::max(hi[i], v[i]);
      }
    }
    for (int i = 0; i < 3; ++i) {
      node.lo[i] = RoundDown(lo[i]);
      node.hi[i] = RoundUp(hi[i]);
    }
#endif
  }
  // Internal nodes bottom-up: in order of height, so one pass sees both children before the
  // parent. Float min/max is exact.
  Node* const nodes = nodes_.data();  // hoisted: the stores below cannot move the vector
  // The AVX2 leaf pass has fitted the nodes of height 1 (internal_'s first) already.
  const size_t first_internal = avx2 ? num_leaf_parents_ : 0;
#if defined(SOMASIM_AABB_AVX2)
  if (avx2) {
    RefitInternalAvx2(nodes, internal_.data() + first_internal, internal_.size() - first_internal);
  }
#endif
  for (size_t n = first_internal; n < internal_.size(); ++n) {
    if (avx2) break;
    const int32_t i = internal_[n];
    Node& node = nodes[i];
    const Node& a = nodes[i + 1];
    const Node& b = nodes[node.index];
#if defined(__SSE2__)
    // 16-byte loads of lo[3] + index and hi[3] + count; the fourth lane keeps the node's own
    // index / count. Whole 16-byte stores, so the parent's loads (often the next iteration) are
    // forwarded from the store buffer instead of stalling on partial stores.
    const __m128 box_lanes = _mm_castsi128_ps(_mm_set_epi32(0, -1, -1, -1));
    const __m128 lo = _mm_min_ps(_mm_loadu_ps(a.lo), _mm_loadu_ps(b.lo));
    const __m128 hi = _mm_max_ps(_mm_loadu_ps(a.hi), _mm_loadu_ps(b.hi));
    _mm_storeu_ps(node.lo, _mm_or_ps(_mm_and_ps(box_lanes, lo),
                                     _mm_andnot_ps(box_lanes, _mm_loadu_ps(node.lo))));
    _mm_storeu_ps(node.hi, _mm_or_ps(_mm_and_ps(box_lanes, hi),
                                     _mm_andnot_ps(box_lanes, _mm_loadu_ps(node.hi))));
#else
    for (int k = 0; k < 3; ++k) {
      node.lo[k] = std::min(a.lo[k], b.lo[k]);
      node.hi[k] = std::max(a.hi[k], b.hi[k]);
    }
#endif
  }
  const Node& root = nodes_[0];
  scale_ = 0.0;
  for (int k = 0; k < 3; ++k) {
    scale_ = std::max({scale_, std::abs(static_cast<double>(root.lo[k])),
                       std::abs(static_cast<double>(root.hi[k]))});
  }
}

namespace {

// The parameter interval of segment s inside box [lo - grow, hi + grow], clipped to
// [0, limit]: true with the entry parameter when they overlap (within kSlabTSlack).
template <typename NodeT>
inline bool SlabEntry(const NodeT& node, const Slab& s, float grow, float limit, float* entry) {
#if defined(__SSE2__)
  // Lanes x, y, z, x: the fourth lane (the node's index / count) is replaced by x.
  const __m128 lo4 = _mm_loadu_ps(node.lo);
  const __m128 hi4 = _mm_loadu_ps(node.hi);
  const __m128 g = _mm_set1_ps(grow);
  const __m128 p = _mm_load_ps(s.p.data());
  const __m128 inv = _mm_load_ps(s.inv.data());
  const __m128 lo = _mm_shuffle_ps(lo4, lo4, _MM_SHUFFLE(0, 2, 1, 0));
  const __m128 hi = _mm_shuffle_ps(hi4, hi4, _MM_SHUFFLE(0, 2, 1, 0));
  const __m128 a = _mm_mul_ps(_mm_sub_ps(_mm_sub_ps(lo, g), p), inv);
  const __m128 b = _mm_mul_ps(_mm_sub_ps(_mm_add_ps(hi, g), p), inv);
  __m128 t0 = _mm_min_ps(a, b);
  __m128 t1 = _mm_max_ps(a, b);
  // Horizontal max of the entries, min of the exits.
  t0 = _mm_max_ps(t0, _mm_shuffle_ps(t0, t0, _MM_SHUFFLE(1, 0, 3, 2)));
  t0 = _mm_max_ps(t0, _mm_shuffle_ps(t0, t0, _MM_SHUFFLE(2, 3, 0, 1)));
  t1 = _mm_min_ps(t1, _mm_shuffle_ps(t1, t1, _MM_SHUFFLE(1, 0, 3, 2)));
  t1 = _mm_min_ps(t1, _mm_shuffle_ps(t1, t1, _MM_SHUFFLE(2, 3, 0, 1)));
  const float enter = std::max(_mm_cvtss_f32(t0), 0.0f);
  const float exit = std::min(_mm_cvtss_f32(t1), limit);
#else
  float enter = 0.0f;
  float exit = limit;
  for (size_t i = 0; i < 3; ++i) {
    const float a = (node.lo[i] - grow - s.p[i]) * s.inv[i];
    const float b = (node.hi[i] + grow - s.p[i]) * s.inv[i];
    enter = std::max(enter, std::min(a, b));
    exit = std::min(exit, std::max(a, b));
  }
#endif
  *entry = enter;
  return enter <= exit + kSlabTSlack;
}

// Whether the node's box overlaps box b: two comparisons, no arithmetic, so it is exact (the
// growth and outward rounding are in b). A short dependency chain: the traversal's decision at
// each node waits on it.
template <typename NodeT>
inline bool BoxesOverlap(const NodeT& node, const GrownBox& b) {
#if defined(__SSE2__)
  const __m128 below = _mm_cmple_ps(_mm_loadu_ps(node.lo), _mm_load_ps(b.hi.data()));
  const __m128 above = _mm_cmpge_ps(_mm_loadu_ps(node.hi), _mm_load_ps(b.lo.data()));
  return (_mm_movemask_ps(_mm_and_ps(below, above)) & 7) == 7;
#else
  for (size_t i = 0; i < 3; ++i) {
    if (!(node.lo[i] <= b.hi[i] && node.hi[i] >= b.lo[i])) return false;
  }
  return true;
#endif
}

// Squared distance [m²] from the segment's start s.p to the box, in single precision: only an
// ordering key (which child to visit first), never a pruning test.
template <typename NodeT>
inline float StartDistanceSquared(const NodeT& node, const Slab& s) {
#if defined(__SSE2__)
  const __m128 p = _mm_load_ps(s.p.data());
  const __m128 lo4 = _mm_loadu_ps(node.lo);
  const __m128 hi4 = _mm_loadu_ps(node.hi);
  const __m128 lo = _mm_shuffle_ps(lo4, lo4, _MM_SHUFFLE(0, 2, 1, 0));
  const __m128 hi = _mm_shuffle_ps(hi4, hi4, _MM_SHUFFLE(0, 2, 1, 0));
  const __m128 d = _mm_max_ps(_mm_max_ps(_mm_sub_ps(lo, p), _mm_sub_ps(p, hi)), _mm_setzero_ps());
  __m128 d2 = _mm_mul_ps(d, d);
  // Lanes x, y, z, x: add x + y + z.
  d2 = _mm_add_ss(_mm_add_ss(d2, _mm_shuffle_ps(d2, d2, _MM_SHUFFLE(1, 1, 1, 1))),
                  _mm_shuffle_ps(d2, d2, _MM_SHUFFLE(2, 2, 2, 2)));
  return _mm_cvtss_f32(d2);
#else
  float d2 = 0.0f;
  for (size_t i = 0; i < 3; ++i) {
    const float d = std::max({node.lo[i] - s.p[i], 0.0f, s.p[i] - node.hi[i]});
    d2 += d * d;
  }
  return d2;
#endif
}

// Whether segment p + t d, t in [0, 1] (inv_d = 1/d, tiny components replaced by 1e200) meets
// box [lo, hi], in double with a relative slack: a conservative reject for single triangles.
inline bool SegmentMeetsBox(const Vector3d& p, const Vector3d& inv_d, const Vector3d& lo,
                            const Vector3d& hi) {
  double enter = 0.0;
  double exit = 1.0;
  for (int i = 0; i < 3; ++i) {
    const double a = (lo[i] - p[i]) * inv_d[i];
    const double b = (hi[i] - p[i]) * inv_d[i];
    enter = std::max(enter, std::min(a, b));
    exit = std::min(exit, std::max(a, b));
  }
  return enter <= exit + 1e-9;
}

// Whether the box of triangle abc overlaps box [lo, hi] (in double, exact).
template <typename Col>
inline bool TriangleMeetsBox(const Col& a, const Col& b, const Col& c, const Vector3d& lo,
                             const Vector3d& hi) {
  for (int i = 0; i < 3; ++i) {
    if (std::max({a[i], b[i], c[i]}) < lo[i] || std::min({a[i], b[i], c[i]}) > hi[i]) {
      return false;
    }
  }
  return true;
}

// Squared distance [m²] from x to box [lo, hi].
template <typename NodeT>
inline double BoxDistanceSquared(const NodeT& node, const Vector3d& x) {
  double d2 = 0.0;
  for (int i = 0; i < 3; ++i) {
    const double lo = static_cast<double>(node.lo[i]);
    const double hi = static_cast<double>(node.hi[i]);
    const double d = std::max({lo - x[i], 0.0, x[i] - hi});
    d2 += d * d;
  }
  return d2;
}

}  // namespace

bool AabbTree::FirstHit(const Vector3d& p, const Vector3d& q, SegmentHit* hit) const {
  const mesh::Points& xs = positions();
  if (nodes_.empty() || !p.allFinite() || !q.allFinite()) return false;
  const PreparedSegment segment(p, q);
  const Slab slab = MakeSlab(p, q);
  const double grow_m = kSlabRelativeMargin * (scale_ + MaxAbs(p) + MaxAbs(q)) + 1e-30;
  const auto grow = static_cast<float>(grow_m);
  const GrownBox box = MakeGrownBox(p, q, grow_m);
  const Vector3d seg_lo = p.cwiseMin(q) - Vector3d::Constant(grow_m);
  const Vector3d seg_hi = p.cwiseMax(q) + Vector3d::Constant(grow_m);
  double best_t = kInf;
  int32_t best_triangle = -1;
  Vector3d best_bary = Vector3d::Zero();
  struct Entry {
    int32_t node;
    float t;
  };
  std::array<Entry, kMaxDepth> stack;  // not value-initialised: only pushed entries are read
  size_t top = 0;
  float entry = 0.0f;
  if (!SlabEntry(nodes_[0], slab, grow, 1.0f, &entry)) return false;
  int32_t current = 0;
  while (true) {
    const Node& node = nodes_[static_cast<size_t>(current)];
    bool descend = false;
    if (node.count > 0) {
      for (int32_t k = node.index; k < node.index + node.count; ++k) {
        const int32_t* v = &order_vertices_[3 * static_cast<size_t>(k)];
        const auto a = xs.col(v[0]);
        const auto b = xs.col(v[1]);
        const auto c = xs.col(v[2]);
        // The triangle's box must overlap the segment's grown box: a triangle farther than
        // grow_m from the segment (1e-6 of the scene's scale, far beyond the exact test's
        // rounding) cannot be crossed, and most of a leaf's triangles are.
        if (!TriangleMeetsBox(a, b, c, seg_lo, seg_hi)) continue;
        double t = 0.0;
        Vector3d bary;
        if (!segment.Intersect(a, b, c, &t, &bary)) continue;
        const int32_t tri = order_[static_cast<size_t>(k)];
        if (t < best_t || (t == best_t && tri < best_triangle)) {
          best_t = t;
          best_triangle = tri;
          best_bary = bary;
        }
      }
    } else {
      const auto limit = static_cast<float>(std::min(1.0, best_t));
      const int32_t left = current + 1;
      const int32_t right = node.index;
      // First the cheap test against the segment's grown box (exact, and weaker than the slab
      // test: a box the segment meets overlaps the segment's box); the slab test only when both
      // children pass it, for their order and entry parameters.
      bool hl = BoxesOverlap(nodes_[static_cast<size_t>(left)], box);
      bool hr = BoxesOverlap(nodes_[static_cast<size_t>(right)], box);
      float tl = 0.0f;
      float tr = 0.0f;
      if (hl && hr) {
        hl = SlabEntry(nodes_[static_cast<size_t>(left)], slab, grow, limit, &tl);
        hr = SlabEntry(nodes_[static_cast<size_t>(right)], slab, grow, limit, &tr);
      }
      if (hl && hr) {
        // Nearer child first: its hits may prune the farther one.
        const bool left_first = tl <= tr;
        stack[top++] = Entry{left_first ? right : left, left_first ? tr : tl};
        current = left_first ? left : right;
        descend = true;
      } else if (hl || hr) {
        current = hl ? left : right;
        descend = true;
      }
    }
    if (descend) continue;
    // Pop the next box that may still hold a crossing at or before the best one.
    bool found = false;
    while (top > 0) {
      const Entry e = stack[--top];
      if (static_cast<double>(e.t) <= best_t + static_cast<double>(kSlabTSlack)) {
        current = e.node;
        found = true;
        break;
      }
    }
    if (!found) break;
  }
  if (best_triangle < 0) return false;
  hit->triangle = best_triangle;
  hit->t = best_t;
  hit->barycentric = best_bary;
  hit->point = p + best_t * (q - p);
  return true;
}

bool AabbTree::Nearest(const Vector3d& x, SurfacePoint* nearest, double max_distance) const {
  const mesh::Points& xs = positions();
  if (nodes_.empty() || !x.allFinite() || !(max_distance >= 0.0)) return false;
  const double margin = kRelativeMargin * (scale_ + MaxAbs(x));
  double best_d2 = max_distance * max_distance;
  double bound = (max_distance + margin) * (max_distance + margin);  // prune boxes beyond
  int32_t best_triangle = -1;
  Vector3d best_bary = Vector3d::Zero();
  struct Entry {
    int32_t node;
    double d2;
  };
  std::array<Entry, kMaxDepth> stack;  // not value-initialised: only pushed entries are read
  size_t top = 0;
  if (BoxDistanceSquared(nodes_[0], x) > bound) return false;
  int32_t current = 0;
  while (true) {
    const Node& node = nodes_[static_cast<size_t>(current)];
    bool descend = false;
    if (node.count > 0) {
      for (int32_t k = node.index; k < node.index + node.count; ++k) {
        const int32_t* v = &order_vertices_[3 * static_cast<size_t>(k)];
        Vector3d bary;
        const double d2 =
            PointTriangleDistanceSquared(x, xs.col(v[0]), xs.col(v[1]), xs.col(v[2]), &bary);
        const int32_t tri = order_[static_cast<size_t>(k)];
        if (d2 < best_d2 || (d2 == best_d2 && (best_triangle < 0 || tri < best_triangle))) {
          best_d2 = d2;
          best_triangle = tri;
          best_bary = bary;
          const double r = std::sqrt(best_d2) + margin;
          bound = r * r;
        }
      }
    } else {
      const int32_t left = current + 1;
      const int32_t right = node.index;
      const double dl = BoxDistanceSquared(nodes_[static_cast<size_t>(left)], x);
      const double dr = BoxDistanceSquared(nodes_[static_cast<size_t>(right)], x);
      const bool hl = dl <= bound;
      const bool hr = dr <= bound;
      if (hl && hr) {
        const bool left_first = dl <= dr;
        stack[top++] = Entry{left_first ? right : left, left_first ? dr : dl};
        current = left_first ? left : right;
        descend = true;
      } else if (hl || hr) {
        current = hl ? left : right;
        descend = true;
      }
    }
    if (descend) continue;
    bool found = false;
    while (top > 0) {
      const Entry e = stack[--top];
      if (e.d2 <= bound) {
        current = e.node;
        found = true;
        break;
      }
    }
    if (!found) break;
  }
  if (best_triangle < 0) return false;
  const auto tri = triangles_.col(best_triangle);
  nearest->triangle = best_triangle;
  nearest->barycentric = best_bary;
  nearest->point = best_bary.x() * xs.col(tri[0]) + best_bary.y() * xs.col(tri[1]) +
                   best_bary.z() * xs.col(tri[2]);
  nearest->distance = std::sqrt(best_d2);
  return true;
}

int32_t AabbTree::SphereQuery(const Vector3d& c, double radius, std::span<int32_t> out) const {
  const mesh::Points& xs = positions();
  if (nodes_.empty() || !c.allFinite() || !(radius >= 0.0) || !std::isfinite(radius)) return 0;
  const double r2 = radius * radius;
  const double grown = radius + kRelativeMargin * (scale_ + MaxAbs(c));
  const double bound = grown * grown;
  std::array<int32_t, kMaxDepth> stack;  // not value-initialised: only pushed entries are read
  size_t top = 0;
  int32_t found = 0;
  if (BoxDistanceSquared(nodes_[0], c) > bound) return 0;
  stack[top++] = 0;
  while (top > 0) {
    int32_t current = stack[--top];
    while (true) {
      const Node& node = nodes_[static_cast<size_t>(current)];
      if (node.count > 0) {
        for (int32_t k = node.index; k < node.index + node.count; ++k) {
          const int32_t* v = &order_vertices_[3 * static_cast<size_t>(k)];
          Vector3d bary;
          const double d2 =
              PointTriangleDistanceSquared(c, xs.col(v[0]), xs.col(v[1]), xs.col(v[2]), &bary);
          if (d2 <= r2) {
            if (static_cast<size_t>(found) < out.size()) {
              out[static_cast<size_t>(found)] = order_[static_cast<size_t>(k)];
            }
            ++found;
          }
        }
        break;
      }
      const int32_t left = current + 1;
      const int32_t right = node.index;
      const bool hl = BoxDistanceSquared(nodes_[static_cast<size_t>(left)], c) <= bound;
      const bool hr = BoxDistanceSquared(nodes_[static_cast<size_t>(right)], c) <= bound;
      if (hl && hr) stack[top++] = right;
      if (!hl && !hr) break;
      current = hl ? left : right;
    }
  }
  return found;
}

int32_t AabbTree::CapsuleQuery(const Vector3d& p, const Vector3d& q, double radius,
                               std::span<int32_t> out) const {
  const mesh::Points& xs = positions();
  if (nodes_.empty() || !p.allFinite() || !q.allFinite() || !(radius >= 0.0) ||
      !std::isfinite(radius)) {
    return 0;
  }
  const PreparedSegment segment(p, q);
  const Slab slab = MakeSlab(p, q);
  const double r2 = radius * radius;
  const double margin = kRelativeMargin * (scale_ + MaxAbs(p) + MaxAbs(q));
  const double grown = radius + margin;
  const auto box_grow =
      static_cast<float>(radius + kSlabRelativeMargin * (scale_ + MaxAbs(p) + MaxAbs(q)) + 1e-30);
  std::array<int32_t, kMaxDepth> stack;  // not value-initialised: only pushed entries are read
  size_t top = 0;
  int32_t found = 0;
  float entry = 0.0f;
  if (!SlabEntry(nodes_[0], slab, box_grow, 1.0f, &entry)) return 0;
  stack[top++] = 0;
  while (top > 0) {
    int32_t current = stack[--top];
    while (true) {
      const Node& node = nodes_[static_cast<size_t>(current)];
      if (node.count > 0) {
        for (int32_t k = node.index; k < node.index + node.count; ++k) {
          const int32_t* v = &order_vertices_[3 * static_cast<size_t>(k)];
          const auto a = xs.col(v[0]);
          const auto b = xs.col(v[1]);
          const auto c = xs.col(v[2]);
          double s = 0.0;
          Vector3d bary;
          if (segment.DistanceSquaredWithin(a, b, c, grown, &s, &bary) <= r2) {
            if (static_cast<size_t>(found) < out.size()) {
              out[static_cast<size_t>(found)] = order_[static_cast<size_t>(k)];
            }
            ++found;
          }
        }
        break;
      }
      const int32_t left = current + 1;
      const int32_t right = node.index;
      const bool hl = SlabEntry(nodes_[static_cast<size_t>(left)], slab, box_grow, 1.0f, &entry);
      const bool hr = SlabEntry(nodes_[static_cast<size_t>(right)], slab, box_grow, 1.0f, &entry);
      if (hl && hr) stack[top++] = right;
      if (!hl && !hr) break;
      current = hl ? left : right;
    }
  }
  return found;
}

bool AabbTree::NearestToSegment(const Vector3d& p, const Vector3d& q, double radius,
                                SurfacePoint* nearest) const {
  const mesh::Points& xs = positions();
  if (nodes_.empty() || !p.allFinite() || !q.allFinite() || !(radius >= 0.0) ||
      !std::isfinite(radius)) {
    return false;
  }
  const PreparedSegment segment(p, q);
  const Slab slab = MakeSlab(p, q);
  Vector3d inv_d;
  for (int i = 0; i < 3; ++i) {
    const double d = q[i] - p[i];
    inv_d[i] = std::abs(d) > 1e-200 ? 1.0 / d : 1e200;
  }
  const double margin = kRelativeMargin * (scale_ + MaxAbs(p) + MaxAbs(q));
  double best_d2 = radius * radius;
  double grown = radius + margin;  // planes farther than this cannot improve
  const double box_margin = kSlabRelativeMargin * (scale_ + MaxAbs(p) + MaxAbs(q)) + 1e-30;
  auto box_grow = static_cast<float>(radius + box_margin);  // nor boxes farther than this
  int32_t best_triangle = -1;
  double best_s = 0.0;
  Vector3d best_bary = Vector3d::Zero();
  struct Entry {
    int32_t node;
    float grow;  // the box growth it was tested with
  };
  std::array<Entry, kMaxDepth> stack;  // not value-initialised: only pushed entries are read
  size_t top = 0;
  float entry = 0.0f;
  if (!SlabEntry(nodes_[0], slab, box_grow, 1.0f, &entry)) return false;
  int32_t current = 0;
  while (true) {
    const Node& node = nodes_[static_cast<size_t>(current)];
    bool descend = false;
    if (node.count > 0) {
      for (int32_t k = node.index; k < node.index + node.count; ++k) {
        const int32_t* v = &order_vertices_[3 * static_cast<size_t>(k)];
        const auto a = xs.col(v[0]);
        const auto b = xs.col(v[1]);
        const auto c = xs.col(v[2]);
        double s = 0.0;
        Vector3d bary;
        // The triangle's own box grown by the radius must meet the segment (a cheap reject of
        // the neighbours of the nearest triangle, whose planes are about as near).
        if (!SegmentMeetsBox(p, inv_d, a.cwiseMin(b).cwiseMin(c) - Vector3d::Constant(grown),
                             a.cwiseMax(b).cwiseMax(c) + Vector3d::Constant(grown))) {
          continue;
        }
        const double d2 = segment.DistanceSquaredWithin(a, b, c, grown, &s, &bary);
        const int32_t tri = order_[static_cast<size_t>(k)];
        if (d2 < best_d2 || (d2 == best_d2 && (best_triangle < 0 || tri < best_triangle))) {
          best_d2 = d2;
          best_triangle = tri;
          best_s = s;
          best_bary = bary;
          grown = std::sqrt(best_d2) + margin;
          box_grow = static_cast<float>(std::sqrt(best_d2) + box_margin);
        }
      }
    } else {
      const int32_t left = current + 1;
      const int32_t right = node.index;
      const bool hl = SlabEntry(nodes_[static_cast<size_t>(left)], slab, box_grow, 1.0f, &entry);
      const bool hr = SlabEntry(nodes_[static_cast<size_t>(right)], slab, box_grow, 1.0f, &entry);
      if (hl && hr) {
        // Nearer the tip p first: the nearest surface point is usually there, and finding it
        // early shrinks the radius that prunes the rest.
        const bool left_first = StartDistanceSquared(nodes_[static_cast<size_t>(left)], slab) <=
                                StartDistanceSquared(nodes_[static_cast<size_t>(right)], slab);
        stack[top++] = Entry{left_first ? right : left, box_grow};
        current = left_first ? left : right;
        descend = true;
      } else if (hl || hr) {
        current = hl ? left : right;
        descend = true;
      }
    }
    if (descend) continue;
    // Boxes on the stack were tested with an older (larger) radius: test again.
    bool found = false;
    while (top > 0) {
      const Entry e = stack[--top];
      if (e.grow == box_grow ||
          SlabEntry(nodes_[static_cast<size_t>(e.node)], slab, box_grow, 1.0f, &entry)) {
        current = e.node;
        found = true;
        break;
      }
    }
    if (!found) break;
  }
  if (best_triangle < 0) return false;
  (void)best_s;
  const auto tri = triangles_.col(best_triangle);
  nearest->triangle = best_triangle;
  nearest->barycentric = best_bary;
  nearest->point = best_bary.x() * xs.col(tri[0]) + best_bary.y() * xs.col(tri[1]) +
                   best_bary.z() * xs.col(tri[2]);
  nearest->distance = std::sqrt(best_d2);
  return true;
}

}  // namespace somasim::contact
