// Cutting the element-free Galerkin liver by the visibility criterion (issue 13; efg_model.h):
// one iteration = one session tick of an incision, the model's Cut for the blade's sweep of that
// tick and then one 1 ms implicit Euler step (which factorises again after a cut that hid
// something; the hybrid also partitions again).
//   BM_EfgCutTick/liver288        the pure EFG.
//   BM_EfgHybridCutTick/liver288  the hybrid (efg_hybrid_model.h, its defaults: radius 5 cm, the
//                                 region centred on the incision's start).
// The incision: a vertical blade 10 mm long, its tip 4 mm under the liver's top node, drawn along
// x at 0.5 mm per tick from 1 cm before the top node: 40 ticks (2 cm), the underside held (z <=
// min + 15 % of the height), no gravity. Fixed at 40 iterations (one incision) per run, each
// run on a fresh state; counters: pairs hidden per tick, factorisations per tick, and the
// Cut call's own share of the tick.
#include <benchmark/benchmark.h>

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/models/meshless/efg_hybrid_model.h"
#include "server/models/meshless/efg_model.h"

namespace somasim::models::meshless {
namespace {

constexpr int kTicks = 40;

template <typename Model>
void CutTicks(benchmark::State& bench, const Model& model, const mesh::Points& x) {
  const double lo = x.row(2).minCoeff(), hi = x.row(2).maxCoeff();
  std::vector<int32_t> fixed;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(2, i) <= lo + 0.15 * (hi - lo)) fixed.push_back(static_cast<int32_t>(i));
  }
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  const Eigen::Vector3d start = x.col(top) + Eigen::Vector3d(-0.01, 0.0, -0.004);  // [m]
  const Eigen::Vector3d up(0.0, 0.0, 0.01), along(0.0005, 0.0, 0.0);               // [m]
  StepInputs inputs;
  inputs.dt = 1e-3;  // [s]
  inputs.fixed_nodes = fixed;
  std::unique_ptr<TissueState> state = model.MakeState();
  int tick = 0;
  int64_t hidden = 0, factorisations = 0;
  double cut_seconds = 0.0;
  const auto fresh = [&] {
    state = model.MakeState();
    model.Step(inputs, state.get());  // the first factorisation, outside the ticks
    tick = 0;
  };
  fresh();
  for (auto _ : bench) {
    if (tick == kTicks) {
      bench.PauseTiming();
      fresh();
      bench.ResumeTiming();
    }
    const Eigen::Vector3d p0 = start + tick * along, p1 = p0 + along;
    const SweptQuad sweep{p0, p0 + up, p1, p1 + up};
    const int64_t before = model.Factorisations(*state);
    const auto cut_start = std::chrono::steady_clock::now();
    hidden += model.Cut(sweep, state.get());
    cut_seconds +=
        std::chrono::duration<double>(std::chrono::steady_clock::now() - cut_start).count();
    benchmark::DoNotOptimize(model.Step(inputs, state.get()));
    factorisations += model.Factorisations(*state) - before;
    ++tick;
  }
  const auto per_tick = [&](double total) {
    return total / static_cast<double>(std::max<int64_t>(bench.iterations(), 1));
  };
  bench.counters["hidden_per_tick"] = per_tick(static_cast<double>(hidden));
  bench.counters["factorisations_per_tick"] = per_tick(static_cast<double>(factorisations));
  bench.counters["cut_call_ms"] = 1e3 * per_tick(cut_seconds);
}

void EfgCutTick(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  const auto model = EfgModel::FromTetMesh(built.volume, EfgParameters{});
  CutTicks(bench, *model, built.volume.vertices);
}

void EfgHybridCutTick(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  const mesh::Points& x = built.volume.vertices;
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  EfgHybridParameters parameters;
  parameters.region_centre = x.col(top);
  parameters.follow_tool = false;
  const auto model = EfgHybridModel::FromTetMesh(built.volume, parameters);
  CutTicks(bench, *model, x);
}

BENCHMARK_CAPTURE(EfgCutTick, liver288, std::string("liver288"))
    ->Name("BM_EfgCutTick/liver288")
    ->Unit(benchmark::kMillisecond)
    ->Iterations(kTicks);
BENCHMARK_CAPTURE(EfgHybridCutTick, liver288, std::string("liver288"))
    ->Name("BM_EfgHybridCutTick/liver288")
    ->Unit(benchmark::kMillisecond)
    ->Iterations(kTicks);

}  // namespace
}  // namespace somasim::models::meshless
