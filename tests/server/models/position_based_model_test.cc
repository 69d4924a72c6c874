// Position-based particles (seed 004, SPEC §4.3): converged XPBD does not depend on the
// iteration count or the step, rigid seed links keep their lengths, projections keep momentum,
// XPBD springs and attachments carry loads with their physical stiffness, forces and local
// stiffness are energy derivatives, divergence is rolled back, steps allocate nothing, bad
// parameters are refused by name; the sweep's colouring is valid and the AVX-512 sweep agrees
// with the scalar one.
#include "server/models/position_based_model.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/closed_surface_mesher.h"
#include "common/mesh_gen/implicit.h"
#include "server/models/mass_spring_model.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models {
namespace {

using Eigen::Vector3d;

// Nodes whose coordinate `axis` lies within `band` [m] of its minimum (or maximum).
std::vector<int32_t> NodesAtExtreme(const mesh::Points& x, int axis, bool maximum, double band) {
  const double extreme = maximum ? x.row(axis).maxCoeff() : x.row(axis).minCoeff();
  std::vector<int32_t> nodes;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (std::abs(x(axis, i) - extreme) <= band) nodes.push_back(static_cast<int32_t>(i));
  }
  return nodes;
}

void Perturb(TissueState* state, double amplitude, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> offset(-amplitude, amplitude);
  for (Eigen::Index i = 0; i < state->positions.size(); ++i) {
    state->positions.data()[i] += offset(rng);
  }
}

PositionBasedParameters Xpbd(int iterations) {
  PositionBasedParameters p;
  p.mode = PositionBasedMode::kXpbd;
  p.youngs_modulus = 1e4;  // soft tissue [Pa]
  p.density = 1000.0;
  p.iterations = iterations;
  return p;
}

// External forces [N], 3 × n: `force` on `node`, zero elsewhere.
mesh::Points PointLoad(int32_t n, int32_t node, const Vector3d& force) {
  mesh::Points forces(3, n);
  for (int32_t i = 0; i < n; ++i) forces.col(i) = i == node ? force : Vector3d::Zero();
  return forces;
}

// The open tissue patch (E = 10 kPa, 5 mm thick), its side x = -25 mm fixed and its side
// x = +25 mm pulled 2 mm outwards, under gravity across its surface.
struct PatchPull {
  mesh::SurfaceMesh mesh = mesh_gen::GenerateBuiltinOrgan("tissue45").surface;
  std::vector<int32_t> left = NodesAtExtreme(mesh.vertices, 0, false, 0.003);
  std::vector<int32_t> right = NodesAtExtreme(mesh.vertices, 0, true, 0.003);
  mesh::Points targets;
  StepInputs Inputs(double dt, double pull) {
    targets.resize(3, static_cast<Eigen::Index>(right.size()));
    for (size_t k = 0; k < right.size(); ++k) {
      targets.col(static_cast<Eigen::Index>(k)) =
          mesh.vertices.col(right[k]) + Vector3d(pull, 0.0, 0.0);
    }
    StepInputs inputs;
    inputs.dt = dt;
    inputs.gravity = Vector3d(0.0, 0.0, -9.81);
    inputs.fixed_nodes = left;
    inputs.prescribed_nodes = right;
    inputs.prescribed_positions = &targets;
    return inputs;
  }
};

// Steps `model` from `start` (at rest) `steps` times; returns the final positions and the
// largest LastConstraintResidual seen.
mesh::Points RunFrom(const PositionBasedModel& model, const mesh::Points& start,
                     const StepInputs& inputs, int steps, double* residual) {
  const auto state = model.MakeState();
  state->positions = start;
  *residual = 0.0;
  for (int step = 0; step < steps; ++step) {
    EXPECT_EQ(model.Step(inputs, state.get()), StepStatus::kOk);
    *residual = std::max(*residual, model.LastConstraintResidual(*state));
  }
  return state->positions;
}

double MaxDistance(const mesh::Points& a, const mesh::Points& b) {
  return (a - b).colwise().norm().maxCoeff();
}

TEST(PositionBasedModel, ConvergedXpbdIsIndependentOfIterationCount) {
  const double kDt = 0.002;  // [s]
  const int kSettleSteps = 60;
  PatchPull patch;
  const mesh::Points& rest = patch.mesh.vertices;
  // 1. The same dynamic steps (the patch released at rest, pulled and falling) with 200 and 400
  //    sweeps: both converge (residual < 1e-8) and agree.
  PositionBasedParameters exact = Xpbd(200);
  exact.primal_correction = true;
  const auto xpbd200 = PositionBasedModel::FromSurface(patch.mesh, exact);
  exact.iterations = 400;
  const auto xpbd400 = PositionBasedModel::FromSurface(patch.mesh, exact);
  double residual200 = 0.0, residual400 = 0.0;
  const mesh::Points a = RunFrom(*xpbd200, rest, patch.Inputs(kDt, 0.002), 2, &residual200);
  const mesh::Points b = RunFrom(*xpbd400, rest, patch.Inputs(kDt, 0.002), 2, &residual400);
  EXPECT_LT(residual200, 1e-8);
  EXPECT_LT(residual400, 1e-8);
  const double moved = MaxDistance(a, rest);
  ASSERT_GT(moved, 0.0005);
  EXPECT_LT(MaxDistance(a, b), 1e-9 * moved);

  // 2. Steps dt and dt/2 at equilibrium. XPBD's springs are 1/compliance, the Van Gelder
  //    springs of the mass-spring model: its static solution (found by damped implicit Euler)
  //    must be a rest state of converged XPBD at any step, and of any sweep count.
  MassSpringParameters springs;
  springs.youngs_modulus = 1e4;
  springs.density = 1000.0;
  springs.damping_ratio = 0.2;
  springs.integrator = MassSpringIntegrator::kImplicitEuler;
  springs.cg_tolerance = 1e-10;
  springs.cg_max_iterations = 5000;
  const auto reference = MassSpringModel::FromSurface(patch.mesh, springs);
  const auto settled = reference->MakeState();
  const StepInputs hold = patch.Inputs(0.05, 0.002);
  for (int step = 0; step < kSettleSteps; ++step) {
    ASSERT_EQ(reference->Step(hold, settled.get()), StepStatus::kOk);
  }
  const mesh::Points& equilibrium = settled->positions;
  // From here the sweeps stop once converged (1e-13), to keep the test short.
  exact.tolerance = 1e-13;
  const auto xpbd = PositionBasedModel::FromSurface(patch.mesh, exact);
  const double sag = MaxDistance(equilibrium, rest);
  double residual = 0.0;
  const mesh::Points coarse = RunFrom(*xpbd, equilibrium, patch.Inputs(kDt, 0.002), 3, &residual);
  EXPECT_LT(residual, 1e-8);
  const mesh::Points fine = RunFrom(*xpbd, equilibrium, patch.Inputs(kDt / 2, 0.002), 6, &residual);
  EXPECT_LT(residual, 1e-8);
  const double drift_coarse = MaxDistance(coarse, equilibrium);
  const double drift_fine = MaxDistance(fine, equilibrium);
  EXPECT_LT(drift_coarse, 1e-6 * sag);
  EXPECT_LT(drift_fine, 1e-6 * sag);
  // Plain Gauss–Seidel XPBD (no primal correction) rests a little off: its lagged gradients.
  const auto plain = PositionBasedModel::FromSurface(patch.mesh, Xpbd(200));
  const double drift_plain = MaxDistance(
      RunFrom(*plain, equilibrium, patch.Inputs(kDt, 0.002), 3, &residual), equilibrium);
  // The seed's stiffness k, by contrast, is not a material: its rest state moves with the step
  // and the sweep count.
  PositionBasedParameters seed = Xpbd(10);
  seed.mode = PositionBasedMode::kSeedStiffness;
  seed.stiffness = 0.5;
  const auto seed_model = PositionBasedModel::FromSurface(patch.mesh, seed);
  const mesh::Points seed_coarse =
      RunFrom(*seed_model, equilibrium, patch.Inputs(kDt, 0.002), 3, &residual);
  EXPECT_GT(MaxDistance(seed_coarse, equilibrium), 100.0 * std::max(drift_coarse, drift_fine));
  std::printf(
      "200 vs 400 sweeps: residual %.1e / %.1e, difference %.1e m of %.1e m moved; from the "
      "static solution (sag %.1e m): xpbd drifts %.1e m (dt) / %.1e m (dt/2), plain xpbd %.1e m, "
      "seed mode %.1e m\n",
      residual200, residual400, MaxDistance(a, b), moved, sag, drift_coarse, drift_fine,
      drift_plain, MaxDistance(seed_coarse, equilibrium));
}

TEST(PositionBasedModel, RigidSeedStiffnessHoldsRestLengths) {
  // A chain of four rigid links (k = 1), fixed at one end, released horizontally: it swings
  // down under gravity while every link keeps its length.
  PositionBasedParameters p;
  p.mode = PositionBasedMode::kSeedStiffness;
  p.stiffness = 1.0;
  p.iterations = 200;
  p.node_mass = 0.01;
  mesh::Points rest(3, 5);
  for (int i = 0; i < 5; ++i) rest.col(i) = Vector3d(0.02 * i, 0.0, 0.0);
  const auto model = PositionBasedModel::FromEdges(rest, {{0, 1}, {1, 2}, {2, 3}, {3, 4}}, p);
  const int32_t fixed[] = {0};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;
  const auto state = model->MakeState();
  double worst = 0.0;
  for (int step = 0; step < 500; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    worst = std::max(worst, model->LastConstraintResidual(*state));
  }
  EXPECT_LT(state->positions(2, 4), -0.03);  // the free end swung down
  EXPECT_LT(worst, 1e-9);                    // yet every link kept its length
  EXPECT_EQ(state->positions.col(0), rest.col(0));
  // A soft link (k = 0.2, 2 sweeps) stretches visibly under the same load.
  p.stiffness = 0.2;
  p.iterations = 2;
  const auto soft = PositionBasedModel::FromEdges(rest, {{0, 1}, {1, 2}, {2, 3}, {3, 4}}, p);
  const auto soft_state = soft->MakeState();
  for (int step = 0; step < 500; ++step) soft->Step(inputs, soft_state.get());
  EXPECT_GT(soft->LastConstraintResidual(*soft_state), 1e-3);
}

TEST(PositionBasedModel, MomentumConservedWithoutExternalForces) {
  const mesh_gen::BuiltinOrgan patch = mesh_gen::GenerateBuiltinOrgan("tissue45");
  for (const PositionBasedMode mode :
       {PositionBasedMode::kSeedStiffness, PositionBasedMode::kXpbd}) {
    PositionBasedParameters p = Xpbd(10);
    p.mode = mode;
    p.stiffness = 0.5;
    const auto model = PositionBasedModel::FromSurface(patch.surface, p);
    const auto state = model->MakeState();
    Perturb(state.get(), 0.002, 4);
    std::mt19937 rng(5);
    std::normal_distribution<double> speed(0.0, 0.01);
    for (Eigen::Index i = 0; i < state->velocities.size(); ++i) {
      state->velocities.data()[i] = speed(rng);
    }
    StepInputs inputs;
    inputs.dt = 1e-3;
    const Vector3d p0 = model->Energy(*state, inputs.gravity).momentum;
    double mass = 0.0;
    for (const double m : model->masses()) mass += m;
    for (int step = 0; step < 50; ++step) {
      ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    }
    const Vector3d p1 = model->Energy(*state, inputs.gravity).momentum;
    EXPECT_LT((p1 - p0).norm(), 1e-12 * mass) << static_cast<int>(mode);
  }
}

TEST(PositionBasedModel, XpbdSpringAndAttachmentCarryTheLoadAtTheirStiffness) {
  // Node 1 hangs from fixed node 0 by one constraint (compliance 1/k) and is held at its rest
  // position by a grasp (k_a): under gravity along the link, static deflection m g / (k + k_a).
  PositionBasedParameters p;
  p.mode = PositionBasedMode::kXpbd;
  p.compliance = 1.0 / 40.0;  // [m/N]
  p.node_mass = 0.01;
  p.iterations = 100;
  mesh::Points rest(3, 2);
  rest << 0.0, 0.0, 0.0, 0.0, 0.0, -0.05;
  const auto model = PositionBasedModel::FromEdges(rest, {{0, 1}}, p);
  const auto state = model->MakeState();
  const int32_t fixed[] = {0};
  const Attachment grasp[] = {{1, rest.col(1), 20.0}};
  StepInputs inputs;
  inputs.dt = 0.05;  // backward-Euler-like steps damp the ringing
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;
  inputs.attachments = grasp;
  for (int step = 0; step < 100; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  }
  EXPECT_NEAR(state->positions(2, 1) - rest(2, 1), -0.01 * 9.81 / 60.0, 1e-9);
}

TEST(PositionBasedModel, ForcesAndLocalStiffnessAreEnergyDerivatives) {
  const mesh_gen::BuiltinOrgan patch = mesh_gen::GenerateBuiltinOrgan("tissue45");
  for (const PositionBasedMode mode :
       {PositionBasedMode::kXpbd, PositionBasedMode::kSeedStiffness}) {
    PositionBasedParameters p = Xpbd(10);
    p.mode = mode;
    p.stiffness = 0.3;
    const auto model = PositionBasedModel::FromSurface(patch.surface, p);
    const auto state = model->MakeState();
    Perturb(state.get(), 0.002, 2);
    const Vector3d g = Vector3d::Zero();
    mesh::Points forces(3, model->num_nodes()), plus(3, model->num_nodes()),
        minus(3, model->num_nodes());
    model->InternalForces(*state, &forces);
    for (const int32_t node : {0, 22, 44}) {
      const Eigen::Matrix3d k = model->LocalStiffness(*state, node);
      Eigen::Matrix3d fd;
      for (int axis = 0; axis < 3; ++axis) {
        const double h = 1e-7;
        const double x0 = state->positions(axis, node);
        state->positions(axis, node) = x0 + h;
        const double e_plus = model->Energy(*state, g).elastic;
        model->InternalForces(*state, &plus);
        state->positions(axis, node) = x0 - h;
        const double e_minus = model->Energy(*state, g).elastic;
        model->InternalForces(*state, &minus);
        state->positions(axis, node) = x0;
        fd.col(axis) = -(plus.col(node) - minus.col(node)) / (2 * h);
        const double gradient = (e_plus - e_minus) / (2 * h);
        EXPECT_NEAR(forces(axis, node), -gradient, 1e-6 * forces.col(node).norm());
      }
      EXPECT_LT((fd - k).norm(), 1e-6 * k.norm()) << "node " << node;
      EXPECT_LT((k - k.transpose()).norm(), 1e-12 * k.norm());
    }
  }
}

TEST(PositionBasedModel, StepAllocatesNothing) {
  const mesh_gen::BuiltinOrgan patch = mesh_gen::GenerateBuiltinOrgan("tissue45");
  const auto model = PositionBasedModel::FromSurface(patch.surface, Xpbd(10));
  const auto state = model->MakeState();
  mesh::Points external = PointLoad(model->num_nodes(), 5, Vector3d(0.0, 0.0, 0.01));
  const int32_t fixed[] = {0, 1, 2};
  const int32_t prescribed[] = {7};
  mesh::Points targets = state->positions.col(7);
  const Attachment grasp[] = {{11, state->positions.col(11) + Vector3d(0, 0, 0.001), 50.0},
                              {11, state->positions.col(11), 10.0}};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0, 0, -9.81);
  inputs.external_forces = &external;
  inputs.fixed_nodes = fixed;
  inputs.prescribed_nodes = prescribed;
  inputs.prescribed_positions = &targets;
  inputs.attachments = grasp;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);  // warm-up
  {
    const testing::AllocationCounter allocations;
    for (int step = 0; step < 20; ++step) model->Step(inputs, state.get());
    const Eigen::Matrix3d k = model->LocalStiffness(*state, 5);
    const double residual = model->LastConstraintResidual(*state);
    EXPECT_EQ(allocations.count(), 0);
    EXPECT_GT(k.trace(), 0.0);
    EXPECT_GE(residual, 0.0);
  }
  {
    // A diverging step, rolled back, allocates nothing either.
    external.col(5) = Vector3d(0.0, 0.0, 1e9);
    const testing::AllocationCounter allocations;
    const StepStatus status = model->Step(inputs, state.get());
    EXPECT_EQ(allocations.count(), 0);
    EXPECT_NE(status, StepStatus::kOk);
  }
}

TEST(PositionBasedModel, DivergenceIsRolledBackWithTheMultipliers) {
  // Projection cannot blow up, but an absurd load can throw a node past the speed limit: the
  // step is rejected, the state (multipliers included) is the last good one.
  const mesh_gen::BuiltinOrgan patch = mesh_gen::GenerateBuiltinOrgan("tissue45");
  const auto model = PositionBasedModel::FromSurface(patch.surface, Xpbd(20));
  const auto state = model->MakeState();
  mesh::Points external = PointLoad(model->num_nodes(), 3, Vector3d(0.0, 0.0, 1e-3));
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.external_forces = &external;
  for (int step = 0; step < 10; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  }
  const mesh::Points positions = state->positions;
  const mesh::Points velocities = state->velocities;
  const double residual = model->LastConstraintResidual(*state);
  external.col(3) = Vector3d(0.0, 0.0, 1e9);
  EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kRejectedTooFast);
  EXPECT_EQ(state->counters.rejected_steps, 1);
  EXPECT_EQ(state->counters.steps, 10);
  EXPECT_EQ(state->positions, positions);
  EXPECT_EQ(state->velocities, velocities);
  EXPECT_EQ(model->LastConstraintResidual(*state), residual);
  external.col(3) = Vector3d(0.0, 0.0, 1e-3);
  EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
}

// The step keeps the state it starts from as the last-good one (SavesGoodStateItself) and checks
// what it writes itself (ChecksStateItself): a rejected step, too fast or not finite, must
// restore that state bit for bit, also twice in a row, and the steps after it must be exactly
// those of a twin that never saw it, on both sweeps.
TEST(PositionBasedModel, RejectedStepRestoresTheStateExactly) {
  const mesh_gen::BuiltinOrgan patch = mesh_gen::GenerateBuiltinOrgan("tissue45");
  for (const bool vectorised : {false, true}) {
    PositionBasedParameters p = Xpbd(8);
    p.vectorised = vectorised;
    const auto model = PositionBasedModel::FromSurface(patch.surface, p);
    const auto state = model->MakeState();
    const auto twin = model->MakeState();
    const int32_t fixed[] = {0, 1};
    StepInputs inputs;
    inputs.dt = 1e-3;
    inputs.gravity = Vector3d(0.0, 0.0, -9.81);
    inputs.fixed_nodes = fixed;
    for (int step = 0; step < 5; ++step) {
      ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
      ASSERT_EQ(model->Step(inputs, twin.get()), StepStatus::kOk);
    }
    const mesh::Points positions = state->positions;
    const mesh::Points velocities = state->velocities;
    const int32_t n = model->num_nodes();
    const mesh::Points fast = PointLoad(n, 7, Vector3d(0.0, 0.0, 1e9));          // [N]
    const mesh::Points overflow = PointLoad(n, 7, Vector3d(0.0, 1e308, 1e308));  // [N]
    StepInputs blow_up = inputs;
    blow_up.external_forces = &fast;
    StepInputs infinite = inputs;
    infinite.external_forces = &overflow;
    EXPECT_EQ(model->Step(blow_up, state.get()), StepStatus::kRejectedTooFast) << vectorised;
    EXPECT_TRUE((state->positions.array() == positions.array()).all());
    EXPECT_TRUE((state->velocities.array() == velocities.array()).all());
    EXPECT_EQ(model->Step(infinite, state.get()), StepStatus::kRejectedNonFinite) << vectorised;
    EXPECT_TRUE((state->positions.array() == positions.array()).all());
    EXPECT_TRUE((state->velocities.array() == velocities.array()).all());
    EXPECT_EQ(state->counters.rejected_steps, 2);
    for (int step = 0; step < 5; ++step) {
      ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
      ASSERT_EQ(model->Step(inputs, twin.get()), StepStatus::kOk);
    }
    EXPECT_TRUE((state->positions.array() == twin->positions.array()).all()) << vectorised;
    EXPECT_TRUE((state->velocities.array() == twin->velocities.array()).all()) << vectorised;
  }
}

TEST(PositionBasedModel, ToleranceStopsTheSweepsEarly) {
  const mesh_gen::BuiltinOrgan patch = mesh_gen::GenerateBuiltinOrgan("tissue45");
  PositionBasedParameters p = Xpbd(1000);
  p.tolerance = 1e-10;
  const auto model = PositionBasedModel::FromSurface(patch.surface, p);
  const auto state = model->MakeState();
  StepInputs inputs;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  const std::vector<int32_t> side = NodesAtExtreme(patch.surface.vertices, 0, false, 0.003);
  inputs.fixed_nodes = side;
  for (int step = 0; step < 20; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  }
  EXPECT_EQ(state->counters.solver_unconverged, 0);
  EXPECT_LT(state->counters.solver_iterations, 20 * 1000);
  EXPECT_LT(model->LastConstraintResidual(*state), 1e-9);
}

// Every constraint is in exactly one colour and no two constraints of a colour share a node.
void ExpectValidColouring(const PositionBasedModel& model) {
  const std::vector<int32_t>& starts = model.colour_starts();
  const std::vector<int32_t>& slots = model.sweep_constraints();
  const int32_t m = model.num_constraints();
  ASSERT_GE(starts.size(), 2U);
  EXPECT_EQ(starts.front(), 0);
  EXPECT_EQ(starts.back(), m);
  ASSERT_EQ(static_cast<int32_t>(slots.size()), m);
  std::vector<int> seen(static_cast<size_t>(m), 0);
  std::vector<int32_t> last_colour(static_cast<size_t>(model.num_nodes()), -1);
  for (size_t c = 0; c + 1 < starts.size(); ++c) {
    EXPECT_LT(starts[c], starts[c + 1]) << "empty colour " << c;
    for (int32_t s = starts[c]; s < starts[c + 1]; ++s) {
      const int32_t e = slots[static_cast<size_t>(s)];
      ASSERT_GE(e, 0);
      ASSERT_LT(e, m);
      ++seen[static_cast<size_t>(e)];
      for (const int32_t node : model.constraint_nodes(e)) {
        EXPECT_NE(last_colour[static_cast<size_t>(node)], static_cast<int32_t>(c))
            << "node " << node << " twice in colour " << c;
        last_colour[static_cast<size_t>(node)] = static_cast<int32_t>(c);
      }
    }
  }
  EXPECT_EQ(std::count(seen.begin(), seen.end(), 1), m);
}

TEST(PositionBasedModel, ColouringPartitionsConstraintsWithoutSharedNodes) {
  for (const char* organ : {"tissue45", "spleen600", "kidney424"}) {
    const mesh_gen::BuiltinOrgan built = mesh_gen::GenerateBuiltinOrgan(organ);
    const auto model = built.spec->kind == mesh_gen::OrganKind::kVolume
                           ? PositionBasedModel::FromTetMesh(built.volume, Xpbd(10))
                           : PositionBasedModel::FromSurface(built.surface, Xpbd(10));
    SCOPED_TRACE(organ);
    ExpectValidColouring(*model);
    // Greedy colouring needs at most 2 · (max degree) - 1 colours; triangle and tetrahedron
    // meshes need a handful.
    EXPECT_LE(model->colour_starts().size() - 1, 40U);
  }
  // A star of 100 links: every constraint shares the hub, so 100 colours (past one 64-bit word).
  PositionBasedParameters p = Xpbd(10);
  p.node_mass = 0.01;
  p.compliance = 1e-3;
  mesh::Points rest(3, 101);
  std::vector<std::array<int32_t, 2>> star;
  for (int32_t i = 0; i <= 100; ++i) {
    rest.col(i) = Vector3d(std::cos(0.06 * i), std::sin(0.06 * i), 0.001 * i);
    if (i > 0) star.push_back({0, i});
  }
  const auto hub = PositionBasedModel::FromEdges(rest, star, p);
  ExpectValidColouring(*hub);
  EXPECT_EQ(hub->colour_starts().size(), 101U);
}

// The sweeps run on an internal renumbering of the nodes (reverse Cuthill–McKee): the public
// numbering is the caller's. The same patch numbered two ways, with fixed, prescribed, attached
// and loaded nodes, converges (tolerance 1e-12, primal correction: exact backward-Euler steps)
// to the same positions node for node.
TEST(PositionBasedModel, NodeNumberingDoesNotChangeTheSolution) {
  const mesh::SurfaceMesh mesh = mesh_gen::GenerateBuiltinOrgan("tissue45").surface;
  const auto n = static_cast<int32_t>(mesh.vertices.cols());
  std::vector<int32_t> renamed(static_cast<size_t>(n));  // old node -> new node
  for (int32_t i = 0; i < n; ++i) renamed[static_cast<size_t>(i)] = i;
  std::shuffle(renamed.begin(), renamed.end(), std::mt19937(7));
  mesh::SurfaceMesh shuffled = mesh;
  for (int32_t i = 0; i < n; ++i) {
    shuffled.vertices.col(renamed[static_cast<size_t>(i)]) = mesh.vertices.col(i);
  }
  for (Eigen::Index t = 0; t < mesh.triangles.cols(); ++t) {
    for (Eigen::Index k = 0; k < 3; ++k) {
      shuffled.triangles(k, t) = renamed[static_cast<size_t>(mesh.triangles(k, t))];
    }
  }
  PositionBasedParameters p = Xpbd(5000);
  p.tolerance = 1e-12;
  p.primal_correction = true;  // a converged step is then unique, whatever the sweep order
  const auto model_a = PositionBasedModel::FromSurface(mesh, p);
  const auto model_b = PositionBasedModel::FromSurface(shuffled, p);
  const auto a = model_a->MakeState();
  const auto b = model_b->MakeState();
  const auto to_b = [&renamed](int32_t i) { return renamed[static_cast<size_t>(i)]; };
  const std::vector<int32_t> fixed_a = NodesAtExtreme(mesh.vertices, 0, false, 0.003);
  std::vector<int32_t> fixed_b(fixed_a.size());
  std::transform(fixed_a.begin(), fixed_a.end(), fixed_b.begin(), to_b);
  const int32_t prescribed_a[] = {20};
  const int32_t prescribed_b[] = {to_b(20)};
  const mesh::Points target = mesh.vertices.col(20) + Vector3d(0.0, 0.0, 0.001);
  const Attachment grasp_a[] = {{30, mesh.vertices.col(30) + Vector3d(0.002, 0, 0), 40.0}};
  const Attachment grasp_b[] = {{to_b(30), grasp_a[0].target, 40.0}};
  const mesh::Points load_a = PointLoad(n, 12, Vector3d(0.0, 0.01, 0.0));
  const mesh::Points load_b = PointLoad(n, to_b(12), Vector3d(0.0, 0.01, 0.0));
  StepInputs inputs_a;
  inputs_a.dt = 1e-3;
  inputs_a.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs_a.external_forces = &load_a;
  inputs_a.prescribed_positions = &target;
  StepInputs inputs_b = inputs_a;
  inputs_b.external_forces = &load_b;
  inputs_a.fixed_nodes = fixed_a;
  inputs_b.fixed_nodes = fixed_b;
  inputs_a.prescribed_nodes = prescribed_a;
  inputs_b.prescribed_nodes = prescribed_b;
  inputs_a.attachments = grasp_a;
  inputs_b.attachments = grasp_b;
  for (int step = 0; step < 10; ++step) {
    ASSERT_EQ(model_a->Step(inputs_a, a.get()), StepStatus::kOk);
    ASSERT_EQ(model_b->Step(inputs_b, b.get()), StepStatus::kOk);
  }
  EXPECT_EQ(a->counters.solver_unconverged, 0);
  EXPECT_EQ(b->counters.solver_unconverged, 0);
  EXPECT_EQ(b->positions.col(to_b(20)), target.col(0));
  for (const int32_t i : fixed_a) EXPECT_EQ(b->positions.col(to_b(i)), mesh.vertices.col(i));
  const double moved = MaxDistance(a->positions, mesh.vertices);
  ASSERT_GT(moved, 1e-4);
  double difference = 0.0;
  for (int32_t i = 0; i < n; ++i) {
    difference = std::max(difference, (a->positions.col(i) - b->positions.col(to_b(i))).norm());
  }
  EXPECT_LT(difference, 1e-8 * moved);
  std::printf("moved %.2e m, renumbered vs original %.2e m\n", moved, difference);
}

TEST(PositionBasedModel, VectorisedSweepMatchesScalarSweep) {
  const mesh_gen::BuiltinOrgan spleen = mesh_gen::GenerateBuiltinOrgan("spleen600");
  for (const PositionBasedMode mode :
       {PositionBasedMode::kXpbd, PositionBasedMode::kSeedStiffness}) {
    PositionBasedParameters p = Xpbd(10);
    p.mode = mode;
    p.stiffness = 0.5;
    p.vectorised = false;
    const auto scalar = PositionBasedModel::FromSurface(spleen.surface, p);
    p.vectorised = true;
    const auto simd = PositionBasedModel::FromSurface(spleen.surface, p);
    EXPECT_FALSE(scalar->uses_simd());
    if (!simd->uses_simd()) GTEST_SKIP() << "no AVX-512 on this CPU: the scalar sweep only";
    const auto a = scalar->MakeState();
    const auto b = simd->MakeState();
    const int32_t fixed[] = {0, 1, 2};
    const Attachment grasp[] = {
        {40, spleen.surface.vertices.col(40) + Vector3d(0, 0, 0.002), 30.0}};
    StepInputs inputs;
    inputs.dt = 1e-3;
    inputs.gravity = Vector3d(0.0, 0.0, -9.81);
    inputs.fixed_nodes = fixed;
    inputs.attachments = grasp;
    for (int step = 0; step < 15; ++step) {
      ASSERT_EQ(scalar->Step(inputs, a.get()), StepStatus::kOk);
      ASSERT_EQ(simd->Step(inputs, b.get()), StepStatus::kOk);
    }
    const double moved = MaxDistance(a->positions, spleen.surface.vertices);
    ASSERT_GT(moved, 1e-5);
    const double difference = MaxDistance(a->positions, b->positions);
    EXPECT_LT(difference, 1e-12 * moved) << static_cast<int>(mode);
    // The residual (relative, ~1e-7 here) is a difference of nearly equal terms: absolute.
    EXPECT_NEAR(scalar->LastConstraintResidual(*a), simd->LastConstraintResidual(*b), 1e-12);
    std::printf("mode %d: moved %.2e m, SIMD vs scalar %.2e m\n", static_cast<int>(mode), moved,
                difference);
  }
}

// The multipliers are not zeroed between steps: the first sweep of a step takes every λ as 0
// and writes it. A state with a history of multipliers must step exactly like a fresh state
// at the same positions and velocities, in both sweeps.
TEST(PositionBasedModel, EachStepStartsItsMultipliersFromZero) {
  const mesh_gen::BuiltinOrgan spleen = mesh_gen::GenerateBuiltinOrgan("spleen600");
  for (const bool vectorised : {false, true}) {
    PositionBasedParameters p = Xpbd(6);
    p.vectorised = vectorised;
    const auto model = PositionBasedModel::FromSurface(spleen.surface, p);
    const int32_t fixed[] = {0, 1, 2};
    StepInputs inputs;
    inputs.dt = 1e-3;
    inputs.gravity = Vector3d(0.0, 0.0, -9.81);
    inputs.fixed_nodes = fixed;
    const auto used = model->MakeState();
    for (int step = 0; step < 12; ++step) {
      ASSERT_EQ(model->Step(inputs, used.get()), StepStatus::kOk);
    }
    ASSERT_GT(model->LastConstraintResidual(*used), 0.0);
    const auto fresh = model->MakeState();
    fresh->positions = used->positions;
    fresh->velocities = used->velocities;
    ASSERT_EQ(model->Step(inputs, used.get()), StepStatus::kOk);
    ASSERT_EQ(model->Step(inputs, fresh.get()), StepStatus::kOk);
    EXPECT_EQ(MaxDistance(used->positions, fresh->positions), 0.0) << vectorised;
    EXPECT_EQ(model->LastConstraintResidual(*used), model->LastConstraintResidual(*fresh));
  }
}

// The vectorised prediction (external forces, fixed and prescribed nodes) and sweeps against
// the scalar ones.
TEST(PositionBasedModel, VectorisedStepWithExternalForcesMatchesScalarStep) {
  PatchPull patch;
  const auto n = static_cast<int32_t>(patch.mesh.vertices.cols());
  PositionBasedParameters p = Xpbd(8);
  p.vectorised = false;
  const auto scalar = PositionBasedModel::FromSurface(patch.mesh, p);
  p.vectorised = true;
  const auto simd = PositionBasedModel::FromSurface(patch.mesh, p);
  if (!simd->uses_simd()) GTEST_SKIP() << "no AVX-512 on this CPU: the scalar step only";
  const mesh::Points push = PointLoad(n, n / 2, Vector3d(0.0, 0.02, 0.05));
  StepInputs inputs = patch.Inputs(1e-3, 0.002);
  inputs.external_forces = &push;
  const auto a = scalar->MakeState();
  const auto b = simd->MakeState();
  for (int step = 0; step < 20; ++step) {
    ASSERT_EQ(scalar->Step(inputs, a.get()), StepStatus::kOk);
    ASSERT_EQ(simd->Step(inputs, b.get()), StepStatus::kOk);
  }
  const double moved = MaxDistance(a->positions, patch.mesh.vertices);
  ASSERT_GT(moved, 1e-4);
  EXPECT_LT(MaxDistance(a->positions, b->positions), 1e-12 * moved);
  EXPECT_LT(MaxDistance(a->velocities, b->velocities), 1e-12 * moved / inputs.dt);
  for (const int32_t i : patch.left) EXPECT_EQ(b->positions.col(i), patch.mesh.vertices.col(i));
}

TEST(PositionBasedModel, BadParametersAreRefusedNamingThem) {
  const mesh_gen::BuiltinOrgan patch = mesh_gen::GenerateBuiltinOrgan("tissue45");
  const auto message = [&](const PositionBasedParameters& p) -> std::string {
    try {
      PositionBasedModel::FromSurface(patch.surface, p);
    } catch (const std::invalid_argument& error) {
      return error.what();
    }
    return "accepted";
  };
  const auto refused = [&](void (*change)(PositionBasedParameters*), const char* name) {
    PositionBasedParameters p = Xpbd(10);
    change(&p);
    EXPECT_NE(message(p).find(name), std::string::npos) << name << ": " << message(p);
  };
  refused([](PositionBasedParameters* p) { p->iterations = 0; }, "iterations");
  refused([](PositionBasedParameters* p) { p->stiffness = 0.0; }, "stiffness");
  refused([](PositionBasedParameters* p) { p->stiffness = 1.5; }, "stiffness");
  refused([](PositionBasedParameters* p) { p->stiffness = std::nan(""); }, "stiffness");
  refused([](PositionBasedParameters* p) { p->compliance = -1e-3; }, "compliance");
  refused([](PositionBasedParameters* p) { p->compliance = std::nan(""); }, "compliance");
  refused([](PositionBasedParameters* p) { p->youngs_modulus = std::nan(""); }, "youngs_modulus");
  refused([](PositionBasedParameters* p) { p->youngs_modulus = -5.0; }, "youngs_modulus");
  refused([](PositionBasedParameters* p) { p->density = 0.0; }, "density");
  refused([](PositionBasedParameters* p) { p->node_mass = -1.0; }, "node_mass");
  refused([](PositionBasedParameters* p) { p->thickness = std::nan(""); }, "thickness");
  refused([](PositionBasedParameters* p) { p->tolerance = -1.0; }, "tolerance");
  refused([](PositionBasedParameters* p) { p->speed_limit = 0.0; }, "speed_limit");
  EXPECT_EQ(message(Xpbd(10)), "accepted");
  // Seed mode needs no Young's modulus; XPBD with a raw compliance neither.
  PositionBasedParameters seed;
  seed.mode = PositionBasedMode::kSeedStiffness;
  EXPECT_EQ(message(seed), "accepted");
  PositionBasedParameters raw = Xpbd(10);
  raw.youngs_modulus = 0.0;
  raw.compliance = 1e-3;
  EXPECT_EQ(message(raw), "accepted");

  mesh::SurfaceMesh broken = patch.surface;
  broken.triangles(1, 4) = 999;
  EXPECT_THROW(PositionBasedModel::FromSurface(broken, Xpbd(10)), std::invalid_argument);
  mesh::Points two = mesh::Points::Zero(3, 2);
  raw.node_mass = 1.0;
  EXPECT_THROW(PositionBasedModel::FromEdges(two, {{0, 1}}, raw), std::invalid_argument);
  two(0, 1) = 1.0;
  EXPECT_THROW(PositionBasedModel::FromEdges(two, {{0, 2}}, raw), std::invalid_argument);
  EXPECT_NO_THROW(PositionBasedModel::FromEdges(two, {{0, 1}}, raw));
}

// A closed sphere of radius 2 cm (80 vertices), for the volume reaction.
mesh::SurfaceMesh SmallSphere() {
  const mesh_gen::Ellipsoid sphere(Vector3d::Zero(), Vector3d::Constant(0.02));
  mesh_gen::ClosedSurfaceOptions options;
  options.num_vertices = 80;
  return mesh_gen::MeshClosedSurface(sphere, options);
}

// x with node `node` scaled by `factor` towards the origin.
mesh::Points Scaled(const mesh::Points& x, int32_t node, double factor) {
  mesh::Points result = x;
  result.col(node) = factor * x.col(node);
  return result;
}

mesh::Points VolumeForces(const SolidAngleVolumeTerm& term, const mesh::Points& x) {
  mesh::Points forces = PointLoad(static_cast<int32_t>(x.cols()), 0, Vector3d::Zero());
  term.AddForces(x, &forces);
  return forces;
}

SolidAngleVolumeParameters VolumeReaction(double sigma, double gamma) {
  SolidAngleVolumeParameters v;
  v.sigma_plus = v.sigma_minus = sigma;
  v.gamma_plus = v.gamma_minus = gamma;
  return v;
}

TEST(PositionBasedModel, VolumeReactionForcesAndStiffnessAreEnergyDerivatives) {
  const mesh::SurfaceMesh sphere = SmallSphere();
  PositionBasedParameters p = Xpbd(10);
  p.volume = VolumeReaction(2e-3, 5e-3);
  const auto model = PositionBasedModel::FromSurface(sphere, p);
  ASSERT_NE(model->volume_term(), nullptr);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.002, 5);
  const Vector3d g = Vector3d::Zero();
  const int32_t n = model->num_nodes();
  mesh::Points forces(3, n), plus(3, n), minus(3, n);
  model->InternalForces(*state, &forces);
  for (const int32_t node : {0, 17, 41, 79}) {
    const Eigen::Matrix3d k = model->LocalStiffness(*state, node);
    Eigen::Matrix3d fd;
    for (int axis = 0; axis < 3; ++axis) {
      const double h = 1e-7;
      const double x0 = state->positions(axis, node);
      state->positions(axis, node) = x0 + h;
      const double e_plus = model->Energy(*state, g).elastic;
      model->InternalForces(*state, &plus);
      state->positions(axis, node) = x0 - h;
      const double e_minus = model->Energy(*state, g).elastic;
      model->InternalForces(*state, &minus);
      state->positions(axis, node) = x0;
      fd.col(axis) = -(plus.col(node) - minus.col(node)) / (2 * h);
      EXPECT_NEAR(forces(axis, node), -(e_plus - e_minus) / (2 * h),
                  1e-6 * forces.col(node).norm());
    }
    EXPECT_LT((fd - k).norm(), 1e-5 * k.norm()) << "node " << node;
  }
  // The reaction itself is a potential force: with the springs at rest length (a uniformly
  // scaled sphere keeps every solid angle, so it is zero) and a dent, it restores.
  const mesh::Points dented = Scaled(sphere.vertices, 17, 0.9);  // node 17 2 mm inwards
  const mesh::Points volume_only = VolumeForces(*model->volume_term(), dented);
  EXPECT_GT(volume_only.col(17).dot(dented.col(17)), 0.0);  // pushed back outwards
}

TEST(PositionBasedModel, VolumeReactionResistsADent) {
  // A sphere held at its bottom, pressed down at its top by a constant force: the volume
  // reaction makes the dent shallower than with the distance constraints alone.
  const mesh::SurfaceMesh sphere = SmallSphere();
  const std::vector<int32_t> bottom = NodesAtExtreme(sphere.vertices, 2, false, 0.004);
  int32_t top = 0;
  for (int32_t i = 0; i < sphere.vertices.cols(); ++i) {
    if (sphere.vertices(2, i) > sphere.vertices(2, top)) top = i;
  }
  const auto dent = [&](const SolidAngleVolumeParameters& volume) {
    PositionBasedParameters p = Xpbd(20);
    p.volume = volume;
    const auto model = PositionBasedModel::FromSurface(sphere, p);
    const auto state = model->MakeState();
    const mesh::Points load = PointLoad(model->num_nodes(), top, Vector3d(0.0, 0.0, -0.01));
    StepInputs inputs;
    inputs.dt = 1e-3;
    inputs.external_forces = &load;
    inputs.fixed_nodes = bottom;
    double mean = 0.0;
    for (int step = 0; step < 400; ++step) {
      EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kOk)
          << "step " << step << " sigma " << volume.sigma_plus;
      if (step >= 200) mean += sphere.vertices(2, top) - state->positions(2, top);
    }
    return mean / 200.0;  // [m], averaged over the last 200 steps
  };
  const double springs_only = dent(SolidAngleVolumeParameters{});
  const double with_volume = dent(VolumeReaction(5e-5, 0.0));
  const double stiffer_volume = dent(VolumeReaction(2e-4, 0.0));
  EXPECT_GT(springs_only, 1e-4);
  EXPECT_LT(with_volume, springs_only);
  EXPECT_LT(stiffer_volume, with_volume);
}

TEST(PositionBasedModel, VolumeReactionNeedsAClosedSurface) {
  PositionBasedParameters p = Xpbd(10);
  p.volume = VolumeReaction(1e-3, 0.0);
  const mesh::SurfaceMesh patch = mesh_gen::GenerateBuiltinOrgan("tissue45").surface;  // open
  try {
    PositionBasedModel::FromSurface(patch, p);
    ADD_FAILURE() << "an open surface was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("solid-angle volume"), std::string::npos) << e.what();
  }
  p.node_mass = 0.001;
  p.compliance = 0.01;
  const std::vector<std::array<int32_t, 2>> edges = {{0, 1}, {1, 2}};
  EXPECT_THROW(PositionBasedModel::FromEdges(patch.vertices, edges, p), std::invalid_argument);
  p.volume.sigma_plus = -1.0;
  EXPECT_THROW(PositionBasedModel::FromSurface(SmallSphere(), p), std::invalid_argument);
  p.volume.sigma_plus = std::nan("");
  EXPECT_THROW(PositionBasedModel::FromSurface(SmallSphere(), p), std::invalid_argument);
}

TEST(PositionBasedModel, VolumeReactionStepAllocatesNothing) {
  PositionBasedParameters p = Xpbd(10);
  p.volume = VolumeReaction(1e-4, 1e-4);
  const auto model = PositionBasedModel::FromSurface(SmallSphere(), p);
  const auto state = model->MakeState();
  const mesh::Points load = PointLoad(model->num_nodes(), 3, Vector3d(0.0, 0.0, -0.01));
  StepInputs inputs;
  inputs.external_forces = &load;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  testing::AllocationCounter counter;
  for (int step = 0; step < 20; ++step)
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_EQ(counter.count(), 0);
}

}  // namespace
}  // namespace somasim::models
