// The AABB tree's Refit: leaves first (their distinct vertices' box in double, rounded outwards
// to float once; an AVX2 pass where the CPU has it, else SSE2 or scalar, all giving identical
// boxes), then the internal nodes by height (float min / max).
#include <algorithm>
#include <atomic>
#include <cmath>
#include <stdexcept>
#include <string>

#include "server/contact/aabb_tree.h"
#include "server/contact/aabb_tree_internal.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace somasim::contact {
namespace {

using aabb_internal::kInf;
using aabb_internal::kOutwardAbsolute;
using aabb_internal::kOutwardRelative;

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
      node.lo[i] = aabb_internal::RoundDown(lo[i]);
      node.hi[i] = aabb_internal::RoundUp(hi[i]);
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

}  // namespace somasim::contact
