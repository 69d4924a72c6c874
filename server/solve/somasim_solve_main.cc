// somasim-solve: runs a scene's analysis offline and writes its results (SPEC §6).
//   somasim-solve SCENE --out DIR
// SCENE is a *.scene.txtpb file or builtin:NAME (the organ's default scene). Writes
// DIR/<organ>_<output index>.vtu (point data displacement [m], reaction_force [N], input node
// order) and DIR/<organ>_history.csv, and prints one JSON object (docs/solve.md).
// Exit codes: 0 solved, 1 did not converge (the JSON says where), 2 bad command line, 3 bad
// scene or mesh, 4 a file could not be read or written, 70 a bug.
#include <CLI/CLI.hpp>
#include <exception>
#include <filesystem>
#include <iostream>

#include "common/app/blas_kernels.h"
#include "common/app/exit_codes.h"
#include "common/mesh_io/mesh_error.h"
#include "common/scene/scene.h"
#include "server/organs/file_errors.h"
#include "server/solve/solve_runner.h"

#ifndef SOMASIM_VERSION
#define SOMASIM_VERSION "unknown"
#endif

namespace {

using somasim::app::kExitBadInput;
using somasim::app::kExitBug;
using somasim::app::kExitFailed;
using somasim::app::kExitIo;
using somasim::app::kExitOk;
using somasim::app::kExitUsage;

int RunMain(int argc, char** argv) {
  CLI::App app{
      "somasim-solve: run a scene's static, quasi-static or dynamic analysis offline; write VTU "
      "results and print a JSON summary"};
  std::string scene_arg, out_dir;
  app.add_option("scene", scene_arg, "Scene file (*.scene.txtpb) or builtin:NAME")->required();
  app.add_option("--out", out_dir, "Folder for the results (created if missing)")->required();
  app.set_version_flag("--version", std::string("somasim-solve ") + SOMASIM_VERSION);
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForVersion& e) {
    return app.exit(e);
  } catch (const CLI::ParseError& e) {
    app.exit(e);
    return kExitUsage;
  }
  // CHOLMOD's factorisations are most of the work: the CPU's own BLAS kernels, not the generic
  // ones Debian's OpenBLAS falls back to on CPUs it does not know (common/app/blas_kernels.h;
  // after the command line is parsed: --help and --version need no kernels).
  somasim::app::PreferFastBlasKernels("somasim-solve", argv);
  try {
    somasim::scene::SceneLines lines;
    somasim::scene::Scene scene;
    somasim::solve::SolveOptions options;
    options.out_dir = out_dir;
    constexpr std::string_view kBuiltin = "builtin:";
    if (scene_arg.rfind(kBuiltin, 0) == 0) {
      try {
        scene = somasim::scene::DefaultScene(scene_arg.substr(kBuiltin.size()));
      } catch (const std::invalid_argument& e) {
        std::cerr << "somasim-solve: " << e.what() << "\n";
        return kExitBadInput;
      }
      lines = somasim::scene::SceneLines(scene_arg);
    } else {
      scene = somasim::scene::LoadSceneFile(scene_arg, &lines);
      options.scene_dir = std::filesystem::path(scene_arg).parent_path().string();
      if (options.scene_dir.empty()) options.scene_dir = ".";
    }
    const somasim::solve::SolveSummary summary = somasim::solve::RunSolve(scene, lines, options);
    std::cout << somasim::solve::SummaryJson(summary).dump(2) << "\n";
    return summary.converged ? kExitOk : kExitFailed;
  } catch (const std::runtime_error&) {
    return somasim::organs::ReportFileError("somasim-solve", kExitIo);
  }
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return RunMain(argc, argv);
  } catch (const std::exception& e) {
    std::cerr << "somasim-solve: internal error: " << e.what() << "\n";
    return kExitBug;
  }
}
