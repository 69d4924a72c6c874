// The contact pipeline's per-step cost (issue 6):
//   BM_ContactStep/liver4055  one physics step's contact work for a probe pressing into the
//                             liver (seed 000's mesh, 4055 nodes): refit of the surface's AABB
//                             tree to moved positions, the proxy's FirstHit-checked moves and
//                             nearest-point query, the contact springs for the model.
#include <benchmark/benchmark.h>

#include <cmath>
#include <numbers>
#include <vector>

#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "server/contact/contact_pipeline.h"

namespace somasim::contact {
namespace {

void BM_ContactStep(benchmark::State& state) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrganVolume("liver4055");
  const mesh::Triangles triangles = mesh::ExtractBoundarySurface(liver).triangles;
  const mesh::Points& rest = liver.vertices;
  // Two shapes to alternate between (every vertex moves each step, as under a real model): at
  // rest, and pressed in up to 2 mm around the contact.
  Eigen::Index top = 0;
  rest.row(2).maxCoeff(&top);
  const Eigen::Vector3d contact = rest.col(top);
  mesh::Points pressed = rest;
  for (Eigen::Index i = 0; i < rest.cols(); ++i) {
    const double r2 = (rest.col(i) - contact).squaredNorm();
    pressed(2, i) -= 0.002 * std::exp(-r2 / (0.02 * 0.02)) + 1e-5;
  }
  OrganSurface surface(rest, triangles);
  ToolPose pose;
  pose.tip = contact + Eigen::Vector3d(0.0, 0.0, 0.01);
  ToolContact tool(ToolShape{}, ContactSettings{}, pose);
  // The tip circles 3 mm deep under the surface, 1 mm per step.
  std::vector<ToolPose> poses(64);
  for (size_t k = 0; k < poses.size(); ++k) {
    const double a = 2.0 * std::numbers::pi * static_cast<double>(k) / 64.0;
    poses[k].tip = contact + Eigen::Vector3d(0.01 * std::cos(a), 0.01 * std::sin(a), -0.003);
  }
  size_t k = 0;
  for (auto _ : state) {
    const mesh::Points& x = (k & 1) != 0 ? pressed : rest;
    surface.Refit(x);
    tool.Update(poses[k % poses.size()], surface, x);
    benchmark::DoNotOptimize(tool.attachments().data());
    ++k;
  }
  state.counters["triangles"] = static_cast<double>(triangles.cols());
}
BENCHMARK(BM_ContactStep)->Name("BM_ContactStep/liver4055")->Unit(benchmark::kMicrosecond);

}  // namespace
}  // namespace somasim::contact
