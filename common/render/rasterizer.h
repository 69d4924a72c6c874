// Off-screen software rendering of triangle and tetrahedral meshes to an RGB image: orthographic
// camera auto-fitted to the mesh, z-buffer, two-sided Lambert + ambient + a little specular
// shading with crease-aware smooth normals, an optional thin wireframe overlay, supersampled
// anti-aliasing. No OpenGL, no display, no file I/O; deterministic (same input, same options →
// bit-identical pixels).
#pragma once

#include <Eigen/Core>

#include "common/mesh/mesh_types.h"
#include "common/render/image.h"

namespace somasim::render {

inline constexpr int kMaxImageSize = 8192;  // pixels, largest accepted width or height

struct RenderOptions {
  int width = 800;   // output pixels, 1..kMaxImageSize
  int height = 600;  // output pixels, 1..kMaxImageSize
  // Direction from the camera towards the object (any length > 0, finite). The default looks
  // from the front-right and above at a y-up scene (camera at +x, +y, +z of the object).
  Eigen::Vector3d view_direction = Eigen::Vector3d(-0.55, -0.45, -0.70);
  // World direction shown pointing up in the picture (finite). Only its part orthogonal to
  // view_direction counts; when that part vanishes (zero, or parallel to view_direction) the
  // world axis most orthogonal to view_direction is used instead.
  Eigen::Vector3d up = Eigen::Vector3d::UnitY();
  // sRGB colours, each channel in [0, 1]. Back faces (seen from inside, e.g. the underside of an
  // open patch) are shaded with surface_color darkened to kBackFaceFactor of it.
  Eigen::Vector3d surface_color = Eigen::Vector3d(0.80, 0.40, 0.36);  // tissue-like red
  Eigen::Vector3d background_color = Eigen::Vector3d(1.0, 1.0, 1.0);
  // Smooth shading interpolates per-corner normals, averaged over the triangles round a vertex
  // whose normals differ by less than crease_angle_deg from the triangle's own (so a cube keeps
  // sharp edges and an organ looks smooth). Off = flat shading per triangle.
  bool smooth_shading = true;
  double crease_angle_deg = 45.0;  // (0, 180]
  // Thin darker lines along the triangle edges of the visible surface.
  bool draw_edges = true;
  double edge_width_px = 0.9;   // width of a line between two triangles [output pixels], > 0
  double edge_darkening = 0.3;  // 0 = invisible .. 1 = black lines
  // Samples per output pixel along each axis (anti-aliasing by a box filter), 1..4.
  int supersampling = 3;
  // Free border on each side as a fraction of the image width and height, [0, 0.45].
  double margin = 0.05;
};

// Fraction of surface_color (in linear light) used for back faces.
inline constexpr double kBackFaceFactor = 0.7;

// Renders the triangles of `surface` (orientation need not be consistent: both sides are
// drawn). The orthographic projection is fitted to the projected extent of the vertices the
// triangles use, so a mesh of any size and unit fills the frame (up to the margin); unused
// vertices are ignored. No triangles → an image filled with background_color.
// Throws std::invalid_argument, naming the field or element, for options out of range, a
// non-finite vertex coordinate, a triangle index outside 0..num_vertices-1, or coordinates so
// large that the projected extent overflows. All checks happen before any rendering.
Image RenderSurface(const mesh::SurfaceMesh& surface, const RenderOptions& options);

// Renders the boundary surface of a tetrahedral mesh (mesh::ExtractBoundarySurface). Same
// checks and behaviour as RenderSurface, with tetrahedron indices checked up front.
Image RenderTetMesh(const mesh::TetMesh& mesh, const RenderOptions& options);

}  // namespace somasim::render
