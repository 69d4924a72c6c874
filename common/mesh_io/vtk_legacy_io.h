// Legacy VTK (.vtk), ASCII and BINARY (big-endian), DATASET POLYDATA and UNSTRUCTURED_GRID,
// both the classic `CELLS n size` layout and the 5.1 `OFFSETS`/`CONNECTIVITY` layout.
// Point/cell attribute sections are parsed (and their sizes checked) but not kept.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/stl_io.h"  // Encoding

namespace somasim::mesh_io {

MeshData ReadVtkLegacy(std::string_view bytes, const std::string& file_name,
                       const ReadOptions& options);
// POLYDATA when the mesh has no tetrahedra, else UNSTRUCTURED_GRID (tetrahedra and triangles).
std::string WriteVtkLegacy(const MeshData& mesh, Encoding encoding);

// VTK cell type codes (vtkCellType.h), shared by the legacy and the XML (.vtu) readers.
inline constexpr int64_t kVtkTriangle = 5;
inline constexpr int64_t kVtkTetra = 10;

struct VtkCellTypeInfo {
  const char* name = nullptr;  // e.g. "VTK_QUADRATIC_TETRA"; nullptr for codes VTK does not define
  int num_points = -1;         // points of the cell; -1 when the cell type has a variable count
};

inline VtkCellTypeInfo VtkCellType(int64_t code) {
  struct Entry {
    int64_t code;
    VtkCellTypeInfo info;
  };
  // clang-format off
  static constexpr Entry kTypes[] = {
      {0, {"VTK_EMPTY_CELL", 0}},
      {1, {"VTK_VERTEX", 1}},
      {2, {"VTK_POLY_VERTEX", -1}},
      {3, {"VTK_LINE", 2}},
      {4, {"VTK_POLY_LINE", -1}},
      {5, {"VTK_TRIANGLE", 3}},
      {6, {"VTK_TRIANGLE_STRIP", -1}},
      {7, {"VTK_POLYGON", -1}},
      {8, {"VTK_PIXEL", 4}},
      {9, {"VTK_QUAD", 4}},
      {10, {"VTK_TETRA", 4}},
      {11, {"VTK_VOXEL", 8}},
      {12, {"VTK_HEXAHEDRON", 8}},
      {13, {"VTK_WEDGE", 6}},
      {14, {"VTK_PYRAMID", 5}},
      {15, {"VTK_PENTAGONAL_PRISM", 10}},
      {16, {"VTK_HEXAGONAL_PRISM", 12}},
      {21, {"VTK_QUADRATIC_EDGE", 3}},
      {22, {"VTK_QUADRATIC_TRIANGLE", 6}},
      {23, {"VTK_QUADRATIC_QUAD", 8}},
      {24, {"VTK_QUADRATIC_TETRA", 10}},
      {25, {"VTK_QUADRATIC_HEXAHEDRON", 20}},
      {26, {"VTK_QUADRATIC_WEDGE", 15}},
      {27, {"VTK_QUADRATIC_PYRAMID", 13}},
      {28, {"VTK_BIQUADRATIC_QUAD", 9}},
      {29, {"VTK_TRIQUADRATIC_HEXAHEDRON", 27}},
      {30, {"VTK_QUADRATIC_LINEAR_QUAD", 6}},
      {31, {"VTK_QUADRATIC_LINEAR_WEDGE", 12}},
      {32, {"VTK_BIQUADRATIC_QUADRATIC_WEDGE", 18}},
      {33, {"VTK_BIQUADRATIC_QUADRATIC_HEXAHEDRON", 24}},
      {34, {"VTK_BIQUADRATIC_TRIANGLE", 7}},
      {35, {"VTK_CUBIC_LINE", 4}},
      {36, {"VTK_QUADRATIC_POLYGON", -1}},
      {37, {"VTK_TRIQUADRATIC_PYRAMID", 19}},
      {41, {"VTK_CONVEX_POINT_SET", -1}},
      {42, {"VTK_POLYHEDRON", -1}},
      {51, {"VTK_PARAMETRIC_CURVE", -1}},
      {52, {"VTK_PARAMETRIC_SURFACE", -1}},
      {53, {"VTK_PARAMETRIC_TRI_SURFACE", -1}},
      {54, {"VTK_PARAMETRIC_QUAD_SURFACE", -1}},
      {55, {"VTK_PARAMETRIC_TETRA_REGION", -1}},
      {56, {"VTK_PARAMETRIC_HEX_REGION", -1}},
      {60, {"VTK_HIGHER_ORDER_EDGE", -1}},
      {61, {"VTK_HIGHER_ORDER_TRIANGLE", -1}},
      {62, {"VTK_HIGHER_ORDER_QUAD", -1}},
      {63, {"VTK_HIGHER_ORDER_POLYGON", -1}},
      {64, {"VTK_HIGHER_ORDER_TETRAHEDRON", -1}},
      {65, {"VTK_HIGHER_ORDER_WEDGE", -1}},
      {66, {"VTK_HIGHER_ORDER_PYRAMID", -1}},
      {67, {"VTK_HIGHER_ORDER_HEXAHEDRON", -1}},
      {68, {"VTK_LAGRANGE_CURVE", -1}},
      {69, {"VTK_LAGRANGE_TRIANGLE", -1}},
      {70, {"VTK_LAGRANGE_QUADRILATERAL", -1}},
      {71, {"VTK_LAGRANGE_TETRAHEDRON", -1}},
      {72, {"VTK_LAGRANGE_HEXAHEDRON", -1}},
      {73, {"VTK_LAGRANGE_WEDGE", -1}},
      {74, {"VTK_LAGRANGE_PYRAMID", -1}},
      {75, {"VTK_BEZIER_CURVE", -1}},
      {76, {"VTK_BEZIER_TRIANGLE", -1}},
      {77, {"VTK_BEZIER_QUADRILATERAL", -1}},
      {78, {"VTK_BEZIER_TETRAHEDRON", -1}},
      {79, {"VTK_BEZIER_HEXAHEDRON", -1}},
      {80, {"VTK_BEZIER_WEDGE", -1}},
      {81, {"VTK_BEZIER_PYRAMID", -1}},
  };
  // clang-format on
  for (const Entry& e : kTypes) {
    if (e.code == code) return e.info;
  }
  return {};
}

}  // namespace somasim::mesh_io
