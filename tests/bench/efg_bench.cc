// Element-free Galerkin steps (issue 13; seed 001's EFG liver, whose step took 17.4 ms at 295
// nodes): one iteration = one implicit Euler step of 1 ms through TissueModel::Step.
//   BM_EfgStep/<organ>  liver288 (seed 001's node count) and liver4055, E = 5000 Pa, ν = 0.35,
//                       ρ = 1055 kg/m³ (EfgParameters' defaults), gravity, the nodes within 10 %
//                       of the length from one end fixed, 0.5 N along z on the top node.
//   BM_EfgGraspStep/liver288[/full]  the same, plus a grasp of the 4 highest nodes (1000 N/m
//                       shared equally, GraspSettings' default) whose targets move every step
//                       (a 1 mm circle, period 0.1 s), and LocalStiffness at the first held node
//                       as the session asks it every tick. /full: max_low_rank_nodes = 0, the
//                       path before the low-rank update (A factorised with the grasp inside; a
//                       constant stiffness costs no factorisation there either).
//   BM_EfgContactStep/liver288[/full]  a probe contact instead: 3 corner springs whose
//                       barycentric shares of 1000 N/m change every step (/full re-factorises
//                       every step).
//   BM_EfgHybridStep/<organ>  the hybrid (efg_hybrid_model.h: the EFG condensed onto a surgical
//                       region) stepped as BM_EfgStep (gravity, the same fixed end, 0.5 N along z
//                       on the top node) plus a probe at the top node: a 1000 N/m spring whose
//                       target moves on a 1 mm circle (period 0.1 s), and LocalStiffness there
//                       every tick. liver288: the defaults (radius 5 cm, the region following the
//                       tool, so centred on the top node); liver4055: radius 3 cm centred on the
//                       top node, follow_tool off (a partition there costs seconds). /adaptive:
//                       seed 001's adaptivity on (every 250 steps; its cost is in the average).
//   BM_EfgHybridRepartition/liver288  one rebuild of the region as a grasp alternates between
//                       two nodes 6 cm apart.
//   BM_EfgMssCoupledStep/liver288  seed 001's table 1 middle variant (efg_mss_coupled_model.h:
//                       EFG in the 5 cm ball around the top node, linear springs elsewhere, one
//                       sparse system) stepped exactly as BM_EfgStep (gravity, the same fixed
//                       end, 0.5 N along z on the top node), so the seed's three variants (EFG
//                       17.4 ms, coupled 14.8 ms, hybrid 12.9 ms) compare in one run.
// The factorisation (first step) is outside the timed loop and reported as a counter, with the
// model's construction (MLS, Gauss points, assembly), its size and the factorisations made
// inside the loop per step. For the hybrid, the first step (partition and factors) and a few
// warm-up steps are outside the loop; the counters add the region's size, the partitions in the
// loop and the particular far responses solved per step.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>
#include <numbers>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/models/meshless/efg_hybrid_model.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/meshless/efg_mss_coupled_model.h"

namespace somasim::models::meshless {
namespace {

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

enum class Tool { kNone, kGrasp, kContact };

void EfgSteps(benchmark::State& bench, const std::string& organ, Tool tool, bool full) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  const mesh::Points& x = built.volume.vertices;
  EfgParameters parameters;
  if (full) parameters.max_low_rank_nodes = 0;
  const auto build_start = std::chrono::steady_clock::now();
  const auto model = EfgModel::FromTetMesh(built.volume, parameters);
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
  // The tool's springs on the highest nodes.
  std::vector<int32_t> highest(static_cast<size_t>(x.cols()));
  for (size_t i = 0; i < highest.size(); ++i) highest[i] = static_cast<int32_t>(i);
  std::stable_sort(highest.begin(), highest.end(),
                   [&](int32_t a, int32_t b) { return x(2, a) > x(2, b); });
  std::vector<Attachment> springs(tool == Tool::kGrasp ? 4 : tool == Tool::kContact ? 3 : 0);
  int step = 0;
  const auto move_tool = [&] {
    const double phase = 2.0 * std::numbers::pi * step / 100.0;
    const Eigen::Vector3d offset(1e-3 * std::cos(phase), 1e-3 * std::sin(phase), 1e-3);
    for (size_t k = 0; k < springs.size(); ++k) {
      const int32_t node = highest[k];
      const double share =
          tool == Tool::kGrasp ? 0.25 : (1.0 + 0.5 * std::sin(phase + 2.1 * double(k))) / 3.0;
      springs[k] = {node, x.col(node) + offset, 1000.0 * share};  // [N/m], [m]
    }
    inputs.attachments = springs;
    ++step;
  };
  move_tool();
  const auto factor_start = std::chrono::steady_clock::now();
  model->Step(inputs, state.get());  // factorises
  const double factor_seconds = SecondsSince(factor_start);
  const int64_t factorised = model->Factorisations(*state);
  for (auto _ : bench) {
    move_tool();
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
    if (tool != Tool::kNone) benchmark::DoNotOptimize(model->LocalStiffness(*state, highest[0]));
  }
  bench.counters["nodes"] = model->num_nodes();
  bench.counters["gauss_points"] = static_cast<double>(model->num_gauss_points());
  bench.counters["stiffness_blocks"] = static_cast<double>(model->stiffness_blocks());
  bench.counters["build_s"] = build_seconds;
  bench.counters["first_step_s"] = factor_seconds;
  bench.counters["factorisations_per_step"] =
      static_cast<double>(model->Factorisations(*state) - factorised) /
      static_cast<double>(std::max<int64_t>(bench.iterations(), 1));
}

void EfgHybridSteps(benchmark::State& bench, const std::string& organ, bool adaptive) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  const mesh::Points& x = built.volume.vertices;
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  EfgHybridParameters parameters;
  parameters.adaptive = adaptive;
  if (organ == "liver4055") {
    parameters.region_radius = 0.03;  // [m]
    parameters.follow_tool = false;
    parameters.region_centre = x.col(top);
  }
  const auto build_start = std::chrono::steady_clock::now();
  const auto model = EfgHybridModel::FromTetMesh(built.volume, parameters);
  const double build_seconds = SecondsSince(build_start);
  const auto state = model->MakeState();
  const double lo = x.row(0).minCoeff(), hi = x.row(0).maxCoeff();
  std::vector<int32_t> fixed;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(0, i) <= lo + 0.1 * (hi - lo)) fixed.push_back(static_cast<int32_t>(i));
  }
  mesh::Points forces = mesh::Points::Zero(3, x.cols());
  forces(2, top) = 0.5;  // [N]
  const auto node = static_cast<int32_t>(top);
  Attachment probe{node, x.col(top), 1000.0};  // [N/m]
  StepInputs inputs;
  inputs.dt = 1e-3;  // [s]
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  inputs.external_forces = &forces;
  inputs.fixed_nodes = fixed;
  inputs.attachments = {&probe, 1};
  int step = 0;
  const auto move_probe = [&] {
    const double phase = 2.0 * std::numbers::pi * step / 100.0;
    probe.target = x.col(top) + Eigen::Vector3d(1e-3 * std::cos(phase), 1e-3 * std::sin(phase),
                                                1e-3);  // [m]
    ++step;
  };
  move_probe();
  const auto first_start = std::chrono::steady_clock::now();
  model->Step(inputs, state.get());  // partitions and factorises
  const double first_seconds = SecondsSince(first_start);
  for (int k = 0; k < 5; ++k) {  // warm-up: the probe's cached columns, LocalStiffness's cache
    move_probe();
    model->Step(inputs, state.get());
    benchmark::DoNotOptimize(model->LocalStiffness(*state, node));
  }
  const int64_t factorised = model->Factorisations(*state);
  const int64_t partitioned = model->Partitions(*state);
  const int64_t far_solved = model->FarSolves(*state);
  for (auto _ : bench) {
    move_probe();
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
    benchmark::DoNotOptimize(model->LocalStiffness(*state, node));
  }
  const auto per_step = [&](int64_t count) {
    return static_cast<double>(count) /
           static_cast<double>(std::max<int64_t>(bench.iterations(), 1));
  };
  bench.counters["nodes"] = model->num_nodes();
  bench.counters["RegionNodes"] = model->RegionNodes(*state);
  bench.counters["build_s"] = build_seconds;
  bench.counters["first_step_s"] = first_seconds;
  bench.counters["partitions_in_loop"] =
      static_cast<double>(model->Partitions(*state) - partitioned);
  bench.counters["factorisations_per_step"] = per_step(model->Factorisations(*state) - factorised);
  bench.counters["far_solves_per_step"] = per_step(model->FarSolves(*state) - far_solved);
  bench.counters["adaptations"] = static_cast<double>(model->Adaptations(*state));
}

// One rebuild of the hybrid's region (a partition: 3k solves with the static factor, the dense
// products) as the tool moves between two nodes 6 cm apart, the static factor kept.
void EfgHybridRepartition(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  const mesh::Points& x = built.volume.vertices;
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  Eigen::Index other = 0;
  (x.colwise() - (x.col(top) + Eigen::Vector3d(0.06, 0.0, 0.0)))
      .colwise()
      .squaredNorm()
      .minCoeff(&other);
  const auto model = EfgHybridModel::FromTetMesh(built.volume, EfgHybridParameters{});
  const auto state = model->MakeState();
  const double lo = x.row(0).minCoeff(), hi = x.row(0).maxCoeff();
  std::vector<int32_t> fixed;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(0, i) <= lo + 0.1 * (hi - lo)) fixed.push_back(static_cast<int32_t>(i));
  }
  Attachment grasp{static_cast<int32_t>(top), x.col(top), 100.0};  // [N/m]
  StepInputs inputs;
  inputs.dt = 1e-3;  // [s]
  inputs.fixed_nodes = fixed;
  inputs.attachments = {&grasp, 1};
  model->Step(inputs, state.get());  // the static factor
  bool at_top = true;
  for (auto _ : bench) {
    at_top = !at_top;
    grasp.node = static_cast<int32_t>(at_top ? top : other);
    grasp.target = x.col(grasp.node);
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  }
  bench.counters["RegionNodes"] = model->RegionNodes(*state);
  bench.counters["partitions_per_step"] =
      static_cast<double>(model->Partitions(*state) - 1) /
      static_cast<double>(std::max<int64_t>(bench.iterations(), 1));
}

// The coupled EFG + MSS model, driven as EfgSteps without a tool; the region centred on the
// loaded top node (the default radius, 5 cm).
void EfgMssCoupledSteps(benchmark::State& bench, const std::string& organ) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
  const mesh::Points& x = built.volume.vertices;
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  EfgMssCoupledParameters parameters;
  parameters.region_centre = x.col(top);
  const auto build_start = std::chrono::steady_clock::now();
  const auto model = EfgMssCoupledModel::FromTetMesh(built.volume, parameters);
  const double build_seconds = SecondsSince(build_start);
  const auto state = model->MakeState();
  const double lo = x.row(0).minCoeff(), hi = x.row(0).maxCoeff();
  std::vector<int32_t> fixed;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(0, i) <= lo + 0.1 * (hi - lo)) fixed.push_back(static_cast<int32_t>(i));
  }
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
  const int64_t factorised = model->Factorisations(*state);
  for (auto _ : bench) benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  bench.counters["nodes"] = model->num_nodes();
  bench.counters["efg_nodes"] = model->num_efg_nodes();
  bench.counters["interface_nodes"] = model->num_interface_nodes();
  bench.counters["springs"] = model->num_springs();
  bench.counters["gauss_points"] = static_cast<double>(model->num_gauss_points());
  bench.counters["stiffness_blocks"] = static_cast<double>(model->stiffness_blocks());
  bench.counters["build_s"] = build_seconds;
  bench.counters["first_step_s"] = factor_seconds;
  bench.counters["factorisations_per_step"] =
      static_cast<double>(model->Factorisations(*state) - factorised) /
      static_cast<double>(std::max<int64_t>(bench.iterations(), 1));
}

BENCHMARK_CAPTURE(EfgSteps, liver288, std::string("liver288"), Tool::kNone, false)
    ->Name("BM_EfgStep/liver288")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgMssCoupledSteps, liver288, std::string("liver288"))
    ->Name("BM_EfgMssCoupledStep/liver288")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgSteps, liver4055, std::string("liver4055"), Tool::kNone, false)
    ->Name("BM_EfgStep/liver4055")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgSteps, grasp288, std::string("liver288"), Tool::kGrasp, false)
    ->Name("BM_EfgGraspStep/liver288")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgSteps, grasp288_full, std::string("liver288"), Tool::kGrasp, true)
    ->Name("BM_EfgGraspStep/liver288/full")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgSteps, contact288, std::string("liver288"), Tool::kContact, false)
    ->Name("BM_EfgContactStep/liver288")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgSteps, contact288_full, std::string("liver288"), Tool::kContact, true)
    ->Name("BM_EfgContactStep/liver288/full")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgHybridSteps, liver288, std::string("liver288"), false)
    ->Name("BM_EfgHybridStep/liver288")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgHybridSteps, liver288_adaptive, std::string("liver288"), true)
    ->Name("BM_EfgHybridStep/liver288/adaptive")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgHybridSteps, liver4055, std::string("liver4055"), false)
    ->Name("BM_EfgHybridStep/liver4055")
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(EfgHybridRepartition, liver288, std::string("liver288"))
    ->Name("BM_EfgHybridRepartition/liver288")
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace somasim::models::meshless
