#include "common/mesh/topology.h"

#include <algorithm>
#include <array>
#include <numeric>
#include <tuple>

namespace somasim::mesh {
namespace {

// Local faces of a positively oriented tetrahedron, outward, face k opposite corner k.
constexpr int kTetFaces[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};

template <int N>
Adjacency NodeToElements(int32_t num_nodes, const Eigen::Matrix<int32_t, N, Eigen::Dynamic>& e) {
  Adjacency adj;
  adj.offsets.assign(static_cast<size_t>(num_nodes) + 1, 0);
  for (Eigen::Index t = 0; t < e.cols(); ++t) {
    for (int k = 0; k < N; ++k) ++adj.offsets[static_cast<size_t>(e(k, t)) + 1];
  }
  for (size_t i = 1; i < adj.offsets.size(); ++i) adj.offsets[i] += adj.offsets[i - 1];
  adj.entries.resize(static_cast<size_t>(adj.offsets.back()));
  std::vector<int32_t> fill(adj.offsets.begin(), adj.offsets.end() - 1);
  // Elements are visited in increasing order, so each list comes out sorted.
  for (Eigen::Index t = 0; t < e.cols(); ++t) {
    for (int k = 0; k < N; ++k) {
      adj.entries[static_cast<size_t>(fill[static_cast<size_t>(e(k, t))]++)] =
          static_cast<int32_t>(t);
    }
  }
  return adj;
}

struct FaceRecord {
  std::array<int32_t, 3> key;  // sorted node indices
  int32_t tet;
  int32_t face;
  bool operator<(const FaceRecord& o) const {
    return std::tie(key, tet, face) < std::tie(o.key, o.tet, o.face);
  }
};

std::vector<FaceRecord> SortedFaces(const Tetrahedra& tets) {
  std::vector<FaceRecord> faces;
  faces.reserve(4 * static_cast<size_t>(tets.cols()));
  for (Eigen::Index t = 0; t < tets.cols(); ++t) {
    for (int f = 0; f < 4; ++f) {
      std::array<int32_t, 3> key = {tets(kTetFaces[f][0], t), tets(kTetFaces[f][1], t),
                                    tets(kTetFaces[f][2], t)};
      std::sort(key.begin(), key.end());
      faces.push_back({key, static_cast<int32_t>(t), f});
    }
  }
  std::sort(faces.begin(), faces.end());
  return faces;
}

// Union-find with path halving.
struct DisjointSets {
  std::vector<int32_t> parent;
  explicit DisjointSets(size_t n) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  int32_t Find(int32_t i) {
    while (parent[static_cast<size_t>(i)] != i) {
      parent[static_cast<size_t>(i)] = parent[static_cast<size_t>(parent[static_cast<size_t>(i)])];
      i = parent[static_cast<size_t>(i)];
    }
    return i;
  }
  void Unite(int32_t a, int32_t b) {
    a = Find(a);
    b = Find(b);
    if (a != b) parent[static_cast<size_t>(std::max(a, b))] = std::min(a, b);
  }
};

}  // namespace

Adjacency NodeToTets(int32_t num_nodes, const Tetrahedra& tets) {
  return NodeToElements<4>(num_nodes, tets);
}

Adjacency NodeToTriangles(int32_t num_nodes, const Triangles& triangles) {
  return NodeToElements<3>(num_nodes, triangles);
}

Eigen::Matrix<int32_t, 4, Eigen::Dynamic> TetFaceNeighbours(int32_t /*num_nodes*/,
                                                            const Tetrahedra& tets) {
  Eigen::Matrix<int32_t, 4, Eigen::Dynamic> neighbours =
      Eigen::Matrix<int32_t, 4, Eigen::Dynamic>::Constant(4, tets.cols(), -1);
  const std::vector<FaceRecord> faces = SortedFaces(tets);
  for (size_t i = 0; i < faces.size();) {
    size_t j = i + 1;
    while (j < faces.size() && faces[j].key == faces[i].key) ++j;
    if (j - i == 2) {
      neighbours(faces[i].face, faces[i].tet) = faces[i + 1].tet;
      neighbours(faces[i + 1].face, faces[i + 1].tet) = faces[i].tet;
    } else if (j - i > 2) {
      for (size_t k = i; k < j; ++k) neighbours(faces[k].face, faces[k].tet) = -2;
    }
    i = j;
  }
  return neighbours;
}

SurfaceMesh ExtractBoundarySurface(const TetMesh& mesh) {
  const Eigen::Matrix<int32_t, 4, Eigen::Dynamic> neighbours =
      TetFaceNeighbours(static_cast<int32_t>(mesh.vertices.cols()), mesh.tetrahedra);
  int64_t count = 0;
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    for (int f = 0; f < 4; ++f) count += neighbours(f, t) == -1 ? 1 : 0;
  }
  SurfaceMesh surface;
  surface.vertices = mesh.vertices;
  surface.triangles.resize(3, count);
  Eigen::Index out = 0;
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    for (int f = 0; f < 4; ++f) {
      if (neighbours(f, t) != -1) continue;
      for (int k = 0; k < 3; ++k) surface.triangles(k, out) = mesh.tetrahedra(kTetFaces[f][k], t);
      ++out;
    }
  }
  return surface;
}

std::vector<int32_t> UnreferencedNodes(int32_t num_nodes, const Triangles& triangles,
                                       const Tetrahedra& tets) {
  std::vector<char> used(static_cast<size_t>(std::max(num_nodes, 0)), 0);
  const auto mark = [&](const int32_t* cells, Eigen::Index size) {
    for (Eigen::Index k = 0; k < size; ++k) {
      if (cells[k] >= 0 && cells[k] < num_nodes) used[static_cast<size_t>(cells[k])] = 1;
    }
  };
  mark(triangles.data(), triangles.size());
  mark(tets.data(), tets.size());
  std::vector<int32_t> unused;
  for (size_t i = 0; i < used.size(); ++i) {
    if (used[i] == 0) unused.push_back(static_cast<int32_t>(i));
  }
  return unused;
}

SurfaceMesh CompactSurface(const SurfaceMesh& surface, std::vector<int32_t>* old_to_new) {
  std::vector<int32_t> map(static_cast<size_t>(surface.vertices.cols()), -1);
  for (Eigen::Index i = 0; i < surface.triangles.size(); ++i) {
    map[static_cast<size_t>(surface.triangles.data()[i])] = 0;
  }
  int32_t next = 0;
  for (int32_t& m : map) {
    if (m == 0) m = next++;
  }
  SurfaceMesh out;
  out.vertices.resize(3, next);
  for (size_t i = 0; i < map.size(); ++i) {
    if (map[i] >= 0) out.vertices.col(map[i]) = surface.vertices.col(static_cast<Eigen::Index>(i));
  }
  out.triangles.resize(3, surface.triangles.cols());
  for (Eigen::Index i = 0; i < surface.triangles.size(); ++i) {
    out.triangles.data()[i] = map[static_cast<size_t>(surface.triangles.data()[i])];
  }
  if (old_to_new != nullptr) *old_to_new = std::move(map);
  return out;
}

SurfaceTopology AnalyseSurfaceTopology(const SurfaceMesh& surface) {
  SurfaceTopology topo;
  const Triangles& tris = surface.triangles;
  const auto num_tris = static_cast<int32_t>(tris.cols());
  const auto num_nodes = static_cast<int32_t>(surface.vertices.cols());

  // Half-edges (a→b) of every triangle, grouped by their undirected edge.
  struct HalfEdge {
    int32_t lo, hi;  // undirected key
    int32_t from;    // a
    int32_t tri;
    bool operator<(const HalfEdge& o) const {
      return std::tie(lo, hi, tri, from) < std::tie(o.lo, o.hi, o.tri, o.from);
    }
  };
  std::vector<HalfEdge> half;
  half.reserve(3 * static_cast<size_t>(num_tris));
  for (int32_t t = 0; t < num_tris; ++t) {
    const int32_t v[3] = {tris(0, t), tris(1, t), tris(2, t)};
    if (v[0] == v[1] || v[1] == v[2] || v[2] == v[0]) {
      ++topo.num_degenerate_triangles;
      continue;
    }
    for (int k = 0; k < 3; ++k) {
      const int32_t a = v[k], b = v[(k + 1) % 3];
      half.push_back({std::min(a, b), std::max(a, b), a, t});
    }
  }
  std::sort(half.begin(), half.end());

  DisjointSets components(static_cast<size_t>(num_tris));
  // Per vertex: union-find of its incident triangles joined across manifold edges at it.
  DisjointSets fans(static_cast<size_t>(num_tris) * 3);
  // Slot of (triangle, corner) in `fans`, found by the vertex's corner in the triangle.
  const auto slot = [&](int32_t t, int32_t vertex) {
    int k = 0;
    while (tris(k, t) != vertex) ++k;
    return 3 * t + k;
  };
  for (size_t i = 0; i < half.size();) {
    size_t j = i + 1;
    while (j < half.size() && half[j].lo == half[i].lo && half[j].hi == half[i].hi) ++j;
    const size_t count = j - i;
    ++topo.num_edges;
    if (count == 1) {
      ++topo.num_boundary_edges;
    } else if (count > 2) {
      ++topo.num_nonmanifold_edges;
    } else if (half[i].from == half[i + 1].from) {
      ++topo.num_misoriented_edges;
    }
    for (size_t k = i + 1; k < j; ++k) components.Unite(half[i].tri, half[k].tri);
    if (count == 2) {
      for (int32_t v : {half[i].lo, half[i].hi}) {
        fans.Unite(slot(half[i].tri, v), slot(half[i + 1].tri, v));
      }
    }
    i = j;
  }

  // A vertex is non-manifold when its incident triangles form more than one fan.
  std::vector<int32_t> first_fan(static_cast<size_t>(num_nodes), -1);
  std::vector<char> bad(static_cast<size_t>(num_nodes), 0);
  std::vector<char> referenced(static_cast<size_t>(num_nodes), 0);
  for (int32_t t = 0; t < num_tris; ++t) {
    const int32_t v[3] = {tris(0, t), tris(1, t), tris(2, t)};
    if (v[0] == v[1] || v[1] == v[2] || v[2] == v[0]) continue;
    for (int k = 0; k < 3; ++k) {
      const auto vi = static_cast<size_t>(v[k]);
      referenced[vi] = 1;
      const int32_t root = fans.Find(3 * t + k);
      if (first_fan[vi] == -1) {
        first_fan[vi] = root;
      } else if (first_fan[vi] != root) {
        bad[vi] = 1;
      }
    }
  }
  int64_t num_referenced = 0;
  for (int32_t v = 0; v < num_nodes; ++v) {
    topo.num_nonmanifold_vertices += bad[static_cast<size_t>(v)];
    num_referenced += referenced[static_cast<size_t>(v)];
  }
  for (int32_t t = 0; t < num_tris; ++t) {
    if (components.Find(t) == t) ++topo.num_components;
  }
  topo.num_components -= topo.num_degenerate_triangles;  // isolated degenerate triangles
  topo.euler_characteristic =
      num_referenced - topo.num_edges + (num_tris - topo.num_degenerate_triangles);
  topo.manifold = topo.num_nonmanifold_edges == 0 && topo.num_nonmanifold_vertices == 0;
  topo.watertight = num_tris > 0 && topo.num_boundary_edges == 0 &&
                    topo.num_nonmanifold_edges == 0 && topo.num_misoriented_edges == 0 &&
                    topo.num_degenerate_triangles == 0;
  return topo;
}

}  // namespace somasim::mesh
