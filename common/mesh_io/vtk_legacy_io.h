// Legacy VTK (.vtk), ASCII and BINARY (big-endian), DATASET POLYDATA and UNSTRUCTURED_GRID,
// both the classic `CELLS n size` layout and the 5.1 `OFFSETS`/`CONNECTIVITY` layout.
// Point/cell attribute sections are parsed (and their sizes checked) but not kept.
#pragma once

#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/stl_io.h"  // Encoding

namespace somasim::mesh_io {

MeshData ReadVtkLegacy(std::string_view bytes, const std::string& file_name,
                       const ReadOptions& options);
// POLYDATA when the mesh has no tetrahedra, else UNSTRUCTURED_GRID (tetrahedra and triangles).
std::string WriteVtkLegacy(const MeshData& mesh, Encoding encoding);

}  // namespace somasim::mesh_io
