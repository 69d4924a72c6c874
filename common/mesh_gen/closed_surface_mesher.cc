#include "common/mesh_gen/closed_surface_mesher.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <tuple>
#include <vector>

#include "common/mesh_gen/sphere_layout.h"

namespace somasim::mesh_gen {
namespace {

using Eigen::Vector3d;
// Steps 1 and 2, the layout and the rays that map it onto the surface, are in sphere_layout.h.
using sphere_layout::Fail;
using sphere_layout::Format;
using sphere_layout::Frame;
using sphere_layout::IsRadiallyEmbedded;
using sphere_layout::MakeFrame;
using sphere_layout::MakeSphereLayout;
using sphere_layout::MeasureProfile;
using sphere_layout::OctantEllipsoid;
using sphere_layout::RayCaster;
using sphere_layout::RayDirection;
using sphere_layout::SphereLayout;
using sphere_layout::Triangle;
using sphere_layout::UnitSphereProfile;

// |Value| below which a vertex counts as on the surface [m].
constexpr double kSurfaceTolerance = 1e-10;
// Fraction of the remaining way to the centroid a smoothing step covers. Below 1 it damps the
// Gauss–Seidel sweep against overshoot on coarse meshes.
constexpr double kSmoothingStep = 0.9;
// Halvings of a smoothing step tried before a vertex that would fold a triangle stays put.
constexpr int kStepHalvings = 3;
// A flip must lower the cosine of the smaller angle of the edge's two triangles by this much;
// the max-min criterion with a margin cannot cycle (the sorted angle vector grows each flip).
constexpr double kFlipGain = 1e-12;
// A vertex that moves less than this fraction of the mean edge length counts as settled: its
// neighbours are not smoothed again on its account (active-set relaxation; the sweeps then cost
// little once most of the mesh has converged).
constexpr double kSettleFraction = 1e-2;
// Flip passes per relaxation sweep, at most.
constexpr int kMaxFlipPasses = 50;

// The working surface during relaxation.
struct WorkMesh {
  std::vector<Vector3d> positions;               // [m], on the surface
  std::vector<Vector3d> normals;                 // unit outward normals of the solid there
  std::vector<Triangle> triangles;               // CCW from outside
  std::vector<Triangle> across;                  // triangle → triangle across edge k (k → k+1)
  std::vector<std::vector<int32_t>> neighbours;  // vertex → adjacent vertices (edges)
  Vector3d centre;                               // options.centre [m]
  // Vertices whose one-ring changed (a neighbour or the vertex moved by more than
  // settle_distance, or an incident edge flipped) since they were last smoothed.
  std::vector<char> active;
  double settle_distance = 0.0;  // [m]
};

size_t Index(int32_t i) { return static_cast<size_t>(i); }

// Fills mesh->across and mesh->neighbours from mesh->triangles (closed, consistently oriented).
void BuildAdjacency(WorkMesh* mesh) {
  struct EdgeRecord {
    int32_t lo;
    int32_t hi;
    int32_t triangle;
    int32_t local;  // edge from corner local to corner local + 1
    bool operator<(const EdgeRecord& o) const {
      return std::tie(lo, hi, triangle, local) < std::tie(o.lo, o.hi, o.triangle, o.local);
    }
  };
  std::vector<EdgeRecord> edges;
  edges.reserve(3 * mesh->triangles.size());
  mesh->neighbours.assign(mesh->positions.size(), {});
  for (size_t t = 0; t < mesh->triangles.size(); ++t) {
    for (int32_t k = 0; k < 3; ++k) {
      const int32_t u = mesh->triangles[t][Index(k)];
      const int32_t v = mesh->triangles[t][Index((k + 1) % 3)];
      edges.push_back({std::min(u, v), std::max(u, v), static_cast<int32_t>(t), k});
      // The edge is u → v here and v → u in the other triangle: each end gets it once.
      mesh->neighbours[Index(u)].push_back(v);
    }
  }
  std::sort(edges.begin(), edges.end());
  mesh->across.assign(mesh->triangles.size(), {-1, -1, -1});
  for (size_t e = 0; e + 1 < edges.size(); e += 2) {
    // A closed manifold surface has exactly two triangles per edge.
    assert(edges[e].lo == edges[e + 1].lo && edges[e].hi == edges[e + 1].hi);
    mesh->across[Index(edges[e].triangle)][Index(edges[e].local)] = edges[e + 1].triangle;
    mesh->across[Index(edges[e + 1].triangle)][Index(edges[e + 1].local)] = edges[e].triangle;
  }
}

Vector3d UnitNormal(const ImplicitSolid& solid, const Vector3d& p) {
  const Vector3d gradient = ImplicitGradient(solid, p);
  const double norm = gradient.norm();
  return norm > 0.0 ? Vector3d(gradient / norm) : Vector3d::Zero();
}

// p moved onto the surface: ProjectToSurface, and where its damped Newton steps have not
// reached kSurfaceTolerance (a Value much flatter than a distance, |∇Value| << 1), a root
// bracketed along the normal line and found by FindSegmentRoot. Returns p unchanged if neither
// works (a vanishing gradient).
Vector3d SnapToSurface(const ImplicitSolid& solid, const Vector3d& p) {
  Vector3d q = ProjectToSurface(solid, p, kSurfaceTolerance);
  const double value = solid.Value(q);
  if (std::abs(value) < kSurfaceTolerance) return q;
  const Vector3d normal = UnitNormal(solid, q);
  if (!(normal.squaredNorm() > 0.5)) return q;
  // Walk against the sign of Value with doubling steps until it changes sign.
  const Vector3d towards = value > 0.0 ? Vector3d(-normal) : normal;
  double step = std::abs(value);
  for (int doubling = 0; doubling < 60; ++doubling, step *= 2.0) {
    const Vector3d far = q + step * towards;
    if ((solid.Value(far) < 0.0) != (value < 0.0)) return FindSegmentRoot(solid, q, far);
  }
  return q;
}

// Cosine of the triangle's smallest angle (the largest of its three angle cosines).
double MinAngleCosine(const Vector3d& a, const Vector3d& b, const Vector3d& c) {
  const Vector3d ab = (b - a).normalized();
  const Vector3d bc = (c - b).normalized();
  const Vector3d ca = (a - c).normalized();
  return std::max({-ab.dot(ca), -bc.dot(ab), -ca.dot(bc)});
}

// Whether triangle t passes both orientation tests: it faces the same way as the solid's
// normals at its corners, and it is counter-clockwise seen from the centre. The second, kept by
// every triangle from the radial initial map on, makes the radial projection from the centre a
// local homeomorphism of degree one from the mesh onto a sphere, hence a bijection: the mesh
// stays embedded (no fold, no self-intersection), whatever the relaxation does.
//
// Written out in scalars: it runs for every triangle around every move and every flip, and
// Eigen's expression templates cost dearly in the unoptimised sanitizer build.
bool FacesOutwards(const WorkMesh& mesh, const Triangle& t) {
  const Vector3d& a = mesh.positions[Index(t[0])];
  const Vector3d& b = mesh.positions[Index(t[1])];
  const Vector3d& c = mesh.positions[Index(t[2])];
  const Vector3d& na = mesh.normals[Index(t[0])];
  const Vector3d& nb = mesh.normals[Index(t[1])];
  const Vector3d& nc = mesh.normals[Index(t[2])];
  const double ux = b.x() - a.x(), uy = b.y() - a.y(), uz = b.z() - a.z();
  const double vx = c.x() - a.x(), vy = c.y() - a.y(), vz = c.z() - a.z();
  const double nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
  const double along_normals = nx * (na.x() + nb.x() + nc.x()) + ny * (na.y() + nb.y() + nc.y()) +
                               nz * (na.z() + nb.z() + nc.z());
  const double seen_from_centre = nx * (a.x() - mesh.centre.x()) + ny * (a.y() - mesh.centre.y()) +
                                  nz * (a.z() - mesh.centre.z());
  return along_normals > 0.0 && seen_from_centre > 0.0;
}

bool Contains(const std::vector<int32_t>& list, int32_t value) {
  return std::find(list.begin(), list.end(), value) != list.end();
}

void Erase(std::vector<int32_t>* list, int32_t value) {
  list->erase(std::find(list->begin(), list->end(), value));
}

// Points the entry of triangle t that referred to `from` at `to`.
void Repoint(WorkMesh* mesh, int32_t t, int32_t from, int32_t to) {
  Triangle& across = mesh->across[Index(t)];
  *std::find(across.begin(), across.end(), from) = to;
}

// Flips edge k of triangle t1 if that raises the smaller angle of its two triangles and keeps
// the surface a valid, outward-facing simplicial sphere. Returns whether it flipped.
bool TryFlip(WorkMesh* mesh, int32_t t1, int32_t k) {
  // T1 = (a, b, c) and T2 = (b, a, d), both counter-clockwise; the flip gives (c, a, d) and
  // (d, b, c) with the new edge c–d.
  const int32_t t2 = mesh->across[Index(t1)][Index(k)];
  const Triangle tri1 = mesh->triangles[Index(t1)];
  const Triangle tri2 = mesh->triangles[Index(t2)];
  const int32_t a = tri1[Index(k)];
  const int32_t b = tri1[Index((k + 1) % 3)];
  const int32_t c = tri1[Index((k + 2) % 3)];
  const auto k2 = static_cast<int32_t>(std::find(tri2.begin(), tri2.end(), b) - tri2.begin());
  assert(tri2[Index((k2 + 1) % 3)] == a);
  const int32_t d = tri2[Index((k2 + 2) % 3)];
  // Each of a and b loses an edge and must keep three, and the edge c–d must not exist already
  // (it would be doubled).
  if (c == d || mesh->neighbours[Index(a)].size() <= 3 || mesh->neighbours[Index(b)].size() <= 3 ||
      Contains(mesh->neighbours[Index(c)], d)) {
    return false;
  }
  const Vector3d& pa = mesh->positions[Index(a)];
  const Vector3d& pb = mesh->positions[Index(b)];
  const Vector3d& pc = mesh->positions[Index(c)];
  const Vector3d& pd = mesh->positions[Index(d)];
  // Cheap filter first: the edge is locally Delaunay (no flip wanted) when the angles at c and
  // d sum to at most π, i.e. sin(γ + δ) >= 0, which needs neither normalisation nor acos.
  const Vector3d ca = pa - pc;
  const Vector3d cb = pb - pc;
  const Vector3d db = pb - pd;
  const Vector3d da = pa - pd;
  if (ca.dot(cb) * db.cross(da).norm() + db.dot(da) * ca.cross(cb).norm() >= 0.0) return false;
  const double old_cosine = std::max(MinAngleCosine(pa, pb, pc), MinAngleCosine(pb, pa, pd));
  const double new_cosine = std::max(MinAngleCosine(pc, pa, pd), MinAngleCosine(pd, pb, pc));
  if (!(new_cosine < old_cosine - kFlipGain)) return false;
  const Triangle new1 = {c, a, d};
  const Triangle new2 = {d, b, c};
  // The new triangles must face outwards and not fold onto each other.
  if (!FacesOutwards(*mesh, new1) || !FacesOutwards(*mesh, new2) ||
      !((pa - pc).cross(pd - pc).dot((pb - pd).cross(pc - pd)) > 0.0)) {
    return false;
  }
  // Outer neighbours, by the edge they share: b→c and c→a of T1, a→d and d→b of T2.
  const int32_t n_bc = mesh->across[Index(t1)][Index((k + 1) % 3)];
  const int32_t n_ca = mesh->across[Index(t1)][Index((k + 2) % 3)];
  const int32_t n_ad = mesh->across[Index(t2)][Index((k2 + 1) % 3)];
  const int32_t n_db = mesh->across[Index(t2)][Index((k2 + 2) % 3)];
  mesh->triangles[Index(t1)] = new1;  // edges c→a, a→d, d→c
  mesh->triangles[Index(t2)] = new2;  // edges d→b, b→c, c→d
  mesh->across[Index(t1)] = {n_ca, n_ad, t2};
  mesh->across[Index(t2)] = {n_db, n_bc, t1};
  Repoint(mesh, n_ad, t2, t1);
  Repoint(mesh, n_bc, t1, t2);
  Erase(&mesh->neighbours[Index(a)], b);
  Erase(&mesh->neighbours[Index(b)], a);
  mesh->neighbours[Index(c)].push_back(d);
  mesh->neighbours[Index(d)].push_back(c);
  for (int32_t v : {a, b, c, d}) mesh->active[Index(v)] = 1;
  return true;
}

// Max-min-angle edge flips in passes over the triangles in index order, until a pass flips
// nothing or kMaxFlipPasses have run. With only_active, edges whose two triangles have no
// active vertex are skipped: nothing around them has moved noticeably since they were checked.
void FlipEdges(WorkMesh* mesh, bool only_active) {
  const auto num_triangles = static_cast<int32_t>(mesh->triangles.size());
  auto any_active = [&](int32_t t) {
    const Triangle& tri = mesh->triangles[Index(t)];
    return mesh->active[Index(tri[0])] || mesh->active[Index(tri[1])] ||
           mesh->active[Index(tri[2])];
  };
  for (int pass = 0; pass < kMaxFlipPasses; ++pass) {
    int flips = 0;
    for (int32_t t = 0; t < num_triangles; ++t) {
      for (int32_t k = 0; k < 3; ++k) {
        // Each edge once per pass, from its lower-numbered triangle.
        const int32_t other = mesh->across[Index(t)][Index(k)];
        if (other < t || (only_active && !any_active(t) && !any_active(other))) continue;
        if (TryFlip(mesh, t, k)) ++flips;
      }
    }
    if (flips == 0) break;
  }
}

// One Gauss–Seidel sweep of tangential area-weighted centroid smoothing (Botsch & Kobbelt 2004),
// each vertex projected back onto the surface.
void SmoothSweep(const ImplicitSolid& solid, WorkMesh* mesh) {
  const size_t num_vertices = mesh->positions.size();
  // Vertex → incident triangles, compressed (offsets: num_vertices + 1).
  std::vector<int32_t> offsets(num_vertices + 1, 0);
  for (const Triangle& t : mesh->triangles) {
    for (int32_t v : t) ++offsets[static_cast<size_t>(v) + 1];
  }
  for (size_t i = 1; i <= num_vertices; ++i) offsets[i] += offsets[i - 1];
  std::vector<int32_t> incident(static_cast<size_t>(offsets.back()));
  std::vector<int32_t> fill(offsets.begin(), offsets.end() - 1);
  for (size_t t = 0; t < mesh->triangles.size(); ++t) {
    for (int32_t v : mesh->triangles[t]) {
      incident[static_cast<size_t>(fill[static_cast<size_t>(v)]++)] = static_cast<int32_t>(t);
    }
  }

  std::vector<char> next_active(num_vertices, 0);
  for (size_t i = 0; i < num_vertices; ++i) {
    if (!mesh->active[i]) continue;
    const auto begin = static_cast<size_t>(offsets[i]);
    const auto end = static_cast<size_t>(offsets[i + 1]);
    Vector3d weighted = Vector3d::Zero();
    Vector3d mesh_normal = Vector3d::Zero();
    double total_area = 0.0;
    for (size_t j = begin; j < end; ++j) {
      const Triangle& t = mesh->triangles[static_cast<size_t>(incident[j])];
      const Vector3d& a = mesh->positions[static_cast<size_t>(t[0])];
      const Vector3d& b = mesh->positions[static_cast<size_t>(t[1])];
      const Vector3d& c = mesh->positions[static_cast<size_t>(t[2])];
      const Vector3d twice_area_normal = (b - a).cross(c - a);
      const double area = 0.5 * twice_area_normal.norm();
      weighted += area * (a + b + c) / 3.0;
      mesh_normal += twice_area_normal;
      total_area += area;
    }
    if (!(total_area > 0.0) || !(mesh_normal.norm() > 0.0)) continue;
    // The tangent plane is the mesh's own (area-weighted face normals), not the solid's: the
    // centroid lies off the surface by the curvature, along the mesh normal, and projecting
    // with the solid's normal would turn that offset into a spurious sideways push wherever
    // the two normals differ (coarse meshes, sharp ends), which makes vertices slide off the
    // tips of elongated shapes.
    mesh_normal.normalize();
    const Vector3d old_position = mesh->positions[i];
    const Vector3d old_normal = mesh->normals[i];
    Vector3d move = weighted / total_area - old_position;
    move -= move.dot(mesh_normal) * mesh_normal;  // tangential part only
    move *= kSmoothingStep;
    bool accepted = false;
    for (int attempt = 0; attempt <= kStepHalvings && !accepted; ++attempt, move *= 0.5) {
      const Vector3d candidate = SnapToSurface(solid, old_position + move);
      const Vector3d normal = UnitNormal(solid, candidate);
      if (!(normal.squaredNorm() > 0.5) || !candidate.allFinite()) continue;
      mesh->positions[i] = candidate;
      mesh->normals[i] = normal;
      // Every incident triangle must pass both orientation tests after the move (one that
      // failed before, on a coarse mesh, may only be mended).
      accepted = true;
      for (size_t j = begin; j < end && accepted; ++j) {
        accepted = FacesOutwards(*mesh, mesh->triangles[static_cast<size_t>(incident[j])]);
      }
    }
    if (!accepted) {
      mesh->positions[i] = old_position;
      mesh->normals[i] = old_normal;
    } else if ((mesh->positions[i] - old_position).norm() > mesh->settle_distance) {
      // The vertex and its neighbours see a changed one-ring: smooth them again next sweep.
      next_active[i] = 1;
      for (int32_t v : mesh->neighbours[i]) next_active[Index(v)] = 1;
    }
  }
  mesh->active.swap(next_active);
}

void Validate(const ImplicitSolid& solid, const ClosedSurfaceOptions& options) {
  if (options.num_vertices < 4) {
    Fail("options.num_vertices must be >= 4 (got " + std::to_string(options.num_vertices) + ")");
  }
  if (options.num_vertices > std::numeric_limits<int32_t>::max() / 2) {
    Fail("options.num_vertices is too large (got " + std::to_string(options.num_vertices) + ")");
  }
  if (options.smoothing_iterations < 0) {
    Fail("options.smoothing_iterations must be >= 0 (got " +
         std::to_string(options.smoothing_iterations) + ")");
  }
  if (!options.long_axis.allFinite() || !(std::abs(options.long_axis.norm() - 1.0) <= 1e-6)) {
    Fail("options.long_axis must be a unit vector (got " + Format(options.long_axis) + ")");
  }
  if (!options.centre.allFinite()) {
    Fail("options.centre must be finite (got " + Format(options.centre) + ")");
  }
  const double value = solid.Value(options.centre);
  if (!(value < 0.0)) {
    Fail("options.centre " + Format(options.centre) +
         " must lie inside the solid (Value = " + std::to_string(value) + ")");
  }
}

}  // namespace

mesh::SurfaceMesh MeshClosedSurface(const ImplicitSolid& solid,
                                    const ClosedSurfaceOptions& options) {
  Validate(solid, options);
  const int n = options.num_vertices;
  const Frame frame = MakeFrame(options.long_axis);
  const RayCaster caster(solid, options.centre);

  // 1. Reach of the solid along the frame's six half-axes, and the layout fitted to it.
  OctantEllipsoid shape{};
  for (int axis = 0; axis < 3; ++axis) {
    const Vector3d direction = frame.ToWorld(Vector3d::Unit(axis));
    const auto a = static_cast<size_t>(axis);
    shape.plus[a] = (caster.Cast(direction) - options.centre).norm();
    shape.minus[a] = (caster.Cast(-direction) - options.centre).norm();
  }
  // The layout fitted to the surface can be tangled when it is sparse (a few points per ring,
  // rings crowded in θ where the surface runs away from the centre): then fall back to the plain
  // latitude layout of the sphere, cast along its own directions, and let the relaxation even
  // it out.
  SphereLayout layout = MakeSphereLayout(n, MeasureProfile(caster, frame, shape));
  std::vector<Vector3d> directions;
  directions.reserve(static_cast<size_t>(n));
  for (const Vector3d& u : layout.points) directions.push_back(RayDirection(frame, shape, u));
  if (!IsRadiallyEmbedded(layout.triangles, directions)) {
    layout = MakeSphereLayout(n, UnitSphereProfile());
    directions.clear();
    for (const Vector3d& u : layout.points) directions.push_back(frame.ToWorld(u).normalized());
    assert(IsRadiallyEmbedded(layout.triangles, directions));
  }

  // 2. Radial map from the centre onto the surface.
  WorkMesh mesh;
  mesh.positions.reserve(static_cast<size_t>(n));
  mesh.normals.reserve(static_cast<size_t>(n));
  for (const Vector3d& direction : directions) {
    const Vector3d p = SnapToSurface(solid, caster.Cast(direction));
    mesh.positions.push_back(p);
    mesh.normals.push_back(UnitNormal(solid, p));
  }
  mesh.triangles = layout.triangles;
  mesh.centre = options.centre;
  BuildAdjacency(&mesh);
  mesh.active.assign(static_cast<size_t>(n), 1);
  double edge_sum = 0.0;
  for (const Triangle& t : mesh.triangles) {
    for (size_t k = 0; k < 3; ++k) {
      edge_sum += (mesh.positions[Index(t[(k + 1) % 3])] - mesh.positions[Index(t[k])]).norm();
    }
  }
  mesh.settle_distance =
      kSettleFraction * edge_sum / (3.0 * static_cast<double>(mesh.triangles.size()));

  // 3. Relaxation: flips, then tangential smoothing, repeated; a last flip pass.
  for (int sweep = 0; sweep < options.smoothing_iterations; ++sweep) {
    FlipEdges(&mesh, /*only_active=*/sweep > 0);
    SmoothSweep(solid, &mesh);
  }
  FlipEdges(&mesh, /*only_active=*/false);

  mesh::SurfaceMesh surface;
  surface.vertices.resize(3, n);
  for (int i = 0; i < n; ++i) surface.vertices.col(i) = mesh.positions[static_cast<size_t>(i)];
  surface.triangles.resize(3, static_cast<Eigen::Index>(mesh.triangles.size()));
  for (size_t t = 0; t < mesh.triangles.size(); ++t) {
    for (size_t k = 0; k < 3; ++k) {
      surface.triangles(static_cast<Eigen::Index>(k), static_cast<Eigen::Index>(t)) =
          mesh.triangles[t][k];
    }
  }
  return surface;
}

}  // namespace somasim::mesh_gen
