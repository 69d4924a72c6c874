// somasim-reduce: makes a reduced model of a scene's organ from its full FEM model (issue 12;
// docs/reduced.md).
//   somasim-reduce SCENE --out FILE.somared [--nonlinear-out NL.somared] [--organ ID]
//   somasim-reduce SCENE --evaluate FILE.somared --plan PLAN.txtpb [--per-step CSV] [--organ ID]
// SCENE is a *.scene.txtpb with a `reduction` block (the sampling plan) for the organ. Prints
// progress on stderr and one JSON object on stdout: the modes, eigenvalues, candidates for K
// with their errors, creep curves, the build's wall time. --evaluate prints the evaluation
// table (markdown) of the plan's cases instead (--per-step: and each step's errors as CSV).
// Exit codes: 0 written, 1 the build failed (no full solve converged), 2 bad command line,
// 3 bad scene or mesh, 4 a file could not be read or written (FILE exists: never overwritten),
// 70 a bug.
#include <google/protobuf/text_format.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <exception>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>

#include "common/app/blas_kernels.h"
#include "common/app/exit_codes.h"
#include "common/mesh/topology.h"
#include "common/mesh_io/mesh_error.h"
#include "common/scene/scene.h"
#include "server/organs/file_errors.h"
#include "server/organs/organ_builder.h"
#include "server/organs/reduced_file.h"
#include "server/reduce/builder.h"
#include "server/reduce/evaluate.h"

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

namespace scene = somasim::scene;
namespace reduce = somasim::reduce;
namespace organs = somasim::organs;
namespace models = somasim::models;

// Up to `count` nodes of `candidates` spread out: the one nearest their centroid first, then
// each time the one farthest from those chosen (all of them when count is 0 or larger).
std::vector<int32_t> Spread(const std::vector<int32_t>& candidates, const somasim::mesh::Points& x,
                            size_t count) {
  if (count == 0 || count >= candidates.size()) return candidates;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  for (const int32_t c : candidates) centroid += x.col(c);
  centroid /= static_cast<double>(candidates.size());
  std::vector<double> distance(candidates.size());
  for (size_t k = 0; k < candidates.size(); ++k) {
    distance[k] = -(x.col(candidates[k]) - centroid).norm();  // nearest first
  }
  std::vector<int32_t> chosen;
  while (chosen.size() < count) {
    const size_t best =
        static_cast<size_t>(std::max_element(distance.begin(), distance.end()) - distance.begin());
    const int32_t node = candidates[best];
    chosen.push_back(node);
    for (size_t k = 0; k < candidates.size(); ++k) {
      const double d = (x.col(candidates[k]) - x.col(node)).norm();
      distance[k] = chosen.size() == 1 ? d : std::min(distance[k], d);
    }
    distance[best] = -1.0;
  }
  return chosen;
}

// --evaluate: the reduced model against the scene's full model on the plan's cases.
int RunEvaluation(const scene::Scene& s, const scene::SceneLines& lines,
                  const std::string& scene_dir, const std::string& organ_id,
                  const std::string& model_file, const std::string& plan_file,
                  const std::string& per_step_file) {
  int organ_index = -1;
  for (int k = 0; k < s.organ_size(); ++k) {
    if (s.organ(k).id() == organ_id || (organ_id.empty() && organ_index < 0)) organ_index = k;
  }
  if (organ_index < 0) {
    std::cerr << "somasim-reduce: no organ \"" << organ_id << "\" in the scene\n";
    return kExitBadInput;
  }
  const somasim::organs::BuiltOrgan organ =
      somasim::organs::BuildOrgan(s, organ_index, lines, scene_dir);
  if (organ.fem == nullptr) {
    std::cerr << "somasim-reduce: " << organ.field << " (" << organ.id
              << ") is not a FEM model: nothing to compare with\n";
    return kExitBadInput;
  }
  if (!per_step_file.empty() && std::filesystem::exists(per_step_file)) {
    std::cerr << "somasim-reduce: " << per_step_file << " exists (never overwritten)\n";
    return kExitIo;
  }
  const organs::LoadedReducedModel loaded = organs::LoadReducedModel(model_file, &organ.volume);
  std::ifstream in(plan_file);
  if (!in) {
    std::cerr << "somasim-reduce: cannot read " << plan_file << "\n";
    return kExitIo;
  }
  std::ostringstream text;
  text << in.rdbuf();
  somasim::reduced::EvaluationPlan plan;
  if (!google::protobuf::TextFormat::ParseFromString(text.str(), &plan)) {
    std::cerr << "somasim-reduce: " << plan_file << " is not an evaluation plan (text format)\n";
    return kExitBadInput;
  }
  try {
    reduce::CheckPlan(plan, organ.fem->num_nodes(), organ.fixed_nodes);
  } catch (const std::invalid_argument& e) {
    std::cerr << "somasim-reduce: " << plan_file << ": " << e.what() << "\n";
    return kExitBadInput;
  }
  const auto started = std::chrono::steady_clock::now();
  const models::TissueModel& reduced = loaded.model != nullptr
                                           ? static_cast<const models::TissueModel&>(*loaded.model)
                                           : *loaded.nonlinear;
  const std::vector<reduce::CaseResult> results =
      reduce::Evaluate(*organ.fem, organ.fixed_nodes, reduced, plan, &loaded.modes());
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  const std::string what =
      loaded.nonlinear != nullptr
          ? std::string(loaded.nonlinear->petrov_galerkin() ? "nonlinear Petrov–Galerkin"
                                                            : "nonlinear") +
                ", ECSW on " + std::to_string(loaded.nonlinear->num_elements()) + " elements"
          : loaded.metadata.stiffness();
  std::printf("Reduced model %s (%s, %d modes; %s) against the full model of %s, plan %s\n\n",
              model_file.c_str(), loaded.metadata.kind().c_str(), loaded.num_modes(), what.c_str(),
              organ.id.c_str(), plan_file.c_str());
  std::printf(
      "| case | group | steps | field L2 error | loaded-node error | basis floor | "
      "|u| full [mm] | |u| reduced [mm] | reduced step [µs] |\n"
      "|---|---|---|---|---|---|---|---|---|\n");
  bool all_converged = true;
  for (const reduce::CaseResult& r : results) {
    std::string notes;
    if (!r.converged) notes += " (a full step did not converge)";
    if (r.reduced_unconverged > 0) {
      notes += " (" + std::to_string(r.reduced_unconverged) + " reduced steps unconverged)";
    }
    std::printf("| %s | %s | %d | %.1f %% | %.1f %% | %.1f %% | %.3f | %.3f | %.0f |%s\n",
                r.name.c_str(), r.group.c_str(), r.steps, 100.0 * r.field_error,
                100.0 * r.node_error, 100.0 * r.basis_error, 1e3 * r.full_end_m,
                1e3 * r.reduced_end_m, r.reduced_step_us, notes.c_str());
    all_converged = all_converged && r.converged;
  }
  std::printf("\nwall time %.1f s\n", seconds);
  if (!per_step_file.empty()) {
    // One row per case and step: the curves behind the table.
    std::ofstream csv(per_step_file);
    csv << "case,time_s,scale,field_error,near_error,far_error,basis_error,"
           "node_full_x_m,node_full_y_m,node_full_z_m,node_reduced_x_m,node_reduced_y_m,"
           "node_reduced_z_m\n";
    csv.precision(9);
    for (const reduce::CaseResult& r : results) {
      for (const reduce::StepRecord& p : r.per_step) {
        csv << '"' << r.name << "\"," << p.time_s << ',' << p.scale << ',' << p.field_error << ','
            << p.near_error << ',' << p.far_error << ',' << p.basis_error << ','
            << p.node_full_m.x() << ',' << p.node_full_m.y() << ',' << p.node_full_m.z() << ','
            << p.node_reduced_m.x() << ',' << p.node_reduced_m.y() << ',' << p.node_reduced_m.z()
            << '\n';
      }
    }
    csv.flush();
    if (!csv) {
      std::cerr << "somasim-reduce: cannot write " << per_step_file << "\n";
      return kExitIo;
    }
  }
  return all_converged ? kExitOk : kExitFailed;
}

struct Args {
  std::string scene, out_file, organ_id, evaluate_file, plan_file, nonlinear_file, per_step_file;
  std::string command;  // the whole command line, for the file's metadata
};

// The command line into `a`; an exit code when the program ends here, else -1.
int ParseArgs(int argc, char** argv, Args* a) {
  CLI::App app{
      "somasim-reduce: make a reduced model (seed 000's Karhunen-Loeve model) of a scene's organ "
      "from its full FEM model, by the scene's sampling plan (its reduction block)"};
  app.add_option("scene", a->scene, "Scene file (*.scene.txtpb) with a reduction block")
      ->required();
  auto* out_option = app.add_option("--out", a->out_file,
                                    "The reduced model to write (*.somared; must not exist)");
  app.add_option("--nonlinear-out", a->nonlinear_file,
                 "Also write the nonlinear reduced model (ECSW) made from the same snapshots "
                 "(*.somared; must not exist; hyperelastic organs)")
      ->needs(out_option);
  app.add_option("--organ", a->organ_id, "The organ to reduce (default: the first reduction's)");
  auto* evaluate_option = app.add_option(
      "--evaluate", a->evaluate_file,
      "Instead of building: compare this reduced model with the scene's full model on --plan");
  app.add_option("--plan", a->plan_file, "The evaluation plan (*.txtpb, EvaluationPlan)")
      ->needs(evaluate_option);
  app.add_option("--per-step", a->per_step_file,
                 "With --evaluate: also write each case's per-step errors to this CSV file "
                 "(never overwritten)")
      ->needs(evaluate_option);
  evaluate_option->excludes(out_option);
  app.set_version_flag("--version", std::string("somasim-reduce ") + SOMASIM_VERSION);
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
  if (a->evaluate_file.empty() && a->out_file.empty()) {
    std::cerr << "somasim-reduce: give --out FILE (build) or --evaluate FILE --plan PLAN\n";
    return kExitUsage;
  }
  if (!a->evaluate_file.empty() && a->plan_file.empty()) {
    std::cerr << "somasim-reduce: --evaluate needs --plan\n";
    return kExitUsage;
  }
  for (int k = 0; k < argc; ++k) a->command += (k > 0 ? " " : "") + std::string(argv[k]);
  return -1;
}

// The sampling plan of reduction `plan_index` for `organ`: the boundary nodes of each
// interaction region that are not held, spread; the loads and the reduction's settings.
reduce::SamplingPlan MakePlan(const scene::Reduction& r, int plan_index,
                              const organs::BuiltOrgan& organ, const scene::SceneLines& lines) {
  reduce::SamplingPlan plan;
  plan.fixed = organ.fixed_nodes;
  const somasim::mesh::Points normals = reduce::BoundaryNormals(organ.volume);
  const std::set<int32_t> held(plan.fixed.begin(), plan.fixed.end());
  const std::string field = "reduction[" + std::to_string(plan_index) + "]";
  for (int i = 0; i < r.interaction_size(); ++i) {
    const std::string where = field + ".interaction[" + std::to_string(i) + "]";
    std::vector<int32_t> candidates;
    for (const int32_t n : organs::SelectRegion(r.interaction(i), organ.rest(), where, lines)) {
      if (held.count(n) == 0 && normals.col(n).squaredNorm() > 0.5) candidates.push_back(n);
    }
    if (candidates.empty()) throw lines.Error(where, "holds no free boundary node to load");
    const std::vector<int32_t> chosen =
        Spread(candidates, organ.rest(),
               static_cast<size_t>(r.points_per_region() > 0 ? r.points_per_region() : 6));
    plan.points.insert(plan.points.end(), chosen.begin(), chosen.end());
    plan.region_nodes.insert(plan.region_nodes.end(), candidates.begin(), candidates.end());
  }
  if (r.force_size() > 0) plan.forces.assign(r.force().begin(), r.force().end());
  if (r.directions() != 0) plan.directions = r.directions();
  if (r.creep_duration() > 0.0) plan.creep_duration = r.creep_duration();
  if (r.creep_interval() > 0.0) plan.creep_interval = r.creep_interval();
  if (r.energy_fraction() > 0.0) plan.pod.energy_fraction = r.energy_fraction();
  if (r.max_modes() > 0) plan.pod.max_modes = r.max_modes();
  if (r.creep_radius() > 0.0) plan.creep_radius = r.creep_radius();
  plan.nonlinear_pod.energy_fraction = plan.pod.energy_fraction;
  if (r.nonlinear_max_modes() > 0) plan.nonlinear_pod.max_modes = r.nonlinear_max_modes();
  plan.energy_inner_product = r.nonlinear_inner_product() == scene::Reduction::ENERGY;
  plan.petrov_galerkin = r.nonlinear_projection() == scene::Reduction::PETROV_GALERKIN;
  if (r.cubature_tolerance() > 0.0) {
    plan.cubature.tolerance = r.cubature_tolerance();
  } else if (plan.petrov_galerkin) {
    plan.cubature.tolerance = 0.001;  // what a Petrov–Galerkin model needs (builder.h)
  }
  if (r.nonlinear_tilts() > 0) plan.tilts = r.nonlinear_tilts();
  if (r.nonlinear_tilt_deg() > 0.0) plan.tilt_deg = r.nonlinear_tilt_deg();
  plan.nonlinear_forces.assign(r.nonlinear_force().begin(), r.nonlinear_force().end());
  return plan;
}

// The Karhunen–Loève model's file metadata: what was reduced, how, by which command.
somasim::reduced::ReducedModelMetadata KlMetadata(const Args& a, const scene::Organ& scene_organ,
                                                  const organs::BuiltOrgan& organ,
                                                  const reduce::BuildReport& report) {
  somasim::reduced::ReducedModelMetadata m;
  m.set_kind("kl_seed000");
  m.set_software_version(SOMASIM_VERSION);
  m.set_command(a.command);
  m.set_organ(organ.id);
  m.set_mesh(organ.mesh_name);
  m.set_mesh_hash(organs::MeshHash(organ.volume));
  m.set_num_nodes(static_cast<uint64_t>(organ.volume.vertices.cols()));
  m.set_num_tets(static_cast<uint64_t>(organ.volume.tetrahedra.cols()));
  m.set_material(scene_organ.model().ShortDebugString() + " " +
                 scene_organ.material().ShortDebugString());
  for (const double e : report.eigenvalues) m.add_eigenvalues(e);
  m.set_kept_fraction(report.kept_fraction);
  std::string stiffness = "K = " + report.candidates[report.chosen] + "; relative L2 errors:";
  for (size_t k = 0; k < report.candidates.size(); ++k) {
    char text[160];
    std::snprintf(text, sizeof text, " %s %.4f;", report.candidates[k].c_str(),
                  report.candidate_errors[k]);
    stiffness += text;
  }
  m.set_stiffness(stiffness);
  m.set_created_unix_ns(std::chrono::duration_cast<std::chrono::nanoseconds>(
                            std::chrono::system_clock::now().time_since_epoch())
                            .count());
  m.set_build_seconds(report.seconds);
  return m;
}

// The nonlinear (ECSW) model from the same snapshots, written to `file`; its summary.
nlohmann::json BuildNonlinear(const std::string& file, const organs::BuiltOrgan& organ,
                              const reduce::SamplingPlan& plan, const reduce::BuildReport& report,
                              const somasim::reduced::ReducedModelMetadata& kl,
                              const std::function<void(const reduce::BuildProgress&)>& progress) {
  const reduce::NonlinearBuildReport nl =
      reduce::BuildNonlinearModel(*organ.fem, organ.volume, plan, report, progress);
  somasim::reduced::ReducedModelMetadata nm = kl;
  nm.clear_eigenvalues();
  for (const double e : nl.eigenvalues) nm.add_eigenvalues(e);
  nm.set_kept_fraction(nl.kept_fraction);
  nm.set_stiffness(std::string(plan.petrov_galerkin ? "nonlinear, Petrov–Galerkin (Ψ = K0⁻¹ B)"
                                                    : "nonlinear, Galerkin") +
                   ": ECSW cubature on " + std::to_string(nl.cubature.elements.size()) +
                   " elements");
  nm.set_cubature_residual(nl.cubature.relative_residual);
  nm.set_build_seconds(report.seconds + nl.seconds);
  organs::WriteReducedModel(file, nm, nl.data);
  nlohmann::json j;
  j["file"] = file;
  j["modes"] = nl.data.modes.cols();
  j["snapshots"] = nl.snapshots;
  j["kept_fraction"] = nl.kept_fraction;
  j["projection"] = plan.petrov_galerkin ? "petrov_galerkin" : "galerkin";
  j["cubature_elements"] = nl.cubature.elements.size();
  j["cubature_residual"] = nl.cubature.relative_residual;
  j["cubature_converged"] = nl.cubature.converged;
  j["cubature_states"] = nl.cubature.snapshots;
  j["cubature_states_inverted"] = nl.cubature.inverted;
  j["region_nodes"] = plan.region_nodes;
  j["region_solves"] = nl.region_solves;
  j["correction_nodes"] = nl.correction_nodes;
  j["correction_magnitudes"] = nl.data.correction_magnitudes;
  j["correction_scale_mean"] =
      std::vector<double>(nl.correction_scale_mean.data(),
                          nl.correction_scale_mean.data() + nl.correction_scale_mean.size());
  j["correction_in_modes"] = nl.data.correction_coefficients.size() > 0;
  j["in_span_error_before"] = nl.in_span_error_before;
  j["in_span_error_after"] = nl.in_span_error_after;
  j["region_unconverged"] = nl.unconverged;
  j["build_seconds"] = nl.seconds;
  return j;
}

nlohmann::json KlSummary(const std::string& file, const organs::BuiltOrgan& organ,
                         const reduce::SamplingPlan& plan, const reduce::BuildReport& report) {
  nlohmann::json j;
  j["file"] = file;
  j["organ"] = organ.id;
  j["mesh"] = organ.mesh_name;
  j["nodes"] = organ.volume.vertices.cols();
  j["points"] = plan.points;
  j["snapshots"] = report.snapshots;
  j["unconverged"] = report.unconverged;
  j["modes"] = report.data.modes.cols();
  j["kept_fraction"] = report.kept_fraction;
  std::vector<double> leading;
  for (Eigen::Index k = 0; k < std::min<Eigen::Index>(report.eigenvalues.size(), 12); ++k) {
    leading.push_back(report.eigenvalues(k));
  }
  j["eigenvalues"] = leading;
  for (size_t k = 0; k < report.candidates.size(); ++k) {
    j["stiffness_candidates"].push_back(
        {{"candidate", report.candidates[k]}, {"l2_error", report.candidate_errors[k]}});
  }
  j["stiffness"] = report.candidates[report.chosen];
  j["creep_curves"] = report.data.creep.size();
  j["build_seconds"] = report.seconds;
  return j;
}

// Builds reduction `plan_index` of the scene: the Karhunen–Loève model (and the nonlinear one)
// into their files, the summary on stdout.
int Build(const Args& a, const scene::Scene& s, const scene::SceneLines& lines,
          const std::string& scene_dir, int plan_index) {
  for (const std::string& f : {a.out_file, a.nonlinear_file}) {
    if (!f.empty() && std::filesystem::exists(f)) {
      std::cerr << "somasim-reduce: " << f << " exists (a reduced model is never overwritten)\n";
      return kExitIo;
    }
  }
  const scene::Reduction& r = s.reduction(plan_index);
  int organ_index = 0;
  while (s.organ(organ_index).id() != r.organ()) ++organ_index;
  const organs::BuiltOrgan organ = organs::BuildOrgan(s, organ_index, lines, scene_dir);
  const std::string why = organs::UnheldParts(organ, organ.fixed_nodes);
  if (!why.empty()) {
    std::cerr << "somasim-reduce: " << organ.field << ": " << why << "\n";
    return kExitBadInput;
  }
  const reduce::SamplingPlan plan = MakePlan(r, plan_index, organ, lines);
  std::fprintf(stderr, "somasim-reduce: %s: %zu points, %zu magnitudes, %d directions\n",
               organ.id.c_str(), plan.points.size(), plan.forces.size(), plan.directions);
  auto last_print = std::chrono::steady_clock::now() - std::chrono::seconds(10);
  const auto progress = [&](const reduce::BuildProgress& p) {
    const auto now = std::chrono::steady_clock::now();
    if (p.done == p.total || now - last_print > std::chrono::seconds(2)) {
      std::fprintf(stderr, "somasim-reduce: %s %zu/%zu\n", p.stage.c_str(), p.done, p.total);
      last_print = now;
    }
  };
  if (!a.nonlinear_file.empty() && organ.fem->kind() != models::fem::FemKind::kHyperelastic) {
    std::cerr << "somasim-reduce: --nonlinear-out: " << organ.field
              << " is not fem_hyperelastic (the nonlinear reduced model reduces a hyperelastic "
                 "organ)\n";
    return kExitBadInput;
  }
  const reduce::BuildReport report = reduce::BuildKlModel(*organ.fem, organ.volume, plan, progress);
  const somasim::reduced::ReducedModelMetadata m =
      KlMetadata(a, s.organ(organ_index), organ, report);
  organs::WriteReducedModel(a.out_file, m, report.data);
  nlohmann::json j = KlSummary(a.out_file, organ, plan, report);
  if (!a.nonlinear_file.empty()) {
    j["nonlinear"] = BuildNonlinear(a.nonlinear_file, organ, plan, report, m, progress);
  }
  std::cout << j.dump(2) << "\n";
  return kExitOk;
}

int RunMain(int argc, char** argv) {
  Args a;
  if (const int rc = ParseArgs(argc, argv, &a); rc >= 0) return rc;
  // CHOLMOD's factorisations are most of the work: the CPU's own BLAS kernels, not the generic
  // ones Debian's OpenBLAS falls back to on CPUs it does not know (common/app/blas_kernels.h;
  // after the command line is parsed: --help and --version need no kernels).
  somasim::app::PreferFastBlasKernels("somasim-reduce", argv);
  try {
    scene::SceneLines lines;
    const scene::Scene s = scene::LoadSceneFile(a.scene, &lines);
    std::string scene_dir = std::filesystem::path(a.scene).parent_path().string();
    if (scene_dir.empty()) scene_dir = ".";
    int plan_index = -1;
    for (int k = 0; k < s.reduction_size(); ++k) {
      if (a.organ_id.empty() || s.reduction(k).organ() == a.organ_id) {
        plan_index = k;
        break;
      }
    }
    if (!a.evaluate_file.empty()) {
      return RunEvaluation(
          s, lines, scene_dir,
          a.organ_id.empty() && plan_index >= 0 ? s.reduction(plan_index).organ() : a.organ_id,
          a.evaluate_file, a.plan_file, a.per_step_file);
    }
    if (plan_index < 0) {
      std::cerr << "somasim-reduce: " << a.scene << " has no reduction block"
                << (a.organ_id.empty() ? "" : " for organ \"" + a.organ_id + "\"") << "\n";
      return kExitBadInput;
    }
    return Build(a, s, lines, scene_dir, plan_index);
  } catch (const std::runtime_error&) {
    return organs::ReportFileError("somasim-reduce");
  } catch (const std::invalid_argument& e) {
    std::cerr << "somasim-reduce: " << e.what() << "\n";
    return kExitFailed;
  }
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return RunMain(argc, argv);
  } catch (const std::exception& e) {
    std::cerr << "somasim-reduce: internal error: " << e.what() << "\n";
    return kExitBug;
  }
}
