// Closed-surface mesher: a genus-0 triangle surface with an exact vertex count fitted to an
// implicit solid (the built-in surface organs: spleen, kidney, gallbladder).
//
// The method:
//  1. Layout. Exactly N points on the unit sphere in rings around the long axis (one vertex at
//     each pole), with ring positions and ring sizes chosen so that, once mapped to an
//     "octant ellipsoid" fitted to the solid's extent along ±long axis and ±two cross axes, the
//     triangles are roughly equilateral and of equal area. Neighbouring rings are zipped into
//     strips. A closed triangulation of a sphere has F = 2V − 4 (Euler: V − E + F = 2 and
//     3F = 2E), so the triangle count follows from N.
//  2. Mapping. Each layout point is moved onto the surface along the ray from options.centre
//     through it (bracketing by sampling, then FindSegmentRoot). Because the solid must be
//     star-shaped from the centre, this radial map is a bijection from the sphere to the
//     surface and the initial mesh is an embedding with outward orientation.
//  3. Relaxation, smoothing_iterations sweeps of:
//     - Delaunay edge flips (flip when the two angles opposite an edge sum to more than π),
//       which keep the vertex count and maximise the smallest angle of a planar triangulation
//       (Lawson 1977; on surfaces see Dyer, Zhang, Möller, "Delaunay mesh construction",
//       SGP 2007);
//     - one Gauss–Seidel sweep of tangential smoothing: every vertex moves, within the tangent
//       plane of the surface, towards the area-weighted average of its incident triangles'
//       centroids, then back onto the surface with ProjectToSurface. This is the tangential
//       relaxation of Botsch & Kobbelt, "A remeshing approach to multiresolution modeling",
//       SGP 2004, §3 (an approximation of a centroidal Voronoi tessellation), which evens out
//       triangle areas. A move that would fold an incident triangle against the surface normal
//       is shortened or rejected.
//  A final flip pass ends the relaxation. Everything runs in a fixed order: bit-identical output
//  for the same input.
//
// Requirements on the solid: it must be star-shaped from options.centre (every ray from the
// centre leaves the solid exactly once before leaving Bounds()), and its features should be
// larger than the mesh's edge length (about sqrt(2.3 · area / N)). Concave parts (a kidney's
// hilum) are fine as long as no ray from the centre is tangent to the surface inside the solid.
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
// lies on the surface (|Value| < 1e-9 unless ProjectToSurface fails to converge); the surface is
// watertight, manifold, of genus 0 and has no triangle facing against the solid's outward normal
// at its vertices.
//
// Throws std::invalid_argument naming the field for bad options (num_vertices < 4,
// smoothing_iterations < 0, long_axis not a unit vector, non-finite centre, centre not strictly
// inside the solid), for an empty or non-finite solid.Bounds(), and when the solid is not
// star-shaped from the centre: a ray that leaves Bounds() without leaving the solid, or that
// re-enters the solid after leaving it (detected by sampling each ray at 128 points, so a
// re-entry thinner than Bounds' diagonal / 128 can be missed).
mesh::SurfaceMesh MeshClosedSurface(const ImplicitSolid& solid,
                                    const ClosedSurfaceOptions& options);

}  // namespace somasim::mesh_gen
