// Element-free Galerkin steps (issue 13; seed 001's EFG liver, whose step took 17.4 ms at 295
// nodes): one iteration = one implicit Euler step of 1 ms through TissueModel::Step.
//   BM_EfgStep/<organ>  liver288 (seed 001's node count) and liver4055, E = 5000 Pa, ν = 0.35,
//                       ρ = 1055 kg/m³ (EfgParameters' defaults), gravity, the nodes within 10 %
//                       of the length from one end fixed, 0.5 N along z on the top node.
// The factorisation (first step) is outside the timed loop and reported as a counter, with the
// model's construction (MLS, Gauss points, assembly) and its size.
#include <benchmark/benchmark.h>

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/models/meshless/efg_model.h"

namespace somasim::models::meshless {
namespace {

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

void EfgSteps(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  const mesh::Points& x = built.volume.vertices;
  const auto build_start = std::chrono::steady_clock::now();
  const auto model = EfgModel::FromTetMesh(built.volume, EfgParameters{});
  const double build_seconds = SecondsSince(build_start);
  const auto state = model->MakeState();
  const double lo = x.row(0).minCoeff(), hi = x.row(0).maxCoeff();
  std::vector<int32_t> fixed;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(0, i) <= lo + 0.1 * (hi - lo)) fixed.push_back(static_cast<int32_t>(i));
  }
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  mesh::Points forces = mesh::Points::Zero(3, x.cols());
  forces(2, top) = 0.5;  // [N]
  StepInputs inputs;
  inputs.dt = 1e-3;  // [s]
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  inputs.external_forces = &forces;
  inputs.fixed_nodes = fixed;
  const auto factor_start = std::chrono::steady_clock::now();
  model->Step(inputs, state.get());  // factorises
  const double factor_seconds = SecondsSince(factor_start);
  for (auto _ : bench) {
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  }
  bench.counters["nodes"] = model->num_nodes();
  bench.counters["gauss_points"] = static_cast<double>(model->num_gauss_points());
  bench.counters["stiffness_blocks"] = static_cast<double>(model->stiffness_blocks());
  bench.counters["build_s"] = build_seconds;
  bench.counters["first_step_s"] = factor_seconds;
}

BENCHMARK_CAPTURE(EfgSteps, liver288, std::string("liver288"))
    ->Name("BM_EfgStep/liver288")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgSteps, liver4055, std::string("liver4055"))
    ->Name("BM_EfgStep/liver4055")
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace somasim::models::meshless
