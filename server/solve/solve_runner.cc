#include "server/solve/solve_runner.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <stdexcept>

#include "common/mesh_io/mesh_io.h"
#include "server/organs/organ_builder.h"

namespace somasim::solve {
namespace {

namespace fem = models::fem;
namespace meshless = models::meshless;
using organs::BuildOrgan;
using organs::BuiltOrgan;
using organs::HistoryScale;
using organs::PressureForces;
using organs::SelectRegion;
using organs::UnheldParts;

// One of the scene's loads on this organ, with its nodes.
struct AppliedLoad {
  int index = 0;  // in scene.load
  const scene::Load* load = nullptr;
  std::vector<int32_t> nodes;  // sorted
  mesh::Points pressure;       // pressure loads: the nodal forces at scale 1 [N], 3 × n
};

// Everything an organ's run needs that does not change with time.
struct OrganRun {
  BuiltOrgan organ;
  std::vector<AppliedLoad> loads;
  std::vector<int32_t> prescribed;   // nodes of displacement loads, in load order
  std::vector<int> prescribed_load;  // which AppliedLoad moves prescribed[k]
  std::vector<std::pair<std::string, std::vector<int32_t>>> held;  // reaction regions
  // Per time: the loads' values.
  mesh::Points forces;                // [N], 3 × n
  mesh::Points prescribed_positions;  // [m], 3 × prescribed
};

// The largest relative residual an EFG static solve may leave on the free nodes (when the scene
// gives no solver_tolerance): a direct solve leaves ~1e-12; more means a badly conditioned system.
constexpr double kEfgResidualTolerance = 1e-6;

std::string LoadField(int index) { return "load[" + std::to_string(index) + "]"; }

OrganRun PrepareOrgan(const scene::Scene& scene, int index, const scene::SceneLines& lines,
                      const SolveOptions& options) {
  OrganRun run;
  run.organ = BuildOrgan(scene, index, lines, options.scene_dir);
  const BuiltOrgan& o = run.organ;
  const int64_t n = o.rest().cols();
  std::vector<char> held(static_cast<size_t>(n), 0);
  for (const int32_t i : o.fixed_nodes) held[static_cast<size_t>(i)] = 1;
  for (int k = 0; k < scene.organ(index).fixed_size(); ++k) {
    const std::string field = o.field + ".fixed[" + std::to_string(k) + "]";
    run.held.emplace_back(field, SelectRegion(scene.organ(index).fixed(k), o.rest(), field, lines));
  }
  for (int k = 0; k < scene.load_size(); ++k) {
    const scene::Load& load = scene.load(k);
    if (load.organ() != o.id) continue;
    AppliedLoad applied;
    applied.index = k;
    applied.load = &load;
    applied.nodes = SelectRegion(load.region(), o.rest(), LoadField(k) + ".region", lines);
    if (load.kind_case() == scene::Load::kPressure) {
      applied.pressure = PressureForces(o.rest(), o.triangles, applied.nodes, 1.0);
      if (applied.pressure.isZero(0.0)) {
        throw lines.Error(LoadField(k) + ".region",
                          "holds no whole boundary triangle for the pressure to act on");
      }
    }
    if (load.kind_case() == scene::Load::kDisplacement) {
      for (const int32_t i : applied.nodes) {
        if (held[static_cast<size_t>(i)] != 0) {
          throw lines.Error(LoadField(k) + ".region",
                            "node " + std::to_string(i) +
                                " is already held (by a fixed region, another displacement "
                                "load, or because it is in no element)");
        }
        held[static_cast<size_t>(i)] = 1;
        run.prescribed.push_back(i);
        run.prescribed_load.push_back(static_cast<int>(run.loads.size()));
      }
      run.held.emplace_back(LoadField(k), applied.nodes);
    }
    run.loads.push_back(std::move(applied));
  }
  run.forces = mesh::Points::Zero(3, n);
  run.prescribed_positions =
      mesh::Points::Zero(3, static_cast<Eigen::Index>(run.prescribed.size()));
  return run;
}

// The loads' values at time t into run->forces and run->prescribed_positions.
void LoadsAt(double t, OrganRun* run) {
  run->forces.setZero();
  for (const AppliedLoad& l : run->loads) {
    const double s = HistoryScale(*l.load, t);
    if (l.load->kind_case() == scene::Load::kForce) {
      const scene::Vec3& f = l.load->force();
      const Eigen::Vector3d share =
          s * Eigen::Vector3d(f.x(), f.y(), f.z()) / static_cast<double>(l.nodes.size());
      for (const int32_t i : l.nodes) run->forces.col(i) += share;
    } else if (l.load->kind_case() == scene::Load::kPressure) {
      run->forces += (s * l.load->pressure()) * l.pressure;
    }
  }
  for (size_t k = 0; k < run->prescribed.size(); ++k) {
    const AppliedLoad& l = run->loads[static_cast<size_t>(run->prescribed_load[k])];
    const scene::Vec3& d = l.load->displacement();
    const int32_t i = run->prescribed[k];
    run->prescribed_positions.col(static_cast<Eigen::Index>(k)) =
        run->organ.rest().col(i) + HistoryScale(*l.load, t) * Eigen::Vector3d(d.x(), d.y(), d.z());
  }
}

double MaxDisplacement(const mesh::Points& x, const mesh::Points& rest) {
  return x.cols() == 0 ? 0.0 : (x - rest).colwise().norm().maxCoeff();
}

double MeanDisplacement(const mesh::Points& x, const mesh::Points& rest,
                        const std::vector<int32_t>& nodes) {
  double sum = 0.0;
  for (const int32_t i : nodes) sum += (x.col(i) - rest.col(i)).norm();
  return sum / static_cast<double>(nodes.size());
}

std::vector<Reaction> SumReactions(const OrganRun& run, const mesh::Points& reactions) {
  std::vector<Reaction> out;
  for (const auto& [field, nodes] : run.held) {
    Reaction r;
    r.region = field;
    r.nodes = static_cast<int>(nodes.size());
    for (const int32_t i : nodes) r.force += reactions.col(i);
    out.push_back(r);
  }
  return out;
}

// The run's history: one CSV row per recorded time.
class History {
 public:
  History(const std::string& path, const OrganRun& run) : run_(run) {
    if (path.empty()) return;
    file_.open(path);
    if (!file_) throw std::runtime_error(path + ": cannot write the file");
    file_ << "t_s,max_displacement_m";
    for (const AppliedLoad& l : run.loads) {
      file_ << "," << LoadField(l.index) << "_mean_displacement_m";
    }
    file_ << "\n";
    file_.precision(10);
  }
  void Record(double t, const mesh::Points& x) {
    if (!file_.is_open()) return;
    const mesh::Points& rest = run_.organ.rest();
    file_ << t << "," << MaxDisplacement(x, rest);
    for (const AppliedLoad& l : run_.loads) file_ << "," << MeanDisplacement(x, rest, l.nodes);
    file_ << std::endl;  // flushed: a long run can be watched (tail -f)
  }
  void Close(const std::string& path) {
    if (!file_.is_open()) return;
    file_.close();
    if (!file_) throw std::runtime_error(path + ": cannot write the file");
  }

 private:
  const OrganRun& run_;
  std::ofstream file_;
};

// Writes DIR/<organ>_<k>.vtu: the input mesh (rest shape, metres), point data displacement
// and reaction_force.
std::string WriteOutput(const SolveOptions& options, const OrganRun& run, int k,
                        const mesh::Points& x, const mesh::Points& reactions) {
  if (options.out_dir.empty()) return "";
  const BuiltOrgan& o = run.organ;
  mesh_io::MeshData data;
  data.vertices = o.rest();
  if (o.volume.tetrahedra.cols() > 0) {
    data.tetrahedra = o.volume.tetrahedra;
  } else {
    data.triangles = o.triangles;
  }
  const mesh::Points u = x - o.rest();
  data.point_data.push_back(
      {"displacement", 3, std::vector<double>(u.data(), u.data() + u.size())});
  data.point_data.push_back(
      {"reaction_force", 3,
       std::vector<double>(reactions.data(), reactions.data() + reactions.size())});
  std::string path =
      (std::filesystem::path(options.out_dir) / (o.id + "_" + std::to_string(k) + ".vtu")).string();
  mesh_io::WriteMeshFile(path, data, mesh_io::WriteOptions{});
  return path;
}

fem::StaticLoads StaticLoadsOf(const scene::Scene& scene, OrganRun& run) {
  fem::StaticLoads l;
  l.external_forces = &run.forces;
  const scene::Vec3& g = scene.gravity();
  l.gravity = Eigen::Vector3d(g.x(), g.y(), g.z());
  l.fixed_nodes = run.organ.fixed_nodes;
  l.prescribed_nodes = run.prescribed;
  l.prescribed_positions = &run.prescribed_positions;
  if (run.organ.solver_tolerance > 0.0) l.tolerance = run.organ.solver_tolerance;
  if (run.organ.solver_max_iterations > 0) {
    l.max_newton_iterations = run.organ.solver_max_iterations;
  }
  return l;
}

// The latest point of the organ's load histories: where the loads reach their final values (0
// when none has a history).
double LastHistoryTime(const OrganRun& run) {
  double end = 0.0;
  for (const AppliedLoad& l : run.loads) {
    if (!l.load->history().empty()) {
      end = std::max(end, l.load->history(l.load->history_size() - 1).t());
    }
  }
  return end;
}

// The lumped node masses [kg] of a FEM, EFG or EFG hybrid organ (num_nodes), or null (particle
// and reduced models: their reactions leave the weight out).
const std::vector<double>* MassesOf(const BuiltOrgan& organ) {
  if (organ.fem != nullptr) return &organ.fem->masses();
  if (organ.efg != nullptr) return &organ.efg->masses();
  if (organ.efg_hybrid != nullptr) return &organ.efg_hybrid->efg().masses();
  return nullptr;
}

// When the outputs are written: the scene's times, or the end.
std::vector<double> OutputTimes(const scene::Scene& scene, double end) {
  std::vector<double> t(scene.output().time().begin(), scene.output().time().end());
  if (t.empty()) t.push_back(end);
  return t;
}

// Static: the equilibrium at each output time (load histories evaluated there), reached by
// adaptive continuation from the last equilibrium: the loads (forces, gravity, prescribed
// displacements) move from their last values to the new ones in increments that start at
// 1/load_steps, halve when Newton fails (the state goes back to the last equilibrium) and grow
// again after easy increments. Large deformations that defeat a fixed number of increments (a
// soft organ's lobe folding under its weight) converge this way.
void RunStatic(const scene::Scene& scene, const SolveOptions& options, OrganRun& run,
               OrganSummary* s) {
  const double end = LastHistoryTime(run);
  const auto state = run.organ.model->MakeState();
  fem::StaticLoads loads = StaticLoadsOf(scene, run);
  const Eigen::Vector3d gravity = loads.gravity;
  const int max_newton = run.organ.solver_max_iterations > 0 ? run.organ.solver_max_iterations : 25;
  loads.max_newton_iterations = max_newton;
  fem::StaticWorkspace workspace;  // CHOLMOD's analysis and buffers, kept between solves
  const double first = 1.0 / std::max(1, scene.analysis().static_solve().load_steps());
  History history(s->history_file, run);
  const std::vector<double> times = OutputTimes(scene, end);
  const mesh::Points& rest = run.organ.rest();
  mesh::Points reactions = mesh::Points::Zero(3, rest.cols());
  // The last equilibrium's loads (none at the start) and this output's.
  mesh::Points last_forces = mesh::Points::Zero(3, rest.cols());
  mesh::Points last_positions(3, static_cast<Eigen::Index>(run.prescribed.size()));
  for (size_t k = 0; k < run.prescribed.size(); ++k) {
    last_positions.col(static_cast<Eigen::Index>(k)) = rest.col(run.prescribed[k]);
  }
  double last_gravity = 0.0;
  for (size_t k = 0; k < times.size(); ++k) {
    LoadsAt(times[k], &run);
    const mesh::Points target_forces = run.forces, target_positions = run.prescribed_positions;
    double reached = 0.0, increment = first;
    while (reached < 1.0) {
      const double a = std::min(1.0, reached + increment);
      run.forces = last_forces + a * (target_forces - last_forces);
      run.prescribed_positions = last_positions + a * (target_positions - last_positions);
      loads.gravity = (last_gravity + a * (1.0 - last_gravity)) * gravity;
      const mesh::Points before = state->positions;
      const fem::StaticResult r = run.organ.fem->SolveStatic(loads, state.get(), &workspace);
      s->newton_iterations += r.newton_iterations;
      s->final_residual = r.final_residual;
      if (r.converged) {
        reached = a;
        reactions = r.reactions;
        if (r.newton_iterations <= 8) increment *= 2.0;
        continue;
      }
      state->positions = before;
      increment *= 0.5;
      if (increment < 1.0 / 1024.0) {  // give up: report where it stopped
        s->converged = false;
        break;
      }
    }
    ++s->steps;
    last_forces = target_forces;
    last_positions = target_positions;
    last_gravity = 1.0;
    history.Record(times[k], state->positions);
    s->outputs.push_back(
        {times[k], WriteOutput(options, run, static_cast<int>(k), state->positions, reactions),
         MaxDisplacement(state->positions, rest)});
    if (!s->converged) break;
  }
  s->max_displacement_m = MaxDisplacement(state->positions, rest);
  s->reactions = SumReactions(run, reactions);
  history.Close(s->history_file);
}

// Static, EFG (EfgModel) or its hybrid (EfgHybridModel, whose reduced system gives the same
// equilibrium): the model is linear, so each output time is one solve (K + P) û = f̂ with the
// loads at that time (no continuation; load_steps does not matter), counted as one Newton
// iteration. Reactions: the supports' force on each held node, -(elastic + external forces +
// weight) there, which is what the penalty springs exert; on the free nodes the same sum is the
// residual that final_residual reports, relative to the loads and reactions. Both take the
// pressure as nodal forces (external_forces), never as parameter_forces (the hybrid refuses
// those).
template <typename EfgLike>
void RunStaticEfg(const EfgLike& efg, const std::vector<double>& masses, const scene::Scene& scene,
                  const SolveOptions& options, OrganRun& run, OrganSummary* s) {
  const auto state = efg.MakeState();
  meshless::EfgStaticLoads loads;
  loads.external_forces = &run.forces;
  const scene::Vec3& g = scene.gravity();
  loads.gravity = Eigen::Vector3d(g.x(), g.y(), g.z());
  loads.fixed_nodes = run.organ.fixed_nodes;
  loads.prescribed_nodes = run.prescribed;
  loads.prescribed_positions = &run.prescribed_positions;
  const double tolerance =
      run.organ.solver_tolerance > 0.0 ? run.organ.solver_tolerance : kEfgResidualTolerance;
  const mesh::Points& rest = run.organ.rest();
  std::vector<char> held(static_cast<size_t>(rest.cols()), 0);
  for (const int32_t i : run.organ.fixed_nodes) held[static_cast<size_t>(i)] = 1;
  for (const int32_t i : run.prescribed) held[static_cast<size_t>(i)] = 1;
  mesh::Points internal = mesh::Points::Zero(3, rest.cols());
  mesh::Points reactions = mesh::Points::Zero(3, rest.cols());
  History history(s->history_file, run);
  const std::vector<double> times = OutputTimes(scene, LastHistoryTime(run));
  for (size_t k = 0; k < times.size(); ++k) {
    LoadsAt(times[k], &run);
    try {
      efg.SolveStatic(loads, state.get());
    } catch (const std::runtime_error&) {  // not positive definite: too little held
      s->converged = false;
      break;
    }
    ++s->newton_iterations;
    ++s->steps;
    efg.InternalForces(*state, &internal);
    double residual = 0.0, scale = 0.0;  // squared norms [N²]
    for (Eigen::Index i = 0; i < rest.cols(); ++i) {
      const Eigen::Vector3d load =
          run.forces.col(i) + masses[static_cast<size_t>(i)] * loads.gravity;
      const Eigen::Vector3d r = -(internal.col(i) + load);
      scale += load.squaredNorm();
      if (held[static_cast<size_t>(i)] != 0) {
        reactions.col(i) = r;
        scale += r.squaredNorm();
      } else {
        reactions.col(i).setZero();
        residual += r.squaredNorm();
      }
    }
    s->final_residual = scale > 0.0 ? std::sqrt(residual / scale) : 0.0;
    if (!state->positions.allFinite() || !(s->final_residual <= tolerance)) s->converged = false;
    history.Record(times[k], state->positions);
    s->outputs.push_back(
        {times[k], WriteOutput(options, run, static_cast<int>(k), state->positions, reactions),
         MaxDisplacement(state->positions, rest)});
    if (!s->converged) break;
  }
  s->max_displacement_m = MaxDisplacement(state->positions, rest);
  s->reactions = SumReactions(run, reactions);
  history.Close(s->history_file);
}

// Steps t = 0 → end by dt; `advance(t, dt)` takes one step and returns false to stop. Outputs
// go to the step that ends nearest each output time.
template <typename Advance, typename Reactions>
void RunSteps(const scene::Scene& scene, const SolveOptions& options, OrganRun& run,
              const models::TissueState& state, double end, double dt, Advance advance,
              Reactions reactions, OrganSummary* s) {
  const std::vector<double> times = OutputTimes(scene, end);
  const auto steps = static_cast<int64_t>(std::ceil(end / dt - 1e-9));
  const int64_t every = std::max<int64_t>(1, steps / 4000);  // history rows: at most ~4000
  History history(s->history_file, run);
  history.Record(0.0, state.positions);
  size_t next = 0;
  while (next < times.size() && times[next] < 0.5 * dt) {  // outputs at t = 0: the rest
    s->outputs.push_back(
        {times[next],
         WriteOutput(options, run, static_cast<int>(next), state.positions, reactions()), 0.0});
    ++next;
  }
  for (int64_t step = 0; step < steps; ++step) {
    const double t0 = static_cast<double>(step) * dt;
    const double t1 = std::min(end, static_cast<double>(step + 1) * dt);
    // The step is dt exactly but for a shorter last one: t1 - t0 differs from dt by rounding,
    // and a model that keeps a factorisation per dt (efg) would factorise every step.
    if (!advance(t0, step + 1 < steps ? dt : t1 - t0)) break;
    if ((step + 1) % every == 0 || step + 1 == steps) history.Record(t1, state.positions);
    while (next < times.size() && times[next] < t1 + 0.5 * dt) {
      s->outputs.push_back(
          {times[next],
           WriteOutput(options, run, static_cast<int>(next), state.positions, reactions()),
           MaxDisplacement(state.positions, run.organ.rest())});
      ++next;
    }
  }
  s->max_displacement_m = MaxDisplacement(state.positions, run.organ.rest());
  history.Close(s->history_file);
}

void RunQuasiStatic(const scene::Scene& scene, const SolveOptions& options, OrganRun& run,
                    OrganSummary* s) {
  const auto state = run.organ.model->MakeState();
  fem::StaticLoads loads = StaticLoadsOf(scene, run);
  // Small steps change the tangent little: modified Newton keeps a factorisation while it still
  // cuts the residual by half per iteration (same tolerance, far fewer factorisations).
  loads.reuse_factorisation = true;
  fem::StaticWorkspace workspace;
  mesh::Points reactions = mesh::Points::Zero(3, run.organ.rest().cols());
  const scene::QuasiStaticSolve& q = scene.analysis().quasi_static();
  RunSteps(
      scene, options, run, *state, q.end_time(), q.dt(),
      [&](double t, double dt) {
        LoadsAt(t + dt, &run);
        const fem::StaticResult r =
            run.organ.fem->SolveQuasiStatic(loads, dt, state.get(), &workspace);
        s->newton_iterations += r.newton_iterations;
        s->final_residual = r.final_residual;
        s->converged = s->converged && r.converged;
        ++s->steps;
        reactions = r.reactions;
        return true;
      },
      [&] { return reactions; }, s);
  s->reactions = SumReactions(run, reactions);
}

void RunDynamic(const scene::Scene& scene, const SolveOptions& options, OrganRun& run,
                OrganSummary* s) {
  const models::TissueModel& model = *run.organ.model;
  const auto state = model.MakeState();
  models::StepInputs inputs;
  inputs.dt = run.organ.dt;
  const scene::Vec3& g = scene.gravity();
  inputs.gravity = Eigen::Vector3d(g.x(), g.y(), g.z());
  inputs.external_forces = &run.forces;
  inputs.fixed_nodes = run.organ.fixed_nodes;
  inputs.prescribed_nodes = run.prescribed;
  inputs.prescribed_positions = &run.prescribed_positions;
  mesh::Points internal = mesh::Points::Zero(3, run.organ.rest().cols());
  std::vector<char> held(static_cast<size_t>(internal.cols()), 0);
  for (const int32_t i : run.organ.fixed_nodes) held[static_cast<size_t>(i)] = 1;
  for (const int32_t i : run.prescribed) held[static_cast<size_t>(i)] = 1;
  // The supports' force: -(internal + external) on the held nodes (+ their weight for FEM and
  // EFG, whose masses are known); inertia and damping left out.
  const std::vector<double>* masses = MassesOf(run.organ);
  const auto reactions = [&] {
    model.InternalForces(*state, &internal);
    mesh::Points r = -(internal + run.forces);
    if (masses != nullptr) {
      for (Eigen::Index i = 0; i < r.cols(); ++i) {
        r.col(i) -= (*masses)[static_cast<size_t>(i)] * inputs.gravity;
      }
    }
    for (Eigen::Index i = 0; i < r.cols(); ++i) {
      if (held[static_cast<size_t>(i)] == 0) r.col(i).setZero();
    }
    return r;
  };
  int consecutive_rejections = 0;
  RunSteps(
      scene, options, run, *state, scene.analysis().dynamic().end_time(), run.organ.dt,
      [&](double t, double dt) {
        LoadsAt(t + dt, &run);
        inputs.dt = dt;
        const models::StepStatus status = model.Step(inputs, state.get());
        if (status == models::StepStatus::kBadInput) {
          throw std::runtime_error(run.organ.field + ": the model refused the step's inputs");
        }
        consecutive_rejections = status == models::StepStatus::kOk ? 0 : consecutive_rejections + 1;
        if (consecutive_rejections >= 20) {  // it will not recover: stop and say so
          s->converged = false;
          return false;
        }
        return true;
      },
      reactions, s);
  s->steps = state->counters.steps;
  s->rejected_steps = state->counters.rejected_steps;
  s->solver_iterations = state->counters.solver_iterations;
  if (state->counters.rejected_steps > 0) s->converged = false;
  if (run.organ.fem != nullptr) s->final_residual = run.organ.fem->LastSolverResidual(*state);
  s->reactions = SumReactions(run, reactions());
}

}  // namespace

SolveSummary RunSolve(const scene::Scene& scene, const scene::SceneLines& lines,
                      const SolveOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  SolveSummary summary;
  summary.scene = scene.name();
  const scene::Analysis& analysis = scene.analysis();
  switch (analysis.kind_case()) {
    case scene::Analysis::kStaticSolve:
      summary.analysis = "static";
      break;
    case scene::Analysis::kQuasiStatic:
      summary.analysis = "quasi_static";
      break;
    case scene::Analysis::kDynamic:
      summary.analysis = "dynamic";
      break;
    case scene::Analysis::KIND_NOT_SET:
      throw lines.Error("analysis",
                        "somasim-solve needs an analysis: static_solve, quasi_static or dynamic");
  }
  const double end = analysis.has_quasi_static() ? analysis.quasi_static().end_time()
                     : analysis.has_dynamic()    ? analysis.dynamic().end_time()
                                                 : -1.0;
  for (int k = 0; k < scene.output().time_size(); ++k) {
    if (end >= 0.0 && scene.output().time(k) > end) {
      throw lines.Error("output.time[" + std::to_string(k) + "]",
                        "is after the analysis' end_time (" + std::to_string(end) + " s)");
    }
  }
  if (!options.out_dir.empty()) {
    std::error_code error;
    std::filesystem::create_directories(options.out_dir, error);
    if (error) {
      throw std::runtime_error(options.out_dir + ": cannot create the folder (" + error.message() +
                               ")");
    }
  }
  for (int k = 0; k < scene.organ_size(); ++k) {
    OrganRun run = PrepareOrgan(scene, k, lines, options);
    const bool efg = run.organ.efg != nullptr || run.organ.efg_hybrid != nullptr;
    if (analysis.has_quasi_static() && efg) {
      throw lines.Error(run.organ.field + ".model",
                        "a quasi_static analysis needs a FEM model: " + run.organ.model_name +
                            " is elastic (it has no creep), so its equilibria come from "
                            "static_solve with output times, its motion from a dynamic analysis");
    }
    if (!analysis.has_dynamic() && run.organ.fem == nullptr && !efg) {
      throw lines.Error(run.organ.field + ".model",
                        "a " + summary.analysis + " analysis needs a FEM model (fem_linear, " +
                            "fem_corotational or fem_hyperelastic), efg or efg_hybrid; " +
                            run.organ.model_name + " runs in a dynamic analysis");
    }
    if (!analysis.has_dynamic()) {
      std::vector<int32_t> held = run.organ.fixed_nodes;
      held.insert(held.end(), run.prescribed.begin(), run.prescribed.end());
      std::sort(held.begin(), held.end());
      const std::string why = UnheldParts(run.organ, held);
      if (!why.empty()) throw lines.Error(run.organ.field, run.organ.mesh_name + ": " + why);
    }
    OrganSummary s;
    const BuiltOrgan& o = run.organ;
    s.id = o.id;
    s.model = o.model_name;
    s.mesh = o.mesh_name;
    s.unit = o.unit;
    s.nodes = o.rest().cols();
    s.tetrahedra = o.volume.tetrahedra.cols();
    s.triangles = o.triangles.cols();
    s.unused_nodes = static_cast<int64_t>(o.unused_nodes.size());
    if (!options.out_dir.empty()) {
      s.history_file = (std::filesystem::path(options.out_dir) / (o.id + "_history.csv")).string();
    }
    switch (analysis.kind_case()) {
      case scene::Analysis::kStaticSolve:
        if (o.efg != nullptr) {
          RunStaticEfg(*o.efg, o.efg->masses(), scene, options, run, &s);
        } else if (o.efg_hybrid != nullptr) {
          RunStaticEfg(*o.efg_hybrid, o.efg_hybrid->efg().masses(), scene, options, run, &s);
        } else {
          RunStatic(scene, options, run, &s);
        }
        break;
      case scene::Analysis::kQuasiStatic:
        RunQuasiStatic(scene, options, run, &s);
        break;
      default:
        RunDynamic(scene, options, run, &s);
    }
    summary.max_displacement_m = std::max(summary.max_displacement_m, s.max_displacement_m);
    summary.newton_iterations += s.newton_iterations;
    summary.final_residual = std::max(summary.final_residual, s.final_residual);
    summary.converged = summary.converged && s.converged;
    summary.organs.push_back(std::move(s));
  }
  summary.wall_time_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return summary;
}

nlohmann::json SummaryJson(const SolveSummary& summary) {
  nlohmann::json organs = nlohmann::json::array();
  for (const OrganSummary& s : summary.organs) {
    nlohmann::json reactions = nlohmann::json::array();
    for (const Reaction& r : s.reactions) {
      reactions.push_back({{"region", r.region},
                           {"nodes", r.nodes},
                           {"force_n", {r.force.x(), r.force.y(), r.force.z()}}});
    }
    nlohmann::json outputs = nlohmann::json::array();
    for (const OutputRecord& o : s.outputs) {
      outputs.push_back(
          {{"time_s", o.time}, {"file", o.file}, {"max_displacement_m", o.max_displacement_m}});
    }
    organs.push_back({{"id", s.id},
                      {"model", s.model},
                      {"mesh", s.mesh},
                      {"unit", s.unit},
                      {"nodes", s.nodes},
                      {"tetrahedra", s.tetrahedra},
                      {"triangles", s.triangles},
                      {"unused_nodes", s.unused_nodes},
                      {"max_displacement_m", s.max_displacement_m},
                      {"newton_iterations", s.newton_iterations},
                      {"solver_iterations", s.solver_iterations},
                      {"steps", s.steps},
                      {"rejected_steps", s.rejected_steps},
                      {"final_residual", s.final_residual},
                      {"converged", s.converged},
                      {"reactions", reactions},
                      {"outputs", outputs},
                      {"history", s.history_file}});
  }
  return {{"scene", summary.scene},
          {"analysis", summary.analysis},
          {"max_displacement_m", summary.max_displacement_m},
          {"newton_iterations", summary.newton_iterations},
          {"final_residual", summary.final_residual},
          {"converged", summary.converged},
          {"wall_time_s", summary.wall_time_s},
          {"organs", organs}};
}

}  // namespace somasim::solve
