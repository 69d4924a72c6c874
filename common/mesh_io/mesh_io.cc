#include "common/mesh_io/mesh_io.h"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "common/mesh/topology.h"
#include "common/mesh_io/obj_io.h"
#include "common/mesh_io/tetgen_io.h"
#include "common/mesh_io/vtk_legacy_io.h"

namespace somasim::mesh_io {
namespace {

std::string Lower(std::string_view s) {
  std::string out(s);
  for (char& c : out) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return out;
}

std::string Extension(std::string_view path) {
  return Lower(std::filesystem::path(path).extension().string());
}

[[noreturn]] void FailIo(const std::string& path, const std::string& fault) {
  throw MeshError(MeshErrorKind::kIo, path, {}, fault);
}

void WriteFileBytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out.is_open()) FailIo(path, std::string("cannot create the file: ") + std::strerror(errno));
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  out.flush();
  if (!out.good()) FailIo(path, std::string("write failed: ") + std::strerror(errno));
}

}  // namespace

std::optional<FileFormat> FormatFromPath(std::string_view path) {
  const std::string ext = Extension(path);
  if (ext == ".obj") return FileFormat::kObj;
  if (ext == ".stl") return FileFormat::kStl;
  if (ext == ".vtk") return FileFormat::kVtkLegacy;
  if (ext == ".vtu") return FileFormat::kVtu;
  if (ext == ".msh") return FileFormat::kGmsh;
  if (ext == ".node" || ext == ".ele" || ext == ".face") return FileFormat::kTetGen;
  return std::nullopt;
}

const char* FormatName(FileFormat format) {
  switch (format) {
    case FileFormat::kObj:
      return "Wavefront OBJ";
    case FileFormat::kStl:
      return "STL";
    case FileFormat::kVtkLegacy:
      return "legacy VTK";
    case FileFormat::kVtu:
      return "VTK XML unstructured grid";
    case FileFormat::kGmsh:
      return "Gmsh";
    case FileFormat::kTetGen:
      return "TetGen";
  }
  return "unknown";
}

bool FormatHoldsTetrahedra(FileFormat format) {
  return format != FileFormat::kObj && format != FileFormat::kStl;
}

std::string ReadFileBytes(const std::string& path) {
  std::error_code ec;
  const auto status = std::filesystem::status(path, ec);
  if (ec || !std::filesystem::exists(status)) FailIo(path, "no such file");
  if (!std::filesystem::is_regular_file(status)) FailIo(path, "not a regular file");
  std::ifstream in(path, std::ios::binary);
  if (!in.is_open()) FailIo(path, std::string("cannot open: ") + std::strerror(errno));
  std::ostringstream ss;
  ss << in.rdbuf();
  if (in.bad()) FailIo(path, std::string("read failed: ") + std::strerror(errno));
  return ss.str();
}

MeshData ReadMeshBytes(FileFormat format, std::string_view bytes, const std::string& name,
                       const ReadOptions& options) {
  switch (format) {
    case FileFormat::kObj:
      return ReadObj(bytes, name, options);
    case FileFormat::kStl:
      return ReadStl(bytes, name, options);
    case FileFormat::kVtkLegacy:
      return ReadVtkLegacy(bytes, name, options);
    case FileFormat::kVtu:
      return ReadVtu(bytes, name, options);
    case FileFormat::kGmsh:
      return ReadGmsh(bytes, name, options);
    case FileFormat::kTetGen: {
      TetGenInput input;
      input.node = bytes;
      input.node_name = name;
      return ReadTetGen(input, options);
    }
  }
  throw MeshError(MeshErrorKind::kUnsupported, name, {}, "unknown format");
}

MeshData ReadMeshFile(const std::string& path, const ReadOptions& options) {
  const std::optional<FileFormat> format = FormatFromPath(path);
  if (!format) {
    throw MeshError(MeshErrorKind::kUnsupported, path, {},
                    "unknown mesh file extension '" + Extension(path) +
                        "' (expected .obj .stl .vtk .vtu .msh .node .ele .face)");
  }
  if (*format != FileFormat::kTetGen) {
    const std::string bytes = ReadFileBytes(path);
    return ReadMeshBytes(*format, bytes, path, options);
  }
  // TetGen: the .node file plus whichever of .ele and .face exist beside it.
  const std::filesystem::path base = std::filesystem::path(path).replace_extension();
  TetGenInput input;
  input.node_name = base.string() + ".node";
  input.ele_name = base.string() + ".ele";
  input.face_name = base.string() + ".face";
  const std::string node = ReadFileBytes(input.node_name);
  input.node = node;
  std::string ele, face;
  if (std::filesystem::exists(input.ele_name)) {
    ele = ReadFileBytes(input.ele_name);
    input.ele = ele;
  } else if (Extension(path) == ".ele") {
    FailIo(input.ele_name, "no such file");
  }
  if (std::filesystem::exists(input.face_name)) {
    face = ReadFileBytes(input.face_name);
    input.face = face;
  } else if (Extension(path) == ".face") {
    FailIo(input.face_name, "no such file");
  }
  return ReadTetGen(input, options);
}

WriteReport WriteMeshFile(const std::string& path, const MeshData& mesh,
                          const WriteOptions& options) {
  const std::optional<FileFormat> format = FormatFromPath(path);
  if (!format) {
    throw MeshError(MeshErrorKind::kUnsupported, path, {},
                    "cannot tell the output format from the extension '" + Extension(path) +
                        "' (expected .obj .stl .vtk .vtu .msh .node)");
  }
  WriteReport report;
  MeshData out = mesh;
  const double scale = UnitToMetres(options.unit);
  if (scale != 1.0) out.vertices /= scale;
  if (!FormatHoldsTetrahedra(*format) && out.tetrahedra.cols() > 0) {
    // OBJ and STL hold surfaces only: write the volume's boundary, without interior nodes.
    const mesh::SurfaceMesh boundary =
        mesh::CompactSurface(mesh::ExtractBoundarySurface({out.vertices, out.tetrahedra}), nullptr);
    out.vertices = boundary.vertices;
    out.triangles = boundary.triangles;
    out.tetrahedra.resize(4, 0);
    report.wrote_boundary_surface = true;
  }
  switch (*format) {
    case FileFormat::kObj:
      WriteFileBytes(path, WriteObj(out));
      break;
    case FileFormat::kStl:
      WriteFileBytes(path, WriteStl(out, options.encoding));
      break;
    case FileFormat::kVtkLegacy:
      WriteFileBytes(path, WriteVtkLegacy(out, options.encoding));
      break;
    case FileFormat::kVtu: {
      VtuWriteOptions vtu;
      vtu.encoding = options.encoding == Encoding::kAscii ? VtuEncoding::kAscii
                     : options.vtu_base64                 ? VtuEncoding::kBase64
                                                          : VtuEncoding::kAppendedRaw;
      vtu.big_endian = options.big_endian;
      WriteFileBytes(path, WriteVtu(out, vtu));
      break;
    }
    case FileFormat::kGmsh:
      WriteFileBytes(path, WriteGmsh(out, options.gmsh_version, options.encoding));
      break;
    case FileFormat::kTetGen: {
      const std::string base = std::filesystem::path(path).replace_extension().string();
      const TetGenFiles files = WriteTetGen(out);
      WriteFileBytes(base + ".node", files.node);
      report.files = base + ".node";
      if (!files.ele.empty()) {
        WriteFileBytes(base + ".ele", files.ele);
        report.files += " " + base + ".ele";
      }
      if (!files.face.empty()) {
        WriteFileBytes(base + ".face", files.face);
        report.files += " " + base + ".face";
      }
      return report;
    }
  }
  report.files = path;
  return report;
}

}  // namespace somasim::mesh_io
