#include "common/mesh_gen/isosurface_stuffing.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

#include "common/checks/finite.h"
#include "common/mesh/geometry.h"
#include "common/mesh/quality.h"

namespace somasim::mesh_gen {
namespace {

using Eigen::Vector3d;

enum class Sign : int8_t { kInside = -1, kZero = 0, kOutside = 1 };

// One cut point: where the surface crosses the lattice edge (u, v), u < v.
struct CutEdge {
  int32_t u = 0;
  int32_t v = 0;
  Vector3d position;
  bool is_long = false;
  bool discarded = false;  // an endpoint was warped onto the surface
};

// The BCC lattice: black vertices on the cube corners, red vertices at the cube centres.
class BccLattice {
 public:
  BccLattice(const mesh::BoundingBox& bounds, const StuffingOptions& options,
             int64_t max_vertices) {
    const double h = options.spacing;
    const Vector3d lo = bounds.min - Vector3d::Constant(2.0 * h);
    const Vector3d hi = bounds.max + Vector3d::Constant(2.0 * h);
    int64_t total_black = 1;
    for (int axis = 0; axis < 3; ++axis) {
      const double first = std::floor(lo[axis] / h - options.offset[axis]);
      origin_[axis] = h * (first + options.offset[axis]);
      const double cells = std::ceil((hi[axis] - origin_[axis]) / h);
      if (!(cells >= 1.0 && cells < 1e6)) {
        throw std::invalid_argument("isosurface stuffing: the lattice along axis " +
                                    std::to_string(axis) + " would have " + std::to_string(cells) +
                                    " cells");
      }
      black_dims_[axis] = static_cast<int32_t>(cells) + 1;
      total_black *= black_dims_[axis];
    }
    const int64_t total_red =
        int64_t{black_dims_[0] - 1} * (black_dims_[1] - 1) * (black_dims_[2] - 1);
    if (total_black + total_red > max_vertices) {
      throw std::invalid_argument("isosurface stuffing: spacing " + std::to_string(h) +
                                  " m needs " + std::to_string(total_black + total_red) +
                                  " lattice vertices, more than the limit of " +
                                  std::to_string(max_vertices));
    }
    num_black_ = static_cast<int32_t>(total_black);
    num_vertices_ = static_cast<int32_t>(total_black + total_red);
    spacing_ = h;
  }

  int32_t num_vertices() const { return num_vertices_; }
  int32_t Black(int i, int j, int k) const { return i + black_dims_[0] * (j + black_dims_[1] * k); }
  int32_t Red(int i, int j, int k) const {
    return num_black_ + i + (black_dims_[0] - 1) * (j + (black_dims_[1] - 1) * k);
  }
  bool IsRed(int32_t vertex) const { return vertex >= num_black_; }
  Vector3d Position(int32_t vertex) const {
    if (vertex < num_black_) {
      const int i = vertex % black_dims_[0];
      const int j = (vertex / black_dims_[0]) % black_dims_[1];
      const int k = vertex / (black_dims_[0] * black_dims_[1]);
      return origin_ + spacing_ * Vector3d(i, j, k);
    }
    const int32_t r = vertex - num_black_;
    const int i = r % (black_dims_[0] - 1);
    const int j = (r / (black_dims_[0] - 1)) % (black_dims_[1] - 1);
    const int k = r / ((black_dims_[0] - 1) * (black_dims_[1] - 1));
    return origin_ + spacing_ * Vector3d(i + 0.5, j + 0.5, k + 0.5);
  }

  // Calls visit(edge u, v, is_long) once for every lattice edge: black–black and red–red along
  // the axes (long, length h), red–black to the 8 corners of the red vertex's cube (short).
  template <typename Visit>
  void ForEachEdge(Visit&& visit) const {
    const auto& d = black_dims_;
    for (int k = 0; k < d[2]; ++k) {
      for (int j = 0; j < d[1]; ++j) {
        for (int i = 0; i < d[0]; ++i) {
          const int32_t b = Black(i, j, k);
          if (i + 1 < d[0]) visit(b, Black(i + 1, j, k), true);
          if (j + 1 < d[1]) visit(b, Black(i, j + 1, k), true);
          if (k + 1 < d[2]) visit(b, Black(i, j, k + 1), true);
        }
      }
    }
    for (int k = 0; k + 1 < d[2]; ++k) {
      for (int j = 0; j + 1 < d[1]; ++j) {
        for (int i = 0; i + 1 < d[0]; ++i) {
          const int32_t r = Red(i, j, k);
          if (i + 2 < d[0]) visit(r, Red(i + 1, j, k), true);
          if (j + 2 < d[1]) visit(r, Red(i, j + 1, k), true);
          if (k + 2 < d[2]) visit(r, Red(i, j, k + 1), true);
          for (int corner = 0; corner < 8; ++corner) {
            visit(Black(i + (corner & 1), j + ((corner >> 1) & 1), k + ((corner >> 2) & 1)), r,
                  false);
          }
        }
      }
    }
  }

  // Calls visit(std::array<int32_t, 4>) for every BCC tetrahedron: around each red–red edge, the
  // four tetrahedra formed with the sides of the square face between the two cubes.
  template <typename Visit>
  void ForEachTet(Visit&& visit) const {
    const auto& d = black_dims_;
    for (int k = 0; k + 1 < d[2]; ++k) {
      for (int j = 0; j + 1 < d[1]; ++j) {
        for (int i = 0; i + 1 < d[0]; ++i) {
          const std::array<int, 3> cell = {i, j, k};
          for (int axis = 0; axis < 3; ++axis) {
            std::array<int, 3> next = cell;
            ++next[axis];
            if (next[axis] + 1 >= d[axis]) continue;
            const int32_t r0 = Red(cell[0], cell[1], cell[2]);
            const int32_t r1 = Red(next[0], next[1], next[2]);
            // Corners of the shared square, in cyclic order.
            const int b_axis = (axis + 1) % 3;
            const int c_axis = (axis + 2) % 3;
            constexpr std::array<std::array<int, 2>, 4> kSquare = {
                {{0, 0}, {1, 0}, {1, 1}, {0, 1}}};
            std::array<int32_t, 4> corners{};
            for (int s = 0; s < 4; ++s) {
              std::array<int, 3> black = cell;
              black[axis] += 1;
              black[b_axis] += kSquare[s][0];
              black[c_axis] += kSquare[s][1];
              corners[s] = Black(black[0], black[1], black[2]);
            }
            for (int s = 0; s < 4; ++s)
              visit(std::array<int32_t, 4>{r0, r1, corners[s], corners[(s + 1) % 4]});
          }
        }
      }
    }
  }

 private:
  Vector3d origin_ = Vector3d::Zero();
  std::array<int32_t, 3> black_dims_{};
  int32_t num_black_ = 0;
  int32_t num_vertices_ = 0;
  double spacing_ = 0.0;
};

uint64_t EdgeKey(int32_t a, int32_t b) {
  const auto lo = static_cast<uint64_t>(std::min(a, b));
  const auto hi = static_cast<uint64_t>(std::max(a, b));
  return (hi << 32) | lo;
}

// Collects output tetrahedra over global vertex ids: lattice vertices are [0, num_lattice), cut
// points are num_lattice + cut index.
class TetAssembler {
 public:
  TetAssembler(const std::vector<Vector3d>& lattice_positions, const std::vector<CutEdge>& cuts)
      : lattice_positions_(lattice_positions), cuts_(cuts) {}

  const Vector3d& Position(int32_t id) const {
    const auto num_lattice = static_cast<int32_t>(lattice_positions_.size());
    return id < num_lattice ? lattice_positions_[static_cast<size_t>(id)]
                            : cuts_[static_cast<size_t>(id - num_lattice)].position;
  }

  // Adds (a, b, c, d), positively oriented.
  void Add(int32_t a, int32_t b, int32_t c, int32_t d) {
    if (mesh::TetSignedVolume(Position(a), Position(b), Position(c), Position(d)) < 0.0) {
      std::swap(c, d);
    }
    tets_.push_back({a, b, c, d});
  }

  double MinDihedral(int32_t a, int32_t b, int32_t c, int32_t d) const {
    return mesh::ComputeTetQuality(Position(a), Position(b), Position(c), Position(d))
        .min_dihedral_deg;
  }

  // Fills the triangular prism with ends (p0, p1, p2) and (q0, q1, q2) (p_i joined to q_i) by
  // three tetrahedra. diagonal_from_p[m] for the side quads m = (0,1), (1,2), (0,2): +1 if its
  // diagonal must be p_i–q_j (i < j), -1 if p_j–q_i, 0 if free. Free sides take the choice with
  // the best smallest dihedral angle. The staircase triangulation for the order (s0, s1, s2) has
  // diagonals p_earlier–q_later on every side, so a choice is valid iff it is acyclic.
  void AddPrism(const std::array<int32_t, 3>& p, const std::array<int32_t, 3>& q,
                const std::array<int, 3>& diagonal_from_p) {
    constexpr std::array<std::array<int, 3>, 6> kOrders = {
        {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}}};
    constexpr std::array<std::array<int, 2>, 3> kSides = {{{0, 1}, {1, 2}, {0, 2}}};
    int best = -1;
    double best_quality = -1.0;
    for (int o = 0; o < 6; ++o) {
      const auto& order = kOrders[static_cast<size_t>(o)];
      std::array<int, 3> rank{};
      for (int r = 0; r < 3; ++r) rank[static_cast<size_t>(order[static_cast<size_t>(r)])] = r;
      bool matches = true;
      for (size_t m = 0; m < 3; ++m) {
        const int want = diagonal_from_p[m];
        const int got =
            rank[static_cast<size_t>(kSides[m][0])] < rank[static_cast<size_t>(kSides[m][1])] ? 1
                                                                                              : -1;
        if (want != 0 && want != got) matches = false;
      }
      if (!matches) continue;
      const auto tets = Staircase(p, q, order);
      double quality = 180.0;
      for (const auto& t : tets) quality = std::min(quality, MinDihedral(t[0], t[1], t[2], t[3]));
      if (quality > best_quality) {
        best_quality = quality;
        best = o;
      }
    }
    // An acyclic choice always exists for the rules used by the caller.
    const auto tets = Staircase(p, q, kOrders[static_cast<size_t>(best < 0 ? 0 : best)]);
    for (const auto& t : tets) Add(t[0], t[1], t[2], t[3]);
  }

  const std::vector<std::array<int32_t, 4>>& tets() const { return tets_; }

 private:
  static std::array<std::array<int32_t, 4>, 3> Staircase(const std::array<int32_t, 3>& p,
                                                         const std::array<int32_t, 3>& q,
                                                         const std::array<int, 3>& order) {
    const auto s0 = static_cast<size_t>(order[0]);
    const auto s1 = static_cast<size_t>(order[1]);
    const auto s2 = static_cast<size_t>(order[2]);
    return {
        {{p[s0], p[s1], p[s2], q[s2]}, {p[s0], p[s1], q[s1], q[s2]}, {p[s0], q[s0], q[s1], q[s2]}}};
  }

  const std::vector<Vector3d>& lattice_positions_;
  const std::vector<CutEdge>& cuts_;
  std::vector<std::array<int32_t, 4>> tets_;
};

void CheckOptions(const StuffingOptions& options) {
  if (!checks::FinitePositive(options.spacing)) {
    throw std::invalid_argument("isosurface stuffing: spacing must be a finite length > 0 m");
  }
  for (int axis = 0; axis < 3; ++axis) {
    if (!(options.offset[axis] >= 0.0 && options.offset[axis] < 1.0)) {
      throw std::invalid_argument("isosurface stuffing: offset must lie in [0, 1) on each axis");
    }
  }
  if (!(options.alpha_long > 0.0 && options.alpha_long < 0.5)) {
    throw std::invalid_argument("isosurface stuffing: alpha_long must lie in (0, 0.5)");
  }
  if (!(options.alpha_short > 0.0 && options.alpha_short < 0.5)) {
    throw std::invalid_argument("isosurface stuffing: alpha_short must lie in (0, 0.5)");
  }
}

// 1. The lattice vertices' positions and the signs of the implicit function there.
void EvaluateSigns(const ImplicitSolid& solid, const BccLattice& lattice,
                   std::vector<Vector3d>* positions, std::vector<Sign>* signs) {
  const int32_t num_lattice = lattice.num_vertices();
  positions->resize(static_cast<size_t>(num_lattice));
  signs->resize(static_cast<size_t>(num_lattice));
  for (int32_t v = 0; v < num_lattice; ++v) {
    (*positions)[static_cast<size_t>(v)] = lattice.Position(v);
    const double value = solid.Value((*positions)[static_cast<size_t>(v)]);
    (*signs)[static_cast<size_t>(v)] =
        value < 0.0 ? Sign::kInside : (value > 0.0 ? Sign::kOutside : Sign::kZero);
  }
}

// 2. Cut points on the edges whose ends lie strictly on opposite sides, in lattice edge order.
std::vector<CutEdge> FindCutPoints(const ImplicitSolid& solid, const BccLattice& lattice,
                                   const std::vector<Vector3d>& positions,
                                   const std::vector<Sign>& signs) {
  std::vector<CutEdge> cuts;
  lattice.ForEachEdge([&](int32_t u, int32_t v, bool is_long) {
    const Sign su = signs[static_cast<size_t>(u)];
    const Sign sv = signs[static_cast<size_t>(v)];
    if (su == Sign::kZero || sv == Sign::kZero || su == sv) return;
    CutEdge cut;
    cut.u = std::min(u, v);
    cut.v = std::max(u, v);
    cut.position = FindSegmentRoot(solid, positions[static_cast<size_t>(cut.u)],
                                   positions[static_cast<size_t>(cut.v)]);
    cut.is_long = is_long;
    cuts.push_back(cut);
  });
  return cuts;
}

// The cut edges incident to each lattice vertex, compressed rows: vertex v's are
// incident[first[v] .. first[v + 1]).
struct IncidentCuts {
  std::vector<int32_t> first;     // num_lattice + 1
  std::vector<int32_t> incident;  // 2 per cut
};

IncidentCuts CutsPerVertex(int32_t num_lattice, const std::vector<CutEdge>& cuts) {
  IncidentCuts out;
  std::vector<int32_t>& first = out.first;
  first.assign(static_cast<size_t>(num_lattice) + 1, 0);
  for (const CutEdge& cut : cuts) {
    ++first[static_cast<size_t>(cut.u) + 1];
    ++first[static_cast<size_t>(cut.v) + 1];
  }
  for (size_t v = 0; v < static_cast<size_t>(num_lattice); ++v) first[v + 1] += first[v];
  std::vector<int32_t>& incident = out.incident;
  incident.resize(static_cast<size_t>(first.back()));
  std::vector<int32_t> fill(first.begin(), first.end() - 1);
  for (size_t c = 0; c < cuts.size(); ++c) {
    incident[static_cast<size_t>(fill[static_cast<size_t>(cuts[c].u)]++)] = static_cast<int32_t>(c);
    incident[static_cast<size_t>(fill[static_cast<size_t>(cuts[c].v)]++)] = static_cast<int32_t>(c);
  }
  return out;
}

// 3. Warping (paper §3): a vertex violated by a cut point — closer than α·edge length — moves
// to the closest violating cut point and becomes a surface vertex; the cut points on its
// edges are discarded. Vertices are visited in lattice order, so the result is deterministic.
// Returns how many vertices were warped.
int64_t Warp(const StuffingOptions& options, const IncidentCuts& incident_cuts,
             std::vector<Vector3d>* positions_out, std::vector<Sign>* signs,
             std::vector<CutEdge>* cuts_out) {
  std::vector<Vector3d>& positions = *positions_out;
  std::vector<CutEdge>& cuts = *cuts_out;
  const std::vector<int32_t>& first = incident_cuts.first;
  const std::vector<int32_t>& incident = incident_cuts.incident;
  const auto num_lattice = static_cast<int32_t>(positions.size());
  int64_t warped = 0;
  for (int32_t v = 0; v < num_lattice; ++v) {
    const Vector3d& here = positions[static_cast<size_t>(v)];
    double best_distance = std::numeric_limits<double>::infinity();
    int32_t best_cut = -1;
    for (int32_t e = first[static_cast<size_t>(v)]; e < first[static_cast<size_t>(v) + 1]; ++e) {
      const CutEdge& cut = cuts[static_cast<size_t>(incident[static_cast<size_t>(e)])];
      if (cut.discarded) continue;
      const double length =
          (positions[static_cast<size_t>(cut.u)] - positions[static_cast<size_t>(cut.v)]).norm();
      const double alpha = cut.is_long ? options.alpha_long : options.alpha_short;
      const double distance = (cut.position - here).norm();
      if (distance < alpha * length && distance < best_distance) {
        best_distance = distance;
        best_cut = incident[static_cast<size_t>(e)];
      }
    }
    if (best_cut < 0) continue;
    positions[static_cast<size_t>(v)] = cuts[static_cast<size_t>(best_cut)].position;
    (*signs)[static_cast<size_t>(v)] = Sign::kZero;
    ++warped;
    for (int32_t e = first[static_cast<size_t>(v)]; e < first[static_cast<size_t>(v) + 1]; ++e) {
      cuts[static_cast<size_t>(incident[static_cast<size_t>(e)])].discarded = true;
    }
  }
  return warped;
}

// The global id of the cut point on lattice edge (a, b): num_lattice + its index among the cuts
// (the discarded ones have none).
class CutIds {
 public:
  CutIds(const std::vector<CutEdge>& cuts, int32_t num_lattice) : num_lattice_(num_lattice) {
    cut_of_edge_.reserve(cuts.size());
    for (size_t c = 0; c < cuts.size(); ++c) {
      if (!cuts[c].discarded)
        cut_of_edge_.emplace(EdgeKey(cuts[c].u, cuts[c].v), static_cast<int32_t>(c));
    }
  }
  int32_t operator()(int32_t a, int32_t b) const {
    const auto found = cut_of_edge_.find(EdgeKey(a, b));
    // Present by construction: a and b are unwarped and on opposite sides.
    return num_lattice_ + found->second;
  }
  int64_t size() const { return static_cast<int64_t>(cut_of_edge_.size()); }

 private:
  std::unordered_map<uint64_t, int32_t> cut_of_edge_;
  int32_t num_lattice_;
};

// 4. Fills one lattice tetrahedron by the stencil of its sign pattern (paper §4, figure 3).
// Returns whether the surface cuts it: false when it is filled whole or left out.
bool FillLatticeTet(const std::array<int32_t, 4>& tet, const std::vector<Sign>& signs,
                    const CutIds& cut_id, TetAssembler* assembler) {
  std::array<int32_t, 4> in{}, zero{}, out{};
  int n_in = 0, n_zero = 0, n_out = 0;
  for (const int32_t v : tet) {
    switch (signs[static_cast<size_t>(v)]) {
      case Sign::kInside:
        in[static_cast<size_t>(n_in++)] = v;
        break;
      case Sign::kZero:
        zero[static_cast<size_t>(n_zero++)] = v;
        break;
      case Sign::kOutside:
        out[static_cast<size_t>(n_out++)] = v;
        break;
    }
  }
  // No inside vertex: nothing to fill. (Four surface vertices can be a sliver lying on the
  // surface; dropping it keeps the angle guarantee.)
  if (n_in == 0) return false;
  if (n_out == 0) {
    assembler->Add(tet[0], tet[1], tet[2], tet[3]);
    return false;
  }
  // A quadrilateral on a lattice face with inside corners a, b and outside corner o is shared
  // with the neighbouring lattice tetrahedron, so both must split it alike: the diagonal
  // starts at the inside corner with the smaller lattice index. Any total order keeps every
  // prism acyclic, hence triangulable.
  if (n_in == 1) {
    const int32_t a = in[0];
    if (n_out == 3) {
      assembler->Add(a, cut_id(a, out[0]), cut_id(a, out[1]), cut_id(a, out[2]));
    } else if (n_out == 2) {
      assembler->Add(a, zero[0], cut_id(a, out[0]), cut_id(a, out[1]));
    } else {
      assembler->Add(a, zero[0], zero[1], cut_id(a, out[0]));
    }
  } else if (n_in == 2) {
    const int32_t a = in[0];
    const int32_t b = in[1];
    const int from_a = a < b ? 1 : -1;
    if (n_out == 2) {
      // Prism with ends (a, a|c, a|d) and (b, b|c, b|d); the side between the cut points lies
      // inside this lattice tetrahedron and is free.
      const int32_t c = out[0];
      const int32_t d = out[1];
      assembler->AddPrism({a, cut_id(a, c), cut_id(a, d)}, {b, cut_id(b, c), cut_id(b, d)},
                          {from_a, 0, from_a});
    } else {
      // Pyramid: apex at the surface vertex z over the quadrilateral (a, b, b|o, a|o).
      const int32_t z = zero[0];
      const int32_t o = out[0];
      const int32_t ao = cut_id(a, o);
      const int32_t bo = cut_id(b, o);
      if (from_a > 0) {
        assembler->Add(z, a, b, bo);
        assembler->Add(z, a, bo, ao);
      } else {
        assembler->Add(z, a, b, ao);
        assembler->Add(z, b, bo, ao);
      }
    }
  } else {
    // Three inside corners and one outside: prism (a, b, c) – (a|o, b|o, c|o), all three
    // sides on lattice faces.
    const int32_t o = out[0];
    const std::array<int32_t, 3> p = {in[0], in[1], in[2]};
    const std::array<int32_t, 3> q = {cut_id(p[0], o), cut_id(p[1], o), cut_id(p[2], o)};
    assembler->AddPrism(p, q, {p[0] < p[1] ? 1 : -1, p[1] < p[2] ? 1 : -1, p[0] < p[2] ? 1 : -1});
  }
  return true;
}

// 5. Keeps only the vertices the tetrahedra use, numbered in global order (lattice, then cuts).
mesh::TetMesh Compact(const TetAssembler& assembler, size_t num_global) {
  const auto& tets = assembler.tets();
  std::vector<int32_t> new_id(num_global, -1);
  for (const auto& t : tets) {
    for (const int32_t v : t) new_id[static_cast<size_t>(v)] = 0;
  }
  int32_t count = 0;
  for (auto& id : new_id) {
    if (id == 0) id = count++;
  }
  mesh::TetMesh result;
  result.vertices.resize(3, count);
  for (size_t g = 0; g < num_global; ++g) {
    if (new_id[g] < 0) continue;
    result.vertices.col(new_id[g]) = assembler.Position(static_cast<int32_t>(g));
  }
  result.tetrahedra.resize(4, static_cast<Eigen::Index>(tets.size()));
  for (size_t t = 0; t < tets.size(); ++t) {
    for (int c = 0; c < 4; ++c) {
      result.tetrahedra(c, static_cast<Eigen::Index>(t)) =
          new_id[static_cast<size_t>(tets[t][static_cast<size_t>(c)])];
    }
  }
  return result;
}

}  // namespace

mesh::TetMesh StuffIsosurface(const ImplicitSolid& solid, const StuffingOptions& options,
                              StuffingStatistics* statistics, int64_t max_lattice_vertices) {
  CheckOptions(options);
  const mesh::BoundingBox bounds = solid.Bounds();
  if (bounds.empty || !bounds.min.allFinite() || !bounds.max.allFinite() ||
      !(bounds.min.array() <= bounds.max.array()).all()) {
    throw std::invalid_argument("isosurface stuffing: the solid's bounds are empty or not finite");
  }
  const BccLattice lattice(bounds, options, max_lattice_vertices);
  const int32_t num_lattice = lattice.num_vertices();
  std::vector<Vector3d> positions;
  std::vector<Sign> signs;
  EvaluateSigns(solid, lattice, &positions, &signs);
  std::vector<CutEdge> cuts = FindCutPoints(solid, lattice, positions, signs);
  const int64_t warped = Warp(options, CutsPerVertex(num_lattice, cuts), &positions, &signs, &cuts);
  const CutIds cut_id(cuts, num_lattice);
  TetAssembler assembler(positions, cuts);
  int64_t tets_cut = 0;
  lattice.ForEachTet([&](const std::array<int32_t, 4>& tet) {
    tets_cut += FillLatticeTet(tet, signs, cut_id, &assembler) ? 1 : 0;
  });
  mesh::TetMesh result = Compact(assembler, static_cast<size_t>(num_lattice) + cuts.size());
  if (statistics != nullptr) {
    statistics->lattice_vertices = num_lattice;
    statistics->warped_vertices = warped;
    statistics->cut_points = cut_id.size();
    statistics->lattice_tets_cut = tets_cut;
  }
  return result;
}

}  // namespace somasim::mesh_gen
