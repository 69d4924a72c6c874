// somasim-solve's engine (SPEC §6): runs a scene's analysis — static (Newton with load steps;
// the linear EFG model and its hybrid: one solve per output time), quasi-static (viscoelastic
// creep/relaxation without inertia) or dynamic (each model's Step) — on every organ, writes
// DIR/<organ>_<output index>.vtu with point data `displacement` [m] in the input mesh's node
// order, a DIR/<organ>_history.csv of the run, and returns the summary that the tool prints as
// one JSON object. Organs do not touch one another (contact arrives with issue 6), so each organ
// is solved on its own.
#pragma once

#include <Eigen/Core>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/scene/scene.h"

namespace somasim::solve {

struct SolveOptions {
  std::string scene_dir = ".";  // where the scene's mesh files are looked up
  std::string out_dir;          // created if missing; empty: write no files
};

// The force the supports exert on the organ through a held region [N] at the end of the run:
// the sum over its nodes of the reaction (static and quasi-static: the equilibrium residual;
// dynamic: -(elastic + external + gravity) forces, inertia and damping left out).
struct Reaction {
  std::string region;  // "organ[0].fixed[1]" or "load[2]" (a displacement load)
  int nodes = 0;
  Eigen::Vector3d force = Eigen::Vector3d::Zero();
};

struct OutputRecord {
  double time = 0.0;  // [s]
  std::string file;   // the VTU written, or empty
  double max_displacement_m = 0.0;
};

struct OrganSummary {
  std::string id, model, mesh, unit;
  int64_t nodes = 0, tetrahedra = 0, triangles = 0, unused_nodes = 0;
  double max_displacement_m = 0.0;  // at the end [m]
  int newton_iterations = 0;        // static and quasi-static, summed over all solves
  int64_t solver_iterations = 0;    // dynamic: the model's linear or constraint solver
  int64_t steps = 0, rejected_steps = 0;
  double final_residual = 0.0;  // the last solve's relative residual
  bool converged = true;
  std::vector<Reaction> reactions;
  std::vector<OutputRecord> outputs;
  std::string history_file;
};

struct SolveSummary {
  std::string scene, analysis;  // analysis: "static", "quasi_static", "dynamic"
  std::vector<OrganSummary> organs;
  double max_displacement_m = 0.0;  // over all organs, at the end
  int newton_iterations = 0;        // over all organs
  double final_residual = 0.0;      // the largest of the organs'
  bool converged = true;
  double wall_time_s = 0.0;
};

// Runs the scene. Throws scene::SceneError for faults that only its meshes reveal (and for a
// scene without an analysis), mesh_io::MeshError for a mesh file that cannot be read, and
// std::runtime_error when an output cannot be written. A solve that does not converge is not an
// error: it is reported (converged = false).
SolveSummary RunSolve(const scene::Scene& scene, const scene::SceneLines& lines,
                      const SolveOptions& options);

// The JSON that somasim-solve prints: max_displacement_m, newton_iterations, final_residual,
// wall_time_s, converged, analysis, and per organ the same with reactions and outputs.
nlohmann::json SummaryJson(const SolveSummary& summary);

}  // namespace somasim::solve
