// What a mesh file holds once read: nodes, triangles, tetrahedra, and what was skipped.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh/mesh_types.h"

namespace somasim::mesh_io {

// Length unit of the numbers in a file. Files carry no reliable unit (SPEC §6).
enum class Unit { kMetre, kCentimetre, kMillimetre };
double UnitToMetres(Unit unit);   // 1, 0.01, 0.001
const char* UnitName(Unit unit);  // "m", "cm", "mm"
std::optional<Unit> ParseUnit(std::string_view text);

struct ReadOptions {
  Unit unit = Unit::kMetre;      // unit of the file's coordinates; results are in metres
  bool fix_orientation = false;  // flip inverted tetrahedra instead of refusing the file
};

// Element kinds found in a file that are neither triangles nor tetrahedra (lines, quads,
// hexahedra, quadratic elements...), with how many of each were skipped.
struct SkippedElements {
  std::string type;
  int64_t count = 0;
};

// A named array of values per node (e.g. "displacement", 3 components, metres), written by the
// VTU writer as point data; readers leave it empty.
struct PointArray {
  std::string name;
  int components = 1;          // > 0
  std::vector<double> values;  // components × num_nodes, node-major
};

struct MeshData {
  mesh::Points vertices;        // [m], 3 × num_nodes, in file order
  mesh::Triangles triangles;    // 3 × num_triangles, file order
  mesh::Tetrahedra tetrahedra;  // 4 × num_tets, file order, positively oriented
  std::vector<SkippedElements> skipped;
  int64_t num_flipped = 0;  // tetrahedra re-oriented because of ReadOptions::fix_orientation
  std::string format;       // what was read, e.g. "Gmsh 2.2 ASCII"
  std::vector<PointArray> point_data;  // written by WriteVtu; not read
};

// Adds count elements of the given type to the skipped list (merging equal types).
void AddSkipped(std::vector<SkippedElements>* skipped, std::string_view type, int64_t count);

}  // namespace somasim::mesh_io
