// The layout stage of the closed-surface mesher (closed_surface_mesher.h, steps 1 and 2): a frame
// along the solid's long axis, rays cast from the centre to the surface (which check that the
// solid is star-shaped from it), the octant ellipsoid fitted to the solid's reach, the profile
// of the surface measured through it, and the sphere layout of exactly N points whose rings are
// placed by that profile.
//
// Internal: these are MeshClosedSurface's building blocks, not an API of their own. They assume
// the options MeshClosedSurface has already validated (unit long axis, finite centre inside the
// solid), and their errors are std::invalid_argument prefixed "MeshClosedSurface: ".
// Pure kernel: no I/O.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "common/mesh_gen/implicit.h"

namespace somasim::mesh_gen::sphere_layout {

// Corner indices of a triangle, counter-clockwise seen from outside.
using Triangle = std::array<int32_t, 3>;

// The shortest step along a ray, when bracketing the surface and checking star-shapedness, is
// the (enlarged) box's diagonal / kRaySamples: a re-entry thinner than that can be missed.
constexpr int kRaySamples = 128;
// Rows of constant polar angle, and rays per row, with which the surface is measured to place
// the rings of the layout (SurfaceProfile).
constexpr int kProfileRows = 32;
constexpr size_t kProfileColumns = 16;

// Throws std::invalid_argument("MeshClosedSurface: " + message).
[[noreturn]] void Fail(const std::string& message);

// "(x, y, z)" with 6 significant digits, for error messages.
std::string Format(const Eigen::Vector3d& v);

// An orthonormal right-handed frame whose first axis is the solid's long axis (world, unit).
struct Frame {
  Eigen::Vector3d e1;
  Eigen::Vector3d e2;
  Eigen::Vector3d e3;
  // Frame coordinates → world direction (no translation).
  Eigen::Vector3d ToWorld(const Eigen::Vector3d& local) const {
    return local.x() * e1 + local.y() * e2 + local.z() * e3;
  }
};

// The frame with e1 = long_axis (normalised; nonzero and finite), e2 built from the coordinate
// axis least aligned with it, e3 = e1 × e2.
Frame MakeFrame(const Eigen::Vector3d& long_axis);

// Casts rays from the centre to the surface of a solid that must be star-shaped from it.
class RayCaster {
 public:
  // `solid` must outlive the caster; `centre` [m] must lie inside the solid (Value < 0). Throws
  // (see the file comment) when solid.Bounds() is empty or not finite, or does not strictly
  // contain the centre.
  RayCaster(const ImplicitSolid& solid, const Eigen::Vector3d& centre);

  // The point [m] where the ray from the centre along `direction` (unit) leaves the solid.
  //
  // The ray is walked from the centre to where it leaves the enlarged box, by steps of half the
  // current |Value| (a distance-like Value that overestimates the distance by at most a factor
  // two cannot skip the surface so) but at least kRaySamples-th of the box's diagonal. The first
  // inside → outside change brackets the surface; a later inside point means the ray re-enters,
  // i.e. the solid is not star-shaped from the centre. Throws for a re-entry, for a ray that
  // finds no crossing inside the box, and for a NaN Value.
  Eigen::Vector3d Cast(const Eigen::Vector3d& direction) const;

 private:
  const ImplicitSolid& solid_;
  Eigen::Vector3d centre_;   // [m]
  Eigen::Vector3d box_min_;  // solid.Bounds() enlarged by 1 % of its diagonal [m]
  Eigen::Vector3d box_max_;
  double min_step_ = 0.0;      // [m]
  double centre_value_ = 0.0;  // Value at the centre, < 0
};

// The solid's reach from the centre along ±e1, ±e2, ±e3 [m], each > 0: an "octant ellipsoid"
// whose eight octants are ellipsoid pieces with these semi-axes, continuous across the frame's
// planes.
struct OctantEllipsoid {
  std::array<double, 3> plus;   // along +e1, +e2, +e3 [m]
  std::array<double, 3> minus;  // along −e1, −e2, −e3 [m]
  // Maps a point of the unit sphere (frame coordinates) onto the octant ellipsoid (frame
  // coordinates [m]).
  Eigen::Vector3d Map(const Eigen::Vector3d& u) const {
    Eigen::Vector3d q;
    for (int axis = 0; axis < 3; ++axis) {
      q[axis] = u[axis] * (u[axis] >= 0.0 ? plus[static_cast<size_t>(axis)]
                                          : minus[static_cast<size_t>(axis)]);
    }
    return q;
  }
};

// The ray direction (world, unit) for a point u of the unit sphere (frame coordinates): through
// u's image on the octant ellipsoid.
Eigen::Vector3d RayDirection(const Frame& frame, const OctantEllipsoid& shape,
                             const Eigen::Vector3d& u);

// The solid's surface seen through the sphere's (θ, φ) parametrisation (polar angle θ from e1,
// azimuth φ from e2): for rows of constant θ (θ_i = π·i / kProfileRows), the perimeter of the
// row's image curve, how that perimeter is shared out over the azimuth, and the mean arc length
// along the images of the meridians from the pole θ = 0.
struct SurfaceProfile {
  std::vector<double> arc;        // [m], kProfileRows + 1, arc[0] = 0, nondecreasing
  std::vector<double> perimeter;  // [m], kProfileRows + 1, 0 at the poles
  // (kProfileRows + 1) × (kProfileColumns + 1), row-major: the fraction of row i's perimeter
  // between φ = 0 and φ_j = 2π·j / kProfileColumns (0 at j = 0, 1 at the last column; uniform
  // at the poles).
  std::vector<double> fraction;
  double area = 0.0;  // ≈ ∫ perimeter d(arc) [m²]
};

// The profile of the solid's surface, measured with kProfileRows × kProfileColumns rays (plus
// one at the first pole) cast along RayDirection.
SurfaceProfile MeasureProfile(const RayCaster& caster, const Frame& frame,
                              const OctantEllipsoid& shape);

// The profile of the unit sphere itself (lengths in radians rather than [m]): rings equally
// spaced in θ, sized by sin θ, points equally spaced in φ. With RayDirection replaced by the
// identity this is the classic latitude layout, whose zipped strips are valid spherical
// triangles (checked for every N up to 12000).
SurfaceProfile UnitSphereProfile();

// Exactly n points on the unit sphere (frame coordinates) and a closed triangulation of them.
struct SphereLayout {
  std::vector<Eigen::Vector3d> points;  // n unit vectors; points[0] = +e1 (the first pole)
  std::vector<Triangle> triangles;      // 2n − 4, CCW seen from outside the sphere
};

// Rings of points around e1 (a pole at each end; for n = 4 a single ring of three and one pole),
// placed so that on the surface (by `profile`) the rings are about one equilateral-triangle
// height apart and the points along each ring about one edge apart; strips between consecutive
// rings zipped by increasing azimuth. Requires n >= 4 (not checked: MeshClosedSurface validates
// it).
SphereLayout MakeSphereLayout(int n, const SurfaceProfile& profile);

// Whether every triangle is counter-clockwise seen from the origin when its corners are moved
// along the given directions (one per vertex, any nonzero length): then the radial map of the
// layout is an embedding (see FacesOutwards in closed_surface_mesher.cc).
bool IsRadiallyEmbedded(const std::vector<Triangle>& triangles,
                        const std::vector<Eigen::Vector3d>& directions);

}  // namespace somasim::mesh_gen::sphere_layout
