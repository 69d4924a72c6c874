// The commands of somasim-mesh, as functions returning a process exit code, so that tests can
// call them without a shell. The CLI parsing lives in somasim_mesh_main.cc.
#pragma once

#include <iosfwd>
#include <optional>
#include <string>
#include <string_view>

#include "common/app/exit_codes.h"
#include "common/mesh_io/mesh_io.h"

namespace somasim::tools {

// Exit codes (all in 1..125, as shells and CTest expect).
using app::kExitBadInput;  // exit codes: common/app/exit_codes.h
using app::kExitBug;
using app::kExitIo;
using app::kExitOk;
using app::kExitTetrahedralize;
using app::kExitUsage;

struct InfoOptions {
  std::string file;
  mesh_io::ReadOptions read;
  bool json = false;
};

struct ConvertOptions {
  std::string input;
  std::string output;
  mesh_io::ReadOptions read;
  mesh_io::WriteOptions write;
};

struct TetrahedralizeOptions {
  std::string input;   // a closed surface (or a volume mesh, whose boundary is used)
  std::string output;  // any format that holds tetrahedra
  mesh_io::ReadOptions read;
  mesh_io::WriteOptions write;
  double radius_edge_ratio = 1.414;  // TetGen -q bound, > 1 (smaller = better shaped, more tets)
  double max_volume_m3 = 0.0;        // TetGen -a bound [m³]; 0 = none
  std::string tetgen = "tetgen";     // the TetGen program (AGPL: run, never linked)
};

struct ListOptions {
  bool json = false;
};

struct GenerateOptions {
  std::string name;    // a built-in organ or its alias (somasim-mesh list)
  std::string output;  // any supported format
  mesh_io::WriteOptions write;
  bool surface = false;  // write a volume organ's boundary surface instead of its tetrahedra
  bool volume = false;   // write a closed surface organ filled with tetrahedra (stuffing)
};

// The prefix that names a built-in organ wherever a mesh file is expected: "builtin:liver".
inline constexpr std::string_view kBuiltinPrefix = "builtin:";

// Reads a mesh file, or generates the built-in organ for "builtin:NAME" (always in metres, so
// a unit other than metres is refused). Throws mesh_io::MeshError: kIo for an unknown organ or an
// unreadable file, other kinds for a malformed file.
mesh_io::MeshData LoadMesh(const std::string& path, const mesh_io::ReadOptions& read);

int RunInfo(const InfoOptions& options, std::ostream& out, std::ostream& err);
int RunList(const ListOptions& options, std::ostream& out, std::ostream& err);
int RunGenerate(const GenerateOptions& options, std::ostream& out, std::ostream& err);
int RunConvert(const ConvertOptions& options, std::ostream& out, std::ostream& err);
int RunTetrahedralize(const TetrahedralizeOptions& options, std::ostream& out, std::ostream& err);

}  // namespace somasim::tools
