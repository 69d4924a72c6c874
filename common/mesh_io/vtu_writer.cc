// The VTU writer: one piece of Float64 points and Int64/UInt8 cell arrays (and any point data),
// in ascii, inline base64 or appended raw data, either byte order.
#include <algorithm>
#include <cctype>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <type_traits>

#include "common/mesh_io/base64.h"
#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/vtk_legacy_io.h"  // kVtkTetra, kVtkTriangle
#include "common/mesh_io/vtu_io.h"

namespace somasim::mesh_io {
namespace {

// Appends one array's binary block: a UInt32/UInt64 byte count then the values.
template <typename T, typename Get>
void AppendBlock(std::string* out, size_t n, Get get, Endian endian, bool header64) {
  const uint64_t bytes = n * sizeof(T);
  if (header64) {
    AppendBinary(out, bytes, endian);
  } else {
    AppendBinary(out, static_cast<uint32_t>(bytes), endian);
  }
  for (size_t i = 0; i < n; ++i) AppendBinary(out, static_cast<T>(get(i)), endian);
}

}  // namespace

std::string WriteVtu(const MeshData& mesh, const VtuWriteOptions& options) {
  const Endian endian = options.big_endian ? Endian::kBig : Endian::kLittle;
  const size_t n = static_cast<size_t>(mesh.vertices.cols());
  const size_t ntri = static_cast<size_t>(mesh.triangles.cols());
  const size_t ntet = static_cast<size_t>(mesh.tetrahedra.cols());
  const size_t ncells = ntet + ntri;
  const size_t nconn = 4 * ntet + 3 * ntri;
  // A UInt32 header cannot count more than 4 GiB; larger arrays need UInt64 headers.
  const bool header64 = std::max(3 * n, nconn) * 8 > UINT32_MAX;
  const auto point = [&](size_t i) {
    return mesh.vertices(static_cast<Eigen::Index>(i % 3), static_cast<Eigen::Index>(i / 3));
  };
  const auto connectivity = [&](size_t i) -> int64_t {
    if (i < 4 * ntet) {
      return mesh.tetrahedra(static_cast<Eigen::Index>(i % 4), static_cast<Eigen::Index>(i / 4));
    }
    const size_t k = i - 4 * ntet;
    return mesh.triangles(static_cast<Eigen::Index>(k % 3), static_cast<Eigen::Index>(k / 3));
  };
  const auto offset = [&](size_t c) -> int64_t {
    return static_cast<int64_t>(c < ntet ? 4 * (c + 1) : 4 * ntet + 3 * (c + 1 - ntet));
  };
  const auto type = [&](size_t c) -> int64_t { return c < ntet ? kVtkTetra : kVtkTriangle; };

  std::string out = "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" ";
  out += options.big_endian ? "byte_order=\"BigEndian\"" : "byte_order=\"LittleEndian\"";
  out += header64 ? " header_type=\"UInt64\">\n" : " header_type=\"UInt32\">\n";
  out += "  <UnstructuredGrid>\n    <Piece NumberOfPoints=\"" + std::to_string(n) +
         "\" NumberOfCells=\"" + std::to_string(ncells) + "\">\n";
  std::string appended;
  const char* format = options.encoding == VtuEncoding::kAscii    ? "ascii"
                       : options.encoding == VtuEncoding::kBase64 ? "binary"
                                                                  : "appended";
  // Writes one DataArray; values are produced by get(i), i < count.
  const auto write_array = [&](const char* type_name, const char* name, int components,
                               size_t count, auto get, auto binary_tag) {
    using T = decltype(binary_tag);
    out += std::string("        <DataArray type=\"") + type_name + "\" Name=\"" + name + "\"";
    if (components != 1) out += " NumberOfComponents=\"" + std::to_string(components) + "\"";
    out += std::string(" format=\"") + format + "\"";
    if (options.encoding == VtuEncoding::kAppendedRaw) {
      out += " offset=\"" + std::to_string(appended.size()) + "\"/>\n";
      AppendBlock<T>(&appended, count, get, endian, header64);
      return;
    }
    out += ">\n          ";
    if (options.encoding == VtuEncoding::kBase64) {
      std::string block;
      AppendBlock<T>(&block, count, get, endian, header64);
      AppendBase64(&out, block);
      out += '\n';
    } else {
      for (size_t i = 0; i < count; ++i) {
        if constexpr (std::is_floating_point_v<T>) {
          AppendDouble(&out, static_cast<double>(get(i)));
        } else {
          out += std::to_string(static_cast<int64_t>(get(i)));
        }
        const bool end_of_row =
            (i + 1) % static_cast<size_t>(components == 1 ? 6 : components) == 0;
        out += end_of_row || i + 1 == count ? "\n          " : " ";
      }
      if (count > 0) out.resize(out.size() - 10);
      if (count == 0) out += '\n';
    }
    out += "        </DataArray>\n";
  };
  if (!mesh.point_data.empty()) {
    out += "      <PointData>\n";
    for (const PointArray& array : mesh.point_data) {
      for (const char c : array.name) {  // the name goes into an XML attribute as is
        if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-' || c == ' ')) {
          throw std::invalid_argument("WriteVtu: point data name \"" + array.name +
                                      "\" may hold only letters, digits, ' ', '_' and '-'");
        }
      }
      if (array.name.empty() || array.components <= 0 ||
          array.values.size() != static_cast<size_t>(array.components) * n) {
        throw std::invalid_argument("WriteVtu: point data \"" + array.name + "\" has " +
                                    std::to_string(array.values.size()) + " values, not " +
                                    std::to_string(array.components) + " per node for " +
                                    std::to_string(n) + " nodes");
      }
      write_array(
          "Float64", array.name.c_str(), array.components, array.values.size(),
          [&array](size_t i) { return array.values[i]; }, double{});
    }
    out += "      </PointData>\n";
  }
  out += "      <Points>\n";
  write_array("Float64", "Points", 3, 3 * n, point, double{});
  out += "      </Points>\n      <Cells>\n";
  write_array("Int64", "connectivity", 1, nconn, connectivity, int64_t{});
  write_array("Int64", "offsets", 1, ncells, offset, int64_t{});
  write_array("UInt8", "types", 1, ncells, type, uint8_t{});
  out += "      </Cells>\n    </Piece>\n  </UnstructuredGrid>\n";
  if (options.encoding == VtuEncoding::kAppendedRaw) {
    out += "  <AppendedData encoding=\"raw\">\n   _";
    out += appended;
    out += "\n  </AppendedData>\n";
  }
  out += "</VTKFile>\n";
  return out;
}

}  // namespace somasim::mesh_io
