// The haptic node's 1 kHz evaluation of the local force model (issue 6, ≤ 1 µs):
//   BM_LocalForceModelEval  one EvaluateLocalForceModel of a model in contact and grasping (both
//                           terms, damping and the clamp check), at device positions and
//                           velocities cycling through 256 precomputed ones (some above the
//                           plane, some below, some clamped), so that nothing can be hoisted.
#include <benchmark/benchmark.h>

#include <cstddef>
#include <random>
#include <vector>

#include "server/contact/force_model_maker.h"

namespace somasim::contact {
namespace {

void LocalForceModelEval(benchmark::State& state) {
  ContactForModel contact;
  contact.in_contact = true;
  contact.grasping = true;
  contact.normal = Eigen::Vector3d(0.0, 0.6, 0.8);
  contact.device = Eigen::Vector3d(0.01, 0.02, 0.03);
  contact.proxy = contact.device + 0.002 * contact.normal;
  contact.grasp_force = Eigen::Vector3d(0.1, -0.2, 0.5);
  contact.tool_stiffness = 1000.0;
  contact.tissue_compliance << 0.010, 0.001, 0.000,  //
      0.001, 0.020, 0.002,                           //
      0.000, 0.002, 0.015;
  contact.damping = 0.5;
  contact.force_limit = 8.0;
  const LocalForceModel model = MakeLocalForceModel(contact, 1, 0.0);
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> offset(-0.01, 0.01);
  constexpr size_t kCount = 256;
  std::vector<Eigen::Vector3d> xs(kCount), vs(kCount);
  for (size_t k = 0; k < kCount; ++k) {
    xs[k] = contact.device + Eigen::Vector3d(offset(rng), offset(rng), offset(rng));
    vs[k] = 10.0 * Eigen::Vector3d(offset(rng), offset(rng), offset(rng));
  }
  size_t k = 0;
  for (auto _ : state) {
    force_model::ForceSample s = force_model::EvaluateLocalForceModel(model, xs[k], vs[k]);
    benchmark::DoNotOptimize(s);
    k = (k + 1) & (kCount - 1);
  }
  state.SetItemsProcessed(state.iterations());
}

BENCHMARK(LocalForceModelEval)->Name("BM_LocalForceModelEval");

}  // namespace
}  // namespace somasim::contact
