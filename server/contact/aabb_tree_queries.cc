// The AABB tree's queries: the first crossing of a segment, the nearest surface point to a point
// or a segment, every triangle within a sphere or a capsule. Boxes only prune (single-precision
// tests with margins); the answers come from the exact double-precision triangle tests.
#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <span>

#include "common/checks/finite.h"
#include "server/contact/aabb_tree.h"
#include "server/contact/aabb_tree_internal.h"
#include "server/contact/triangle_queries.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace somasim::contact {
namespace {

using aabb_internal::kInf;
using aabb_internal::RoundDown;
using aabb_internal::RoundUp;
using Eigen::Vector3d;

// Slack of the box tests. Boxes only prune, so they may be generous: each is grown by
// kRelativeMargin × (scene scale + query scale) [m] (far above the ~1e-16 relative rounding of
// the exact triangle tests, far below any geometric size), so a triangle the exact test accepts
// is never pruned by rounding (the single-precision slab test below has its own, larger margin).
constexpr double kRelativeMargin = 1e-12;

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

// The stack of a best-first traversal (FirstHit, Nearest, NearestToSegment): when both children
// of a node pass, the traversal goes on into the one that may answer best and pushes the other
// with its key (its entry parameter, squared distance or the growth it was tested with); a pop
// takes the next entry whose key says it may still hold a better answer. Depth is bounded
// (AabbTree::kMaxDepth), so the stack is a fixed array.
template <typename Key>
class BestFirstStack {
 public:
  // From an internal node whose children `left` and `right` passed the box tests hl and hr: into
  // the only one that passed, or, when both did, into the one left_first() picks (left when
  // true), the other pushed with its key. False when neither passed (the caller pops then).
  template <typename LeftFirst>
  bool Descend(int32_t left, int32_t right, bool hl, bool hr, Key key_left, Key key_right,
               LeftFirst left_first, int32_t* current) {
    if (hl && hr) {
      const bool first_left = left_first();
      entries_[top_++] = Entry{first_left ? right : left, first_left ? key_right : key_left};
      *current = first_left ? left : right;
      return true;
    }
    if (hl || hr) {
      *current = hl ? left : right;
      return true;
    }
    return false;
  }
  // Pops entries until one that keep(node, key) accepts, which becomes *current; false when the
  // stack runs out.
  template <typename Keep>
  bool Pop(Keep keep, int32_t* current) {
    while (top_ > 0) {
      const Entry e = entries_[--top_];
      if (keep(e.node, e.key)) {
        *current = e.node;
        return true;
      }
    }
    return false;
  }

 private:
  struct Entry {
    int32_t node;
    Key key;
  };
  std::array<Entry, AabbTree::kMaxDepth>
      entries_;  // not value-initialised: only pushed ones are read
  size_t top_ = 0;
};

// Depth-first over the nodes whose box passes(node) accepts (a node's two children tested as a
// pair; when both pass, the second waits on the stack), calling visit_leaf(leaf) for every leaf
// reached (SphereQuery, CapsuleQuery). The root is visited untested: the callers test it first.
template <typename NodeT, typename Passes, typename VisitLeaf>
inline void VisitPassing(const NodeT* nodes, Passes passes, VisitLeaf visit_leaf) {
  std::array<int32_t, AabbTree::kMaxDepth>
      stack;  // not value-initialised: only pushed entries are read
  size_t top = 0;
  stack[top++] = 0;
  while (top > 0) {
    int32_t current = stack[--top];
    while (true) {
      const NodeT& node = nodes[current];
      if (node.count > 0) {
        visit_leaf(node);
        break;
      }
      const int32_t left = current + 1;
      const int32_t right = node.index;
      const bool hl = passes(nodes[left]);
      const bool hr = passes(nodes[right]);
      if (hl && hr) stack[top++] = right;
      if (!hl && !hr) break;
      current = hl ? left : right;
    }
  }
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
  BestFirstStack<float> stack;  // keyed by the entry parameter
  float entry = 0.0f;
  if (!SlabEntry(nodes_[0], slab, grow, 1.0f, &entry)) return false;
  int32_t current = 0;
  while (true) {
    const Node& node = nodes_[static_cast<size_t>(current)];
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
      // Nearer child first: its hits may prune the farther one.
      if (stack.Descend(
              left, right, hl, hr, tl, tr, [&] { return tl <= tr; }, &current))
        continue;
    }
    // Pop the next box that may still hold a crossing at or before the best one.
    const auto may_hold_better = [&](int32_t, float t) {
      return static_cast<double>(t) <= best_t + static_cast<double>(kSlabTSlack);
    };
    if (!stack.Pop(may_hold_better, &current)) break;
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
  BestFirstStack<double> stack;  // keyed by the squared distance to the box
  if (BoxDistanceSquared(nodes_[0], x) > bound) return false;
  int32_t current = 0;
  while (true) {
    const Node& node = nodes_[static_cast<size_t>(current)];
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
      if (stack.Descend(
              left, right, hl, hr, dl, dr, [&] { return dl <= dr; }, &current))
        continue;
    }
    if (!stack.Pop([&](int32_t, double d2) { return d2 <= bound; }, &current)) break;
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
  if (nodes_.empty() || !c.allFinite() || !checks::FiniteNonNegative(radius)) return 0;
  const double r2 = radius * radius;
  const double grown = radius + kRelativeMargin * (scale_ + MaxAbs(c));
  const double bound = grown * grown;
  int32_t found = 0;
  if (BoxDistanceSquared(nodes_[0], c) > bound) return 0;
  VisitPassing(
      nodes_.data(), [&](const Node& n) { return BoxDistanceSquared(n, c) <= bound; },
      [&](const Node& node) {
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
      });
  return found;
}

int32_t AabbTree::CapsuleQuery(const Vector3d& p, const Vector3d& q, double radius,
                               std::span<int32_t> out) const {
  const mesh::Points& xs = positions();
  if (nodes_.empty() || !p.allFinite() || !q.allFinite() || !checks::FiniteNonNegative(radius)) {
    return 0;
  }
  const PreparedSegment segment(p, q);
  const Slab slab = MakeSlab(p, q);
  const double r2 = radius * radius;
  const double margin = kRelativeMargin * (scale_ + MaxAbs(p) + MaxAbs(q));
  const double grown = radius + margin;
  const auto box_grow =
      static_cast<float>(radius + kSlabRelativeMargin * (scale_ + MaxAbs(p) + MaxAbs(q)) + 1e-30);
  int32_t found = 0;
  float entry = 0.0f;
  if (!SlabEntry(nodes_[0], slab, box_grow, 1.0f, &entry)) return 0;
  VisitPassing(
      nodes_.data(), [&](const Node& n) { return SlabEntry(n, slab, box_grow, 1.0f, &entry); },
      [&](const Node& node) {
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
      });
  return found;
}

bool AabbTree::NearestToSegment(const Vector3d& p, const Vector3d& q, double radius,
                                SurfacePoint* nearest) const {
  const mesh::Points& xs = positions();
  if (nodes_.empty() || !p.allFinite() || !q.allFinite() || !checks::FiniteNonNegative(radius)) {
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
  Vector3d best_bary = Vector3d::Zero();
  BestFirstStack<float> stack;  // keyed by the box growth the node was tested with
  float entry = 0.0f;
  if (!SlabEntry(nodes_[0], slab, box_grow, 1.0f, &entry)) return false;
  int32_t current = 0;
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
      // Nearer the tip p first: the nearest surface point is usually there, and finding it
      // early shrinks the radius that prunes the rest.
      const auto left_first = [&] {
        return StartDistanceSquared(nodes_[static_cast<size_t>(left)], slab) <=
               StartDistanceSquared(nodes_[static_cast<size_t>(right)], slab);
      };
      if (stack.Descend(left, right, hl, hr, box_grow, box_grow, left_first, &current)) continue;
    }
    // Boxes on the stack were tested with an older (larger) radius: test again.
    const auto still_near = [&](int32_t n, float grow) {
      return grow == box_grow ||
             SlabEntry(nodes_[static_cast<size_t>(n)], slab, box_grow, 1.0f, &entry);
    };
    if (!stack.Pop(still_near, &current)) break;
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

}  // namespace somasim::contact
