#include "common/mesh_gen/closed_surface_mesher.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <sstream>
#include <stdexcept>
#include <string>
#include <tuple>
#include <vector>

namespace somasim::mesh_gen {
namespace {

using Eigen::Vector3d;
using Triangle = std::array<int32_t, 3>;

// The shortest step along a ray, when bracketing the surface and checking star-shapedness, is
// the (enlarged) box's diagonal / kRaySamples: a re-entry thinner than that can be missed.
constexpr int kRaySamples = 128;
// |Value| below which a vertex counts as on the surface [m].
constexpr double kSurfaceTolerance = 1e-10;
// Rows of constant polar angle, and rays per row, with which the surface is measured to place
// the rings of the initial layout.
constexpr int kProfileRows = 32;
constexpr size_t kProfileColumns = 16;
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

[[noreturn]] void Fail(const std::string& message) {
  throw std::invalid_argument("MeshClosedSurface: " + message);
}

std::string Format(const Vector3d& v) {
  std::ostringstream text;
  text.precision(6);
  text << '(' << v.x() << ", " << v.y() << ", " << v.z() << ')';
  return text.str();
}

// An orthonormal right-handed frame whose first axis is the solid's long axis.
struct Frame {
  Vector3d e1;
  Vector3d e2;
  Vector3d e3;
  Vector3d ToWorld(const Vector3d& local) const {
    return local.x() * e1 + local.y() * e2 + local.z() * e3;
  }
};

Frame MakeFrame(const Vector3d& long_axis) {
  Frame frame;
  frame.e1 = long_axis.normalized();
  // The coordinate axis least aligned with e1 (first one on ties) gives a well-conditioned e2.
  int least = 0;
  for (int axis = 1; axis < 3; ++axis) {
    if (std::abs(frame.e1[axis]) < std::abs(frame.e1[least])) least = axis;
  }
  const Vector3d helper = Vector3d::Unit(least);
  frame.e2 = (helper - helper.dot(frame.e1) * frame.e1).normalized();
  frame.e3 = frame.e1.cross(frame.e2);
  return frame;
}

// Casts rays from the centre to the surface of a solid that must be star-shaped from it.
class RayCaster {
 public:
  RayCaster(const ImplicitSolid& solid, const Vector3d& centre) : solid_(solid), centre_(centre) {
    const mesh::BoundingBox bounds = solid.Bounds();
    if (bounds.empty || !bounds.min.allFinite() || !bounds.max.allFinite() ||
        !(bounds.min.array() < bounds.max.array()).all()) {
      Fail("solid.Bounds() is empty or not finite");
    }
    if (!((centre.array() > bounds.min.array()).all() &&
          (centre.array() < bounds.max.array()).all())) {
      Fail("options.centre " + Format(centre) + " lies outside solid.Bounds()");
    }
    // Slightly enlarged so the last sample of a ray is strictly outside the solid.
    const Vector3d margin = Vector3d::Constant(0.01 * (bounds.max - bounds.min).norm());
    box_min_ = bounds.min - margin;
    box_max_ = bounds.max + margin;
    min_step_ = (box_max_ - box_min_).norm() / kRaySamples;
    centre_value_ = solid.Value(centre);
  }

  // The point where the ray from the centre along `direction` (unit) leaves the solid.
  //
  // The ray is walked from the centre to where it leaves the enlarged box, by steps of half the
  // current |Value| (a distance-like Value that overestimates the distance by at most a factor
  // two cannot skip the surface so) but at least kRaySamples-th of the box's diagonal. The first
  // inside → outside change brackets the surface; a later inside point means the ray re-enters,
  // i.e. the solid is not star-shaped from the centre.
  Vector3d Cast(const Vector3d& direction) const {
    double exit = std::numeric_limits<double>::infinity();
    for (int axis = 0; axis < 3; ++axis) {
      if (direction[axis] > 0.0) {
        exit = std::min(exit, (box_max_[axis] - centre_[axis]) / direction[axis]);
      } else if (direction[axis] < 0.0) {
        exit = std::min(exit, (box_min_[axis] - centre_[axis]) / direction[axis]);
      }
    }
    bool found = false;
    Vector3d hit = centre_;
    double t = 0.0;
    double value = centre_value_;
    while (t < exit) {
      const double t_next = std::min(t + std::max(0.5 * std::abs(value), min_step_), exit);
      const Vector3d point = centre_ + t_next * direction;
      value = solid_.Value(point);
      if (std::isnan(value)) Fail("solid.Value is NaN at " + Format(point));
      if (!found) {
        if (!(value < 0.0)) {
          hit = FindSegmentRoot(solid_, centre_ + t * direction, point);
          found = true;
        }
      } else if (value < 0.0) {
        Fail("the solid is not star-shaped from options.centre " + Format(centre_) +
             ": the ray towards " + Format(direction) + " re-enters the solid at " + Format(point));
      }
      t = t_next;
    }
    if (!found) {
      Fail("the ray from options.centre " + Format(centre_) + " towards " + Format(direction) +
           " finds no surface crossing inside solid.Bounds()");
    }
    return hit;
  }

 private:
  const ImplicitSolid& solid_;
  Vector3d centre_;
  Vector3d box_min_;
  Vector3d box_max_;
  double min_step_ = 0.0;      // [m]
  double centre_value_ = 0.0;  // Value at the centre, < 0
};

// The solid's reach from the centre along ±e1, ±e2, ±e3 [m]: an "octant ellipsoid" whose eight
// octants are ellipsoid pieces with these semi-axes, continuous across the frame's planes.
struct OctantEllipsoid {
  std::array<double, 3> plus;
  std::array<double, 3> minus;
  // Maps a point of the unit sphere (frame coordinates) onto the octant ellipsoid.
  Vector3d Map(const Vector3d& u) const {
    Vector3d q;
    for (int axis = 0; axis < 3; ++axis) {
      q[axis] = u[axis] * (u[axis] >= 0.0 ? plus[static_cast<size_t>(axis)]
                                          : minus[static_cast<size_t>(axis)]);
    }
    return q;
  }
};

// Exactly n points on the unit sphere (frame coordinates) and a closed triangulation of them.
struct SphereLayout {
  std::vector<Vector3d> points;
  std::vector<Triangle> triangles;
};

// Ring sizes proportional to `weights`, each >= 3, summing to `total` (largest remainder).
std::vector<int> RingSizes(const std::vector<double>& weights, int total) {
  double weight_sum = 0.0;
  for (double w : weights) weight_sum += w;
  const size_t rings = weights.size();
  std::vector<double> ideal(rings);
  std::vector<int> sizes(rings);
  int assigned = 0;
  for (size_t k = 0; k < rings; ++k) {
    ideal[k] = total * weights[k] / weight_sum;
    sizes[k] = std::max(3, static_cast<int>(std::floor(ideal[k])));
    assigned += sizes[k];
  }
  // The first ring with the largest (or smallest) remainder ideal − size wins ties.
  while (assigned < total) {
    size_t best = 0;
    for (size_t k = 1; k < rings; ++k) {
      if (ideal[k] - sizes[k] > ideal[best] - sizes[best]) best = k;
    }
    ++sizes[best];
    ++assigned;
  }
  while (assigned > total) {
    size_t best = rings;
    for (size_t k = 0; k < rings; ++k) {
      if (sizes[k] > 3 && (best == rings || ideal[k] - sizes[k] < ideal[best] - sizes[best])) {
        best = k;
      }
    }
    assert(best < rings);
    --sizes[best];
    --assigned;
  }
  return sizes;
}

// A point of the unit sphere in frame coordinates: polar angle θ from e1, azimuth φ from e2.
Vector3d SpherePoint(double theta, double phi) {
  return {std::cos(theta), std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi)};
}

// The ray direction (world, unit) for a sphere point u: through u's image on the octant ellipsoid.
Vector3d RayDirection(const Frame& frame, const OctantEllipsoid& shape, const Vector3d& u) {
  return frame.ToWorld(shape.Map(u)).normalized();
}

// The solid's surface seen through the sphere's (θ, φ) parametrisation: for rows of constant θ
// (θ_i = π·i / kProfileRows), the perimeter of the row's image curve, how that perimeter is
// shared out over the azimuth, and the mean arc length along the images of the meridians from
// the pole θ = 0 [m].
struct SurfaceProfile {
  std::vector<double> arc;        // kProfileRows + 1, arc[0] = 0
  std::vector<double> perimeter;  // kProfileRows + 1, 0 at the poles
  // (kProfileRows + 1) × (kProfileColumns + 1), row-major: the fraction of row i's perimeter
  // between φ = 0 and φ_j = 2π·j / kProfileColumns (0 at j = 0, 1 at the last column; uniform
  // at the poles).
  std::vector<double> fraction;
  double area = 0.0;  // ≈ ∫ perimeter d(arc) [m²]
};

SurfaceProfile MeasureProfile(const RayCaster& caster, const Frame& frame,
                              const OctantEllipsoid& shape) {
  constexpr double kPi = std::numbers::pi;
  SurfaceProfile profile;
  profile.arc.assign(kProfileRows + 1, 0.0);
  profile.perimeter.assign(kProfileRows + 1, 0.0);
  profile.fraction.assign((kProfileRows + 1) * (kProfileColumns + 1), 0.0);
  for (size_t j = 0; j <= kProfileColumns; ++j) {
    profile.fraction[j] = static_cast<double>(j) / kProfileColumns;
  }
  std::vector<Vector3d> previous(kProfileColumns,
                                 caster.Cast(RayDirection(frame, shape, SpherePoint(0.0, 0.0))));
  std::vector<Vector3d> current(kProfileColumns);
  for (int i = 1; i <= kProfileRows; ++i) {
    const double theta = kPi * i / kProfileRows;
    for (size_t j = 0; j < kProfileColumns; ++j) {
      const double phi = 2.0 * kPi * static_cast<double>(j) / kProfileColumns;
      // The last row is the other pole: one point.
      current[j] = (i == kProfileRows && j > 0)
                       ? current[0]
                       : caster.Cast(RayDirection(frame, shape, SpherePoint(theta, phi)));
    }
    double ds = 0.0;
    double perimeter = 0.0;
    for (size_t j = 0; j < kProfileColumns; ++j) {
      ds += (current[j] - previous[j]).norm() / kProfileColumns;
      perimeter += (current[(j + 1) % kProfileColumns] - current[j]).norm();
    }
    const auto row = static_cast<size_t>(i);
    profile.arc[row] = profile.arc[row - 1] + ds;
    profile.perimeter[row] = perimeter;
    double* fraction = &profile.fraction[row * (kProfileColumns + 1)];
    double walked = 0.0;
    for (size_t j = 0; j <= kProfileColumns; ++j) {
      fraction[j] = perimeter > 0.0 ? walked / perimeter : static_cast<double>(j) / kProfileColumns;
      walked += (current[(j + 1) % kProfileColumns] - current[j % kProfileColumns]).norm();
    }
    fraction[kProfileColumns] = 1.0;
    profile.area += 0.5 * (profile.perimeter[row - 1] + perimeter) * ds;
    std::swap(previous, current);
  }
  return profile;
}

// The profile of the unit sphere itself: rings equally spaced in θ, sized by sin θ, points
// equally spaced in φ. With RayDirection replaced by the identity this is the classic latitude
// layout, whose zipped strips are valid spherical triangles (checked for every N up to 12000).
SurfaceProfile UnitSphereProfile() {
  constexpr double kPi = std::numbers::pi;
  SurfaceProfile profile;
  profile.arc.resize(kProfileRows + 1);
  profile.perimeter.resize(kProfileRows + 1);
  profile.fraction.resize((kProfileRows + 1) * (kProfileColumns + 1));
  for (size_t i = 0; i <= kProfileRows; ++i) {
    const double theta = kPi * static_cast<double>(i) / kProfileRows;
    profile.arc[i] = theta;
    profile.perimeter[i] = 2.0 * kPi * std::sin(theta);
    for (size_t j = 0; j <= kProfileColumns; ++j) {
      profile.fraction[i * (kProfileColumns + 1) + j] = static_cast<double>(j) / kProfileColumns;
    }
  }
  profile.area = 4.0 * kPi;
  return profile;
}

// Rings of points around e1 (a pole at each end; for n = 4 a single ring of three and one pole),
// placed so that on the surface (by `profile`) the rings are about one equilateral-triangle
// height apart and the points along each ring about one edge apart.
SphereLayout MakeSphereLayout(int n, const SurfaceProfile& profile) {
  constexpr double kPi = std::numbers::pi;
  const std::vector<double>& arc = profile.arc;
  const double length = arc.back();
  // The polar angle at arc length s, and the row perimeter at a polar angle, by linear
  // interpolation in the profile's table.
  auto theta_at = [&](double s) {
    const auto it = std::lower_bound(arc.begin() + 1, arc.end(), s);
    const auto k = static_cast<size_t>(std::min<std::ptrdiff_t>(it - arc.begin(), kProfileRows));
    const double span = arc[k] - arc[k - 1];
    const double f = span > 0.0 ? std::clamp((s - arc[k - 1]) / span, 0.0, 1.0) : 0.0;
    return kPi * (static_cast<double>(k - 1) + f) / kProfileRows;
  };
  auto perimeter_at = [&](double theta) {
    const double x = std::clamp(theta / kPi * kProfileRows, 0.0, double{kProfileRows});
    const auto k = std::min(static_cast<size_t>(x), size_t{kProfileRows - 1});
    const double f = x - static_cast<double>(k);
    return (1.0 - f) * profile.perimeter[k] + f * profile.perimeter[k + 1];
  };
  // The azimuth φ ∈ [0, 2π) that splits the ring at θ so that a fraction t ∈ [0, 1) of its
  // perimeter lies between φ = 0 and φ: rows' fraction tables interpolated in θ, then inverted.
  auto azimuth_at = [&](double theta, double t) {
    const double x = std::clamp(theta / kPi * kProfileRows, 0.0, double{kProfileRows});
    const auto k = std::min(static_cast<size_t>(x), size_t{kProfileRows - 1});
    const double f = x - static_cast<double>(k);
    const double* lower = &profile.fraction[k * (kProfileColumns + 1)];
    const double* upper = lower + (kProfileColumns + 1);
    auto fraction = [&](size_t j) { return (1.0 - f) * lower[j] + f * upper[j]; };
    size_t j = 0;
    while (j + 1 < kProfileColumns && fraction(j + 1) <= t) ++j;
    const double span = fraction(j + 1) - fraction(j);
    const double within = span > 0.0 ? std::clamp((t - fraction(j)) / span, 0.0, 1.0) : 0.0;
    return 2.0 * kPi * (static_cast<double>(j) + within) / kProfileColumns;
  };

  // Equilateral triangles of equal area: edge h, ring spacing h·√3/2 (the triangle's height).
  const double triangle_area = profile.area / (2.0 * n - 4.0);
  const double edge = std::sqrt(4.0 * triangle_area / std::sqrt(3.0));
  const bool single_pole = (n == 4);
  const int ring_points = single_pole ? n - 1 : n - 2;
  int rings = static_cast<int>(std::lround(length / (edge * std::sqrt(3.0) / 2.0))) - 1;
  rings = std::clamp(rings, 1, ring_points / 3);
  if (single_pole) rings = 1;

  std::vector<double> thetas(static_cast<size_t>(rings));
  std::vector<double> weights(static_cast<size_t>(rings));
  for (int k = 0; k < rings; ++k) {
    // A tetrahedron's ring sits at θ = arccos(−1/3).
    thetas[static_cast<size_t>(k)] =
        single_pole ? std::acos(-1.0 / 3.0) : theta_at(length * (k + 1) / (rings + 1));
    // Tiny floor: a ring never gets a zero share.
    weights[static_cast<size_t>(k)] =
        std::max(perimeter_at(thetas[static_cast<size_t>(k)]), 1e-9 * length);
  }
  const std::vector<int> sizes = RingSizes(weights, ring_points);

  SphereLayout layout;
  layout.points.reserve(static_cast<size_t>(n));
  layout.points.emplace_back(1.0, 0.0, 0.0);
  // first[k]: index of ring k's first point; phis[k]: its points' azimuths, increasing,
  // unwrapped to [phis[k][0], phis[k][0] + 2π). Points split each ring's perimeter evenly, and
  // consecutive rings start a golden-ratio fraction further round so that no seam lines up
  // along the meridians.
  std::vector<int32_t> first(static_cast<size_t>(rings));
  std::vector<std::vector<double>> phis(static_cast<size_t>(rings));
  const double golden_fraction = (3.0 - std::sqrt(5.0)) / 2.0;
  for (int k = 0; k < rings; ++k) {
    const size_t kk = static_cast<size_t>(k);
    first[kk] = static_cast<int32_t>(layout.points.size());
    const double start = std::fmod(golden_fraction * k, 1.0);
    for (int i = 0; i < sizes[kk]; ++i) {
      const double t = start + static_cast<double>(i) / sizes[kk];
      const double turns = std::floor(t);
      phis[kk].push_back(azimuth_at(thetas[kk], t - turns) + 2.0 * kPi * turns);
      layout.points.push_back(SpherePoint(thetas[kk], phis[kk].back()));
    }
  }
  auto ring_vertex = [&](int k, int i) {
    const int size = sizes[static_cast<size_t>(k)];
    return first[static_cast<size_t>(k)] + static_cast<int32_t>(((i % size) + size) % size);
  };

  // Cap at the first pole, strips zipped between consecutive rings by increasing azimuth (each
  // strip of rings of m and p points gives m + p triangles), and the cap or the last pole at
  // the other end. Azimuth grows counter-clockwise seen from outside above the first pole
  // (e1 × e2 = e3), which fixes the corner order of each kind of triangle.
  for (int i = 0; i < sizes[0]; ++i) {
    layout.triangles.push_back({0, ring_vertex(0, i), ring_vertex(0, i + 1)});
  }
  for (int k = 0; k + 1 < rings; ++k) {
    const std::vector<double>& ring_a = phis[static_cast<size_t>(k)];
    const std::vector<double>& ring_b = phis[static_cast<size_t>(k) + 1];
    const int m = static_cast<int>(ring_a.size());
    const int p = static_cast<int>(ring_b.size());
    // Ring b's azimuths unwrapped to [ring_a[0], ring_a[0] + 2π); the zip starts at the
    // smallest, point j0.
    std::vector<double> unwrapped(ring_b.size());
    int j0 = 0;
    for (size_t j = 0; j < ring_b.size(); ++j) {
      unwrapped[j] =
          ring_a[0] + std::fmod(std::fmod(ring_b[j] - ring_a[0], 2.0 * kPi) + 2.0 * kPi, 2.0 * kPi);
      if (unwrapped[j] < unwrapped[static_cast<size_t>(j0)]) j0 = static_cast<int>(j);
    }
    auto angle_a = [&](int i) {
      return i < m ? ring_a[static_cast<size_t>(i)] : ring_a[0] + 2.0 * kPi;
    };
    auto angle_b = [&](int i) {
      const double angle = unwrapped[static_cast<size_t>((j0 + i) % p)];
      return i < p ? angle : angle + 2.0 * kPi;
    };
    int ia = 0;
    int ib = 0;
    while (ia < m || ib < p) {
      const bool advance_a = ib == p || (ia < m && angle_a(ia + 1) <= angle_b(ib + 1));
      if (advance_a) {
        layout.triangles.push_back(
            {ring_vertex(k, ia), ring_vertex(k + 1, j0 + ib), ring_vertex(k, ia + 1)});
        ++ia;
      } else {
        layout.triangles.push_back(
            {ring_vertex(k, ia), ring_vertex(k + 1, j0 + ib), ring_vertex(k + 1, j0 + ib + 1)});
        ++ib;
      }
    }
  }
  const int last_ring = rings - 1;
  if (single_pole) {
    layout.triangles.push_back(
        {ring_vertex(last_ring, 0), ring_vertex(last_ring, 2), ring_vertex(last_ring, 1)});
  } else {
    const auto pole = static_cast<int32_t>(layout.points.size());
    layout.points.emplace_back(-1.0, 0.0, 0.0);
    for (int i = 0; i < sizes[static_cast<size_t>(last_ring)]; ++i) {
      layout.triangles.push_back({pole, ring_vertex(last_ring, i + 1), ring_vertex(last_ring, i)});
    }
  }
  assert(layout.points.size() == static_cast<size_t>(n));
  assert(layout.triangles.size() == static_cast<size_t>(2 * n - 4));
  return layout;
}

// Whether every triangle is counter-clockwise seen from the origin when its corners are moved
// along the given directions: then the radial map of the layout is an embedding (see
// FacesOutwards).
bool IsRadiallyEmbedded(const std::vector<Triangle>& triangles,
                        const std::vector<Vector3d>& directions) {
  for (const Triangle& t : triangles) {
    const Vector3d& a = directions[static_cast<size_t>(t[0])];
    const Vector3d& b = directions[static_cast<size_t>(t[1])];
    const Vector3d& c = directions[static_cast<size_t>(t[2])];
    if (!(a.dot(b.cross(c)) > 0.0)) return false;
  }
  return true;
}

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
