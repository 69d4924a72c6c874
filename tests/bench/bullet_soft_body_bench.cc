// BM_BulletSoftBody/<organ>: Bullet's soft body (Debian libbullet 3.24, btScalar = float) on the
// same mesh, step and iteration count as BM_PositionBased/<organ>/10 — the baseline of issue 4.
// One iteration = one btSoftRigidDynamicsWorld::stepSimulation(Δt, 0): maxSubSteps = 0 makes it
// exactly one internal step of Δt, with m_cfg.piterations = 10 position sweeps over the links.
//
// Shared with BM_PositionBased: the organ's surface from GenerateBuiltinOrgan (3 × N vertices
// [m], 3 × T triangles), one link per unique triangle edge (sorted i < j, the order our model
// sweeps; Bullet's randomizeConstraints is not called), the triangles as faces (as
// btSoftBodyHelpers::CreateFromTriMesh makes them: normals and the face tree), lumped masses ρ ·
// area · h / 3 per triangle corner (ρ = 1050 kg/m³, h = 0.005 m, as PositionBasedParameters), Δt =
// 1 ms, gravity (0, 0, -9.81) m/s², nodes 0, 1, 2 held (mass 0).
//
// Bullet's link solver (btSoftBody::PSolve_Links) is seed-004 style PBD: each sweep removes the
// fraction kLST of a link's violation (split by inverse masses), so its stiffness depends on the
// sweep count and Δt, while our XPBD model takes E = 3000 Pa through the Van Gelder spring
// k_e = E · Σ_{t ∋ e} area_t · h / |e|² (docs/models.md). We pick the kLST whose 10 sweeps remove,
// per step, the same fraction of an isolated link's violation as a backward-Euler step of that
// spring (what converged XPBD computes): (1 - kLST)^10 = 1 / (1 + k_e Δt² (w_i + w_j)), w = 1/m,
// taking the median link of the organ (one material for the body, as Bullet users do).
//
// Damping: m_cfg.kDP = 0.001 (v ← (1 - kDP)(x - x₀)/Δt after the sweeps: 0.1 % per step).
// Velocity, drift and cluster solvers off (viterations = diterations = citerations = 0); no pose
// matching, volume, pressure or aerodynamics (their coefficients stay 0). Collisions: only the
// default rigid-vs-soft SDF flag, no self-collision, no clusters, and no other object in the
// world, so nothing collides — but each step still runs Bullet's collision pass (the soft body's
// node and face trees are refitted and the broadphase and dispatcher run), which is part of what
// a Bullet soft-body step costs.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wshadow"
#pragma GCC diagnostic ignored "-Wold-style-cast"
#pragma GCC diagnostic ignored "-Wconversion"
#pragma GCC diagnostic ignored "-Wfloat-conversion"
#pragma GCC diagnostic ignored "-Wdouble-promotion"
#pragma GCC diagnostic ignored "-Wnull-dereference"
#pragma GCC diagnostic ignored "-Wunused-parameter"
#include <BulletSoftBody/btSoftBody.h>
#include <BulletSoftBody/btSoftBodyRigidBodyCollisionConfiguration.h>
#include <BulletSoftBody/btSoftRigidDynamicsWorld.h>
#include <btBulletDynamicsCommon.h>
#pragma GCC diagnostic pop

#include "common/mesh/mesh_types.h"
#include "common/mesh_gen/builtin_organs.h"

namespace {

constexpr double kDensity = 1050.0;        // ρ [kg/m³], as BM_PositionBased
constexpr double kThickness = 0.005;       // h [m], PositionBasedParameters' default
constexpr double kYoungsModulus = 3000.0;  // E [Pa], as BM_PositionBased
constexpr double kDt = 1e-3;               // [s]
constexpr int kIterations = 10;            // position sweeps per step
constexpr float kDamping = 0.001F;         // Bullet's kDP [-]

// The surface as Bullet takes it, with what the stiffness choice needs.
struct LinkedSurface {
  std::vector<btVector3> positions;           // [m], num_nodes
  std::vector<btScalar> masses;               // [kg], num_nodes
  std::vector<std::array<int32_t, 2>> links;  // unique triangle edges, i < j, sorted
  std::vector<std::array<int32_t, 3>> faces;  // the triangles
  double link_stiffness = 0.0;                // kLST [-], in (0, 1]
};

LinkedSurface BuildLinkedSurface(const somasim::mesh::SurfaceMesh& surface) {
  LinkedSurface out;
  const auto num_nodes = static_cast<size_t>(surface.vertices.cols());
  const auto& v = surface.vertices;  // 3 × num_nodes [m]
  std::vector<double> mass(num_nodes, 0.0);
  // (i, j, size) per triangle edge, size = area · h [m³]; merged below.
  std::vector<std::pair<std::array<int32_t, 2>, double>> edge_size;
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    const std::array<int32_t, 3> n = {surface.triangles(0, t), surface.triangles(1, t),
                                      surface.triangles(2, t)};
    const double area =
        0.5 * (v.col(n[1]) - v.col(n[0])).cross(v.col(n[2]) - v.col(n[0])).norm();  // [m²]
    for (int c = 0; c < 3; ++c) {
      mass[static_cast<size_t>(n[static_cast<size_t>(c)])] += kDensity * area * kThickness / 3.0;
      const int32_t a = n[static_cast<size_t>(c)];
      const int32_t b = n[static_cast<size_t>((c + 1) % 3)];
      edge_size.push_back({{std::min(a, b), std::max(a, b)}, area * kThickness});
    }
    out.faces.push_back(n);
  }
  std::sort(edge_size.begin(), edge_size.end());
  // Per unique edge: r_e = k_e Δt² (w_i + w_j), k_e = E Σ size / |e|² (Van Gelder).
  std::vector<double> ratio;
  for (size_t k = 0; k < edge_size.size();) {
    const std::array<int32_t, 2> e = edge_size[k].first;
    double size_sum = 0.0;
    for (; k < edge_size.size() && edge_size[k].first == e; ++k) size_sum += edge_size[k].second;
    const double length2 = (v.col(e[1]) - v.col(e[0])).squaredNorm();  // [m²]
    const double stiffness = kYoungsModulus * size_sum / length2;      // [N/m]
    ratio.push_back(
        stiffness * kDt * kDt *
        (1.0 / mass[static_cast<size_t>(e[0])] + 1.0 / mass[static_cast<size_t>(e[1])]));
    out.links.push_back(e);
  }
  std::nth_element(ratio.begin(), ratio.begin() + static_cast<std::ptrdiff_t>(ratio.size() / 2),
                   ratio.end());
  const double median = ratio[ratio.size() / 2];
  out.link_stiffness = 1.0 - std::pow(1.0 + median, -1.0 / kIterations);
  for (size_t i = 0; i < num_nodes; ++i) {
    out.positions.emplace_back(static_cast<btScalar>(v(0, static_cast<Eigen::Index>(i))),
                               static_cast<btScalar>(v(1, static_cast<Eigen::Index>(i))),
                               static_cast<btScalar>(v(2, static_cast<Eigen::Index>(i))));
    out.masses.push_back(static_cast<btScalar>(mass[i]));
  }
  return out;
}

// A soft-rigid world holding the organ as one btSoftBody and nothing else. Members are declared
// in construction order; the destructor removes the body from the world first, then frees the
// body, world, solver, broadphase, dispatcher and configuration in that order.
class BulletScene {
 public:
  explicit BulletScene(const LinkedSurface& surface)
      : config_(std::make_unique<btSoftBodyRigidBodyCollisionConfiguration>()),
        dispatcher_(std::make_unique<btCollisionDispatcher>(config_.get())),
        broadphase_(std::make_unique<btDbvtBroadphase>()),
        solver_(std::make_unique<btSequentialImpulseConstraintSolver>()),
        world_(std::make_unique<btSoftRigidDynamicsWorld>(dispatcher_.get(), broadphase_.get(),
                                                          solver_.get(), config_.get())) {
    const btVector3 gravity(0.0F, 0.0F, -9.81F);  // [m/s²]
    world_->setGravity(gravity);
    btSoftBodyWorldInfo& info = world_->getWorldInfo();
    info.m_gravity = gravity;
    info.m_broadphase = broadphase_.get();
    info.m_dispatcher = dispatcher_.get();
    info.m_sparsesdf.Initialize();

    body_ = std::make_unique<btSoftBody>(&info, static_cast<int>(surface.positions.size()),
                                         surface.positions.data(), surface.masses.data());
    btSoftBody::Material* material = body_->m_materials[0];
    material->m_kLST = static_cast<btScalar>(surface.link_stiffness);
    for (const auto& l : surface.links) body_->appendLink(l[0], l[1], material, false);
    for (const auto& f : surface.faces) body_->appendFace(f[0], f[1], f[2], material);
    for (int node = 0; node < 3; ++node) body_->setMass(node, 0.0F);  // held

    btSoftBody::Config& cfg = body_->m_cfg;
    cfg.piterations = kIterations;
    cfg.viterations = 0;
    cfg.diterations = 0;
    cfg.citerations = 0;
    cfg.kDP = kDamping;
    cfg.collisions = btSoftBody::fCollision::SDF_RS;  // no VF_SS / CL_SS: no self-collision
    world_->addSoftBody(body_.get());
  }
  BulletScene(const BulletScene&) = delete;
  BulletScene& operator=(const BulletScene&) = delete;
  ~BulletScene() {
    world_->removeSoftBody(body_.get());
    body_.reset();
    world_.reset();
    solver_.reset();
    broadphase_.reset();
    dispatcher_.reset();
    config_.reset();
  }

  // One step of Δt: maxSubSteps = 0 turns off Bullet's fixed-step accumulator.
  int Step() { return world_->stepSimulation(static_cast<btScalar>(kDt), 0); }
  const btSoftBody& body() const { return *body_; }

 private:
  std::unique_ptr<btSoftBodyRigidBodyCollisionConfiguration> config_;
  std::unique_ptr<btCollisionDispatcher> dispatcher_;
  std::unique_ptr<btDbvtBroadphase> broadphase_;
  std::unique_ptr<btSequentialImpulseConstraintSolver> solver_;
  std::unique_ptr<btSoftRigidDynamicsWorld> world_;
  std::unique_ptr<btSoftBody> body_;
};

void BM_BulletSoftBody(benchmark::State& bench, const std::string& organ) {
  const somasim::mesh_gen::BuiltinOrgan built = somasim::mesh_gen::GenerateBuiltinOrgan(organ);
  const LinkedSurface surface = BuildLinkedSurface(built.surface);
  BulletScene scene(surface);
  for (auto _ : bench) {
    benchmark::DoNotOptimize(scene.Step());
  }
  bench.counters["solver_iterations"] = kIterations;
  bench.counters["nodes"] = static_cast<double>(scene.body().m_nodes.size());
  bench.counters["links"] = static_cast<double>(scene.body().m_links.size());
  bench.counters["kLST"] = surface.link_stiffness;
}

BENCHMARK_CAPTURE(BM_BulletSoftBody, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_BulletSoftBody, kidney2000, std::string("kidney2000"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_BulletSoftBody, spleen600, std::string("spleen600"))
    ->Unit(benchmark::kMicrosecond);

}  // namespace
