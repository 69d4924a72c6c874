// somasim-mesh render: a picture of a mesh file as a PNG (software rendering, no display), for
// documentation and quick looks. A function returning a process exit code, like the other
// commands in mesh_commands.h, so that tests call it without a shell.
#pragma once

#include <Eigen/Core>
#include <iosfwd>
#include <optional>
#include <string>
#include <string_view>
#include <utility>

#include "common/mesh_io/mesh_io.h"

namespace somasim::tools {

struct RenderCommandOptions {
  std::string input;   // any mesh file mesh_io reads, or builtin:NAME
  std::string output;  // the PNG to write; must end in .png
  mesh_io::ReadOptions read;
  int width = 800;   // pixels, 1..render::kMaxImageSize
  int height = 600;  // pixels, 1..render::kMaxImageSize
  // Direction from the camera towards the mesh (finite, non-zero); default: the renderer's
  // front-right-above view of a y-up scene.
  std::optional<Eigen::Vector3d> view;
  // The direction that points up in the picture (finite, non-zero); default +y.
  std::optional<Eigen::Vector3d> up;
  bool edges = true;  // thin darker lines along the triangle edges
};

// Reads `input`, renders the boundary of its tetrahedra (or, without tetrahedra, its
// triangles) and writes the PNG. Exit codes of mesh_commands.h: kExitUsage for a bad size, view
// or output name; kExitBadInput / kExitIo for a refused or unreadable input; kExitIo when the
// output cannot be written. Errors go to `err` naming the file; a summary line to `out`.
int RunRender(const RenderCommandOptions& options, std::ostream& out, std::ostream& err);

// "800x600" (also "800X600") → {800, 600}; nullopt unless two positive decimal integers of at
// most 5 digits. Range checks are RunRender's.
std::optional<std::pair<int, int>> ParseImageSize(std::string_view text);
// "x,y,z" → vector; nullopt unless exactly three finite numbers.
std::optional<Eigen::Vector3d> ParseVector3(std::string_view text);

}  // namespace somasim::tools
