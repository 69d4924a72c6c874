// Tissue-model steps (issue 4): one iteration = one step through TissueModel::Step, double
// precision, damping on, on the built-in surface organs of seed 002 — mass-spring (explicit
// symplectic Euler and implicit Euler with CG), molecular, position-based (XPBD, 10 sweeps) —
// and mass-spring on a synthetic grid of more than a million springs.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <string>

#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"
#include "server/models/mass_spring_model.h"
#include "server/models/molecular_model.h"
#include "server/models/position_based_model.h"

namespace somasim::models {
namespace {

MassSpringParameters SoftTissue() {
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;  // [Pa]
  p.density = 1050.0;         // [kg/m³]
  p.damping_ratio = 0.1;
  return p;
}

void RunSteps(benchmark::State& bench, const MassSpringModel& model) {
  const auto state = model.MakeState();
  StepInputs inputs;
  inputs.dt = 1e-4;  // [s], stable for these meshes at this stiffness
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  for (auto _ : bench) {
    benchmark::DoNotOptimize(model.Step(inputs, state.get()));
  }
  bench.counters["springs"] = model.num_springs();
  bench.counters["springs_per_second"] = benchmark::Counter(
      static_cast<double>(model.num_springs()), benchmark::Counter::kIsIterationInvariantRate);
  bench.counters["ns_per_spring_step"] = benchmark::Counter(
      static_cast<double>(model.num_springs()) * 1e-9,
      benchmark::Counter::kIsIterationInvariantRate | benchmark::Counter::kInvert);
}

void BM_MassSpringExplicit(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  const auto model = MassSpringModel::FromSurface(built.surface, SoftTissue());
  RunSteps(bench, *model);
}

void BM_MassSpringImplicit(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  MassSpringParameters p = SoftTissue();
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  const auto model = MassSpringModel::FromSurface(built.surface, p);
  const auto state = model->MakeState();
  StepInputs inputs;
  inputs.dt = 1e-3;  // [s], the server's physics step
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  const int32_t fixed[] = {0, 1, 2};  // hold it so it deforms instead of falling
  inputs.fixed_nodes = fixed;
  for (auto _ : bench) {
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  }
  bench.counters["cg_iterations_per_step"] =
      static_cast<double>(state->counters.solver_iterations) /
      static_cast<double>(std::max<int64_t>(1, state->counters.steps));
}

void BM_Molecular(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  MolecularParameters p;
  p.youngs_modulus = 3000.0;  // [Pa]
  p.density = 1050.0;         // [kg/m³]
  p.damping_ratio = 0.1;
  const auto model = MolecularModel::FromSurface(built.surface, p);
  const auto state = model->MakeState();
  StepInputs inputs;
  inputs.dt = 1e-4;
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  for (auto _ : bench) {
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  }
}

void BM_PositionBased(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  PositionBasedParameters p;
  p.mode = PositionBasedMode::kXpbd;
  p.iterations = static_cast<int>(bench.range(0));
  p.youngs_modulus = 3000.0;  // [Pa]
  p.density = 1050.0;         // [kg/m³]
  const auto model = PositionBasedModel::FromSurface(built.surface, p);
  const auto state = model->MakeState();
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  const int32_t fixed[] = {0, 1, 2};
  inputs.fixed_nodes = fixed;
  for (auto _ : bench) {
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  }
}

void BM_MassSpringExplicitGrid(benchmark::State& bench) {
  // 53³ nodes, 6 tetrahedra per cube: 1,039,676 springs along the tetrahedra's edges.
  const mesh::TetMesh grid =
      mesh_gen::BoxGridTets(53, 53, 53, Eigen::Vector3d::Zero(), Eigen::Vector3d::Constant(0.52));
  const auto model = MassSpringModel::FromTetMesh(grid, SoftTissue());
  RunSteps(bench, *model);
}

BENCHMARK_CAPTURE(BM_MassSpringExplicit, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_MassSpringExplicit, kidney2000, std::string("kidney2000"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_MassSpringExplicit, spleen600, std::string("spleen600"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_MassSpringImplicit, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_MassSpringImplicit, kidney2000, std::string("kidney2000"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_MassSpringImplicit, spleen600, std::string("spleen600"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Molecular, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Molecular, kidney2000, std::string("kidney2000"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Molecular, spleen600, std::string("spleen600"))->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_PositionBased, gallbladder5400, std::string("gallbladder5400"))
    ->Arg(10)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_PositionBased, kidney2000, std::string("kidney2000"))
    ->Arg(10)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_PositionBased, spleen600, std::string("spleen600"))
    ->Arg(10)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_MassSpringExplicitGrid)
    ->Name("BM_MassSpringExplicit/grid1m")
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace somasim::models
