// Closed-surface mesher: a genus-0 triangle surface with an exact vertex count fitted to an
// implicit solid (the built-in surface organs: spleen, kidney, gallbladder).
//
// The method (a layout of exactly N points on the sphere, a radial map onto the solid, then
// relaxation by edge flips and tangential smoothing; bit-identical for the same input):
// docs/builtin_organs.md.
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
