// Reduced models (issue 12):
//   BM_KlReducedStep/liver4055/<n>  one step of seed 000's reduced model with n modes (8, 16,
//                                   32): a point load on a surface node and gravity projected,
//                                   the n × n solve, creep scaling and the reconstruction of the
//                                   full displacement field (4055 nodes) with velocities. Seed
//                                   000 ran its 8-mode model at 500 Hz (2 ms a step); the full
//                                   model's step is BM_FemCorotationalStep/liver4055 (same run).
//   BM_NonlinearReducedStep/liver4055/<n>  one step of the nonlinear reduced model (ECSW, QLV)
//                                   with n modes (16, 32): Newton on the reduced equilibrium
//                                   under a load that changes every step, the Prony update,
//                                   the reconstruction. Target <= 200 µs at 32 modes.
//                                   /32/petrov_galerkin: the same with Ψ = K0⁻¹ B (an LU, the
//                                   cubature at 0.1 %).
// The modes are real: Karhunen–Loève modes of 48 linear-elastic static solutions of liver4055
// (E = 5 kPa, ν = 0.45, the ends within 10 % of the length held) under point loads at random
// surface nodes, as `somasim-reduce` makes them.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <memory>
#include <random>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/models/fem/fem_model.h"
#include "server/models/reduced/ecsw.h"
#include "server/models/reduced/kl_model.h"
#include "server/models/reduced/nonlinear_model.h"
#include "server/models/reduced/pod.h"
#include "server/models/reduced/reduce_fem.h"

namespace somasim::models::reduced {
namespace {

struct Liver {
  Liver() {
    const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan("liver4055");
    fem::FemParameters p;
    p.kind = fem::FemKind::kLinear;
    p.youngs_modulus = 5000.0;
    p.poisson_ratio = 0.45;
    p.density = 1055.0;
    model = fem::FemModel::FromTetMesh(organ.volume, p);
    const mesh::Points& x = organ.volume.vertices;
    const double lo = x.row(0).minCoeff(), hi = x.row(0).maxCoeff();
    std::vector<int32_t> fixed;
    std::vector<uint8_t> held(static_cast<size_t>(x.cols()), 0);
    for (Eigen::Index i = 0; i < x.cols(); ++i) {
      if (x(0, i) <= lo + 0.1 * (hi - lo) || x(0, i) >= hi - 0.1 * (hi - lo)) {
        fixed.push_back(static_cast<int32_t>(i));
        held[static_cast<size_t>(i)] = 1;
      }
    }
    std::vector<int32_t> surface;
    std::vector<uint8_t> on_surface(static_cast<size_t>(x.cols()), 0);
    // Surface nodes: those the boundary triangles use (the surface keeps the volume's order
    // for volume organs: matched by position).
    std::map<std::array<double, 3>, int32_t> by_position;
    for (Eigen::Index i = 0; i < x.cols(); ++i) {
      by_position[{x(0, i), x(1, i), x(2, i)}] = static_cast<int32_t>(i);
    }
    const mesh::Points& s = organ.surface.vertices;
    for (Eigen::Index i = 0; i < s.cols(); ++i) {
      const auto it = by_position.find({s(0, i), s(1, i), s(2, i)});
      if (it != by_position.end() && held[static_cast<size_t>(it->second)] == 0) {
        surface.push_back(it->second);
      }
    }
    std::mt19937 rng(12);
    std::uniform_int_distribution<size_t> pick(0, surface.size() - 1);
    std::normal_distribution<double> normal;
    Eigen::MatrixXd q(3 * x.cols(), 48);
    fem::StaticWorkspace workspace;
    for (Eigen::Index c = 0; c < q.cols(); ++c) {
      mesh::Points f = mesh::Points::Zero(3, x.cols());
      const int32_t node = surface[pick(rng)];
      f.col(node) = Eigen::Vector3d(normal(rng), normal(rng), normal(rng)).normalized();
      fem::StaticLoads loads;
      loads.external_forces = &f;
      loads.fixed_nodes = fixed;
      auto state = model->MakeState();
      model->SolveStatic(loads, state.get(), &workspace);
      const mesh::Points u = state->positions - x;
      q.col(c) = Eigen::Map<const Eigen::VectorXd>(u.data(), u.size());
      if (c == 0) loaded = node;
    }
    snapshots = q;
    supports = fixed;
  }
  std::unique_ptr<fem::FemModel> model;
  std::vector<int32_t> supports;  // the held nodes
  Eigen::MatrixXd snapshots;
  int32_t loaded = 0;
};

const Liver& TheLiver() {
  static const Liver liver;
  return liver;
}

void KlReducedStep(benchmark::State& bench, int modes) {
  const Liver& liver = TheLiver();
  PodSettings settings;
  settings.energy_fraction = 1.0;
  settings.max_modes = modes;
  const PodModes pod = ModesOfSnapshots(liver.snapshots, settings);
  KlModelData data = KlDataFromFem(*liver.model, liver.model->rest_positions(), pod.modes);
  std::vector<double> curve(201);
  for (size_t k = 0; k < curve.size(); ++k)
    curve[k] = 1.0 + 0.5 * (1.0 - std::exp(-0.1 * static_cast<double>(k)));
  data.creep = {{liver.loaded, 0.1, curve}};
  const auto model = KlReducedModel::Create(std::move(data));
  auto state = model->MakeState();
  mesh::Points forces = mesh::Points::Zero(3, model->num_nodes());
  forces.col(liver.loaded) = Eigen::Vector3d(0.0, 0.0, -1.0);  // [N]
  StepInputs inputs;
  inputs.dt = 0.001;  // [s]: a haptic-rate step
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  inputs.external_forces = &forces;
  for (auto _ : bench) {
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  }
  bench.counters["modes"] = model->num_modes();
  bench.counters["nodes"] = model->num_nodes();
  bench.counters["max_displacement_mm"] =
      1e3 * (state->positions - model->data().rest).colwise().norm().maxCoeff();
}

// The nonlinear reduced model (nonlinear_model.h) of the hyperelastic liver (seed 000's material
// and Prony series) on the same snapshots' modes, its ECSW cubature trained (1 % tolerance) on
// those states at 1× and 3× their load, pressed by a 1 N tool load that changes every step (a
// 1 Hz palpation sampled at 1 kHz: each step's Newton solve has work to do), with gravity.
void NonlinearReducedStep(benchmark::State& bench, int modes, bool petrov) {
  const Liver& liver = TheLiver();
  PodSettings settings;
  settings.energy_fraction = 1.0;
  settings.max_modes = modes;
  const PodModes pod = ModesOfSnapshots(liver.snapshots, settings);
  fem::FemParameters p;
  p.kind = fem::FemKind::kHyperelastic;
  p.hyperelastic = fem::LiverNava2008();
  p.prony = fem::LiverNava2008Prony();
  p.density = 1055.0;
  mesh::TetMesh mesh;
  mesh.vertices = liver.model->rest_positions();
  mesh.tetrahedra = liver.model->elements().tets;
  const auto full = fem::FemModel::FromTetMesh(mesh, p);
  std::vector<mesh::Points> training;
  for (Eigen::Index c = 0; c < liver.snapshots.cols(); ++c) {
    for (const double scale : {1.0, 3.0}) {
      training.push_back(scale * Eigen::Map<const mesh::Points>(liver.snapshots.col(c).data(), 3,
                                                                full->num_nodes()));
    }
  }
  // Petrov–Galerkin: Ψ = K0⁻¹ B (reduce_fem.h, as the builder), the cubature trained on Ψᵀ f
  // at 0.1 %.
  Eigen::MatrixXd psi;
  if (petrov) psi = PetrovGalerkinTestBasis(*full, pod.modes, liver.supports);
  CubatureSettings cubature_settings;
  if (petrov) cubature_settings.tolerance = 0.001;
  const Cubature cubature =
      TrainCubature(*full, pod.modes, training, cubature_settings, petrov ? &psi : nullptr);
  NonlinearModelData data;
  data.rest = full->rest_positions();
  data.masses = full->masses();
  data.modes = pod.modes;
  data.test_modes = psi;
  data.tets.resize(4, static_cast<Eigen::Index>(cubature.elements.size()));
  for (size_t k = 0; k < cubature.elements.size(); ++k) {
    data.tets.col(static_cast<Eigen::Index>(k)) = mesh.tetrahedra.col(cubature.elements[k]);
  }
  data.weights = cubature.weights;
  data.material = full->material();
  data.prony = full->prony();
  data.newton_tolerance = 1e-6;
  const auto model = NonlinearReducedModel::Create(std::move(data));
  auto state = model->MakeState();
  mesh::Points forces = mesh::Points::Zero(3, model->num_nodes());
  StepInputs inputs;
  inputs.dt = 0.001;  // [s]: a haptic-rate step
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  inputs.external_forces = &forces;
  int64_t step = 0;
  const int64_t iterations_before = state->counters.solver_iterations;
  for (auto _ : bench) {
    const double t = 1e-3 * static_cast<double>(step++);
    forces.col(liver.loaded) =
        Eigen::Vector3d(0.0, 0.0, -0.5 * (1.0 - std::cos(2.0 * 3.14159265358979 * t)));  // [N]
    benchmark::DoNotOptimize(model->Step(inputs, state.get()));
  }
  bench.counters["modes"] = model->num_modes();
  bench.counters["elements"] = model->num_elements();
  bench.counters["newton_per_step"] =
      static_cast<double>(state->counters.solver_iterations - iterations_before) /
      static_cast<double>(std::max<int64_t>(step, 1));
  bench.counters["rejected"] = static_cast<double>(state->counters.rejected_steps);
}

BENCHMARK_CAPTURE(NonlinearReducedStep, 16, 16, false)
    ->Name("BM_NonlinearReducedStep/liver4055/16")
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(NonlinearReducedStep, 32, 32, false)
    ->Name("BM_NonlinearReducedStep/liver4055/32")
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(NonlinearReducedStep, 32_petrov_galerkin, 32, true)
    ->Name("BM_NonlinearReducedStep/liver4055/32/petrov_galerkin")
    ->Unit(benchmark::kMicrosecond);

BENCHMARK_CAPTURE(KlReducedStep, 8, 8)
    ->Name("BM_KlReducedStep/liver4055/8")
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(KlReducedStep, 16, 16)
    ->Name("BM_KlReducedStep/liver4055/16")
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(KlReducedStep, 32, 32)
    ->Name("BM_KlReducedStep/liver4055/32")
    ->Unit(benchmark::kMicrosecond);

}  // namespace
}  // namespace somasim::models::reduced
