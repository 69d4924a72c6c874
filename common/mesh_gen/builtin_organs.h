// The built-in organs: meshes somasim generates itself, at the sizes of the seeds' models, so that
// demos, tests and benchmarks need no external data and every comparison with a seed runs on a
// model of the same size. Generation is deterministic: the same name gives bit-identical meshes.
//
// How each one is made is in docs/builtin_organs.md: volume organs by isosurface stuffing of an
// implicit shape (organ_shapes.h) with a fixed lattice, or by a structured construction (plate,
// beam); closed surfaces by fitting a sphere layout with exactly N vertices to the shape.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <string_view>

#include "common/mesh/mesh_types.h"

namespace somasim::mesh_gen {

enum class OrganKind {
  kVolume,         // tetrahedra; the boundary surface is offered too
  kClosedSurface,  // watertight, manifold triangle surface
  kOpenSurface,    // a triangulated patch with one boundary loop
};
const char* OrganKindName(OrganKind kind);  // "volume", "closed surface", "open surface"

struct BuiltinOrganSpec {
  std::string_view name;   // e.g. "liver4055"
  std::string_view alias;  // e.g. "liver", or empty
  OrganKind kind = OrganKind::kVolume;
  std::string_view source;       // the seed or benchmark whose model it matches
  std::string_view description;  // one line for `somasim-mesh list`
  // The seed's counts: nodes (vertices) and elements (tetrahedra or triangles), and the allowed
  // relative deviation (0 = exact). A negative element tolerance means "as close as quality
  // allows": the count is reported, not enforced.
  int64_t target_nodes = 0;
  int64_t target_elements = 0;
  double node_tolerance = 0.0;
  double element_tolerance = 0.0;
  // What this generator produces (checked by tests against the generated mesh).
  int64_t num_nodes = 0;
  int64_t num_elements = 0;
  // Plausible size: the longest side of the bounding box [m] and, for closed organs, the volume
  // [m³] must lie in these ranges (anatomy, or the seed's exact dimensions).
  double min_length = 0.0;
  double max_length = 0.0;
  double min_volume = 0.0;  // 0 = not applicable (open patch)
  double max_volume = 0.0;
};

// Every built-in organ, in the order of the seeds' table.
std::span<const BuiltinOrganSpec> BuiltinOrganSpecs();

// The organ called `name` (or its alias); nullptr if none.
const BuiltinOrganSpec* FindBuiltinOrgan(std::string_view name);

// "liver4055 (liver), liver288, ..." for error messages.
std::string BuiltinOrganNames();

struct BuiltinOrgan {
  const BuiltinOrganSpec* spec = nullptr;
  mesh::TetMesh volume;       // volume organs only (else empty)
  mesh::SurfaceMesh surface;  // the surface organ, or the volume's boundary (compact numbering)
};

// Generates the organ `name` (or alias). Throws std::invalid_argument naming the known organs
// when the name is unknown.
BuiltinOrgan GenerateBuiltinOrgan(std::string_view name);

// A volume mesh of the organ `name`, for volume models: a volume organ's own tetrahedra, or a
// closed surface organ's shape filled by isosurface stuffing with a lattice spacing of 1.5× the
// surface's mean edge length, so its dihedral angles are >= 10.7° (its boundary is a new
// triangulation of the same shape, not the surface organ's triangles). Throws
// std::invalid_argument for an unknown name or the open patch, which bounds no volume.
mesh::TetMesh GenerateBuiltinOrganVolume(std::string_view name);

}  // namespace somasim::mesh_gen
