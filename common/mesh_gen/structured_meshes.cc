#include "common/mesh_gen/structured_meshes.h"

#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace somasim::mesh_gen {
namespace {

// A cell's 8 corners are numbered by their local lattice position (a, b, c) ∈ {0,1}³ as
// a + 2b + 4c. Every table below lists tetrahedra over these local numbers, positively oriented
// in the local (a, b, c) frame (checked by the tests through the assembled meshes).
using CellTet = std::array<int, 4>;

// Kuhn / Freudenthal split of the unit cube: one tetrahedron per permutation (p0, p1, p2) of the
// axes, walking 0 → e_p0 → e_p0 + e_p1 → (1,1,1) (Freudenthal 1942; Kuhn 1960). Each cube face
// gets the diagonal through its lowest corner, so translated copies agree on shared faces.
constexpr std::array<CellTet, 6> kKuhnSplit = {{
    {0, 1, 3, 7},
    {0, 1, 7, 5},
    {0, 2, 7, 3},
    {0, 2, 6, 7},
    {0, 4, 5, 7},
    {0, 4, 7, 6},
}};

// 5-tetrahedron split of the unit cube: the central tetrahedron on the even corners
// (0, 3, 5, 6: a + b + c even) and the four corner tetrahedra cut off at the odd corners. All six
// face diagonals join even corners.
constexpr std::array<CellTet, 5> kFiveSplit = {{
    {0, 3, 6, 5},
    {1, 0, 5, 3},
    {2, 0, 3, 6},
    {4, 0, 6, 5},
    {7, 3, 5, 6},
}};

// A 6-tetrahedron triangulation of the unit cube (one of the 72 that use only the cube's corners,
// found by enumerating all sets of lattice tetrahedra of total volume 1 that pair up every interior
// triangle). Its face diagonals are the even ones of kFiveSplit on the faces a = 1, b = 0, b = 1
// and c = 1, and the odd ones (2–4 on a = 0, 1–2 on c = 0) on the other two, so it fits a cell
// whose a = 0 and c = 0 faces lie on the boundary. Among the triangulations with that pattern it
// has the largest minimum dihedral angle in the plate's cells (19.3°, against 17.0° for the
// 6-tetrahedron splits that keep every face even).
constexpr std::array<CellTet, 6> kSixSplitOddA0C0 = {{
    {0, 1, 2, 5},
    {0, 2, 4, 5},
    {1, 2, 5, 3},
    {2, 3, 6, 5},
    {2, 4, 5, 6},
    {3, 5, 7, 6},
}};

// Coordinate t ∈ [0, n-1] along one axis mapped onto [lo, hi]; exact at both ends.
double Lerp(double lo, double hi, int t, int n) {
  const double s = static_cast<double>(t) / static_cast<double>(n - 1);
  return (1.0 - s) * lo + s * hi;
}

// Nodes of a regular nx × ny × nz grid over [lo, hi], index i + nx·(j + ny·k).
mesh::Points GridNodes(int nx, int ny, int nz, const Eigen::Vector3d& lo,
                       const Eigen::Vector3d& hi) {
  mesh::Points points(3, static_cast<Eigen::Index>(nx) * ny * nz);
  Eigen::Index n = 0;
  for (int k = 0; k < nz; ++k) {
    for (int j = 0; j < ny; ++j) {
      for (int i = 0; i < nx; ++i) {
        points.col(n++) << Lerp(lo.x(), hi.x(), i, nx), Lerp(lo.y(), hi.y(), j, ny),
            Lerp(lo.z(), hi.z(), k, nz);
      }
    }
  }
  return points;
}

// Index offsets of a cell's 8 corners from its (0,0,0) corner in a grid with nx × ny nodes per
// layer, by local corner number a + 2b + 4c.
std::array<int32_t, 8> CornerOffsets(int nx, int ny) {
  std::array<int32_t, 8> offset{};
  for (size_t v = 0; v < 8; ++v) {
    offset[v] =
        static_cast<int32_t>((v & 1) + static_cast<size_t>(nx) * ((v >> 1) & 1) +
                             static_cast<size_t>(nx) * static_cast<size_t>(ny) * ((v >> 2) & 1));
  }
  return offset;
}

// Appends the tetrahedra of one cell to tets (starting at column *next). corner[v] is the global
// node at local corner v. mirrored = the local frame is a reflection of the global one, which
// reverses orientation: two corners are swapped back.
template <size_t N>
void EmitCell(const std::array<CellTet, N>& split, const std::array<int32_t, 8>& corner,
              bool mirrored, mesh::Tetrahedra* tets, Eigen::Index* next) {
  for (const CellTet& t : split) {
    auto col = tets->col((*next)++);
    col << corner[static_cast<size_t>(t[0])], corner[static_cast<size_t>(t[1])],
        corner[static_cast<size_t>(t[2])], corner[static_cast<size_t>(t[3])];
    if (mirrored) std::swap(col(2), col(3));
  }
}

}  // namespace

mesh::TetMesh BoxGridTets(int nx, int ny, int nz, const Eigen::Vector3d& min,
                          const Eigen::Vector3d& max) {
  if (nx < 2 || ny < 2 || nz < 2) {
    throw std::invalid_argument("BoxGridTets: node counts must be >= 2 per axis, got " +
                                std::to_string(nx) + " x " + std::to_string(ny) + " x " +
                                std::to_string(nz));
  }
  if (static_cast<int64_t>(nx) * ny * nz > std::numeric_limits<int32_t>::max()) {
    throw std::invalid_argument("BoxGridTets: node count does not fit an int32 index");
  }
  for (int a = 0; a < 3; ++a) {
    // NaN-safe: !(min < max) also refuses NaN; the finiteness check refuses ±inf.
    if (!std::isfinite(min(a)) || !std::isfinite(max(a)) || !(min(a) < max(a))) {
      throw std::invalid_argument("BoxGridTets: box needs finite min < max on every axis (axis " +
                                  std::to_string(a) + ")");
    }
  }

  mesh::TetMesh mesh;
  mesh.vertices = GridNodes(nx, ny, nz, min, max);
  const Eigen::Index num_cells = static_cast<Eigen::Index>(nx - 1) * (ny - 1) * (nz - 1);
  mesh.tetrahedra.resize(4, 6 * num_cells);
  // Corners as the cell's base node plus fixed offsets. (Recomputing each corner from (i, j, k)
  // inside the cell loop, (i + a) + nx·((j + b) + ny·(k + c)), is miscompiled by gcc 12.2 at -O3:
  // its loop vectoriser returned wrong corners for half the tetrahedra.)
  const std::array<int32_t, 8> offset = CornerOffsets(nx, ny);
  Eigen::Index next = 0;
  for (int k = 0; k + 1 < nz; ++k) {
    for (int j = 0; j + 1 < ny; ++j) {
      for (int i = 0; i + 1 < nx; ++i) {
        const int32_t base = i + nx * (j + ny * k);
        std::array<int32_t, 8> corner{};
        for (size_t v = 0; v < 8; ++v) corner[v] = base + offset[v];
        EmitCell(kKuhnSplit, corner, /*mirrored=*/false, &mesh.tetrahedra, &next);
      }
    }
  }
  return mesh;
}

// Why 12 × 8 × 2 nodes, 70 five-tet cells and 7 six-tet cells:
//  - Seed 003 gives only the counts (192 nodes, 392 tetrahedra) and the size 200 × 200 × 10 mm; its
//    Amira mesh is not available. With a grid of nx × ny × nz nodes and C cells cut into 5 or 6
//    tetrahedra, 5C <= 392 <= 6C needs 66 <= C <= 78; among the factorisations of 192 only
//    12 × 8 × 2 (C = 77), 16 × 6 × 2 (75) and 24 × 4 × 2 (69) qualify, and 12 × 8 × 2 has the
//    least stretched cells (18.2 × 28.6 × 10 mm). 392 = 77·5 + 7, so 7 cells take 6 tetrahedra.
//  - The 5-tet split is conforming across cells when every cell puts its central tetrahedron on the
//    globally even nodes (i + j + k even): every face diagonal then joins even nodes, seen the same
//    from both sides. A cell whose corner (i, j, 0) is odd uses the split mirrored in y (local
//    b = 1 - global b), which keeps the local a = 0 face on the cell's x = i face.
//  - With one node layer on each side of the plate, the faces z = 0 and z = 0.01 m are all on the
//    boundary, and so are the x = 0 faces of the column i = 0 (exactly 7 cells). Those cells take
//    kSixSplitOddA0C0, whose face diagonals differ from the even pattern only on its a = 0 (x = 0)
//    and c = 0 (z = 0) faces, both boundary: the mesh stays conforming.
// Minimum dihedral angle: 33.1° in the 5-tet cells, 19.3° in the 6-tet cells.
mesh::TetMesh Plate192() {
  constexpr int kNx = 12;
  constexpr int kNy = 8;
  constexpr int kNz = 2;
  const Eigen::Vector3d lo(0.0, 0.0, 0.0);
  const Eigen::Vector3d hi(0.2, 0.2, 0.01);  // [m]

  mesh::TetMesh mesh;
  mesh.vertices = GridNodes(kNx, kNy, kNz, lo, hi);
  mesh.tetrahedra.resize(4, 392);
  const std::array<int32_t, 8> offset = CornerOffsets(kNx, kNy);
  Eigen::Index next = 0;
  for (int j = 0; j + 1 < kNy; ++j) {
    for (int i = 0; i + 1 < kNx; ++i) {
      const bool mirrored = (i + j) % 2 == 1;
      // Local corner a + 2b + 4c is global corner a + 2(1 - b) + 4c when mirrored in y.
      const int32_t base = i + kNx * j;
      std::array<int32_t, 8> corner{};
      for (size_t v = 0; v < 8; ++v) corner[v] = base + offset[mirrored ? v ^ 2u : v];
      if (i == 0) {
        EmitCell(kSixSplitOddA0C0, corner, mirrored, &mesh.tetrahedra, &next);
      } else {
        EmitCell(kFiveSplit, corner, mirrored, &mesh.tetrahedra, &next);
      }
    }
  }
  return mesh;
}

// Construction: concentric elliptical rings of 1 (the apex), 7, 15 and 22 (the rim) points at
// scaled radii 0, 0.42, 0.72 and 1, evenly spaced in the ellipse's parameter angle; the
// 15-ring is turned by half a step so that its points sit between those of its neighbours. The
// ring sizes grow by about 7.5 per ring, close to the 2π per unit radius of an evenly spaced
// disc, so the triangles are near-equilateral. The apex is fanned to the first ring; each band
// between rings of m and n points is closed by m + n triangles, chosen greedily by the shorter
// diagonal (the classic contour-stitching rule of Christiansen & Sederberg 1978). Euler: a disc
// with 45 vertices of which 22 on the rim has 2·45 - 2 - 22 = 66 triangles. The radii and the
// half-step turn were picked by a small offline search for the largest smallest angle (39.9°);
// the greedy choices win by at least 2 % in length, so rounding cannot flip one, and the
// configuration is mirror-symmetric about the x axis.
mesh::SurfaceMesh TissuePatch45() {
  constexpr double kSemiAxisX = 0.025;  // [m]
  constexpr double kSemiAxisY = 0.020;  // [m]
  constexpr double kDome = 0.004;       // apex height over the rim [m]
  constexpr std::array<int, 4> kRingSize = {1, 7, 15, 22};
  constexpr std::array<double, 4> kRingRadius = {0.0, 0.42, 0.72, 1.0};
  constexpr std::array<int, 4> kRingHalfTurn = {0, 0, 1, 0};  // 1: turned by half a step
  constexpr double kPi = 3.14159265358979323846;

  mesh::SurfaceMesh patch;
  patch.vertices.resize(3, 45);
  std::array<int32_t, 5> ring_start{};  // first vertex of each ring; [4] = total
  int32_t n = 0;
  for (size_t r = 0; r < kRingSize.size(); ++r) {
    ring_start[r] = n;
    for (int k = 0; k < kRingSize[r]; ++k) {
      const double angle =
          kPi * static_cast<double>(2 * k + kRingHalfTurn[r]) / static_cast<double>(kRingSize[r]);
      const double x = kSemiAxisX * kRingRadius[r] * std::cos(angle);
      const double y = kSemiAxisY * kRingRadius[r] * std::sin(angle);
      // Paraboloid dome: apex kDome at the centre, 0 on the rim ellipse.
      const double u = x / kSemiAxisX;
      const double w = y / kSemiAxisY;
      patch.vertices.col(n++) << x, y, kDome * (1.0 - u * u - w * w);
    }
  }
  ring_start[4] = n;

  std::vector<std::array<int32_t, 3>> triangles;
  triangles.reserve(66);  // 2·45 - 2 - 22 (Euler, see above)
  // Apex fan, counter-clockwise seen from +z.
  for (int32_t k = 0; k < kRingSize[1]; ++k) {
    triangles.push_back({0, ring_start[1] + k, ring_start[1] + (k + 1) % kRingSize[1]});
  }
  // Bands between consecutive rings.
  for (size_t r = 1; r + 1 < kRingSize.size(); ++r) {
    const int32_t ni = kRingSize[r];
    const int32_t no = kRingSize[r + 1];
    const auto inner = [&](int32_t k) { return ring_start[r] + k % ni; };
    // The outer ring is walked from its first point at or after the inner ring's first point in
    // angle: compare (2k + h_o) / (2 no) >= h_i / (2 ni) in integers, so no rounding decides it.
    int32_t j0 = 0;
    while (static_cast<int64_t>(2 * j0 + kRingHalfTurn[r + 1]) * ni <
           static_cast<int64_t>(kRingHalfTurn[r]) * no) {
      ++j0;
    }
    const auto outer = [&](int32_t k) { return ring_start[r + 1] + (j0 + k) % no; };
    const auto dist = [&](int32_t p, int32_t q) {
      return (patch.vertices.col(p) - patch.vertices.col(q)).norm();
    };
    int32_t i = 0;
    int32_t j = 0;
    while (i < ni || j < no) {
      // Both triangles (inner_i, outer_j, next) are counter-clockwise: outer_j lies radially
      // outward of inner_i and the next point follows counter-clockwise.
      const bool advance_outer =
          i == ni || (j < no && dist(inner(i), outer(j + 1)) < dist(inner(i + 1), outer(j)));
      if (advance_outer) {
        triangles.push_back({inner(i), outer(j), outer(j + 1)});
        ++j;
      } else {
        triangles.push_back({inner(i), outer(j), inner(i + 1)});
        ++i;
      }
    }
  }

  patch.triangles.resize(3, static_cast<Eigen::Index>(triangles.size()));
  for (size_t t = 0; t < triangles.size(); ++t) {
    patch.triangles.col(static_cast<Eigen::Index>(t)) << triangles[t][0], triangles[t][1],
        triangles[t][2];
  }
  return patch;
}

}  // namespace somasim::mesh_gen
