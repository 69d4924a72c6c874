// Finite-element steps (issue 5): one iteration = one step through TissueModel::Step, or one
// static solve.
//   BM_FemCorotationalStep/<organ>       implicit Euler, dt = 10 ms, exactly 20 CG iterations
//                                        (SOFA's CPU benchmark scene), final residual reported;
//   BM_FemCorotationalConverged/<organ>  the same step with CG to relative residual 1e-6.
//   BM_FemHyperelasticNewtonIter/liver4055  one Newton iteration of the hyperelastic static solve
//                                        (seed 000's liver, LiverNava2008): residual, tangent
//                                        assembly, CHOLMOD factorisation, solve, line search;
//   BM_FemQlvStep/liver4055              one quasi-static hyperelastic + QLV step (seed 000's
//                                        Prony series), dt = 10 ms, Newton to relative residual
//                                        1e-6, under a constant load after warm-up steps;
//   BM_FemAssembly/liver4055             assembling that model's global tangent;
//   BM_FemFactorization/liver4055        CHOLMOD's numeric factorisation of it (free DOFs);
//   BM_FemSolve/liver4055                the triangular solves with that factor;
//   BM_FemSpmvUpper/liver4055            one product with the corotational step's matrix
//                                        (BM_FemSpmvUpperScalar: its portable path).
// The corotational organ hangs from its nodes nearest one end (x ≤ min x + 10 % of the length),
// under gravity. The hyperelastic liver is held at both ends (x ≤ min + 10 %, x ≥ max - 10 %)
// with 1 N down on its top central surface node (seed 000's case).
#include <benchmark/benchmark.h>

#include <algorithm>
#include <memory>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/models/fem/block_sparse.h"
#include "server/models/fem/fem_model.h"
#include "server/models/fem/sparse_cholesky.h"

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

// Seed 000's case: liver4055 held at both ends, 1 N down on the top node nearest the middle.
struct LiverCase {
  std::unique_ptr<FemModel> model;
  std::vector<int32_t> fixed;
  mesh::Points forces;
  StaticLoads loads;
};

std::unique_ptr<LiverCase> MakeLiverCase(bool qlv) {
  auto out = std::make_unique<LiverCase>();
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan("liver4055");
  const mesh::Points& x = built.volume.vertices;
  FemParameters p;
  p.kind = FemKind::kHyperelastic;
  p.hyperelastic = LiverNava2008();
  p.density = 1055.0;
  if (qlv) p.prony = LiverNava2008Prony();
  out->model = FemModel::FromTetMesh(built.volume, p);
  const double lo = x.row(0).minCoeff(), hi = x.row(0).maxCoeff();
  const Eigen::Vector3d middle = 0.5 * (x.rowwise().minCoeff() + x.rowwise().maxCoeff());
  int32_t top = 0;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(0, i) <= lo + 0.1 * (hi - lo) || x(0, i) >= hi - 0.1 * (hi - lo)) {
      out->fixed.push_back(static_cast<int32_t>(i));
    }
    // The top surface near the middle: the highest node within 5 % of the length of the centre
    // line.
    if ((x.col(i).head<2>() - middle.head<2>()).norm() < 0.05 * (hi - lo) && x(2, i) > x(2, top)) {
      top = static_cast<int32_t>(i);
    }
  }
  out->forces = mesh::Points::Zero(3, x.cols());
  out->forces(2, top) = -1.0;  // [N]
  out->loads.fixed_nodes = out->fixed;
  out->loads.external_forces = &out->forces;
  return out;
}

void HyperelasticNewtonIteration(benchmark::State& bench) {
  const auto liver = MakeLiverCase(false);
  StaticWorkspace workspace;
  const auto state = liver->model->MakeState();
  // Start each timed iteration from the state after two iterations from rest (mid-solve).
  for (int k = 0; k < 2; ++k) liver->model->NewtonIteration(liver->loads, state.get(), &workspace);
  const mesh::Points start = state->positions;
  double residual = 0.0;
  for (auto _ : bench) {
    state->positions = start;  // 100 kB copy, no allocation
    residual = liver->model->NewtonIteration(liver->loads, state.get(), &workspace).final_residual;
  }
  bench.counters["residual_after"] = residual;
  bench.counters["tets"] = liver->model->num_tets();
}

void QlvSteps(benchmark::State& bench) {
  const auto liver = MakeLiverCase(true);
  liver->loads.tolerance = 1e-6;
  liver->loads.reuse_factorisation = true;  // modified Newton across steps
  StaticWorkspace workspace;
  const auto state = liver->model->MakeState();
  const double dt = 0.01;        // [s]
  for (int k = 0; k < 5; ++k) {  // warm-up: the jump onto the load, then creep
    if (!liver->model->SolveQuasiStatic(liver->loads, dt, state.get(), &workspace).converged) {
      bench.SkipWithError("warm-up step did not converge");
      return;
    }
  }
  int64_t iterations = 0, factorisations = 0, steps = 0;
  for (auto _ : bench) {
    const StaticResult r =
        liver->model->SolveQuasiStatic(liver->loads, dt, state.get(), &workspace);
    if (!r.converged) {
      bench.SkipWithError("step did not converge");
      return;
    }
    iterations += r.newton_iterations;
    factorisations += r.factorisations;
    ++steps;
  }
  bench.counters["newton_iterations_per_step"] =
      static_cast<double>(iterations) / static_cast<double>(std::max<int64_t>(1, steps));
  bench.counters["factorisations_per_step"] =
      static_cast<double>(factorisations) / static_cast<double>(std::max<int64_t>(1, steps));
  bench.counters["tets"] = liver->model->num_tets();
}

// The tangent of the loaded liver (two Newton iterations from rest) and its free DOFs.
struct LiverTangent {
  std::unique_ptr<LiverCase> liver = MakeLiverCase(false);
  std::unique_ptr<TissueState> state = liver->model->MakeState();
  BlockSparseMatrix matrix;
  std::vector<int32_t> dof;
  int32_t num_dofs = 0;

  LiverTangent() {
    StaticWorkspace workspace;
    for (int k = 0; k < 2; ++k)
      liver->model->NewtonIteration(liver->loads, state.get(), &workspace);
    liver->model->AssembleTangent(state->positions, &matrix);
    dof.assign(3 * static_cast<size_t>(liver->model->num_nodes()), 0);
    for (const int32_t i : liver->fixed) {
      for (size_t c = 0; c < 3; ++c) dof[3 * static_cast<size_t>(i) + c] = -1;
    }
    for (int32_t& d : dof) {
      if (d == 0) d = num_dofs++;
    }
  }
};

void Assembly(benchmark::State& bench) {
  LiverTangent t;
  for (auto _ : bench) {
    t.liver->model->AssembleTangent(t.state->positions, &t.matrix);
    benchmark::DoNotOptimize(t.matrix.block(0).data());
  }
  bench.counters["blocks"] = t.matrix.num_blocks();
}

void Factorization(benchmark::State& bench) {
  LiverTangent t;
  const LowerCsc lower = t.matrix.ScalarLower(t.dof, t.num_dofs);
  SparseCholesky cholesky;
  cholesky.Analyse(lower);
  for (auto _ : bench) {
    if (!cholesky.Factorise(lower)) {
      bench.SkipWithError("not positive definite");
      return;
    }
  }
  bench.counters["dofs"] = t.num_dofs;
  bench.counters["nonzeros_lower"] = static_cast<double>(lower.rows.size());
}

void Solve(benchmark::State& bench) {
  LiverTangent t;
  const LowerCsc lower = t.matrix.ScalarLower(t.dof, t.num_dofs);
  SparseCholesky cholesky;
  cholesky.Analyse(lower);
  if (!cholesky.Factorise(lower)) {
    bench.SkipWithError("not positive definite");
    return;
  }
  const Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(t.num_dofs, -1.0, 1.0);
  Eigen::VectorXd x(t.num_dofs);
  for (auto _ : bench) {
    cholesky.Solve(b.data(), x.data());
    benchmark::DoNotOptimize(x.data());
  }
  bench.counters["dofs"] = t.num_dofs;
}

// One product with the corotational step's matrix storage (upper blocks), the CG's kernel:
// 23 of these are in every BM_FemCorotationalStep (20 CG iterations, CG's initial residual, K v
// for the damping and the held nodes' columns). The portable path alongside, as the in-run
// baseline of the vector one.
void UpperProduct(benchmark::State& bench, bool scalar) {
  const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan("liver4055");
  const auto n = static_cast<int32_t>(built.volume.vertices.cols());
  BlockSparseMatrix a = BlockSparseMatrix::FromTets(built.volume.tetrahedra, n, true);
  a.set_force_scalar(scalar);
  double* values = a.values();
  for (int32_t k = 0; k < 9 * a.num_blocks(); ++k) values[k] = 1.0 / (1.0 + (k % 17));
  std::vector<double> x(3 * static_cast<size_t>(n)), y(x.size());
  for (size_t i = 0; i < x.size(); ++i) x[i] = static_cast<double>(i % 7) - 3.0;
  for (auto _ : bench) {
    a.Multiply(x.data(), y.data(), nullptr);
    benchmark::DoNotOptimize(y.data());
  }
  bench.counters["blocks"] = a.num_blocks();
}

BENCHMARK_CAPTURE(UpperProduct, vector, false)
    ->Name("BM_FemSpmvUpper/liver4055")
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(UpperProduct, scalar, true)
    ->Name("BM_FemSpmvUpperScalar/liver4055")
    ->Unit(benchmark::kMicrosecond);
BENCHMARK(HyperelasticNewtonIteration)
    ->Name("BM_FemHyperelasticNewtonIter/liver4055")
    ->Unit(benchmark::kMillisecond);
BENCHMARK(QlvSteps)->Name("BM_FemQlvStep/liver4055")->Unit(benchmark::kMillisecond);
BENCHMARK(Assembly)->Name("BM_FemAssembly/liver4055")->Unit(benchmark::kMillisecond);
BENCHMARK(Factorization)->Name("BM_FemFactorization/liver4055")->Unit(benchmark::kMillisecond);
BENCHMARK(Solve)->Name("BM_FemSolve/liver4055")->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace somasim::models::fem
