// somasim-mesh: inspect, convert and tetrahedralise mesh files.
//   somasim-mesh info FILE [--unit m|cm|mm] [--json] [--fix-orientation]
//   somasim-mesh convert IN OUT [--unit U] [--out-unit U] [--binary] [--msh-version V] ...
//   somasim-mesh tetrahedralize SURFACE OUT [--quality Q] [--max-volume V] ...
#include <CLI/CLI.hpp>
#include <exception>
#include <iostream>
#include <map>
#include <tuple>

#include "common/tools/mesh_commands.h"
#include "common/tools/render_command.h"

namespace {

using somasim::mesh_io::GmshVersion;
using somasim::mesh_io::Unit;

const std::map<std::string, Unit> kUnits = {
    {"m", Unit::kMetre}, {"cm", Unit::kCentimetre}, {"mm", Unit::kMillimetre}};

void AddReadOptions(CLI::App* cmd, somasim::mesh_io::ReadOptions* read) {
  cmd->add_option("--unit", read->unit, "Unit of the input's coordinates (default m)")
      ->transform(CLI::CheckedTransformer(kUnits, CLI::ignore_case));
  cmd->add_flag("--fix-orientation", read->fix_orientation,
                "Flip inverted tetrahedra instead of refusing the file");
}

void AddWriteOptions(CLI::App* cmd, somasim::mesh_io::WriteOptions* write) {
  cmd->add_option("--out-unit", write->unit, "Unit of the written coordinates (default m)")
      ->transform(CLI::CheckedTransformer(kUnits, CLI::ignore_case));
  cmd->add_flag_callback(
      "--binary", [write] { write->encoding = somasim::mesh_io::Encoding::kBinary; },
      "Binary encoding (STL, legacy VTK, Gmsh 2.2/4.1, VTU appended raw)");
  cmd->add_option("--msh-version", write->gmsh_version, "Gmsh output version: 1, 2.2 or 4.1")
      ->transform(CLI::CheckedTransformer(
          std::map<std::string, GmshVersion>{
              {"1", GmshVersion::kV1}, {"2.2", GmshVersion::kV22}, {"4.1", GmshVersion::kV41}},
          CLI::ignore_case));
  cmd->add_flag("--vtu-base64", write->vtu_base64,
                "VTU binary as inline base64 instead of appended raw data (with --binary)");
  cmd->add_flag("--big-endian", write->big_endian, "VTU binary data in big-endian byte order");
}

int RunMain(int argc, char** argv) {
  CLI::App app{
      "somasim-mesh: inspect, convert and tetrahedralise mesh files (OBJ, STL, legacy "
      "VTK, VTU, Gmsh .msh 1/2.2/4.1, TetGen .node/.ele/.face) and generate the built-in "
      "organs. Wherever a mesh file is expected, builtin:NAME names a built-in organ."};
  app.require_subcommand(1);

  somasim::tools::InfoOptions info;
  CLI::App* info_cmd = app.add_subcommand("info",
                                          "Counts, bounding box, volume, quality, "
                                          "watertightness of a mesh file");
  info_cmd->add_option("file", info.file, "Mesh file")->required();
  info_cmd->add_flag("--json", info.json, "Print one JSON object");
  AddReadOptions(info_cmd, &info.read);

  somasim::tools::ConvertOptions convert;
  CLI::App* convert_cmd =
      app.add_subcommand("convert", "Convert between formats (chosen by the file extensions)");
  convert_cmd->add_option("input", convert.input, "Input mesh file")->required();
  convert_cmd->add_option("output", convert.output, "Output mesh file")->required();
  AddReadOptions(convert_cmd, &convert.read);
  AddWriteOptions(convert_cmd, &convert.write);

  somasim::tools::TetrahedralizeOptions tet;
  CLI::App* tet_cmd = app.add_subcommand(
      "tetrahedralize", "Fill a closed surface with tetrahedra (runs the external tetgen program)");
  tet_cmd->add_option("surface", tet.input, "Closed surface mesh file")->required();
  tet_cmd->add_option("output", tet.output, "Output volume mesh (.vtk .vtu .msh .node)")
      ->required();
  tet_cmd->add_option("--quality", tet.radius_edge_ratio,
                      "Radius-edge ratio bound, > 1 (TetGen -q; default 1.414)");
  tet_cmd->add_option(
      "--max-volume", tet.max_volume_m3,
      "Target largest tetrahedron volume in m^3 (TetGen -a, approximate; default none)");
  tet_cmd->add_option("--tetgen", tet.tetgen, "The tetgen program (default: tetgen on PATH)");
  AddReadOptions(tet_cmd, &tet.read);
  AddWriteOptions(tet_cmd, &tet.write);

  somasim::tools::ListOptions list;
  CLI::App* list_cmd =
      app.add_subcommand("list", "The built-in organs with their node and element counts");
  list_cmd->add_flag("--json", list.json, "Print a JSON array");

  somasim::tools::GenerateOptions generate;
  CLI::App* generate_cmd = app.add_subcommand(
      "generate", "Write a built-in organ in any supported format (chosen by the extension)");
  generate_cmd->add_option("name", generate.name, "Built-in organ (see: somasim-mesh list)")
      ->required();
  generate_cmd->add_option("output", generate.output, "Output mesh file")->required();
  generate_cmd->add_flag("--surface", generate.surface,
                         "Write a volume organ's boundary surface instead of its tetrahedra");
  generate_cmd->add_flag("--volume", generate.volume,
                         "Write a closed surface organ filled with tetrahedra (isosurface "
                         "stuffing of its shape; dihedral angles >= 10.7 deg)");
  AddWriteOptions(generate_cmd, &generate.write);

  somasim::tools::RenderCommandOptions render;
  std::string render_size, render_view, render_up;
  bool render_no_edges = false;
  CLI::App* render_cmd = app.add_subcommand(
      "render", "Draw a mesh to a PNG picture (software rendering, no display needed)");
  render_cmd->add_option("input", render.input, "Mesh file or builtin:NAME")->required();
  render_cmd->add_option("output", render.output, "PNG file to write")->required();
  render_cmd->add_option("--size", render_size, "Picture size WIDTHxHEIGHT (default 800x600)");
  render_cmd->add_option("--view", render_view,
                         "Viewing direction x,y,z, from the camera towards the mesh; write "
                         "--view=-1,0,-1 when it starts with a minus");
  render_cmd->add_option("--up", render_up, "Direction shown upwards x,y,z (default 0,1,0)");
  render_cmd->add_flag("--no-edges", render_no_edges, "Do not draw the triangle edges");
  AddReadOptions(render_cmd, &render.read);

  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
    return app.exit(e);
  } catch (const CLI::ParseError& e) {
    app.exit(e);
    return somasim::tools::kExitUsage;
  }

  try {
    if (*info_cmd) return somasim::tools::RunInfo(info, std::cout, std::cerr);
    if (*convert_cmd) return somasim::tools::RunConvert(convert, std::cout, std::cerr);
    if (*tet_cmd) return somasim::tools::RunTetrahedralize(tet, std::cout, std::cerr);
    if (*render_cmd) {
      if (!render_size.empty()) {
        const auto size = somasim::tools::ParseImageSize(render_size);
        if (!size) {
          std::cerr << "somasim-mesh: --size must look like 800x600 (got \"" << render_size
                    << "\")\n";
          return somasim::tools::kExitUsage;
        }
        render.width = size->first;
        render.height = size->second;
      }
      for (const auto& [text, target, name] : {std::tuple{&render_view, &render.view, "--view"},
                                               std::tuple{&render_up, &render.up, "--up"}}) {
        if (text->empty()) continue;
        *target = somasim::tools::ParseVector3(*text);
        if (!*target) {
          std::cerr << "somasim-mesh: " << name << " must be three numbers x,y,z (got \"" << *text
                    << "\")\n";
          return somasim::tools::kExitUsage;
        }
      }
      render.edges = !render_no_edges;
      return somasim::tools::RunRender(render, std::cout, std::cerr);
    }
    if (*list_cmd) return somasim::tools::RunList(list, std::cout, std::cerr);
    if (*generate_cmd) return somasim::tools::RunGenerate(generate, std::cout, std::cerr);
  } catch (const std::exception& e) {
    std::cerr << "somasim-mesh: internal error: " << e.what() << "\n";
    return somasim::tools::kExitBug;
  }
  return somasim::tools::kExitUsage;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return RunMain(argc, argv);
  } catch (...) {
    // Nothing may escape main (CLI11's own set-up can throw); say so and fail.
    std::cerr << "somasim-mesh: internal error\n";
    return somasim::tools::kExitBug;
  }
}
