// Closed-surface mesher: a genus-0 triangle surface with an exact vertex count fitted to an
// implicit solid (the built-in surface organs: spleen, kidney, gallbladder).
//
// The method (steps 1 and 2 are built from sphere_layout.h, step 3 is in closed_surface_mesher.cc):
//  1. Layout. Exactly N points on the unit sphere in rings around the long axis (one vertex at
//     each pole), zipped into strips. A closed triangulation of a sphere has F = 2V − 4 (Euler:
//     V − E + F = 2 and 3F = 2E), so the triangle count follows from N. The rings are placed
//     from a profile of the actual surface (measured with 32 × 16 rays from the centre through
//     an "octant ellipsoid" fitted to the solid's reach along ±long axis and two cross axes):
//     rings one equilateral-triangle height apart along the surface, ring sizes proportional to
//     their perimeters, points evenly spread along each ring. When that layout would be tangled
//     (a sparse mesh on a solid seen very obliquely from the centre), the plain latitude layout
//     of the sphere is used instead.
//  2. Mapping. Each layout point goes onto the surface along the ray from options.centre
//     through it. Because the solid is star-shaped from the centre and every layout triangle is
//     counter-clockwise seen from it, this radial map is an embedding with outward orientation.
//  3. Relaxation, smoothing_iterations sweeps of:
//     - edge flips that raise the smaller angle of the edge's two triangles (the max-min angle
//       criterion, equivalent to Delaunay flipping in the plane: Lawson 1977; on surfaces see
//       Dyer, Zhang, Möller, "Delaunay mesh construction", SGP 2007); flips keep the counts;
//     - one Gauss–Seidel sweep of tangential smoothing: every vertex moves, within the mesh's
//       tangent plane, towards the area-weighted average of its incident triangles' centroids,
//       then back onto the surface (ProjectToSurface, refined by FindSegmentRoot along the
//       normal where Newton stalls). This is the tangential relaxation of Botsch & Kobbelt,
//       "A remeshing approach to multiresolution modeling", SGP 2004, §3 (an approximation of a
//       centroidal Voronoi tessellation), which evens out triangle areas. Vertices whose
//       neighbourhood has settled (moves below 1 % of the mean edge) are skipped.
//     Every move and flip must leave its triangles counter-clockwise seen from the centre and
//     facing along the solid's normals at their corners, so the mesh stays embedded (no fold,
//     no self-intersection) throughout; a move that would break this is halved, then dropped.
//  A final flip pass ends the relaxation. Everything runs in a fixed order: bit-identical output
//  for the same input and build.
//
// Requirements on the solid: it must be star-shaped from options.centre (every ray from the
// centre leaves the solid exactly once before leaving Bounds()), Value should be distance-like
// (|∇Value| between about 0.5 and 2 near the surface), and its features should be larger than
// the mesh's edge length (about sqrt(1.15 · area / N)). Concave parts (a kidney's hilum) are fine
// as long as no ray from the centre is tangent to the surface inside the solid; the closer rays
// come to grazing the surface, the more the initial layout is stretched there.
// Pure kernel: no I/O.
#pragma once

#include <Eigen/Core>

#include "common/mesh/mesh_types.h"
#include "common/mesh_gen/implicit.h"

namespace somasim::mesh_gen {

struct ClosedSurfaceOptions {
  // Exact number of vertices N, >= 4 (4 gives a tetrahedron). The surface has 2N − 4 triangles.
  int num_vertices = 0;
  // A point inside the solid from which the solid is star-shaped [m], finite.
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  // The solid's long axis, a unit vector (|norm − 1| <= 1e-6): the poles of the initial layout
  // lie on it, so its rings run around the solid's length.
  Eigen::Vector3d long_axis = Eigen::Vector3d::UnitX();
  // Relaxation sweeps (flips + one smoothing sweep each), >= 0. 0 returns the radially mapped
  // layout (after a final flip pass). The default suits the organ sizes (600–5400 vertices).
  int smoothing_iterations = 20;
};

// Meshes the boundary of `solid` with exactly options.num_vertices vertices and
// 2·num_vertices − 4 triangles, counter-clockwise seen from outside (mesh_types.h). Every vertex
// lies on the surface (|Value| < 1e-10 m unless the gradient vanishes there); the surface is
// watertight, manifold, of genus 0, star-shaped from the centre (hence free of folds and
// self-intersections), and each triangle faces along the solid's normals at its corners
// (meshes much coarser than the surface's features may keep a few that do not).
//
// Throws std::invalid_argument naming the field for bad options (num_vertices < 4,
// smoothing_iterations < 0, long_axis not a unit vector, non-finite centre, centre not strictly
// inside the solid or outside solid.Bounds()), for an empty or non-finite solid.Bounds(), for a
// NaN Value on a ray, and when the solid is not star-shaped from the centre: a ray that leaves
// Bounds() without leaving the solid, or that re-enters the solid after leaving it (rays are
// walked by steps of half |Value|, at least Bounds' diagonal / 128, so a re-entry thinner than
// that can be missed).
mesh::SurfaceMesh MeshClosedSurface(const ImplicitSolid& solid,
                                    const ClosedSurfaceOptions& options);

}  // namespace somasim::mesh_gen
