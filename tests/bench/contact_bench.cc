// The AABB tree of somasim::contact (issue 6):
//   BM_AabbRefit/gallbladder5400   one bottom-up refit of the tree over the organ's surface to
//                                  new (deformed) positions;
//   BM_ToolQuery/gallbladder5400   what the contact pipeline asks of the tree per tool per step:
//                                  one god-object update (its FirstHit-checked moves and the
//                                  nearest-point query) for a tip stroking the surface, pressing
//                                  2 mm in and sliding 1 mm per step, in and out of contact;
//   BM_ShaftQuery/gallbladder5400  the first crossing of the tip's motion segment (a few mm) and
//                                  the surface point nearest to the shaft (tip to 3 cm back)
//                                  within 2 mm, over ~1000 poses near the surface (for tools
//                                  whose shaft touches tissue; the pipeline does not ask it yet).
#include <benchmark/benchmark.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <numbers>
#include <random>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/contact/aabb_tree.h"
#include "server/contact/god_object.h"

namespace somasim::contact {
namespace {

using Eigen::Vector3d;

// The surface deformed by a smooth field (two sine modes, amplitude `amplitude` [m]).
mesh::Points Deformed(const mesh::Points& x, double amplitude, double phase) {
  mesh::Points y = x;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    const Vector3d p = x.col(i);
    y.col(i) += amplitude * Vector3d(std::sin(60.0 * p.y() + phase), std::sin(50.0 * p.z() + phase),
                                     std::cos(70.0 * p.x() + phase));
  }
  return y;
}

void BM_AabbRefit(benchmark::State& bench, const std::string& organ) {
  const mesh::SurfaceMesh surface = mesh_gen::GenerateBuiltinOrgan(organ).surface;
  AabbTree tree(surface.vertices, surface.triangles);
  // Two deformed copies, alternated, so every refit moves every box.
  const mesh::Points a = Deformed(surface.vertices, 0.002, 0.0);
  const mesh::Points b = Deformed(surface.vertices, 0.002, 1.0);
  bool flip = false;
  for (auto _ : bench) {
    tree.Refit(flip ? a : b);
    flip = !flip;
    benchmark::ClobberMemory();
  }
  bench.counters["triangles"] = tree.num_triangles();
  bench.counters["nodes"] = tree.num_nodes();
}

struct ToolPose {
  Vector3d last_tip;  // [m]
  Vector3d tip;       // [m]
  Vector3d shaft;     // [m], 3 cm back from the tip
};

// Area-weighted vertex normals (not normalised), 3 × num_vertices.
mesh::Points VertexNormals(const mesh::SurfaceMesh& surface) {
  mesh::Points normals = mesh::Points::Zero(3, surface.vertices.cols());
  for (Eigen::Index j = 0; j < surface.triangles.cols(); ++j) {
    const Vector3d a = surface.vertices.col(surface.triangles(0, j));
    const Vector3d n = (surface.vertices.col(surface.triangles(1, j)) - a)
                           .cross(surface.vertices.col(surface.triangles(2, j)) - a);
    for (int k = 0; k < 3; ++k) normals.col(surface.triangles(k, j)) += n;
  }
  return normals;
}

// Poses around random surface vertices: the tip from 1 mm inside to 3 mm outside along the
// vertex normal, moved up to 3 mm since the last step, the shaft tilted up to ~70° from the
// normal (coming from outside). About half touch the surface.
std::vector<ToolPose> RandomPoses(const mesh::SurfaceMesh& surface, int count) {
  const mesh::Points normals = VertexNormals(surface);
  std::mt19937 rng(42);
  std::uniform_int_distribution<Eigen::Index> vertex(0, surface.vertices.cols() - 1);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<ToolPose> poses;
  for (int i = 0; i < count; ++i) {
    const Eigen::Index v = vertex(rng);
    const Vector3d n = normals.col(v).normalized();
    ToolPose pose;
    pose.tip = surface.vertices.col(v) + n * (0.001 + 0.002 * u(rng));
    pose.last_tip = pose.tip + 0.003 * Vector3d(u(rng), u(rng), u(rng)) / std::sqrt(3.0);
    const Vector3d tilt = (n + 1.5 * Vector3d(u(rng), u(rng), u(rng))).normalized();
    pose.shaft = pose.tip + 0.03 * (tilt.dot(n) < 0.3 ? n : tilt);
    poses.push_back(pose);
  }
  return poses;
}

void BM_ShaftQuery(benchmark::State& bench, const std::string& organ) {
  const mesh::SurfaceMesh surface = mesh_gen::GenerateBuiltinOrgan(organ).surface;
  const AabbTree tree(surface.vertices, surface.triangles);
  const std::vector<ToolPose> poses = RandomPoses(surface, 1024);
  size_t i = 0;
  int64_t hits = 0;
  int64_t touches = 0;
  for (auto _ : bench) {
    const ToolPose& pose = poses[i];
    i = (i + 1) & 1023;
    SegmentHit hit;
    SurfacePoint nearest;
    hits += tree.FirstHit(pose.last_tip, pose.tip, &hit) ? 1 : 0;
    touches += tree.NearestToSegment(pose.tip, pose.shaft, 0.002, &nearest) ? 1 : 0;
    benchmark::DoNotOptimize(hit);
    benchmark::DoNotOptimize(nearest);
  }
  const auto n = static_cast<double>(bench.iterations());
  bench.counters["hit_fraction"] = static_cast<double>(hits) / n;
  bench.counters["touch_fraction"] = static_cast<double>(touches) / n;
}

// Strokes of 32 steps around random surface vertices: the tip comes down the vertex normal from
// 3 mm outside to 2 mm inside in 5 steps, then slides 1 mm per step in a random tangent direction
// (the god-object slides over the surface), then the next stroke starts elsewhere.
std::vector<Vector3d> Strokes(const mesh::SurfaceMesh& surface, int count) {
  const mesh::Points normals = VertexNormals(surface);
  std::mt19937 rng(7);
  std::uniform_int_distribution<Eigen::Index> vertex(0, surface.vertices.cols() - 1);
  std::normal_distribution<double> gauss;
  std::vector<Vector3d> path;
  while (static_cast<int>(path.size()) < count) {
    const Eigen::Index v = vertex(rng);
    const Vector3d n = normals.col(v).normalized();
    Vector3d t(gauss(rng), gauss(rng), gauss(rng));
    t = (t - t.dot(n) * n).normalized();
    const Vector3d start = surface.vertices.col(v) + 0.003 * n;
    for (int k = 0; k < 32; ++k) {
      const double down = 0.001 * std::min(k, 5);
      path.push_back(start - down * n + 0.001 * std::max(k - 5, 0) * t);
    }
  }
  path.resize(static_cast<size_t>(count));
  return path;
}

void BM_ToolQuery(benchmark::State& bench, const std::string& organ) {
  const mesh::SurfaceMesh surface = mesh_gen::GenerateBuiltinOrgan(organ).surface;
  const AabbTree tree(surface.vertices, surface.triangles);
  const std::vector<Vector3d> path = Strokes(surface, 1024);
  GodObject proxy;
  proxy.Reset(path[0]);
  size_t i = 0;
  int64_t touching = 0;
  for (auto _ : bench) {
    if (i % 32 == 0) proxy.Reset(path[i]);  // a new stroke starts outside
    proxy.Update(tree, path[i], /*closed=*/true);
    touching += proxy.in_contact() ? 1 : 0;
    benchmark::DoNotOptimize(proxy.proxy().data());
    i = (i + 1) & 1023;
  }
  bench.counters["touch_fraction"] =
      static_cast<double>(touching) / static_cast<double>(bench.iterations());
}

BENCHMARK_CAPTURE(BM_AabbRefit, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_ToolQuery, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_ShaftQuery, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);

}  // namespace
}  // namespace somasim::contact
