#include "common/tools/render_command.h"

#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <fstream>
#include <ostream>
#include <stdexcept>

#include "common/mesh/mesh_types.h"
#include "common/mesh/topology.h"
#include "common/render/png_encoder.h"
#include "common/render/rasterizer.h"
#include "common/tools/mesh_commands.h"

namespace somasim::tools {
namespace {

using mesh_io::MeshData;
using mesh_io::MeshError;

bool EndsWithPng(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return ext == ".png";
}

// Writes the bytes to `path`; false with `error` set on failure (a partial file is removed).
bool WriteFile(const std::string& path, const std::string& bytes, std::string* error) {
  std::ofstream file(path, std::ios::binary | std::ios::trunc);
  if (!file.is_open()) {
    *error = std::string("cannot create the file: ") + std::strerror(errno);
    return false;
  }
  file.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  file.flush();
  if (!file.good()) {
    *error = std::string("write failed: ") + std::strerror(errno);
    file.close();
    std::remove(path.c_str());
    return false;
  }
  return true;
}

bool ParseInt(std::string_view text, int* value) {
  if (text.empty() || text.size() > 5) return false;
  for (char c : text) {
    if (c < '0' || c > '9') return false;
  }
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), *value);
  return ec == std::errc() && end == text.data() + text.size();
}

}  // namespace

std::optional<std::pair<int, int>> ParseImageSize(std::string_view text) {
  const size_t x = text.find_first_of("xX");
  if (x == std::string_view::npos) return std::nullopt;
  int width = 0, height = 0;
  if (!ParseInt(text.substr(0, x), &width) || !ParseInt(text.substr(x + 1), &height)) {
    return std::nullopt;
  }
  if (width < 1 || height < 1) return std::nullopt;
  return std::pair{width, height};
}

std::optional<Eigen::Vector3d> ParseVector3(std::string_view text) {
  Eigen::Vector3d v;
  for (int k = 0; k < 3; ++k) {
    const size_t comma = text.find(',');
    if ((k < 2) != (comma != std::string_view::npos)) return std::nullopt;
    std::string_view token = text.substr(0, comma);
    if (token.size() > 1 && token[0] == '+' && token[1] != '-') token.remove_prefix(1);
    double value = 0.0;
    const auto [end, ec] = std::from_chars(token.data(), token.data() + token.size(), value);
    if (token.empty() || ec != std::errc() || end != token.data() + token.size() ||
        !std::isfinite(value)) {
      return std::nullopt;
    }
    v[k] = value;
    text = k < 2 ? text.substr(comma + 1) : std::string_view();
  }
  return v;
}

int RunRender(const RenderCommandOptions& options, std::ostream& out, std::ostream& err) {
  if (options.width < 1 || options.width > render::kMaxImageSize || options.height < 1 ||
      options.height > render::kMaxImageSize) {
    err << "somasim-mesh: --size must be WIDTHxHEIGHT with each in 1.." << render::kMaxImageSize
        << " pixels (got " << options.width << "x" << options.height << ")\n";
    return kExitUsage;
  }
  if (options.view && (!options.view->allFinite() || !(options.view->norm() > 0.0))) {
    err << "somasim-mesh: --view must be three finite numbers x,y,z, not all zero\n";
    return kExitUsage;
  }
  if (options.up && (!options.up->allFinite() || !(options.up->norm() > 0.0))) {
    err << "somasim-mesh: --up must be three finite numbers x,y,z, not all zero\n";
    return kExitUsage;
  }
  if (!EndsWithPng(options.output)) {
    err << "somasim-mesh: " << options.output << ": the output must be a .png file\n";
    return kExitUsage;
  }
  try {
    const MeshData m = LoadMesh(options.input, options.read);
    render::RenderOptions ro;
    ro.width = options.width;
    ro.height = options.height;
    if (options.view) ro.view_direction = *options.view;
    if (options.up) ro.up = *options.up;
    ro.draw_edges = options.edges;

    // A volume mesh is seen through its boundary; any triangles it also lists lie on it.
    const mesh::SurfaceMesh surface = m.tetrahedra.cols() > 0
                                          ? mesh::ExtractBoundarySurface({m.vertices, m.tetrahedra})
                                          : mesh::SurfaceMesh{m.vertices, m.triangles};
    render::Image image;
    try {
      image = render::RenderSurface(surface, ro);
    } catch (const std::invalid_argument& e) {
      err << "somasim-mesh: " << options.input << ": cannot render: " << e.what() << "\n";
      return kExitBadInput;
    }
    const std::string png = render::EncodePng(image);
    std::string error;
    if (!WriteFile(options.output, png, &error)) {
      err << "somasim-mesh: " << options.output << ": " << error << "\n";
      return kExitIo;
    }
    out << "wrote " << options.output << ": " << image.width << "x" << image.height << " PNG of "
        << surface.triangles.cols() << " triangles";
    if (m.tetrahedra.cols() > 0) out << " (boundary of " << m.tetrahedra.cols() << " tetrahedra)";
    out << " from " << options.input << " (" << m.format << ")\n";
    if (surface.triangles.cols() == 0) {
      out << "note: the mesh has no triangles or tetrahedra; the picture is empty\n";
    }
    for (const auto& k : m.skipped) {
      out << "note: skipped " << k.count << " " << k.type << " (not a triangle or tetrahedron)\n";
    }
    return kExitOk;
  } catch (const MeshError& e) {
    err << "somasim-mesh: " << e.what() << "\n";
    return mesh_io::ExitCodeOf(e);
  } catch (const std::exception& e) {
    err << "somasim-mesh: internal error while rendering " << options.input << ": " << e.what()
        << "\n";
    return kExitBug;
  }
}

}  // namespace somasim::tools
