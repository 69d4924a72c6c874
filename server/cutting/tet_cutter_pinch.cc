// The cutter's pinch repairs (Step's stage 2): a vertex-preserving cut can never split a vertex,
// so the alive tetrahedra around a vertex or edge must stay one group and the boundary around a
// vertex one fan. Removing a group's or a chain's tetrahedra (all or none, never orphaning a
// vertex), or putting back what this step removed, keeps the boundary a manifold; where nothing
// does, the step is undone. (Kept in one file with every caller of SplitPinch: gcc then
// specialises it for Pinched's constant arguments, the path most of a step's time is in.)
#include <algorithm>

#include "server/cutting/tet_cutter.h"

namespace somasim::cutting {

// Keeps the boundary a manifold (beyond the seed): around each vertex and edge of a removed
// tetrahedron the alive
// tetrahedra must form one group (linked across faces holding that vertex or edge); otherwise two
// parts of the mesh touch only there, a pinch no vertex-preserving cut can open. The smaller
// groups' tetrahedra there are removed too (when that orphans no vertex); where the boundary
// around a vertex forms two fans, the shortest chain joining them; where neither works, a
// tetrahedron this step removed is put back (the wound stays closed there).
void TetCutter::RepairPinches() {
  for (int pass = 0; pass < 6; ++pass) {
    bool changed = false;
    const size_t end = removed_count_;
    for (size_t i = 0; i < end; ++i) {
      const int32_t t = removed_[i];
      for (const auto& e : kTetEdges) {
        changed = SplitPinch(tet_node(e[0], t), tet_node(e[1], t), false) || changed;
      }
      for (int k = 0; k < 4; ++k) {
        const int32_t u = tet_node(k, t);
        if (!Pinched(u)) continue;
        // Split it by removing more; where that would orphan a vertex, put back a tetrahedron
        // this step removed (the wound stays closed there).
        changed = SplitPinch(u, -1, false) || SplitLink(u, false) || RestoreAround(u) || changed;
      }
    }
    if (!changed) break;
  }
}

// Anything still pinched around this step's changes: the step is undone (every tetrahedron it
// removed put back; the severed ones wait for a later step, when the blade has moved on). Whether
// it was undone.
bool TetCutter::UndoIfPinched(size_t severed_removed, CutStepResult* result) {
  for (size_t i = 0; i < removed_count_ && result->unresolved == 0; ++i) {
    const int32_t t = removed_[i];
    for (int k = 0; k < 4; ++k) result->unresolved += Pinched(tet_node(k, t)) ? 1 : 0;
    for (const auto& e : kTetEdges) {
      result->unresolved += SplitPinch(tet_node(e[0], t), tet_node(e[1], t), true) ? 1 : 0;
    }
  }
  if (result->unresolved > 0) {
    for (size_t i = 0; i < removed_count_; ++i) {
      const int32_t t = removed_[i];
      if (alive_[static_cast<size_t>(t)] != 0) continue;
      alive_[static_cast<size_t>(t)] = 1;
      for (int k = 0; k < 4; ++k) ++node_alive_[static_cast<size_t>(tet_node(k, t))];
      if (i < severed_removed && pending_count_ < pending_.size()) {
        pending_[pending_count_++] = t;
      }
    }
    removed_count_ = 0;
    result->removed = 0;
    result->undone = true;
    return true;
  }
  return false;
}

bool TetCutter::Remove(int32_t t) {
  if (removed_count_ == removed_.size()) return false;  // this step's list is full
  alive_[static_cast<size_t>(t)] = 0;
  for (int k = 0; k < 4; ++k) --node_alive_[static_cast<size_t>(tet_node(k, t))];
  removed_[removed_count_++] = t;
  return true;
}

bool TetCutter::SplitPinch(int32_t v, int32_t w, bool dry_run) {
  // The alive tetrahedra around v (and w, for an edge).
  int32_t m = 0;
  for (int32_t j = node_tet_offsets_[static_cast<size_t>(v)];
       j < node_tet_offsets_[static_cast<size_t>(v) + 1]; ++j) {
    const int32_t t = node_tet_entries_[static_cast<size_t>(j)];
    if (alive_[static_cast<size_t>(t)] == 0) continue;
    if (w >= 0 && tet_node(0, t) != w && tet_node(1, t) != w && tet_node(2, t) != w &&
        tet_node(3, t) != w) {
      continue;
    }
    if (m == kMaxFan) return false;  // a fan this large: left alone
    fan_[static_cast<size_t>(m)] = t;
    group_[static_cast<size_t>(m)] = m;
    ++m;
  }
  if (m < 2) return false;
  const auto find = [&](int32_t i) {
    while (group_[static_cast<size_t>(i)] != i) i = group_[static_cast<size_t>(i)];
    return i;
  };
  for (int32_t i = 0; i < m; ++i) {
    const int32_t t = fan_[static_cast<size_t>(i)];
    for (int f = 0; f < 4; ++f) {
      // Only faces holding v (and w): the face opposite corner f holds every other corner.
      if (tet_node(f, t) == v || (w >= 0 && tet_node(f, t) == w)) continue;
      const int32_t nb = surface_.neighbour(f, t);
      if (nb < 0 || alive_[static_cast<size_t>(nb)] == 0) continue;
      for (int32_t j = 0; j < m; ++j) {
        if (fan_[static_cast<size_t>(j)] != nb) continue;
        const int32_t a = find(i), b = find(j);
        if (a != b) group_[static_cast<size_t>(std::max(a, b))] = std::min(a, b);
      }
    }
  }
  // One group stays, the largest whose keeping lets all the others' tetrahedra go without
  // orphaning a vertex (all or none: a half-removed group would leave the pinch).
  int32_t roots[kMaxFan];
  int32_t sizes[kMaxFan];
  int32_t groups = 0;
  for (int32_t i = 0; i < m; ++i) {
    if (find(i) != i) continue;
    roots[groups] = i;
    sizes[groups] = 0;
    for (int32_t j = 0; j < m; ++j) sizes[groups] += find(j) == i ? 1 : 0;
    ++groups;
  }
  if (groups < 2) return false;
  if (dry_run) return true;
  for (int32_t tries = 0; tries < groups; ++tries) {
    int32_t pick = -1;
    for (int32_t g = 0; g < groups; ++g) {
      if (sizes[g] >= 0 && (pick < 0 || sizes[g] > sizes[pick])) pick = g;
    }
    const int32_t keep = roots[pick];
    sizes[pick] = -1;  // tried
    // Every other group's tetrahedra go, all or none.
    int32_t count = 0;
    for (int32_t i = 0; i < m; ++i) {
      if (find(i) != keep) chosen_[static_cast<size_t>(count++)] = fan_[static_cast<size_t>(i)];
    }
    if (!RemoveAllOrNone(count)) continue;
    return true;
  }
  return false;  // every choice would orphan a vertex: the pinch stays (counted by the caller)
}

bool TetCutter::RemoveAllOrNone(int32_t count) {
  // Would removing them all orphan a vertex? Count what each vertex would lose.
  bool orphans = false;
  for (int32_t i = 0; i < count; ++i) {
    const int32_t t = chosen_[static_cast<size_t>(i)];
    for (int k = 0; k < 4; ++k) ++losing_[static_cast<size_t>(tet_node(k, t))];
  }
  for (int32_t i = 0; i < count; ++i) {
    const int32_t t = chosen_[static_cast<size_t>(i)];
    for (int k = 0; k < 4; ++k) {
      const auto node = static_cast<size_t>(tet_node(k, t));
      orphans = orphans || losing_[node] >= node_alive_[node];
    }
  }
  for (int32_t i = 0; i < count; ++i) {
    const int32_t t = chosen_[static_cast<size_t>(i)];
    for (int k = 0; k < 4; ++k) losing_[static_cast<size_t>(tet_node(k, t))] = 0;
  }
  if (orphans) return false;
  for (int32_t i = 0; i < count; ++i) {
    if (!Remove(chosen_[static_cast<size_t>(i)])) break;
  }
  return true;
}

bool TetCutter::Pinched(int32_t v) { return SplitPinch(v, -1, true) || SplitLink(v, true); }

bool TetCutter::RestoreAround(int32_t v) {
  for (size_t i = 0; i < removed_count_; ++i) {
    const int32_t t = removed_[i];
    if (alive_[static_cast<size_t>(t)] != 0) continue;
    if (tet_node(0, t) != v && tet_node(1, t) != v && tet_node(2, t) != v && tet_node(3, t) != v)
      continue;
    alive_[static_cast<size_t>(t)] = 1;
    for (int k = 0; k < 4; ++k) ++node_alive_[static_cast<size_t>(tet_node(k, t))];
    if (!Pinched(v)) return true;
    alive_[static_cast<size_t>(t)] = 0;
    for (int k = 0; k < 4; ++k) --node_alive_[static_cast<size_t>(tet_node(k, t))];
  }
  // No single one: all of them around v (v as it was before this step, when it was sound).
  bool any = false;
  for (size_t i = 0; i < removed_count_; ++i) {
    const int32_t t = removed_[i];
    if (alive_[static_cast<size_t>(t)] != 0) continue;
    if (tet_node(0, t) != v && tet_node(1, t) != v && tet_node(2, t) != v && tet_node(3, t) != v)
      continue;
    alive_[static_cast<size_t>(t)] = 1;
    for (int k = 0; k < 4; ++k) ++node_alive_[static_cast<size_t>(tet_node(k, t))];
    any = true;
  }
  return any && !Pinched(v);
}

bool TetCutter::SplitLink(int32_t v, bool dry_run) {
  // The alive tetrahedra around v, and the boundary triangles holding v: each gives an edge
  // (a, b) of v's link on the surface. Their connected components are v's fans.
  int32_t m = 0;
  for (int32_t j = node_tet_offsets_[static_cast<size_t>(v)];
       j < node_tet_offsets_[static_cast<size_t>(v) + 1]; ++j) {
    const int32_t t = node_tet_entries_[static_cast<size_t>(j)];
    if (alive_[static_cast<size_t>(t)] == 0) continue;
    if (m == kMaxFan) return false;
    fan_[static_cast<size_t>(m++)] = t;
  }
  int32_t nv = 0;  // link vertices in link_
  const auto link_index = [&](int32_t node) {
    for (int32_t i = 0; i < nv; ++i) {
      if (link_[static_cast<size_t>(i)] == node) return i;
    }
    link_[static_cast<size_t>(nv)] = node;
    link_parent_[static_cast<size_t>(nv)] = nv;
    return nv++;
  };
  const auto find = [&](int32_t i) {
    while (link_parent_[static_cast<size_t>(i)] != i) i = link_parent_[static_cast<size_t>(i)];
    return i;
  };
  for (int32_t i = 0; i < m; ++i) {
    const int32_t t = fan_[static_cast<size_t>(i)];
    for (int f = 0; f < 4; ++f) {
      if (tet_node(f, t) == v) continue;  // the face opposite v does not hold it
      const int32_t nb = surface_.neighbour(f, t);
      if (nb >= 0 && alive_[static_cast<size_t>(nb)] != 0) continue;
      int32_t ends[2];
      int32_t e = 0;
      for (int k = 0; k < 3; ++k) {
        const int32_t node = tet_node(kTetFaces[f][k], t);
        if (node != v) ends[e++] = node;
      }
      if (nv + 2 > 3 * kMaxFan) return false;
      const int32_t a = find(link_index(ends[0])), b = find(link_index(ends[1]));
      if (a != b) link_parent_[static_cast<size_t>(std::max(a, b))] = std::min(a, b);
    }
  }
  int32_t fans = 0;
  int32_t first = -1;
  for (int32_t i = 0; i < nv; ++i) {
    if (find(i) != i) continue;
    ++fans;
    if (first < 0) first = i;
  }
  if (fans < 2) return false;
  if (dry_run) return true;
  // Which fan each tetrahedron's boundary triangles at v belong to: 1 the first, 2 another.
  for (int32_t i = 0; i < m; ++i) {
    const int32_t t = fan_[static_cast<size_t>(i)];
    int32_t touches = 0;
    for (int f = 0; f < 4; ++f) {
      if (tet_node(f, t) == v) continue;
      const int32_t nb = surface_.neighbour(f, t);
      if (nb >= 0 && alive_[static_cast<size_t>(nb)] != 0) continue;
      const int32_t node = tet_node(kTetFaces[f][0], t) != v ? tet_node(kTetFaces[f][0], t)
                                                             : tet_node(kTetFaces[f][1], t);
      touches |= find(link_index(node)) == first ? 1 : 2;
    }
    group_[static_cast<size_t>(i)] = touches;
    dist_[static_cast<size_t>(i)] = (touches & 1) != 0 ? 0 : -1;
    parent_[static_cast<size_t>(i)] = -1;
  }
  // The shortest chain of tetrahedra (across faces holding v) from the first fan to another:
  // removing it joins the fans into one.
  int32_t goal = -1;
  for (int32_t i = 0; i < m && goal < 0; ++i) {
    if (dist_[static_cast<size_t>(i)] == 0 && (group_[static_cast<size_t>(i)] & 2) != 0) goal = i;
  }
  for (int32_t d = 0; goal < 0 && d < m; ++d) {
    bool grew = false;
    for (int32_t i = 0; i < m && goal < 0; ++i) {
      if (dist_[static_cast<size_t>(i)] != d) continue;
      const int32_t t = fan_[static_cast<size_t>(i)];
      for (int f = 0; f < 4 && goal < 0; ++f) {
        if (tet_node(f, t) == v) continue;
        const int32_t nb = surface_.neighbour(f, t);
        if (nb < 0 || alive_[static_cast<size_t>(nb)] == 0) continue;
        for (int32_t j = 0; j < m; ++j) {
          if (fan_[static_cast<size_t>(j)] != nb || dist_[static_cast<size_t>(j)] >= 0) continue;
          dist_[static_cast<size_t>(j)] = d + 1;
          parent_[static_cast<size_t>(j)] = i;
          grew = true;
          if ((group_[static_cast<size_t>(j)] & 2) != 0) goal = j;
        }
      }
    }
    if (!grew) break;
  }
  if (goal < 0) return false;
  // All of the chain or none.
  int32_t count = 0;
  for (int32_t i = goal; i >= 0; i = parent_[static_cast<size_t>(i)]) {
    chosen_[static_cast<size_t>(count++)] = fan_[static_cast<size_t>(i)];
  }
  return RemoveAllOrNone(count);
}

}  // namespace somasim::cutting
