// Finite-element steps (issue 5): one iteration = one step through TissueModel::Step, or one
// static solve.
//   BM_FemCorotationalStep/<organ>       implicit Euler, dt = 10 ms, exactly 20 CG iterations
//                                        (SOFA's CPU benchmark scene), final residual reported;
//   BM_FemCorotationalConverged/<organ>  the same step with CG to relative residual 1e-6.
// The organ hangs from its nodes nearest one end (x ≤ min x + 10 % of the length), under gravity.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/models/fem/fem_model.h"

namespace somasim::models::fem {
namespace {

std::vector<int32_t> OneEnd(const mesh::Points& x) {
  const double lo = x.row(0).minCoeff(), hi = x.row(0).maxCoeff();
  std::vector<int32_t> nodes;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(0, i) <= lo + 0.1 * (hi - lo)) nodes.push_back(static_cast<int32_t>(i));
  }
  return nodes;
}

void CorotationalSteps(benchmark::State& bench, const std::string& organ, bool fixed_budget) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  FemParameters p;
  p.kind = FemKind::kCorotational;
  p.youngs_modulus = 5000.0;  // [Pa], seed 001's liver
  p.poisson_ratio = 0.35;
  p.density = 1055.0;
  p.rayleigh_mass = 0.1;
  p.rayleigh_stiffness = 0.1 * 0.01;
  p.cg_max_iterations = fixed_budget ? 20 : 1000;
  p.cg_fixed_iterations = fixed_budget;
  p.cg_tolerance = 1e-6;
  const auto model = FemModel::FromTetMesh(built.volume, p);
  const auto state = model->MakeState();
  const std::vector<int32_t> fixed = OneEnd(built.volume.vertices);
  StepInputs inputs;
  inputs.dt = 0.01;  // [s]
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;
  for (auto _ : bench) {
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  }
  bench.counters["final_residual"] = model->LastSolverResidual(*state);
  bench.counters["cg_iterations_per_step"] =
      static_cast<double>(state->counters.solver_iterations) /
      static_cast<double>(std::max<int64_t>(1, state->counters.steps));
  bench.counters["nodes"] = model->num_nodes();
  bench.counters["tets"] = model->num_tets();
}

BENCHMARK_CAPTURE(CorotationalSteps, liver4055, std::string("liver4055"), true)
    ->Name("BM_FemCorotationalStep/liver4055")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(CorotationalSteps, beam19k, std::string("beam19k"), true)
    ->Name("BM_FemCorotationalStep/beam19k")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(CorotationalSteps, liver4055_converged, std::string("liver4055"), false)
    ->Name("BM_FemCorotationalConverged/liver4055")
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace somasim::models::fem
