// The legacy VTK writer: POLYDATA for a surface, UNSTRUCTURED_GRID for tetrahedra (and
// triangles), ASCII or big-endian BINARY.
#include <cstdint>
#include <string>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/vtk_legacy_io.h"

namespace somasim::mesh_io {
namespace {

void AppendInt(std::string* out, int64_t value) { *out += std::to_string(value); }

}  // namespace

std::string WriteVtkLegacy(const MeshData& mesh, Encoding encoding) {
  const bool binary = encoding == Encoding::kBinary;
  const int64_t n = mesh.vertices.cols();
  const int64_t ntri = mesh.triangles.cols();
  const int64_t ntet = mesh.tetrahedra.cols();
  std::string out = "# vtk DataFile Version 3.0\nsomasim mesh\n";
  out += binary ? "BINARY\n" : "ASCII\n";
  out += ntet > 0 ? "DATASET UNSTRUCTURED_GRID\n" : "DATASET POLYDATA\n";
  out += "POINTS " + std::to_string(n) + " double\n";
  for (int64_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      const double x = mesh.vertices(k, i);
      if (binary) {
        AppendBinary(&out, x, Endian::kBig);
      } else {
        AppendDouble(&out, x);
        out += k < 2 ? ' ' : '\n';
      }
    }
  }
  if (binary) out += '\n';
  // One cell: its point count then its indices (32-bit in BINARY files, as VTK writes them).
  const auto append_cell = [&](const int32_t* v, int m) {
    if (binary) {
      AppendBinary(&out, static_cast<int32_t>(m), Endian::kBig);
      for (int k = 0; k < m; ++k) AppendBinary(&out, v[k], Endian::kBig);
      return;
    }
    AppendInt(&out, m);
    for (int k = 0; k < m; ++k) {
      out += ' ';
      AppendInt(&out, v[k]);
    }
    out += '\n';
  };
  if (ntet == 0) {
    if (ntri > 0) {
      out += "POLYGONS " + std::to_string(ntri) + " " + std::to_string(4 * ntri) + "\n";
      for (int64_t t = 0; t < ntri; ++t) append_cell(mesh.triangles.col(t).data(), 3);
      if (binary) out += '\n';
    }
    return out;
  }
  const int64_t cells = ntet + ntri;
  out += "CELLS " + std::to_string(cells) + " " + std::to_string(5 * ntet + 4 * ntri) + "\n";
  for (int64_t t = 0; t < ntet; ++t) append_cell(mesh.tetrahedra.col(t).data(), 4);
  for (int64_t t = 0; t < ntri; ++t) append_cell(mesh.triangles.col(t).data(), 3);
  if (binary) out += '\n';
  out += "CELL_TYPES " + std::to_string(cells) + "\n";
  for (int64_t c = 0; c < cells; ++c) {
    const int32_t type = static_cast<int32_t>(c < ntet ? kVtkTetra : kVtkTriangle);
    if (binary) {
      AppendBinary(&out, type, Endian::kBig);
    } else {
      AppendInt(&out, type);
      out += '\n';
    }
  }
  if (binary) out += '\n';
  return out;
}

}  // namespace somasim::mesh_io
