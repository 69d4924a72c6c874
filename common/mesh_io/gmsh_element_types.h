// Gmsh element types: the node count of each type number, and the names MeshData::skipped uses.
#pragma once

#include <cstdint>

namespace somasim::mesh_io::gmsh_internal {

constexpr int kTriangleType = 2;
constexpr int kTetrahedronType = 4;

constexpr int kNumTypeSlots = 141;  // type numbers 0..140 (MSH_MAX_NUM)

struct ElementTypeInfo {
  int type;
  int nodes;         // fixed number of nodes of every element of this type
  const char* name;  // what MeshData::skipped calls it
};

// The type with this number if its node count is fixed by the type, else nullptr.
const ElementTypeInfo* FindElementType(int64_t type);

// Types Gmsh defines whose node count is not fixed by the type (or that Gmsh itself cannot read
// back), so that the elements after them cannot be delimited: their name, else nullptr.
const char* UnreadableTypeName(int64_t type);

}  // namespace somasim::mesh_io::gmsh_internal
