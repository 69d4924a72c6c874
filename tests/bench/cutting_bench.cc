// Cutting (issue 10; seed 003 table 2): the stiffness's change when one element is removed,
// against starting over, in the same run. Run with OPENBLAS_NUM_THREADS=1 (the and the
// seed's single-threaded comparison). Each organ as the built-in scenes hold it: the lowest 10 %
// of its height fixed (the plate: along an edge, as the seed's); seed 003's plate material
// (E = 1 MPa, ν = 0.4).
//   BM_CutUpdateSmw/<organ>       seed 003's update: K⁻¹ changed by Sherman–Morrison–Woodbury
//                                 for one removed element (rank 6), the dense inverse of the
//                                 free DOFs (the time of the removal; the element is put back
//                                 untimed, so every iteration removes the same one).
//   BM_FullReinversion/<organ>    the same K inverted from scratch: LAPACK dpotrf + dpotri
//                                 (OpenBLAS).
//   BM_CutUpdateCholmod/<organ>   the sparse factor downdated in place for one removed element
//                                 (CHOLMOD update/downdate, rank 6).
//   BM_Refactorization/<organ>    the same sparse K factorised again (CHOLMOD supernodal numeric
//                                 factorisation, the symbolic analysis reused).
//   BM_CutStep/liver4055          one blade step through the liver: the sweep, the crossed and
//                                 severed elements, relocation, removal (TetCutter), the step's
//                                 element changes summed (StepChange) and applied to the factor,
//                                 and the boundary re-extracted; the time of one step (the mean
//                                 of a 10-step, 2 cm incision 2 cm deep, a fresh liver per
//                                 iteration). Counters: removed and relocated per step.
#include <benchmark/benchmark.h>

#include <Eigen/Core>
#include <chrono>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "server/cutting/stiffness_update.h"
#include "server/cutting/tet_cutter.h"

extern "C" {
void dpotrf_(const char* uplo, const int* n, double* a, const int* lda, int* info);
void dpotri_(const char* uplo, const int* n, double* a, const int* lda, int* info);
}

namespace somasim::cutting {
namespace {

using Clock = std::chrono::steady_clock;

struct Setup {
  mesh::TetMesh rest;
  std::vector<uint8_t> fixed;
  int32_t element = -1;  // an element whose removal keeps K positive definite
};

Setup MakeSetup(const std::string& organ) {
  Setup s;
  s.rest = mesh_gen::GenerateBuiltinOrganVolume(organ);
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(s.rest.vertices);
  // The plate (one element thick) is held along an edge, as seed 003's ("the bottom edge of
  // this model is fixed"); the organs by their lowest tenth.
  const int axis = organ == "plate192" ? 0 : 2;
  const double held = box.min[axis] + 0.1 * (box.max[axis] - box.min[axis]);
  s.fixed.assign(static_cast<size_t>(s.rest.vertices.cols()), 0);
  for (Eigen::Index v = 0; v < s.rest.vertices.cols(); ++v) {
    s.fixed[static_cast<size_t>(v)] = s.rest.vertices(axis, v) < held ? 1 : 0;
  }
  // An element near the middle with every corner free and in other elements too.
  std::vector<int32_t> count(static_cast<size_t>(s.rest.vertices.cols()), 0);
  for (Eigen::Index e = 0; e < s.rest.tetrahedra.cols(); ++e) {
    for (int a = 0; a < 4; ++a) ++count[static_cast<size_t>(s.rest.tetrahedra(a, e))];
  }
  const Eigen::Vector3d centre = 0.5 * (box.min + box.max);
  double best = 1e300;
  for (Eigen::Index e = 0; e < s.rest.tetrahedra.cols(); ++e) {
    bool ok = true;
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (int a = 0; a < 4; ++a) {
      const int32_t v = s.rest.tetrahedra(a, e);
      ok = ok && s.fixed[static_cast<size_t>(v)] == 0 && count[static_cast<size_t>(v)] >= 3;
      c += 0.25 * s.rest.vertices.col(v);
    }
    if (ok && (c - centre).norm() < best) {
      best = (c - centre).norm();
      s.element = static_cast<int32_t>(e);
    }
  }
  if (s.element < 0) throw std::runtime_error(organ + ": no element to remove");
  return s;
}

void BM_CutUpdateSmw(benchmark::State& state, const std::string& organ) {
  const Setup s = MakeSetup(organ);
  CutStiffness problem(s.rest, s.fixed, 1.0e6, 0.4);
  DenseInverseStiffness dense(problem);
  const Matrix12d& ke = problem.element(s.element);
  const LowRankChange remove = SplitChange(problem, s.element, -ke);
  const LowRankChange put_back = SplitChange(problem, s.element, ke);
  for (auto _ : state) {
    const Clock::time_point t0 = Clock::now();
    dense.Apply(remove);
    const Clock::time_point t1 = Clock::now();
    benchmark::DoNotOptimize(dense.inverse().data());
    dense.Apply(put_back);
    state.SetIterationTime(std::chrono::duration<double>(t1 - t0).count());
  }
  state.counters["dofs"] = problem.num_free();
  state.counters["rank"] = remove.rank;
}

void BM_FullReinversion(benchmark::State& state, const std::string& organ) {
  const Setup s = MakeSetup(organ);
  const CutStiffness problem(s.rest, s.fixed, 1.0e6, 0.4);
  const Eigen::MatrixXd k = problem.AssembleDense();
  Eigen::MatrixXd a(k.rows(), k.cols());
  const int n = static_cast<int>(k.rows());
  for (auto _ : state) {
    a = k;
    const Clock::time_point t0 = Clock::now();
    int info = 0;
    dpotrf_("L", &n, a.data(), &n, &info);
    if (info == 0) dpotri_("L", &n, a.data(), &n, &info);
    const Clock::time_point t1 = Clock::now();
    if (info != 0) {
      state.SkipWithError("dpotrf/dpotri failed");
      return;
    }
    benchmark::DoNotOptimize(a.data());
    state.SetIterationTime(std::chrono::duration<double>(t1 - t0).count());
  }
  state.counters["dofs"] = n;
}

void BM_CutUpdateCholmod(benchmark::State& state, const std::string& organ) {
  const Setup s = MakeSetup(organ);
  CutStiffness problem(s.rest, s.fixed, 1.0e6, 0.4);
  SparseFactorStiffness sparse(problem);
  const Matrix12d& ke = problem.element(s.element);
  const LowRankChange remove = SplitChange(problem, s.element, -ke);
  const LowRankChange put_back = SplitChange(problem, s.element, ke);
  sparse.Apply(put_back);  // the first change turns the factor into LDL' (untimed)
  sparse.Apply(remove);
  sparse.Apply(put_back);
  for (auto _ : state) {
    const Clock::time_point t0 = Clock::now();
    const bool ok = sparse.Apply(remove);
    const Clock::time_point t1 = Clock::now();
    if (!ok || !sparse.Apply(put_back)) {
      state.SkipWithError("the factor update failed");
      return;
    }
    state.SetIterationTime(std::chrono::duration<double>(t1 - t0).count());
  }
  state.counters["dofs"] = problem.num_free();
}

void BM_Refactorization(benchmark::State& state, const std::string& organ) {
  const Setup s = MakeSetup(organ);
  const CutStiffness problem(s.rest, s.fixed, 1.0e6, 0.4);
  const models::fem::LowerCsc k = problem.AssembleSparse();
  models::fem::SparseCholesky factor;
  factor.Analyse(k);
  for (auto _ : state) {
    const Clock::time_point t0 = Clock::now();
    const bool ok = factor.Factorise(k);
    const Clock::time_point t1 = Clock::now();
    if (!ok) {
      state.SkipWithError("factorisation failed");
      return;
    }
    state.SetIterationTime(std::chrono::duration<double>(t1 - t0).count());
  }
  state.counters["dofs"] = problem.num_free();
}

void BM_CutStep(benchmark::State& state, const std::string& organ) {
  const Setup s = MakeSetup(organ);
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(s.rest.vertices);
  const Eigen::Vector3d size = box.max - box.min;
  const mesh::Adjacency node_tets =
      mesh::NodeToTets(static_cast<int32_t>(s.rest.vertices.cols()), s.rest.tetrahedra);
  std::vector<uint32_t> stamp(static_cast<size_t>(s.rest.tetrahedra.cols()), 0);
  uint32_t epoch = 0;
  double removed = 0, relocated = 0, steps = 0;
  constexpr int kSteps = 10;
  StepChange change;
  for (auto _ : state) {
    // A fresh liver for each incision (not timed).
    mesh::Points x = s.rest.vertices;
    auto cutter = std::make_unique<TetCutter>(s.rest.tetrahedra, x);
    auto problem = std::make_unique<CutStiffness>(s.rest, s.fixed, 1.0e6, 0.4);
    auto sparse = std::make_unique<SparseFactorStiffness>(*problem);
    const LowRankChange none{};
    mesh::Triangles triangles;
    std::vector<uint8_t> inner;
    // The first change turns the factor into LDL' (allocates): done before the clock starts.
    const Matrix12d ke = problem->element(s.element);
    sparse->Apply(SplitChange(*problem, s.element, -ke));
    sparse->Apply(SplitChange(*problem, s.element, ke));
    // The blade: 2 cm deep into the top, across the middle in y, 2 mm per step.
    const double y = box.min.y() + 0.5 * size.y() + 0.0007;
    const double top = box.max.z() + 0.005;
    const double depth = box.max.z() - 0.02;
    double a = box.min.x() + 0.3 * size.x();
    const Clock::time_point t0 = Clock::now();
    for (int k = 0; k < kSteps; ++k, a += 0.002) {
      const models::SweptQuad q{Eigen::Vector3d(a, y, depth), Eigen::Vector3d(a, y, top),
                                Eigen::Vector3d(a + 0.002, y, depth),
                                Eigen::Vector3d(a + 0.002, y, top)};
      const CutStepResult r = cutter->Step(q, &x);
      // The step's changes summed (StepChange), applied in as few passes as their union allows.
      change.Clear();
      const auto add = [&](int32_t e, const Matrix12d& delta) {
        if (!change.Add(*problem, e, delta)) {
          change.Split();
          sparse->Apply(change);
          change.Clear();
          change.Add(*problem, e, delta);
        }
      };
      for (const int32_t e : cutter->removed_tets()) add(e, problem->Remove(e));
      ++epoch;
      for (const int32_t v : cutter->moved_nodes()) {
        for (int32_t j = node_tets.offsets[static_cast<size_t>(v)];
             j < node_tets.offsets[static_cast<size_t>(v) + 1]; ++j) {
          const int32_t e = node_tets.entries[static_cast<size_t>(j)];
          if (!problem->alive(e) || stamp[static_cast<size_t>(e)] == epoch) continue;
          stamp[static_cast<size_t>(e)] = epoch;
          add(e, problem->Relocate(e, x));
        }
      }
      change.Split();
      sparse->Apply(change);
      if (r.removed > 0) cutter->ExtractSurface(&triangles, &inner);
      removed += r.removed;
      relocated += r.relocated;
      steps += 1;
    }
    const Clock::time_point t1 = Clock::now();
    (void)none;
    state.SetIterationTime(std::chrono::duration<double>(t1 - t0).count() / kSteps);
  }
  state.counters["removed_per_step"] = removed / steps;
  state.counters["relocated_per_step"] = relocated / steps;
}

void Register() {
  for (const char* organ : {"plate192", "liver288", "kidney424"}) {
    benchmark::RegisterBenchmark((std::string("BM_CutUpdateSmw/") + organ).c_str(), BM_CutUpdateSmw,
                                 std::string(organ))
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
    benchmark::RegisterBenchmark((std::string("BM_FullReinversion/") + organ).c_str(),
                                 BM_FullReinversion, std::string(organ))
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
  }
  for (const char* organ : {"kidney424", "liver4055"}) {
    benchmark::RegisterBenchmark((std::string("BM_CutUpdateCholmod/") + organ).c_str(),
                                 BM_CutUpdateCholmod, std::string(organ))
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
    benchmark::RegisterBenchmark((std::string("BM_Refactorization/") + organ).c_str(),
                                 BM_Refactorization, std::string(organ))
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
  }
  benchmark::RegisterBenchmark("BM_CutStep/liver4055", BM_CutStep, std::string("liver4055"))
      ->UseManualTime()
      ->Iterations(5)
      ->Unit(benchmark::kMillisecond);
}

const bool registered = (Register(), true);

}  // namespace
}  // namespace somasim::cutting
