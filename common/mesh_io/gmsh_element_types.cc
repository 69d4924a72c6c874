#include "common/mesh_io/gmsh_element_types.h"

#include <algorithm>
#include <iterator>

namespace somasim::mesh_io::gmsh_internal {
namespace {

// Every element type of Gmsh's MElement::getInfoMSH with a fixed node count, sorted by type.
// Node counts from the Gmsh sources (GmshDefines.h, MElement.cpp); names are ours.
constexpr ElementTypeInfo kElementTypes[] = {
    {1, 2, "line"},
    {2, 3, "triangle"},
    {3, 4, "quadrangle"},
    {4, 4, "tetrahedron"},
    {5, 8, "hexahedron"},
    {6, 6, "prism"},
    {7, 5, "pyramid"},
    {8, 3, "line (3 nodes)"},
    {9, 6, "triangle (6 nodes)"},
    {10, 9, "quadrangle (9 nodes)"},
    {11, 10, "tetrahedron (10 nodes)"},
    {12, 27, "hexahedron (27 nodes)"},
    {13, 18, "prism (18 nodes)"},
    {14, 14, "pyramid (14 nodes)"},
    {15, 1, "point"},
    {16, 8, "quadrangle (8 nodes)"},
    {17, 20, "hexahedron (20 nodes)"},
    {18, 15, "prism (15 nodes)"},
    {19, 13, "pyramid (13 nodes)"},
    {20, 9, "triangle (9 nodes)"},
    {21, 10, "triangle (10 nodes)"},
    {22, 12, "triangle (12 nodes)"},
    {23, 15, "triangle (15 nodes)"},
    {24, 15, "triangle (15 nodes, incomplete)"},
    {25, 21, "triangle (21 nodes)"},
    {26, 4, "line (4 nodes)"},
    {27, 5, "line (5 nodes)"},
    {28, 6, "line (6 nodes)"},
    {29, 20, "tetrahedron (20 nodes)"},
    {30, 35, "tetrahedron (35 nodes)"},
    {31, 56, "tetrahedron (56 nodes)"},
    {32, 22, "tetrahedron (22 nodes)"},
    {33, 28, "tetrahedron (28 nodes)"},
    {36, 16, "quadrangle (16 nodes)"},
    {37, 25, "quadrangle (25 nodes)"},
    {38, 36, "quadrangle (36 nodes)"},
    {39, 12, "quadrangle (12 nodes)"},
    {40, 16, "quadrangle (16 nodes, incomplete)"},
    {41, 20, "quadrangle (20 nodes)"},
    {42, 28, "triangle (28 nodes)"},
    {43, 36, "triangle (36 nodes)"},
    {44, 45, "triangle (45 nodes)"},
    {45, 55, "triangle (55 nodes)"},
    {46, 66, "triangle (66 nodes)"},
    {47, 49, "quadrangle (49 nodes)"},
    {48, 64, "quadrangle (64 nodes)"},
    {49, 81, "quadrangle (81 nodes)"},
    {50, 100, "quadrangle (100 nodes)"},
    {51, 121, "quadrangle (121 nodes)"},
    {52, 18, "triangle (18 nodes)"},
    {53, 21, "triangle (21 nodes, incomplete)"},
    {54, 24, "triangle (24 nodes)"},
    {55, 27, "triangle (27 nodes)"},
    {56, 30, "triangle (30 nodes)"},
    {57, 24, "quadrangle (24 nodes)"},
    {58, 28, "quadrangle (28 nodes)"},
    {59, 32, "quadrangle (32 nodes)"},
    {60, 36, "quadrangle (36 nodes, incomplete)"},
    {61, 40, "quadrangle (40 nodes)"},
    {62, 7, "line (7 nodes)"},
    {63, 8, "line (8 nodes)"},
    {64, 9, "line (9 nodes)"},
    {65, 10, "line (10 nodes)"},
    {66, 11, "line (11 nodes)"},
    {71, 84, "tetrahedron (84 nodes)"},
    {72, 120, "tetrahedron (120 nodes)"},
    {73, 165, "tetrahedron (165 nodes)"},
    {74, 220, "tetrahedron (220 nodes)"},
    {75, 286, "tetrahedron (286 nodes)"},
    {79, 34, "tetrahedron (34 nodes)"},
    {80, 40, "tetrahedron (40 nodes)"},
    {81, 46, "tetrahedron (46 nodes)"},
    {82, 52, "tetrahedron (52 nodes)"},
    {83, 58, "tetrahedron (58 nodes)"},
    {84, 1, "line (1 node)"},
    {85, 1, "triangle (1 node)"},
    {86, 1, "quadrangle (1 node)"},
    {87, 1, "tetrahedron (1 node)"},
    {88, 1, "hexahedron (1 node)"},
    {89, 1, "prism (1 node)"},
    {90, 40, "prism (40 nodes)"},
    {91, 75, "prism (75 nodes)"},
    {92, 64, "hexahedron (64 nodes)"},
    {93, 125, "hexahedron (125 nodes)"},
    {94, 216, "hexahedron (216 nodes)"},
    {95, 343, "hexahedron (343 nodes)"},
    {96, 512, "hexahedron (512 nodes)"},
    {97, 729, "hexahedron (729 nodes)"},
    {98, 1000, "hexahedron (1000 nodes)"},
    {99, 32, "hexahedron (32 nodes)"},
    {100, 44, "hexahedron (44 nodes)"},
    {101, 56, "hexahedron (56 nodes)"},
    {102, 68, "hexahedron (68 nodes)"},
    {103, 80, "hexahedron (80 nodes)"},
    {104, 92, "hexahedron (92 nodes)"},
    {105, 104, "hexahedron (104 nodes)"},
    {106, 126, "prism (126 nodes)"},
    {107, 196, "prism (196 nodes)"},
    {108, 288, "prism (288 nodes)"},
    {109, 405, "prism (405 nodes)"},
    {110, 550, "prism (550 nodes)"},
    {111, 24, "prism (24 nodes)"},
    {112, 33, "prism (33 nodes)"},
    {113, 42, "prism (42 nodes)"},
    {114, 51, "prism (51 nodes)"},
    {115, 60, "prism (60 nodes)"},
    {116, 69, "prism (69 nodes)"},
    {117, 78, "prism (78 nodes)"},
    {118, 30, "pyramid (30 nodes)"},
    {119, 55, "pyramid (55 nodes)"},
    {120, 91, "pyramid (91 nodes)"},
    {121, 140, "pyramid (140 nodes)"},
    {122, 204, "pyramid (204 nodes)"},
    {123, 285, "pyramid (285 nodes)"},
    {124, 385, "pyramid (385 nodes)"},
    {125, 21, "pyramid (21 nodes)"},
    {126, 29, "pyramid (29 nodes)"},
    {127, 37, "pyramid (37 nodes)"},
    {128, 45, "pyramid (45 nodes)"},
    {129, 53, "pyramid (53 nodes)"},
    {130, 61, "pyramid (61 nodes)"},
    {131, 69, "pyramid (69 nodes)"},
    {132, 1, "pyramid (1 node)"},
    {133, 1, "point (xfem)"},
    {134, 2, "line (xfem)"},
    {135, 3, "triangle (xfem)"},
    {136, 4, "tetrahedron (xfem)"},
    {137, 16, "tetrahedron (16 nodes)"},
    {140, 4, "trihedron"},
};

}  // namespace

const ElementTypeInfo* FindElementType(int64_t type) {
  const auto it =
      std::lower_bound(std::begin(kElementTypes), std::end(kElementTypes), type,
                       [](const ElementTypeInfo& info, int64_t t) { return info.type < t; });
  if (it == std::end(kElementTypes) || it->type != type) return nullptr;
  return &*it;
}

const char* UnreadableTypeName(int64_t type) {
  switch (type) {
    case 34:
      return "polygon";
    case 35:
      return "polyhedron";
    case 67:
      return "border line";
    case 68:
      return "border triangle";
    case 69:
      return "border polygon";
    case 70:
      return "child line";
    case 138:
      return "MINI triangle";
    case 139:
      return "MINI tetrahedron";
    default:
      return nullptr;
  }
}

}  // namespace somasim::mesh_io::gmsh_internal
