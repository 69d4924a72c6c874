// Tests of the explicit mass-spring step's kernels (issue 4 speed work): the slice pass
// (AVX-512 where the CPU has it, scalar otherwise) gives the plain spring loop's forces and step
// on graphs built to stress its layout (hubs, other nodes shared by a whole slice, springs
// within a slice, a partial last slice, a structured grid, massless nodes), the two passes
// agree, and cut springs stay cut through the pass.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <optional>
#include <random>
#include <span>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"
#include "server/models/cut_geometry.h"
#include "server/models/mass_spring_model.h"
#include "server/models/mass_spring_state.h"
#include "server/models/particle_mesh.h"

namespace somasim::models {

// Defined in mass_spring_slice_pass.cc: false makes the explicit pass take its scalar path.
void SetMassSpringAvx512ForTesting(bool enabled);
// Defined in mass_spring_model.cc: whether the state keeps each spring's (k, d) as an index into
// the model's table of distinct pairs (instead of k and d themselves).
bool MassSpringStateUsesPairTableForTesting(const TissueState& state);

namespace {

using Eigen::Vector3d;

// Restores the AVX-512 path (where the CPU has it) when a test ends.
class ScalarPass {
 public:
  ScalarPass() { SetMassSpringAvx512ForTesting(false); }
  ~ScalarPass() { SetMassSpringAvx512ForTesting(true); }
  ScalarPass(const ScalarPass&) = delete;
  ScalarPass& operator=(const ScalarPass&) = delete;
};

// Seed 002 eq. 1–3, one spring at a time, with the state's stiffness and damping (0 once cut).
mesh::Points PlainForces(const MassSpringModel& model, const TissueState& state,
                         const std::vector<std::array<int32_t, 2>>& edges,
                         const std::vector<double>& stiffness, const std::vector<double>& damping) {
  mesh::Points f = mesh::Points::Zero(3, model.num_nodes());
  for (size_t s = 0; s < edges.size(); ++s) {
    const auto [i, j] = edges[s];
    const double l0 = (model.rest_positions().col(j) - model.rest_positions().col(i)).norm();
    const Vector3d delta = state.positions.col(j) - state.positions.col(i);
    const double l = delta.norm();
    const Vector3d u = delta / l;
    const double closing = (state.velocities.col(j) - state.velocities.col(i)).dot(u);
    const Vector3d force = (stiffness[s] * (l - l0) + damping[s] * closing) * u;
    f.col(i) += force;
    f.col(j) -= force;
  }
  return f;
}

double RelativeDifference(const mesh::Points& a, const mesh::Points& b) {
  return (a - b).cwiseAbs().maxCoeff() / b.cwiseAbs().maxCoeff();
}

void Randomise(TissueState* state, double offset, double speed, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  for (Eigen::Index k = 0; k < state->positions.size(); ++k) {
    state->positions.data()[k] += offset * unit(rng);
    state->velocities.data()[k] = speed * unit(rng);
  }
}

// Both passes give `reference`, the plain loop's forces on the state of `fast` (which `scalar`
// holds too), and one step from it: seed 002 eq. 4–5 (v += dt (f/m + g), x += dt v), to rounding.
void ExpectBothPassesStepLikeThePlainLoop(const MassSpringModel& model,
                                          const mesh::Points& reference, const StepInputs& inputs,
                                          TissueState* fast, TissueState* scalar) {
  const int32_t n = model.num_nodes();
  mesh::Points forces(3, n);
  model.InternalForces(*fast, &forces);
  EXPECT_LT(RelativeDifference(forces, reference), 1e-12);
  const mesh::Points x0 = fast->positions, v0 = fast->velocities;
  ASSERT_EQ(model.Step(inputs, fast), StepStatus::kOk);
  {
    const ScalarPass scalar_pass;
    model.InternalForces(*scalar, &forces);
    EXPECT_LT(RelativeDifference(forces, reference), 1e-12);
    ASSERT_EQ(model.Step(inputs, scalar), StepStatus::kOk);
  }
  mesh::Points dv(3, n);
  for (int32_t i = 0; i < n; ++i) {
    dv.col(i) =
        inputs.dt * (reference.col(i) / model.masses()[static_cast<size_t>(i)] + inputs.gravity);
  }
  EXPECT_LT(RelativeDifference(fast->velocities - v0, dv), 1e-12);
  EXPECT_LT(RelativeDifference(fast->positions, x0 + inputs.dt * (v0 + dv)), 1e-15);
  EXPECT_LT(RelativeDifference(scalar->velocities, fast->velocities), 1e-12);
}

// A jittered cloud of `n` nodes (n not a multiple of 8: a partial last slice) with springs that
// stress the layout: a hub joined to 150 nodes, every node of slice 3 joined to the same node
// 200 (8 lanes wanting one other node), springs within slices, random springs.
struct Graph {
  mesh::Points rest;
  std::vector<std::array<int32_t, 2>> edges;  // sorted, unique, i < j
};

Graph StressGraph() {
  const int32_t n = 403;
  Graph g;
  g.rest.resize(3, n);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int32_t i = 0; i < n; ++i) {
    g.rest.col(i) = 0.1 * Vector3d(unit(rng), unit(rng), unit(rng));
  }
  const auto add = [&g](int32_t a, int32_t b) {
    if (a != b) g.edges.push_back({std::min(a, b), std::max(a, b)});
  };
  for (int32_t j = 1; j <= 150; ++j) add(0, 2 * j + 1);  // the hub
  for (int32_t i = 24; i < 32; ++i) add(i, 200);         // slice 3 all to node 200
  for (int32_t i = 40; i < 48; ++i) {                    // slice 5: complete within itself
    for (int32_t j = i + 1; j < 48; ++j) add(i, j);
  }
  std::uniform_int_distribution<int32_t> node(0, n - 1);
  for (int e = 0; e < 2000; ++e) add(node(rng), node(rng));
  for (int32_t i = 396; i < n; ++i) add(i - 1, i);  // the partial last slice
  std::sort(g.edges.begin(), g.edges.end());
  g.edges.erase(std::unique(g.edges.begin(), g.edges.end()), g.edges.end());
  return g;
}

TEST(MassSpringExplicit, SlicePassGivesThePlainForcesOnAStressGraph) {
  const Graph g = StressGraph();
  MassSpringParameters p;
  p.spring_stiffness = 30.0;  // [N/m]
  p.node_mass = 0.002;        // [kg]
  p.damping_ratio = 0.4;
  const auto model = MassSpringModel::FromEdges(g.rest, g.edges, p);
  const auto state = model->MakeState();
  Randomise(state.get(), 0.003, 0.1, 6);
  std::vector<double> damping(g.edges.size());
  for (size_t s = 0; s < g.edges.size(); ++s) {
    damping[s] = 2.0 * p.damping_ratio * std::sqrt(p.spring_stiffness * p.node_mass / 2.0);
  }
  const mesh::Points reference = PlainForces(*model, *state, g.edges, model->stiffness(), damping);
  mesh::Points fast(3, model->num_nodes()), scalar(3, model->num_nodes());
  model->InternalForces(*state, &fast);
  {
    const ScalarPass scalar_pass;
    model->InternalForces(*state, &scalar);
  }
  EXPECT_LT(RelativeDifference(fast, reference), 1e-12);
  EXPECT_LT(RelativeDifference(scalar, reference), 1e-12);
  EXPECT_LT(RelativeDifference(fast, scalar), 1e-12);
}

// A jittered 10 × 10 × 12 grid with springs to the +x, +y, +z and diagonal neighbours: in a
// structured numbering a slice's 8 lanes mostly reach 8 consecutive nodes and read the forces
// of springs ending on them from two columns, the pass's load-and-permute paths.
TEST(MassSpringExplicit, StructuredGridGivesThePlainForcesAndStep) {
  const int32_t nx = 10, ny = 10, nz = 12, n = nx * ny * nz;
  mesh::Points rest(3, n);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> jitter(-0.001, 0.001);
  for (int32_t i = 0; i < n; ++i) {
    const int32_t cx = i % nx, cy = (i / nx) % ny, cz = i / (nx * ny);
    rest.col(i) = 0.01 * Vector3d(cx, cy, cz) + Vector3d(jitter(rng), jitter(rng), jitter(rng));
  }
  std::vector<std::array<int32_t, 2>> edges;
  for (int32_t i = 0; i < n; ++i) {
    const int32_t cx = i % nx, cy = (i / nx) % ny, cz = i / (nx * ny);
    for (const auto& [dx, dy, dz] : std::vector<std::array<int32_t, 3>>{
             {1, 0, 0}, {0, 1, 0}, {0, 0, 1}, {1, 1, 0}, {0, 1, 1}, {1, 0, 1}, {1, 1, 1}}) {
      if (cx + dx < nx && cy + dy < ny && cz + dz < nz) {
        edges.push_back({i, i + dx + nx * dy + nx * ny * dz});
      }
    }
  }
  std::sort(edges.begin(), edges.end());
  MassSpringParameters p;
  p.spring_stiffness = 40.0;
  p.node_mass = 0.001;
  p.damping_ratio = 0.2;
  const auto model = MassSpringModel::FromEdges(rest, edges, p);
  const auto fast = model->MakeState();
  Randomise(fast.get(), 0.001, 0.05, 4);
  const auto scalar = model->MakeState();
  scalar->positions = fast->positions;
  scalar->velocities = fast->velocities;
  const double d = 2.0 * p.damping_ratio * std::sqrt(p.spring_stiffness * p.node_mass / 2.0);
  const mesh::Points reference =
      PlainForces(*model, *fast, edges, model->stiffness(), std::vector<double>(edges.size(), d));
  StepInputs inputs;
  inputs.dt = 1e-4;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  ExpectBothPassesStepLikeThePlainLoop(*model, reference, inputs, fast.get(), scalar.get());
}

// Raw constants for the stress graph: 30 N/m springs, 2 g nodes, damping ratio 0.4.
MassSpringParameters StressGraphParameters() {
  MassSpringParameters p;
  p.spring_stiffness = 30.0;  // [N/m]
  p.node_mass = 0.002;        // [kg]
  p.damping_ratio = 0.4;
  return p;
}

// One explicit step with every input (gravity, external forces, a grasp, fixed and prescribed
// nodes, massless nodes from a sparse surface) through both passes, against seed 002 eq. 4–5
// written out: v += dt (f/m + g), x += dt v.
TEST(MassSpringExplicit, AvxAndScalarStepsAgreeWithTheFormula) {
  const Graph g = StressGraph();
  const MassSpringParameters p = StressGraphParameters();
  const auto model = MassSpringModel::FromEdges(g.rest, g.edges, p);
  const int32_t n = model->num_nodes();
  const auto fast = model->MakeState();
  Randomise(fast.get(), 0.003, 0.1, 8);
  const auto scalar = model->MakeState();
  scalar->positions = fast->positions;
  scalar->velocities = fast->velocities;
  mesh::Points external(3, n);  // [N]
  for (int32_t i = 0; i < n; ++i) {
    external.col(i) = Vector3d(0.001 * (i % 5), -0.002 * (i % 3), 0.0005 * (i % 7));
  }
  const Attachment grasp[] = {{40, fast->positions.col(40) + Vector3d(0, 0, 0.001), 5.0}};
  StepInputs inputs;
  inputs.dt = 1e-4;
  inputs.gravity = Vector3d(0.3, -0.2, -9.81);
  inputs.external_forces = &external;
  inputs.attachments = grasp;
  const mesh::Points x0 = fast->positions, v0 = fast->velocities;
  const double d = 2.0 * p.damping_ratio * std::sqrt(p.spring_stiffness * p.node_mass / 2.0);
  mesh::Points total = PlainForces(*model, *fast, g.edges, model->stiffness(),
                                   std::vector<double>(g.edges.size(), d)) +
                       external;
  total.col(40) += grasp[0].stiffness * (grasp[0].target - x0.col(40));
  mesh::Points dv(3, n);
  for (int32_t i = 0; i < n; ++i) {
    dv.col(i) = inputs.dt * (total.col(i) / p.node_mass + inputs.gravity);
  }
  for (int step = 0; step < 2; ++step) {
    ASSERT_EQ(model->Step(inputs, fast.get()), StepStatus::kOk);
    {
      const ScalarPass scalar_pass;
      ASSERT_EQ(model->Step(inputs, scalar.get()), StepStatus::kOk);
    }
    if (step == 0) {
      EXPECT_LT(RelativeDifference(fast->velocities - v0, dv), 1e-12);
      EXPECT_LT(RelativeDifference(fast->positions - x0, inputs.dt * (v0 + dv)), 1e-12);
    }
    // The second step checks that the pass leaves its pending forces at zero.
    EXPECT_LT(RelativeDifference(scalar->velocities, fast->velocities), 1e-12);
    EXPECT_LT(RelativeDifference(scalar->positions, fast->positions), 1e-12);
  }
}

TEST(MassSpringExplicit, ThePassChecksWhatStepWouldCheckOnBothPaths) {
  // The explicit step checks the values its pass writes (ChecksStateItself) instead of Step's own
  // pass over the state, and keeps the state it starts from by a buffer swap. Fixed and
  // prescribed nodes get their values after the pass: a target jump faster than the speed limit
  // must still reject the step, one just under it must not, and a non-finite force must reject
  // it; each rejection restores the state the step started from, bit for bit.
  const Graph g = StressGraph();
  const auto model = MassSpringModel::FromEdges(g.rest, g.edges, StressGraphParameters());
  for (const bool avx : {true, false}) {
    SCOPED_TRACE(avx ? "AVX-512 pass (where the CPU has it)" : "scalar pass");
    std::optional<ScalarPass> scalar_pass;
    if (!avx) scalar_pass.emplace();
    const auto state = model->MakeState();
    Randomise(state.get(), 0.001, 0.01, 10);
    StepInputs inputs;
    inputs.dt = 1e-4;  // [s]
    inputs.gravity = Vector3d(0.0, 0.0, -9.81);
    const int32_t fixed[] = {3};
    const int32_t prescribed[] = {57};
    inputs.fixed_nodes = fixed;
    inputs.prescribed_nodes = prescribed;
    mesh::Points target = state->positions.col(57);
    inputs.prescribed_positions = &target;
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);  // ordinary, with no jump
    const mesh::Points x0 = state->positions, v0 = state->velocities;
    const auto unchanged = [&] {
      return (state->positions.array() == x0.array()).all() &&
             (state->velocities.array() == v0.array()).all();
    };
    // Node 57 jumps at twice the speed limit, along one axis.
    target = x0.col(57);
    target(2, 0) += 2.0 * model->speed_limit() * inputs.dt;
    EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kRejectedTooFast);
    EXPECT_TRUE(unchanged());
    // At 0.9 of the limit along one axis the component is above limit/√3 (the exact test runs)
    // and the step is accepted.
    target = x0.col(57);
    target(2, 0) += 0.9 * model->speed_limit() * inputs.dt;
    EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    EXPECT_EQ(state->positions.col(57), target.col(0));
    // A node placed absurdly far (1e200 m: l² overflows, the spring forces are NaN) by an edit
    // of the state: the step is rejected and the edited state kept as it was.
    state->positions(0, 120) = 1e200;
    const mesh::Points edited_x = state->positions, edited_v = state->velocities;
    target = state->positions.col(57);
    EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kRejectedNonFinite);
    EXPECT_TRUE((state->positions.array() == edited_x.array()).all());
    EXPECT_TRUE((state->velocities.array() == edited_v.array()).all());
    EXPECT_EQ(state->counters.rejected_steps, 2);
  }
}

TEST(MassSpringExplicit, MasslessNodesStayPutAndGravityDoesNotMoveThem) {
  // A generalised surface: the core's nodes are massless and must not move.
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan("kidney424");
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;
  p.density = 1050.0;
  p.anchor_stiffness = 50.0;
  const auto model = MassSpringModel::FromGeneralisedSurface(organ.volume, p);
  const auto state = model->MakeState();
  Randomise(state.get(), 0.0005, 0.0, 9);
  const mesh::Points x0 = state->positions;
  StepInputs inputs;
  inputs.dt = 1e-5;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  for (int step = 0; step < 3; ++step) ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  int32_t massless = 0;
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    if (model->masses()[static_cast<size_t>(i)] > 0.0) continue;
    ++massless;
    EXPECT_EQ(state->positions.col(i), x0.col(i));
    EXPECT_EQ(state->velocities.col(i), Vector3d::Zero());
  }
  EXPECT_GT(massless, 0);
}

TEST(MassSpringExplicit, CutSpringsStayCutThroughThePass) {
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan("spleen600");
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;
  p.density = 1050.0;
  p.damping_ratio = 0.2;
  const auto model = MassSpringModel::FromSurface(organ.surface, p);
  const auto state = model->MakeState();
  // A blade through the organ's middle, across its whole extent.
  const Vector3d low = organ.surface.vertices.rowwise().minCoeff();
  const Vector3d high = organ.surface.vertices.rowwise().maxCoeff();
  const Vector3d mid = 0.5 * (low + high);
  const double reach = (high - low).norm();
  SweptQuad sweep;
  sweep.p0 = Vector3d(mid.x(), low.y() - reach, low.z() - reach);
  sweep.q0 = Vector3d(mid.x(), low.y() - reach, high.z() + reach);
  sweep.p1 = Vector3d(mid.x(), high.y() + reach, low.z() - reach);
  sweep.q1 = Vector3d(mid.x(), high.y() + reach, high.z() + reach);
  const int32_t removed = model->Cut(sweep, state.get());
  ASSERT_GT(removed, 0);
  // Pull the halves apart: cut springs would now pull hard if they still acted.
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    state->positions(0, i) += state->positions(0, i) > mid.x() ? 0.01 : -0.01;
  }
  Randomise(state.get(), 0.0, 0.05, 10);
  // The springs in the model's order: the surface's sorted unique edges.
  std::vector<std::array<int32_t, 2>> edges;
  const mesh::SurfaceMesh& surface = organ.surface;
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    for (int c = 0; c < 3; ++c) {
      const int32_t a = surface.triangles(c, t), b = surface.triangles((c + 1) % 3, t);
      edges.push_back({std::min(a, b), std::max(a, b)});
    }
  }
  std::sort(edges.begin(), edges.end());
  edges.erase(std::unique(edges.begin(), edges.end()), edges.end());
  ASSERT_EQ(static_cast<int32_t>(edges.size()), model->num_springs());
  // The plain loop on the model's constants, with the springs crossing the sweep removed.
  std::vector<double> k = model->stiffness(), d(edges.size());
  int32_t cut = 0;
  for (size_t s = 0; s < edges.size(); ++s) {
    const auto [i, j] = edges[s];
    const double mi = model->masses()[static_cast<size_t>(i)];
    const double mj = model->masses()[static_cast<size_t>(j)];
    d[s] = 2.0 * p.damping_ratio * std::sqrt(k[s] * mi * mj / (mi + mj));
    if (SegmentCrossesSweep(model->rest_positions().col(i), model->rest_positions().col(j),
                            sweep)) {
      k[s] = d[s] = 0.0;
      ++cut;
    }
  }
  ASSERT_EQ(cut, removed);
  const mesh::Points reference = PlainForces(*model, *state, edges, k, d);
  mesh::Points forces(3, model->num_nodes());
  model->InternalForces(*state, &forces);
  EXPECT_LT(RelativeDifference(forces, reference), 1e-12);
  {
    const ScalarPass scalar_pass;
    model->InternalForces(*state, &forces);
    EXPECT_LT(RelativeDifference(forces, reference), 1e-12);
  }
  // Through a step too.
  StepInputs inputs;
  inputs.dt = 1e-5;
  const mesh::Points x0 = state->positions, v0 = state->velocities;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  mesh::Points dv(3, model->num_nodes());
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    dv.col(i) = inputs.dt * reference.col(i) / model->masses()[static_cast<size_t>(i)];
  }
  EXPECT_LT(RelativeDifference(state->velocities - v0, dv), 1e-12);
  // (x - x0 would lose digits to cancellation: dt v is 1e-6 of x here.)
  EXPECT_LT(RelativeDifference(state->positions, x0 + inputs.dt * (v0 + dv)), 1e-15);
}

// Springs that share their (k, d) (raw constants here) keep a 2-byte index into a table of the
// distinct pairs: cutting sets the index to the pair (0, 0), and the pass (both paths) and a
// step with a grasp (the pass then reads the forces added before it) follow the plain loop.
TEST(MassSpringExplicit, PairTableCutsAndStepsLikeThePlainLoop) {
  const Graph g = StressGraph();
  MassSpringParameters p;
  p.spring_stiffness = 30.0;  // [N/m]
  p.node_mass = 0.002;        // [kg]
  p.damping_ratio = 0.4;
  const auto model = MassSpringModel::FromEdges(g.rest, g.edges, p);
  const auto state = model->MakeState();
  ASSERT_TRUE(MassSpringStateUsesPairTableForTesting(*state));
  // The spleen's springs all differ: they keep k and d per spring.
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan("spleen600");
  MassSpringParameters physical;
  physical.youngs_modulus = 3000.0;
  physical.density = 1050.0;
  EXPECT_FALSE(MassSpringStateUsesPairTableForTesting(
      *MassSpringModel::FromSurface(organ.surface, physical)->MakeState()));
  // A blade through the cloud's middle (x = 0.05).
  SweptQuad sweep;
  sweep.p0 = Vector3d(0.05, -1.0, -1.0);
  sweep.q0 = Vector3d(0.05, -1.0, 2.0);
  sweep.p1 = Vector3d(0.05, 2.0, -1.0);
  sweep.q1 = Vector3d(0.05, 2.0, 2.0);
  std::vector<double> k = model->stiffness(), d(g.edges.size());
  int32_t cut = 0;
  for (size_t s = 0; s < g.edges.size(); ++s) {
    d[s] = 2.0 * p.damping_ratio * std::sqrt(p.spring_stiffness * p.node_mass / 2.0);
    const auto [i, j] = g.edges[s];
    if (SegmentCrossesSweep(g.rest.col(i), g.rest.col(j), sweep)) {
      k[s] = d[s] = 0.0;
      ++cut;
    }
  }
  ASSERT_GT(cut, 0);
  ASSERT_EQ(model->Cut(sweep, state.get()), cut);
  Randomise(state.get(), 0.003, 0.1, 11);
  const mesh::Points reference = PlainForces(*model, *state, g.edges, k, d);
  mesh::Points forces(3, model->num_nodes());
  model->InternalForces(*state, &forces);
  EXPECT_LT(RelativeDifference(forces, reference), 1e-12);
  {
    const ScalarPass scalar_pass;
    model->InternalForces(*state, &forces);
    EXPECT_LT(RelativeDifference(forces, reference), 1e-12);
  }
  StepInputs inputs;
  inputs.dt = 1e-5;
  const Attachment grasp{7, Vector3d(0.2, 0.1, 0.0), 40.0};  // node, target [m], k [N/m]
  inputs.attachments = std::span<const Attachment>(&grasp, 1);
  const mesh::Points x0 = state->positions, v0 = state->velocities;
  mesh::Points dv = inputs.dt / p.node_mass * reference;
  dv.col(grasp.node) += inputs.dt / p.node_mass * grasp.stiffness * (grasp.target - x0.col(7));
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_LT(RelativeDifference(state->velocities - v0, dv), 1e-12);
  EXPECT_LT(RelativeDifference(state->positions, x0 + inputs.dt * (v0 + dv)), 1e-15);
}

// A tetrahedral box grid with a physical material (Van Gelder's rule). Congruent springs' constants
// differ only by rounding and are merged (each within 1e-12 of its rule), so the state keeps a
// table of few (k, d) pairs. Most of the pass's columns are runs of one edge kind (8 consecutive
// other nodes, some lanes empty at the box's faces) and one pair; the faces' columns mix kinds and
// pairs. A cut leaves one-pair columns with cut springs in them. Both passes give the plain
// loop's forces and step.
TEST(MassSpringExplicit, TetGridWithAPhysicalMaterialGivesThePlainForcesAfterACut) {
  const mesh::TetMesh grid =
      mesh_gen::BoxGridTets(9, 10, 11, Vector3d::Zero(), Vector3d(0.08, 0.09, 0.1));
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;  // [Pa]
  p.density = 1050.0;         // [kg/m³]
  p.damping_ratio = 0.1;
  const auto model = MassSpringModel::FromTetMesh(grid, p);
  const auto state = model->MakeState();
  ASSERT_TRUE(MassSpringStateUsesPairTableForTesting(*state));
  const MeshEdges edges = TetMeshEdges(grid, "test");
  ASSERT_EQ(edges.edges.size(), model->stiffness().size());
  std::vector<double> distinct = model->stiffness();
  for (size_t s = 0; s < edges.edges.size(); ++s) {
    const auto [i, j] = edges.edges[s];
    const double length = (grid.vertices.col(j) - grid.vertices.col(i)).norm();
    const double rule = p.youngs_modulus * edges.edge_size[s] / (length * length);
    ASSERT_LE(std::abs(model->stiffness()[s] - rule), 1e-12 * rule) << "spring " << s;
  }
  std::sort(distinct.begin(), distinct.end());
  distinct.erase(std::unique(distinct.begin(), distinct.end()), distinct.end());
  EXPECT_LE(distinct.size(), 40U);  // 7 edge kinds × the boxes' faces, edges and corners
  // A blade between two planes of nodes (x = 0.043 m).
  SweptQuad sweep;
  sweep.p0 = Vector3d(0.043, -1.0, -1.0);
  sweep.q0 = Vector3d(0.043, -1.0, 2.0);
  sweep.p1 = Vector3d(0.043, 2.0, -1.0);
  sweep.q1 = Vector3d(0.043, 2.0, 2.0);
  const auto scalar = model->MakeState();
  const int32_t cut = model->Cut(sweep, state.get());
  ASSERT_GT(cut, 0);
  ASSERT_EQ(model->Cut(sweep, scalar.get()), cut);
  Randomise(state.get(), 0.001, 0.05, 21);
  const auto& constants = static_cast<const MassSpringState&>(*state);
  const mesh::Points reference =
      PlainForces(*model, *state, edges.edges, constants.stiffness, constants.damping);
  scalar->positions = state->positions;
  scalar->velocities = state->velocities;
  StepInputs inputs;
  inputs.dt = 1e-5;
  ExpectBothPassesStepLikeThePlainLoop(*model, reference, inputs, state.get(), scalar.get());
}

}  // namespace
}  // namespace somasim::models
