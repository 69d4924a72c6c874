#include "common/tools/mesh_commands.h"

#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <ostream>
#include <sstream>
#include <system_error>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/quality.h"
#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/tetgen_io.h"

extern char** environ;

namespace somasim::tools {
namespace {

using mesh_io::MeshData;
using mesh_io::MeshError;
using mesh_io::MeshErrorKind;

// Everything `info` reports, computed once for text and JSON output.
struct MeshSummary {
  int64_t nodes = 0, tetrahedra = 0, triangles = 0;
  int64_t unreferenced_nodes = 0;
  mesh::BoundingBox bbox;
  std::optional<double> volume_m3;  // tets' volume, or the enclosed volume of a closed surface
  double surface_area_m2 = 0.0;     // of the boundary (volume) or of the triangles (surface)
  int64_t boundary_triangles = 0;
  mesh::SurfaceTopology topology;               // of the boundary surface or of the triangles
  std::optional<mesh::QualitySummary> quality;  // volume meshes only
};

MeshSummary Summarise(const MeshData& m) {
  MeshSummary s;
  s.nodes = m.vertices.cols();
  s.tetrahedra = m.tetrahedra.cols();
  s.triangles = m.triangles.cols();
  s.bbox = mesh::ComputeBoundingBox(m.vertices);
  s.unreferenced_nodes = static_cast<int64_t>(
      mesh::UnreferencedNodes(static_cast<int32_t>(s.nodes), m.triangles, m.tetrahedra).size());

  mesh::SurfaceMesh surface;
  if (s.tetrahedra > 0) {
    const mesh::TetMesh volume{m.vertices, m.tetrahedra};
    surface = mesh::ExtractBoundarySurface(volume);
    s.volume_m3 = mesh::TetMeshVolume(volume);
    s.quality = mesh::SummariseQuality(volume);
  } else {
    surface = {m.vertices, m.triangles};
  }
  s.boundary_triangles = surface.triangles.cols();
  s.topology = mesh::AnalyseSurfaceTopology(surface);
  s.surface_area_m2 = mesh::SurfaceArea(surface);
  if (s.tetrahedra == 0 && s.topology.watertight) {
    s.volume_m3 = mesh::SurfaceEnclosedVolume(surface);
  }
  return s;
}

nlohmann::json Vec(const Eigen::Vector3d& v) { return nlohmann::json::array({v[0], v[1], v[2]}); }

nlohmann::json ToJson(const std::string& file, const MeshData& m, const mesh_io::ReadOptions& ro,
                      const MeshSummary& s) {
  nlohmann::json j;
  j["file"] = file;
  j["format"] = m.format;
  j["unit"] = mesh_io::UnitName(ro.unit);
  j["nodes"] = s.nodes;
  j["tetrahedra"] = s.tetrahedra;
  j["triangles"] = s.triangles;
  j["unreferenced_nodes"] = s.unreferenced_nodes;
  j["bbox_min"] = s.bbox.empty ? nlohmann::json() : Vec(s.bbox.min);
  j["bbox_max"] = s.bbox.empty ? nlohmann::json() : Vec(s.bbox.max);
  j["volume_m3"] = s.volume_m3 ? nlohmann::json(*s.volume_m3) : nlohmann::json();
  j["surface_area_m2"] = s.surface_area_m2;
  j["boundary_triangles"] = s.boundary_triangles;
  j["watertight"] = s.topology.watertight;
  j["manifold"] = s.topology.manifold;
  j["components"] = s.topology.num_components;
  j["euler_characteristic"] = s.topology.euler_characteristic;
  j["boundary_edges"] = s.topology.num_boundary_edges;
  j["nonmanifold_edges"] = s.topology.num_nonmanifold_edges;
  j["misoriented_edges"] = s.topology.num_misoriented_edges;
  if (s.quality) {
    j["min_dihedral_deg"] = s.quality->min_dihedral_deg;
    j["max_dihedral_deg"] = s.quality->max_dihedral_deg;
    j["max_aspect_ratio"] = s.quality->max_aspect_ratio;
    j["mean_aspect_ratio"] = s.quality->mean_aspect_ratio;
    j["min_tet_volume_m3"] = s.quality->min_volume;
  } else {
    j["min_dihedral_deg"] = nullptr;  // a surface has no tetrahedra
  }
  j["flipped_tetrahedra"] = m.num_flipped;
  nlohmann::json skipped = nlohmann::json::array();
  for (const auto& k : m.skipped) skipped.push_back({{"type", k.type}, {"count", k.count}});
  j["skipped"] = skipped;
  return j;
}

void PrintText(std::ostream& out, const std::string& file, const MeshData& m,
               const mesh_io::ReadOptions& ro, const MeshSummary& s) {
  out << file << ": " << m.format << ", coordinates read as " << mesh_io::UnitName(ro.unit) << "\n";
  out << "  nodes " << s.nodes << ", tetrahedra " << s.tetrahedra << ", triangles " << s.triangles;
  if (s.unreferenced_nodes > 0) out << ", unreferenced nodes " << s.unreferenced_nodes;
  out << "\n";
  for (const auto& k : m.skipped) out << "  skipped " << k.count << " " << k.type << "\n";
  if (m.num_flipped > 0) out << "  re-oriented " << m.num_flipped << " inverted tetrahedra\n";
  if (!s.bbox.empty) {
    const Eigen::Vector3d size = s.bbox.max - s.bbox.min;
    out << "  bounding box [m] (" << s.bbox.min.transpose() << ") .. (" << s.bbox.max.transpose()
        << "), size " << size.transpose() << "\n";
  }
  if (s.volume_m3) {
    out << "  volume " << *s.volume_m3 << " m^3 (" << *s.volume_m3 * 1000.0 << " L)\n";
  }
  out << "  " << (s.tetrahedra > 0 ? "boundary surface " : "surface ") << s.boundary_triangles
      << " triangles, area " << s.surface_area_m2 << " m^2, watertight "
      << (s.topology.watertight ? "yes" : "no") << ", manifold "
      << (s.topology.manifold ? "yes" : "no") << ", components " << s.topology.num_components
      << ", Euler characteristic " << s.topology.euler_characteristic << "\n";
  if (!s.topology.watertight) {
    out << "    boundary edges " << s.topology.num_boundary_edges << ", non-manifold edges "
        << s.topology.num_nonmanifold_edges << ", misoriented edges "
        << s.topology.num_misoriented_edges << "\n";
  }
  if (s.quality) {
    out << "  quality: dihedral angles " << s.quality->min_dihedral_deg << ".."
        << s.quality->max_dihedral_deg << " deg, aspect ratio mean " << s.quality->mean_aspect_ratio
        << " max " << s.quality->max_aspect_ratio << "\n";
  }
}

// Runs a program with arguments (no shell), its output going to log_path. Returns its exit
// status, or -1 with `error` set when it could not be started or died by a signal.
int RunProgram(const std::vector<std::string>& argv, const std::string& log_path,
               std::string* error) {
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, STDOUT_FILENO, log_path.c_str(),
                                   O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_adddup2(&actions, STDOUT_FILENO, STDERR_FILENO);
  std::vector<char*> args;
  args.reserve(argv.size() + 1);
  for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  pid_t pid = 0;
  const int rc = posix_spawnp(&pid, args[0], &actions, nullptr, args.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  if (rc != 0) {
    *error = "cannot run '" + argv[0] + "': " + std::strerror(rc);
    return -1;
  }
  int status = 0;
  while (waitpid(pid, &status, 0) < 0) {
    if (errno != EINTR) {
      *error = std::string("waitpid failed: ") + std::strerror(errno);
      return -1;
    }
  }
  if (WIFSIGNALED(status)) {
    *error = "'" + argv[0] + "' was killed by signal " + std::to_string(WTERMSIG(status));
    return -1;
  }
  return WEXITSTATUS(status);
}

std::string Tail(const std::string& path, size_t max_lines) {
  std::ifstream in(path);
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  std::string out;
  for (size_t i = lines.size() > max_lines ? lines.size() - max_lines : 0; i < lines.size(); ++i) {
    out += "    " + lines[i] + "\n";
  }
  return out;
}

// TetGen's .smesh input: a piecewise linear complex of the surface's triangles, 0-based.
std::string WriteSmesh(const mesh::SurfaceMesh& s) {
  std::string out = "# somasim surface for tetgen\n";
  out += std::to_string(s.vertices.cols()) + " 3 0 0\n";
  for (Eigen::Index i = 0; i < s.vertices.cols(); ++i) {
    out += std::to_string(i);
    for (int k = 0; k < 3; ++k) {
      out += ' ';
      mesh_io::AppendDouble(&out, s.vertices(k, i));
    }
    out += '\n';
  }
  out += std::to_string(s.triangles.cols()) + " 0\n";
  for (Eigen::Index t = 0; t < s.triangles.cols(); ++t) {
    out += "3 " + std::to_string(s.triangles(0, t)) + " " + std::to_string(s.triangles(1, t)) +
           " " + std::to_string(s.triangles(2, t)) + "\n";
  }
  out += "0\n0\n";
  return out;
}

}  // namespace

mesh_io::MeshData LoadMesh(const std::string& path, const mesh_io::ReadOptions& read) {
  if (!path.starts_with(kBuiltinPrefix)) return mesh_io::ReadMeshFile(path, read);
  const std::string name = path.substr(kBuiltinPrefix.size());
  if (mesh_gen::FindBuiltinOrgan(name) == nullptr) {
    throw MeshError(MeshErrorKind::kIo, path, {},
                    "no built-in organ called \"" + name + "\" (the built-in organs are " +
                        mesh_gen::BuiltinOrganNames() + ")");
  }
  if (read.unit != mesh_io::Unit::kMetre) {
    throw MeshError(MeshErrorKind::kValue, path, {},
                    "built-in organs are generated in metres; --unit does not apply to them");
  }
  mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan(name);
  MeshData m;
  if (organ.spec->kind == mesh_gen::OrganKind::kVolume) {
    m.vertices = std::move(organ.volume.vertices);
    m.tetrahedra = std::move(organ.volume.tetrahedra);
  } else {
    m.vertices = std::move(organ.surface.vertices);
    m.triangles = std::move(organ.surface.triangles);
  }
  m.format = "built-in organ " + std::string(organ.spec->name) + " (" +
             mesh_gen::OrganKindName(organ.spec->kind) + ")";
  return m;
}

int RunList(const ListOptions& options, std::ostream& out, std::ostream& /*err*/) {
  if (options.json) {
    nlohmann::json list = nlohmann::json::array();
    for (const mesh_gen::BuiltinOrganSpec& spec : mesh_gen::BuiltinOrganSpecs()) {
      const bool volume = spec.kind == mesh_gen::OrganKind::kVolume;
      nlohmann::json j;
      j["name"] = spec.name;
      j["alias"] = spec.alias;
      j["kind"] = mesh_gen::OrganKindName(spec.kind);
      j["nodes"] = spec.num_nodes;
      j[volume ? "tetrahedra" : "triangles"] = spec.num_elements;
      j["target_nodes"] = spec.target_nodes;
      j[volume ? "target_tetrahedra" : "target_triangles"] = spec.target_elements;
      j["source"] = spec.source;
      j["description"] = spec.description;
      list.push_back(j);
    }
    out << list.dump(2) << "\n";
    return kExitOk;
  }
  out << "built-in organs (use as builtin:NAME wherever a mesh file is expected):\n";
  for (const mesh_gen::BuiltinOrganSpec& spec : mesh_gen::BuiltinOrganSpecs()) {
    const bool volume = spec.kind == mesh_gen::OrganKind::kVolume;
    std::string name(spec.name);
    if (!spec.alias.empty()) name += " (" + std::string(spec.alias) + ")";
    std::ostringstream line;
    line << "  " << name;
    for (size_t pad = name.size(); pad < 32; ++pad) line << ' ';
    line << spec.num_nodes << (volume ? " nodes / " : " vertices / ") << spec.num_elements
         << (volume ? " tetrahedra" : " triangles") << ", " << mesh_gen::OrganKindName(spec.kind)
         << ": " << spec.description << " [" << spec.source << "]";
    out << line.str() << "\n";
  }
  return kExitOk;
}

int RunGenerate(const GenerateOptions& options, std::ostream& out, std::ostream& err) {
  const mesh_gen::BuiltinOrganSpec* spec = mesh_gen::FindBuiltinOrgan(options.name);
  if (spec == nullptr) {
    err << "somasim-mesh: no built-in organ called \"" << options.name
        << "\"; the built-in organs are " << mesh_gen::BuiltinOrganNames() << "\n";
    return kExitUsage;
  }
  if (!mesh_io::FormatFromPath(options.output)) {
    err << "somasim-mesh: " << options.output
        << ": unknown output format (use .obj .stl .vtk .vtu .msh .node)\n";
    return kExitUsage;
  }
  if (options.surface && options.volume) {
    err << "somasim-mesh: --surface and --volume exclude each other\n";
    return kExitUsage;
  }
  if (options.volume && spec->kind == mesh_gen::OrganKind::kOpenSurface) {
    err << "somasim-mesh: " << spec->name << " is an open surface patch: it bounds no volume\n";
    return kExitUsage;
  }
  try {
    MeshData m = LoadMesh(std::string(kBuiltinPrefix) + std::string(spec->name), {});
    if (options.volume && m.tetrahedra.cols() == 0) {
      mesh::TetMesh volume = mesh_gen::GenerateBuiltinOrganVolume(spec->name);
      m.vertices = std::move(volume.vertices);
      m.tetrahedra = std::move(volume.tetrahedra);
      m.triangles.resize(3, 0);
    }
    if (options.surface && m.tetrahedra.cols() > 0) {
      const mesh::SurfaceMesh boundary =
          mesh::CompactSurface(mesh::ExtractBoundarySurface({m.vertices, m.tetrahedra}), nullptr);
      m.vertices = boundary.vertices;
      m.triangles = boundary.triangles;
      m.tetrahedra.resize(4, 0);
    }
    const mesh_io::WriteReport report = mesh_io::WriteMeshFile(options.output, m, options.write);
    out << "wrote " << report.files << ": " << spec->name << ", " << m.vertices.cols() << " nodes, "
        << m.tetrahedra.cols() << " tetrahedra, " << m.triangles.cols() << " triangles (in "
        << mesh_io::UnitName(options.write.unit) << ")\n";
    if (report.wrote_boundary_surface) {
      out << "note: the output format holds no tetrahedra; wrote the boundary surface\n";
    }
    return kExitOk;
  } catch (const MeshError& e) {
    err << "somasim-mesh: " << e.what() << "\n";
    return mesh_io::ExitCodeOf(e);
  }
}

int RunInfo(const InfoOptions& options, std::ostream& out, std::ostream& err) {
  try {
    const MeshData m = LoadMesh(options.file, options.read);
    const MeshSummary s = Summarise(m);
    if (options.json) {
      out << ToJson(options.file, m, options.read, s).dump(2) << "\n";
    } else {
      PrintText(out, options.file, m, options.read, s);
    }
    return kExitOk;
  } catch (const MeshError& e) {
    err << "somasim-mesh: " << e.what() << "\n";
    return mesh_io::ExitCodeOf(e);
  }
}

int RunConvert(const ConvertOptions& options, std::ostream& out, std::ostream& err) {
  try {
    const MeshData m = LoadMesh(options.input, options.read);
    const mesh_io::WriteReport report = mesh_io::WriteMeshFile(options.output, m, options.write);
    out << "wrote " << report.files << ": " << m.vertices.cols() << " nodes, "
        << m.tetrahedra.cols() << " tetrahedra, " << m.triangles.cols() << " triangles ("
        << m.format << " read as " << mesh_io::UnitName(options.read.unit) << ", written in "
        << mesh_io::UnitName(options.write.unit) << ")\n";
    if (report.wrote_boundary_surface) {
      out << "note: the output format holds no tetrahedra; wrote the boundary surface of the "
             "volume mesh\n";
    }
    for (const auto& k : m.skipped) {
      out << "note: skipped " << k.count << " " << k.type << " (not a triangle or tetrahedron)\n";
    }
    return kExitOk;
  } catch (const MeshError& e) {
    err << "somasim-mesh: " << e.what() << "\n";
    return mesh_io::ExitCodeOf(e);
  }
}

int RunTetrahedralize(const TetrahedralizeOptions& options, std::ostream& out, std::ostream& err) {
  if (!(options.radius_edge_ratio > 1.0) || !std::isfinite(options.radius_edge_ratio)) {
    err << "somasim-mesh: --quality must be a radius-edge ratio > 1 (got "
        << options.radius_edge_ratio << ")\n";
    return kExitUsage;
  }
  if (!(options.max_volume_m3 >= 0.0) || !std::isfinite(options.max_volume_m3)) {
    err << "somasim-mesh: --max-volume must be >= 0 m^3\n";
    return kExitUsage;
  }
  const std::optional<mesh_io::FileFormat> out_format = mesh_io::FormatFromPath(options.output);
  if (!out_format || !mesh_io::FormatHoldsTetrahedra(*out_format)) {
    err << "somasim-mesh: " << options.output
        << ": the output must be a format that holds tetrahedra (.vtk .vtu .msh .node)\n";
    return kExitUsage;
  }
  try {
    const MeshData in = LoadMesh(options.input, options.read);
    mesh::SurfaceMesh surface = in.tetrahedra.cols() > 0
                                    ? mesh::ExtractBoundarySurface({in.vertices, in.tetrahedra})
                                    : mesh::SurfaceMesh{in.vertices, in.triangles};
    surface = mesh::CompactSurface(surface, nullptr);
    const mesh::SurfaceTopology topo = mesh::AnalyseSurfaceTopology(surface);
    if (!topo.watertight || !topo.manifold) {
      err << "somasim-mesh: " << options.input
          << ": the surface is not closed and manifold, so it bounds no volume (boundary edges "
          << topo.num_boundary_edges << ", non-manifold edges " << topo.num_nonmanifold_edges
          << ", non-manifold vertices " << topo.num_nonmanifold_vertices << ", misoriented edges "
          << topo.num_misoriented_edges << ")\n";
      return kExitTetrahedralize;
    }
    if (mesh::SurfaceEnclosedVolume(surface) < 0) {
      surface.triangles.row(1).swap(surface.triangles.row(2));  // inward-facing: turn it
    }

    std::string pattern = (std::filesystem::temp_directory_path() / "somasim-tetgen-XXXXXX");
    if (mkdtemp(pattern.data()) == nullptr) {
      throw MeshError(MeshErrorKind::kIo, pattern, {}, "cannot create a temporary directory");
    }
    const std::filesystem::path dir = pattern;
    // TetGen's scratch folder goes however this ends (an error reading its output included).
    struct RemoveWhenDone {
      const std::filesystem::path& path;
      ~RemoveWhenDone() {
        std::error_code ignored;  // nothing to tell: the result is already out
        std::filesystem::remove_all(path, ignored);
      }
    } const remove_when_done{dir};
    const std::string smesh = (dir / "surface.smesh").string();
    {
      std::ofstream f(smesh, std::ios::binary);
      f << WriteSmesh(surface);
      if (!f.good()) throw MeshError(MeshErrorKind::kIo, smesh, {}, "cannot write");
    }
    // -p mesh the surface (a PLC), -z 0-based output, -Q quiet, -q radius-edge bound, -a volume.
    std::string switches = "-pzQq" + mesh_io::FormatDouble(options.radius_edge_ratio);
    if (options.max_volume_m3 > 0) switches += "a" + mesh_io::FormatDouble(options.max_volume_m3);
    const std::string log = (dir / "tetgen.log").string();
    std::string error;
    const int status = RunProgram({options.tetgen, switches, smesh}, log, &error);
    if (status != 0) {
      err << "somasim-mesh: tetgen failed on " << options.input << ": "
          << (status < 0 ? error : "exit status " + std::to_string(status)) << "\n"
          << Tail(log, 8);
      return kExitTetrahedralize;
    }
    mesh_io::ReadOptions tetgen_read;  // TetGen wrote metres, our own surface's unit
    MeshData volume = mesh_io::ReadMeshFile((dir / "surface.1.node").string(), tetgen_read);
    volume.format = "TetGen (" + switches + ")";
    volume.triangles.resize(3, 0);  // keep the tetrahedra; the boundary follows from them
    const mesh_io::WriteReport report =
        mesh_io::WriteMeshFile(options.output, volume, options.write);
    const MeshSummary s = Summarise(volume);
    out << "wrote " << report.files << ": " << s.nodes << " nodes, " << s.tetrahedra
        << " tetrahedra (tetgen " << switches << "); volume " << s.volume_m3.value_or(0)
        << " m^3 vs enclosed " << mesh::SurfaceEnclosedVolume(surface) << " m^3; min dihedral "
        << (s.quality ? s.quality->min_dihedral_deg : 0.0) << " deg\n";
    return kExitOk;
  } catch (const MeshError& e) {
    err << "somasim-mesh: " << e.what() << "\n";
    return mesh_io::ExitCodeOf(e);
  } catch (const std::filesystem::filesystem_error& e) {
    err << "somasim-mesh: " << e.what() << "\n";
    return kExitIo;
  }
}

}  // namespace somasim::tools
