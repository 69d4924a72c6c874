// Mass-spring model (seed 002 §2.1, SPEC §4.1): forces are exact energy gradients, the local
// stiffness is the force Jacobian, the integrator keeps energy and momentum, a spring rings at
// √(k/m), divergence is caught and rolled back, steps allocate nothing, bad input is refused.
#include "server/models/mass_spring_model.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models {
namespace {

using Eigen::Vector3d;

std::unique_ptr<MassSpringModel> OrganModel(const std::string& name, double damping_ratio) {
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan(name);
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;  // soft tissue [Pa]
  p.density = 1050.0;
  p.damping_ratio = damping_ratio;
  return organ.spec->kind == mesh_gen::OrganKind::kVolume
             ? MassSpringModel::FromTetMesh(organ.volume, p)
             : MassSpringModel::FromSurface(organ.surface, p);
}

// External forces [N], 3 × n: `force` on `node`, zero elsewhere.
mesh::Points PointLoad(int32_t n, int32_t node, const Vector3d& force) {
  mesh::Points forces(3, n);
  for (int32_t i = 0; i < n; ++i) forces.col(i) = i == node ? force : Vector3d::Zero();
  return forces;
}

// Moves every node by a seeded random offset of up to `amplitude` [m].
void Perturb(TissueState* state, double amplitude, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> offset(-amplitude, amplitude);
  for (Eigen::Index i = 0; i < state->positions.size(); ++i) {
    state->positions.data()[i] += offset(rng);
  }
}

// A time step well inside the explicit stability limit: ω_max² <= max_i 2 Σ_{s∋i} k_s / m_i
// (Gershgorin on M⁻¹K with springs along any direction).
double SafeStep(const MassSpringModel& model, double fraction) {
  std::vector<double> k_sum(static_cast<size_t>(model.num_nodes()), 0.0);
  // Σ k over springs per node, from the local stiffness trace bound at rest (trace = Σ k).
  const auto state = model.MakeState();
  double omega2 = 0.0;
  for (int32_t i = 0; i < model.num_nodes(); ++i) {
    const double k = model.LocalStiffness(*state, i).trace();
    omega2 = std::max(omega2, 4.0 * k / model.masses()[static_cast<size_t>(i)]);
  }
  return fraction * 2.0 / std::sqrt(omega2);
}

TEST(MassSpringModel, ForceIsNegativeEnergyGradient) {
  const auto model = OrganModel("kidney424", 0.0);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.003, 1);
  mesh::Points forces(3, model->num_nodes());
  model->InternalForces(*state, &forces);
  const Vector3d g = Vector3d::Zero();
  double worst = 0.0;
  for (int32_t node = 0; node < model->num_nodes(); node += 37) {
    for (int axis = 0; axis < 3; ++axis) {
      const double h = 1e-7;
      const double x0 = state->positions(axis, node);
      state->positions(axis, node) = x0 + h;
      const double plus = model->Energy(*state, g).elastic;
      state->positions(axis, node) = x0 - h;
      const double minus = model->Energy(*state, g).elastic;
      state->positions(axis, node) = x0;
      const double gradient = (plus - minus) / (2 * h);
      const double scale =
          std::max(std::abs(forces(axis, node)), 1e-3 * forces.cwiseAbs().maxCoeff());
      worst = std::max(worst, std::abs(forces(axis, node) + gradient) / scale);
    }
  }
  EXPECT_LT(worst, 1e-6);
}

// Seed 002 eq. 1–3 written out plainly, one spring at a time: the reference the model's blocked
// (and, where the CPU has it, AVX-512) force pass must reproduce. `edges` sorted as the model
// stores its springs; damping D = 2 ζ √(k m_i m_j / (m_i + m_j)) as documented.
mesh::Points ReferenceForces(const MassSpringModel& model, const TissueState& state,
                             const std::vector<std::array<int32_t, 2>>& edges,
                             double damping_ratio) {
  mesh::Points f = mesh::Points::Zero(3, model.num_nodes());
  EXPECT_EQ(static_cast<int32_t>(edges.size()), model.num_springs());
  for (size_t s = 0; s < edges.size(); ++s) {
    const auto [i, j] = edges[s];
    const double k = model.stiffness()[s];
    const double mi = model.masses()[static_cast<size_t>(i)];
    const double mj = model.masses()[static_cast<size_t>(j)];
    const double d = 2.0 * damping_ratio * std::sqrt(k * mi * mj / (mi + mj));
    const double l0 = (model.rest_positions().col(j) - model.rest_positions().col(i)).norm();
    const Vector3d delta = state.positions.col(j) - state.positions.col(i);
    const double l = delta.norm();
    const Vector3d u = delta / l;
    const double closing = (state.velocities.col(j) - state.velocities.col(i)).dot(u);
    const Vector3d force = (k * (l - l0) + d * closing) * u;
    f.col(i) += force;
    f.col(j) -= force;
  }
  return f;
}

// The sorted unique edges of a triangle surface: the springs of FromSurface, in its order.
std::vector<std::array<int32_t, 2>> SurfaceEdgeList(const mesh::SurfaceMesh& surface) {
  std::vector<std::array<int32_t, 2>> edges;
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    for (int c = 0; c < 3; ++c) {
      const int32_t a = surface.triangles(c, t), b = surface.triangles((c + 1) % 3, t);
      edges.push_back({std::min(a, b), std::max(a, b)});
    }
  }
  std::sort(edges.begin(), edges.end());
  edges.erase(std::unique(edges.begin(), edges.end()), edges.end());
  return edges;
}

// Random velocities of up to `amplitude` [m/s].
void Shake(TissueState* state, double amplitude, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> speed(-amplitude, amplitude);
  for (Eigen::Index i = 0; i < state->velocities.size(); ++i) {
    state->velocities.data()[i] = speed(rng);
  }
}

double RelativeDifference(const mesh::Points& a, const mesh::Points& b) {
  return (a - b).cwiseAbs().maxCoeff() / b.cwiseAbs().maxCoeff();
}

TEST(MassSpringModel, FastForcePassEqualsPlainSpringLoopOnAnOrgan) {
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan("spleen600");
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;
  p.density = 1050.0;
  p.damping_ratio = 0.2;
  const auto model = MassSpringModel::FromSurface(organ.surface, p);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.002, 11);
  Shake(state.get(), 0.05, 12);
  mesh::Points forces(3, model->num_nodes());
  model->InternalForces(*state, &forces);
  const mesh::Points reference =
      ReferenceForces(*model, *state, SurfaceEdgeList(organ.surface), p.damping_ratio);
  EXPECT_LT(RelativeDifference(forces, reference), 1e-12);
}

// Springs on a jittered 12 × 12 × 12 grid with irregular runs (empty runs, runs of 1..40 springs,
// a hub joined to 300 nodes: a run longer than the pass's block of springs), through
// InternalForces and through a whole explicit step with every kind of input.
TEST(MassSpringModel, FastPathsEqualPlainSpringLoopOnIrregularRuns) {
  const int32_t side = 12, n = side * side * side;
  mesh::Points rest(3, n);
  std::mt19937 rng(21);
  std::uniform_real_distribution<double> jitter(-0.002, 0.002);
  for (int32_t i = 0; i < n; ++i) {
    const int32_t cx = i % side, cy = (i / side) % side, cz = i / (side * side);  // grid cell
    rest.col(i) = 0.01 * Vector3d(cx, cy, cz) + Vector3d(jitter(rng), jitter(rng), jitter(rng));
  }
  std::vector<std::array<int32_t, 2>> edges;
  std::uniform_int_distribution<int32_t> count(0, 40), other(0, n - 1);
  for (int32_t i = 0; i < n; ++i) {
    const int32_t run = i % 7 == 3 ? 0 : count(rng);
    for (int32_t e = 0; e < run; ++e) {
      const int32_t j = other(rng);
      if (j != i) edges.push_back({std::min(i, j), std::max(i, j)});
    }
  }
  for (int32_t j = 1; j <= 300; ++j) edges.push_back({0, 5 * j});  // the hub
  std::sort(edges.begin(), edges.end());
  edges.erase(std::unique(edges.begin(), edges.end()), edges.end());
  MassSpringParameters p;
  p.spring_stiffness = 20.0;  // [N/m]
  p.node_mass = 0.001;        // [kg]
  p.damping_ratio = 0.3;
  const auto model = MassSpringModel::FromEdges(rest, edges, p);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.001, 22);
  Shake(state.get(), 0.05, 23);

  mesh::Points forces(3, n);
  model->InternalForces(*state, &forces);
  const mesh::Points reference = ReferenceForces(*model, *state, edges, p.damping_ratio);
  EXPECT_LT(RelativeDifference(forces, reference), 1e-12);

  // One step: v += dt (f/m + g), x += dt v (seed 002 eq. 4–5) with external forces and a grasp.
  const mesh::Points external = PointLoad(n, 17, Vector3d(0.0, 0.01, 0.0));
  const Attachment grasp[] = {{40, state->positions.col(40) + Vector3d(0, 0, 0.001), 5.0}};
  StepInputs inputs;
  inputs.dt = 1e-4;
  inputs.gravity = Vector3d(0, 0, -9.81);
  inputs.external_forces = &external;
  inputs.attachments = grasp;
  mesh::Points total = reference + external;
  total.col(40) += grasp[0].stiffness * (grasp[0].target - state->positions.col(40));
  const mesh::Points x0 = state->positions, v0 = state->velocities;
  mesh::Points dv(3, n);
  for (int32_t i = 0; i < n; ++i) {
    dv.col(i) = inputs.dt * (total.col(i) / p.node_mass + inputs.gravity);
  }
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_LT(RelativeDifference(state->velocities - v0, dv), 1e-12);
  EXPECT_LT(RelativeDifference(state->positions - x0, inputs.dt * (v0 + dv)), 1e-12);
  // A second step starts from zero pending forces: the same again from the new state.
  const mesh::Points reference2 = ReferenceForces(*model, *state, edges, p.damping_ratio);
  mesh::Points total2 = reference2 + external;
  total2.col(40) += grasp[0].stiffness * (grasp[0].target - state->positions.col(40));
  const mesh::Points x1 = state->positions, v1 = state->velocities;
  for (int32_t i = 0; i < n; ++i) {
    dv.col(i) = inputs.dt * (total2.col(i) / p.node_mass + inputs.gravity);
  }
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_LT(RelativeDifference(state->velocities - v1, dv), 1e-12);
  EXPECT_LT(RelativeDifference(state->positions - x1, inputs.dt * (v1 + dv)), 1e-12);
}

TEST(MassSpringModel, LocalStiffnessIsTheForceJacobian) {
  const auto model = OrganModel("spleen600", 0.0);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.002, 2);
  mesh::Points plus(3, model->num_nodes()), minus(3, model->num_nodes());
  for (const int32_t node : {0, 123, 599}) {
    const Eigen::Matrix3d k = model->LocalStiffness(*state, node);
    Eigen::Matrix3d fd;
    for (int axis = 0; axis < 3; ++axis) {
      const double h = 1e-7;
      const double x0 = state->positions(axis, node);
      state->positions(axis, node) = x0 + h;
      model->InternalForces(*state, &plus);
      state->positions(axis, node) = x0 - h;
      model->InternalForces(*state, &minus);
      state->positions(axis, node) = x0;
      fd.col(axis) = -(plus.col(node) - minus.col(node)) / (2 * h);
    }
    EXPECT_LT((fd - k).norm(), 1e-6 * k.norm()) << "node " << node << "\n" << fd << "\n" << k;
    EXPECT_LT((k - k.transpose()).norm(), 1e-12 * k.norm());
  }
}

TEST(MassSpringModel, SingleSpringOscillatesAtSqrtKOverM) {
  MassSpringParameters p;
  p.spring_stiffness = 40.0;  // [N/m]
  p.node_mass = 0.01;         // [kg]
  p.damping_ratio = 0.0;
  mesh::Points rest(3, 2);
  rest << 0.0, 0.05, 0.0, 0.0, 0.0, 0.0;
  const auto model = MassSpringModel::FromEdges(rest, {{0, 1}}, p);
  const auto state = model->MakeState();
  state->positions(0, 1) += 0.001;  // stretch 1 mm
  const double omega = std::sqrt(40.0 / 0.01);
  StepInputs inputs;
  inputs.dt = 2 * std::numbers::pi / omega / 2000.0;
  const int32_t fixed[] = {0};
  inputs.fixed_nodes = fixed;
  // Time the upward zero crossings of the displacement over 20 periods.
  double first = -1.0, last = -1.0;
  int crossings = 0;
  double previous = state->positions(0, 1) - 0.05;
  for (int step = 0; step < 2000 * 20 + 10; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    const double now = state->positions(0, 1) - 0.05;
    if (previous < 0.0 && now >= 0.0) {
      const double t = state->time - inputs.dt * now / (now - previous);
      if (first < 0.0) first = t;
      last = t;
      ++crossings;
    }
    previous = now;
  }
  ASSERT_GE(crossings, 10);
  const double measured = 2 * std::numbers::pi * (crossings - 1) / (last - first);
  EXPECT_NEAR(measured, omega, 0.005 * omega);
}

TEST(MassSpringModel, UndampedSymplecticEulerKeepsEnergyWithinOnePercent) {
  const auto model = OrganModel("spleen600", 0.0);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.002, 3);
  StepInputs inputs;
  // Symplectic Euler conserves a modified energy; the true energy wobbles by about ω·dt/2 of
  // the fastest mode, so the step is a twentieth of the stability bound.
  inputs.dt = SafeStep(*model, 0.05);
  const double e0 = model->Energy(*state, inputs.gravity).total();
  double worst = 0.0;
  for (int step = 0; step < 10000; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    if (step % 100 == 0) {
      worst = std::max(worst, std::abs(model->Energy(*state, inputs.gravity).total() - e0));
    }
  }
  EXPECT_LT(worst, 0.01 * e0);
}

TEST(MassSpringModel, MomentumIsConservedWithoutExternalForce) {
  const auto model = OrganModel("kidney424", 0.3);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.002, 4);
  std::mt19937 rng(5);
  std::normal_distribution<double> speed(0.0, 0.01);
  for (Eigen::Index i = 0; i < state->velocities.size(); ++i)
    state->velocities.data()[i] = speed(rng);
  StepInputs inputs;
  inputs.dt = SafeStep(*model, 0.3);
  const Vector3d p0 = model->Energy(*state, inputs.gravity).momentum;
  double mass = 0.0;
  for (const double m : model->masses()) mass += m;
  for (int step = 0; step < 500; ++step)
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  const Vector3d p1 = model->Energy(*state, inputs.gravity).momentum;
  EXPECT_LT((p1 - p0).norm(), 1e-12 * mass);
  // Damping along the springs took energy out of the internal motion.
  EXPECT_GT(state->counters.steps, 0);
}

TEST(MassSpringModel, DivergenceIsDetectedRolledBackAndCounted) {
  const auto model = OrganModel("liver288", 0.0);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.002, 6);
  StepInputs inputs;
  inputs.dt = SafeStep(*model, 20.0);  // ten times past the stability limit
  StepStatus status = StepStatus::kOk;
  int step = 0;
  for (; step < 1000 && status == StepStatus::kOk; ++step)
    status = model->Step(inputs, state.get());
  ASSERT_NE(status, StepStatus::kOk) << "explicit Euler did not diverge at 10x the limit";
  EXPECT_EQ(state->counters.rejected_steps, 1);
  EXPECT_TRUE(state->positions.allFinite());
  EXPECT_TRUE(state->velocities.allFinite());
  // The state is the last accepted one: a stable step from it succeeds.
  inputs.dt = SafeStep(*model, 0.3);
  EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
}

TEST(MassSpringModel, RejectedExplicitStepRestoresTheStateExactly) {
  // The explicit step saves the state it starts from during its own pass (SavesGoodStateItself):
  // a rejected step must restore it bit for bit and leave nothing behind, so the steps after it
  // are exactly those of a state that never saw it, also after two rejections in a row.
  const auto model = OrganModel("liver288", 0.1);
  const auto state = model->MakeState();
  const auto twin = model->MakeState();
  Perturb(state.get(), 0.002, 7);
  twin->positions = state->positions;
  StepInputs inputs;
  inputs.dt = SafeStep(*model, 0.3);
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  for (int step = 0; step < 3; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    ASSERT_EQ(model->Step(inputs, twin.get()), StepStatus::kOk);
  }
  const mesh::Points positions = state->positions;
  const mesh::Points velocities = state->velocities;
  StepInputs blow_up = inputs;
  const mesh::Points blow = PointLoad(model->num_nodes(), 10, Vector3d(0.0, 0.0, 1e9));  // [N]
  blow_up.external_forces = &blow;
  for (int attempt = 0; attempt < 2; ++attempt) {
    EXPECT_EQ(model->Step(blow_up, state.get()), StepStatus::kRejectedTooFast);
    EXPECT_TRUE((state->positions.array() == positions.array()).all());
    EXPECT_TRUE((state->velocities.array() == velocities.array()).all());
  }
  EXPECT_EQ(state->counters.rejected_steps, 2);
  for (int step = 0; step < 3; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    ASSERT_EQ(model->Step(inputs, twin.get()), StepStatus::kOk);
  }
  EXPECT_TRUE((state->positions.array() == twin->positions.array()).all());
  EXPECT_TRUE((state->velocities.array() == twin->velocities.array()).all());
  EXPECT_EQ(state->time, twin->time);
}

TEST(MassSpringModel, StepAllocatesNothing) {
  const auto model = OrganModel("kidney424", 0.1);
  const auto state = model->MakeState();
  const mesh::Points external = PointLoad(model->num_nodes(), 5, Vector3d(0.0, 0.0, 0.01));
  const int32_t fixed[] = {0, 1, 2};
  const int32_t prescribed[] = {7};
  mesh::Points targets = state->positions.col(7);
  const Attachment grasp[] = {{11, state->positions.col(11) + Vector3d(0, 0, 0.001), 50.0}};
  StepInputs inputs;
  inputs.dt = SafeStep(*model, 0.3);
  inputs.gravity = Vector3d(0, 0, -9.81);
  inputs.external_forces = &external;
  inputs.fixed_nodes = fixed;
  inputs.prescribed_nodes = prescribed;
  inputs.prescribed_positions = &targets;
  inputs.attachments = grasp;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);  // warm-up
  {
    const testing::AllocationCounter allocations;
    for (int step = 0; step < 100; ++step) model->Step(inputs, state.get());
    const Eigen::Matrix3d k = model->LocalStiffness(*state, 5);
    EXPECT_EQ(allocations.count(), 0);
    EXPECT_GT(k.trace(), 0.0);
  }
  {
    // A diverging step, rolled back, allocates nothing either.
    inputs.dt = 1e6;
    const testing::AllocationCounter allocations;
    const StepStatus status = model->Step(inputs, state.get());
    EXPECT_EQ(allocations.count(), 0);
    EXPECT_NE(status, StepStatus::kOk);
  }
}

TEST(MassSpringModel, FixedAndPrescribedNodesFollowTheirInputs) {
  const auto model = OrganModel("plate192", 0.1);
  const auto state = model->MakeState();
  const mesh::Points rest = state->positions;
  const int32_t fixed[] = {0, 1};
  const int32_t prescribed[] = {100};
  mesh::Points targets = rest.col(100) + Vector3d(0, 0, 0.002);
  StepInputs inputs;
  inputs.dt = SafeStep(*model, 0.3);
  inputs.gravity = Vector3d(0, 0, -9.81);
  inputs.fixed_nodes = fixed;
  inputs.prescribed_nodes = prescribed;
  inputs.prescribed_positions = &targets;
  for (int step = 0; step < 50; ++step)
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_EQ(state->positions.col(0), rest.col(0));
  EXPECT_EQ(state->positions.col(1), rest.col(1));
  EXPECT_EQ(state->velocities.col(0), Vector3d::Zero());
  EXPECT_EQ(state->positions.col(100), targets.col(0));
  EXPECT_LT(state->positions(2, 150), rest(2, 150));  // the rest falls under gravity
}

// Nodes of `mesh` whose coordinate `axis` is within `tolerance` [m] of its extreme (max if
// `upper`), e.g. the top edge of the plate.
std::vector<int32_t> NodesAtExtreme(const mesh::Points& points, int axis, bool upper,
                                    double tolerance) {
  const double extreme = upper ? points.row(axis).maxCoeff() : points.row(axis).minCoeff();
  std::vector<int32_t> nodes;
  for (Eigen::Index i = 0; i < points.cols(); ++i) {
    if (std::abs(points(axis, i) - extreme) <= tolerance) nodes.push_back(static_cast<int32_t>(i));
  }
  return nodes;
}

TEST(MassSpringModel, ImplicitEulerIsStableWhereExplicitDiverges) {
  const mesh_gen::BuiltinOrgan liver = mesh_gen::GenerateBuiltinOrgan("liver288");
  MassSpringParameters p;
  p.youngs_modulus = 2e5;  // stiff tissue [Pa]
  p.density = 1050.0;
  p.damping_ratio = 0.05;
  const std::vector<int32_t> fixed = NodesAtExtreme(liver.volume.vertices, 0, false, 0.02);
  ASSERT_GE(fixed.size(), 3u);
  StepInputs inputs;
  inputs.dt = 1e-3;  // [s], the server's physics step
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;

  const auto explicit_model = MassSpringModel::FromTetMesh(liver.volume, p);
  ASSERT_GT(inputs.dt, SafeStep(*explicit_model, 2.0));  // past the explicit limit
  const auto explicit_state = explicit_model->MakeState();
  StepStatus status = StepStatus::kOk;
  for (int step = 0; step < 200 && status == StepStatus::kOk; ++step) {
    status = explicit_model->Step(inputs, explicit_state.get());
  }
  EXPECT_NE(status, StepStatus::kOk);                  // diverged, detected ...
  EXPECT_TRUE(explicit_state->positions.allFinite());  // ... and contained
  EXPECT_EQ(explicit_state->counters.rejected_steps, 1);

  p.integrator = MassSpringIntegrator::kImplicitEuler;
  const auto implicit_model = MassSpringModel::FromTetMesh(liver.volume, p);
  const auto state = implicit_model->MakeState();
  for (int step = 0; step < 500; ++step) {
    ASSERT_EQ(implicit_model->Step(inputs, state.get()), StepStatus::kOk) << "step " << step;
  }
  EXPECT_EQ(state->counters.solver_unconverged, 0);
  const double sag = (state->positions - implicit_model->rest_positions()).row(2).minCoeff();
  EXPECT_LT(sag, 0.0);    // it hangs ...
  EXPECT_GT(sag, -0.05);  // ... by less than 5 cm
}

TEST(MassSpringModel, HangingPlateConvergesToStaticEquilibrium) {
  // Seed 003's plate (E = 1 MPa), its top edge fixed, hanging under gravity in its own plane.
  const mesh_gen::BuiltinOrgan plate = mesh_gen::GenerateBuiltinOrgan("plate192");
  MassSpringParameters p;
  p.youngs_modulus = 1e6;
  p.density = 1000.0;
  p.damping_ratio = 0.2;
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  p.cg_tolerance = 1e-12;
  p.cg_max_iterations = 5000;
  const auto model = MassSpringModel::FromTetMesh(plate.volume, p);
  const std::vector<int32_t> top = NodesAtExtreme(plate.volume.vertices, 1, true, 1e-9);
  ASSERT_EQ(top.size(), 24u);  // 12 × 2 nodes on the edge y = 200 mm
  // Large implicit steps damp every mode, the slow pendulum-like swings too (L-stability), so
  // the state settles where the linearised step no longer moves it: the static solution.
  StepInputs inputs;
  inputs.dt = 0.05;
  inputs.gravity = Vector3d(0.0, -9.81, 0.0);
  inputs.fixed_nodes = top;
  const auto state = model->MakeState();
  for (int step = 0; step < 100; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  }
  EXPECT_EQ(state->counters.solver_unconverged, 0);
  // At equilibrium the springs carry the weight: the net force on every free node vanishes.
  mesh::Points forces(3, model->num_nodes());
  state->velocities.setZero();
  model->InternalForces(*state, &forces);
  double weight = 0.0;
  std::vector<bool> is_fixed(static_cast<size_t>(model->num_nodes()), false);
  for (const int32_t node : top) is_fixed[static_cast<size_t>(node)] = true;
  double worst = 0.0;
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    const double m = model->masses()[static_cast<size_t>(i)];
    weight += m * 9.81;
    if (is_fixed[static_cast<size_t>(i)]) continue;
    worst = std::max(worst, (forces.col(i) + m * inputs.gravity).norm());
  }
  EXPECT_LT(worst, 1e-9 * weight);
  // The supports of the fixed edge carry the whole weight: their reaction, minus the net force
  // on the fixed nodes, points up and equals it.
  double reaction = 0.0;
  for (const int32_t node : top) {
    reaction -= forces(1, node) + model->masses()[static_cast<size_t>(node)] * inputs.gravity.y();
  }
  EXPECT_NEAR(reaction, weight, 1e-6 * weight);
}

TEST(MassSpringModel, ImplicitStepAllocatesNothing) {
  const mesh_gen::BuiltinOrgan kidney = mesh_gen::GenerateBuiltinOrgan("kidney424");
  MassSpringParameters p;
  p.youngs_modulus = 5e4;
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  const auto model = MassSpringModel::FromTetMesh(kidney.volume, p);
  const auto state = model->MakeState();
  const int32_t fixed[] = {0, 1, 2};
  const Attachment grasp[] = {{11, state->positions.col(11) + Vector3d(0, 0, 0.002), 50.0}};
  StepInputs inputs;
  inputs.gravity = Vector3d(0, 0, -9.81);
  inputs.fixed_nodes = fixed;
  inputs.attachments = grasp;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  const testing::AllocationCounter allocations;
  for (int step = 0; step < 20; ++step)
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_EQ(allocations.count(), 0);
  EXPECT_GT(state->counters.solver_iterations, 0);
}

TEST(MassSpringModel, BadStepInputsAreRefusedAndChangeNothing) {
  const auto model = OrganModel("plate192", 0.1);
  const auto state = model->MakeState();
  const mesh::Points before = state->positions;
  const auto refused = [&](const StepInputs& inputs) {
    return model->Step(inputs, state.get()) == StepStatus::kBadInput && state->positions == before;
  };
  StepInputs inputs;
  inputs.dt = 0.0;
  EXPECT_TRUE(refused(inputs));
  inputs.dt = std::nan("");
  EXPECT_TRUE(refused(inputs));
  inputs.dt = 1e-5;
  const int32_t out_of_range[] = {192};
  inputs.fixed_nodes = out_of_range;
  EXPECT_TRUE(refused(inputs));
  inputs.fixed_nodes = {};
  mesh::Points wrong_size = mesh::Points::Zero(3, 10);
  inputs.external_forces = &wrong_size;
  EXPECT_TRUE(refused(inputs));
  mesh::Points nan_force = mesh::Points::Zero(3, 192);
  nan_force(1, 3) = std::nan("");
  inputs.external_forces = &nan_force;
  EXPECT_TRUE(refused(inputs));
  inputs.external_forces = nullptr;
  const int32_t prescribed[] = {4};
  inputs.prescribed_nodes = prescribed;  // without positions
  EXPECT_TRUE(refused(inputs));
  inputs.prescribed_nodes = {};
  const Attachment negative[] = {{3, Vector3d::Zero(), -1.0}};
  inputs.attachments = negative;
  EXPECT_TRUE(refused(inputs));
  EXPECT_EQ(state->counters.bad_inputs, 7);
  EXPECT_EQ(state->counters.steps, 0);
}

TEST(MassSpringModel, BadParametersAreRefusedNamingThem) {
  const mesh_gen::BuiltinOrgan plate = mesh_gen::GenerateBuiltinOrgan("plate192");
  const auto message = [&](const MassSpringParameters& p) -> std::string {
    try {
      MassSpringModel::FromTetMesh(plate.volume, p);
    } catch (const std::invalid_argument& error) {
      return error.what();
    }
    return "accepted";
  };
  MassSpringParameters p;
  p.youngs_modulus = -1.0;
  EXPECT_NE(message(p).find("youngs_modulus"), std::string::npos);
  p.youngs_modulus = std::nan("");
  EXPECT_NE(message(p).find("youngs_modulus"), std::string::npos);
  p.youngs_modulus = 1e4;
  p.density = 0.0;
  EXPECT_NE(message(p).find("density"), std::string::npos);
  p.density = 1000.0;
  p.damping_ratio = -0.1;
  EXPECT_NE(message(p).find("damping_ratio"), std::string::npos);
  p.damping_ratio = 0.1;
  p.spring_stiffness = -5.0;
  EXPECT_NE(message(p).find("spring_stiffness"), std::string::npos);
  p.spring_stiffness = 0.0;
  EXPECT_EQ(message(p), "accepted");
  mesh::TetMesh broken = plate.volume;
  broken.tetrahedra(2, 7) = 500;
  EXPECT_THROW(MassSpringModel::FromTetMesh(broken, p), std::invalid_argument);
  broken = plate.volume;
  broken.vertices(0, 3) = std::nan("");
  EXPECT_THROW(MassSpringModel::FromTetMesh(broken, p), std::invalid_argument);
  mesh::Points two = mesh::Points::Zero(3, 2);
  MassSpringParameters raw;
  raw.spring_stiffness = 1.0;
  raw.node_mass = 1.0;
  EXPECT_THROW(MassSpringModel::FromEdges(two, {{0, 1}}, raw), std::invalid_argument);  // l = 0
  two(0, 1) = 1.0;
  EXPECT_THROW(MassSpringModel::FromEdges(two, {{0, 2}}, raw), std::invalid_argument);
  EXPECT_NO_THROW(MassSpringModel::FromEdges(two, {{0, 1}}, raw));
}

// Implicit Euler solver (mass_spring_implicit*.cc): the preconditioned, warm-started CG step is
// the linearised backward Euler step of Baraff & Witkin 1998, solved to the tolerance.

// A 3 × 3 × 2 lattice of nodes 1 cm apart with springs to every neighbour within √3 cells,
// displaced at random so that some springs are stretched (transverse stiffness on).
struct Lattice {
  mesh::Points rest;
  std::vector<std::array<int32_t, 2>> edges;
};

Lattice MakeLattice() {
  Lattice lattice;
  const int nx = 3, ny = 3, nz = 2;
  lattice.rest.resize(3, nx * ny * nz);
  for (int z = 0; z < nz; ++z) {
    for (int y = 0; y < ny; ++y) {
      for (int x = 0; x < nx; ++x) {
        lattice.rest.col(x + nx * (y + ny * z)) = 0.01 * Vector3d(x, y, z);
      }
    }
  }
  for (int32_t i = 0; i < lattice.rest.cols(); ++i) {
    for (int32_t j = i + 1; j < lattice.rest.cols(); ++j) {
      if ((lattice.rest.col(i) - lattice.rest.col(j)).norm() < 0.01 * 1.8) {
        lattice.edges.push_back({i, j});
      }
    }
  }
  return lattice;
}

// The linearised backward Euler step, assembled densely: (M + dt C + dt² K) Δv = dt (f - dt K v)
// over the free nodes, with the spring blocks of mass_spring_model.h (K keeps the transverse
// stiffness k (1 - l0/l)₊) and k_a I per attachment. Returns the new velocities, 3 × n.
mesh::Points DenseImplicitVelocities(const MassSpringModel& model, const TissueState& state,
                                     const std::vector<std::array<int32_t, 2>>& edges,
                                     double stiffness, double node_mass, double damping_ratio,
                                     const StepInputs& inputs) {
  const Eigen::Index n = model.num_nodes();
  const double dt = inputs.dt;
  const double damping = 2.0 * damping_ratio * std::sqrt(stiffness * 0.5 * node_mass);
  Eigen::MatrixXd a = Eigen::MatrixXd::Identity(3 * n, 3 * n) * node_mass;
  Eigen::MatrixXd k = Eigen::MatrixXd::Zero(3 * n, 3 * n);
  for (const auto& [i, j] : edges) {
    const Vector3d d = state.positions.col(j) - state.positions.col(i);
    const double length = d.norm();
    const Vector3d u = d / length;
    const double l0 = (model.rest_positions().col(j) - model.rest_positions().col(i)).norm();
    const double c = std::max(0.0, 1.0 - l0 / length);
    const Eigen::Matrix3d uu = u * u.transpose();
    const Eigen::Matrix3d ks = stiffness * (c * Eigen::Matrix3d::Identity() + (1.0 - c) * uu);
    const Eigen::Matrix3d block = dt * damping * uu + dt * dt * ks;
    for (const auto& [r, s, sign] :
         {std::tuple{i, i, 1.0}, {j, j, 1.0}, {i, j, -1.0}, {j, i, -1.0}}) {
      a.block<3, 3>(3 * r, 3 * s) += sign * block;
      k.block<3, 3>(3 * r, 3 * s) += sign * ks;
    }
  }
  for (const Attachment& attachment : inputs.attachments) {
    a.block<3, 3>(3 * attachment.node, 3 * attachment.node) +=
        dt * dt * attachment.stiffness * Eigen::Matrix3d::Identity();
    k.block<3, 3>(3 * attachment.node, 3 * attachment.node) +=
        attachment.stiffness * Eigen::Matrix3d::Identity();
  }
  mesh::Points forces(3, n);
  model.InternalForces(state, &forces);
  for (Eigen::Index i = 0; i < n; ++i) forces.col(i) += node_mass * inputs.gravity;
  if (inputs.external_forces != nullptr) forces += *inputs.external_forces;
  for (const Attachment& attachment : inputs.attachments) {
    forces.col(attachment.node) +=
        attachment.stiffness * (attachment.target - state.positions.col(attachment.node));
  }
  const Eigen::VectorXd v = state.velocities.reshaped();
  const Eigen::VectorXd rhs = dt * (forces.reshaped() - dt * k * v);
  std::vector<bool> held(static_cast<size_t>(n), false);
  for (const int32_t node : inputs.fixed_nodes) held[static_cast<size_t>(node)] = true;
  for (const int32_t node : inputs.prescribed_nodes) held[static_cast<size_t>(node)] = true;
  std::vector<Eigen::Index> free_dofs;
  for (Eigen::Index i = 0; i < 3 * n; ++i) {
    if (!held[static_cast<size_t>(i / 3)]) free_dofs.push_back(i);
  }
  const auto m = static_cast<Eigen::Index>(free_dofs.size());
  Eigen::MatrixXd a_free(m, m);
  Eigen::VectorXd rhs_free(m);
  for (Eigen::Index r = 0; r < m; ++r) {
    rhs_free(r) = rhs(free_dofs[static_cast<size_t>(r)]);
    for (Eigen::Index s = 0; s < m; ++s) {
      a_free(r, s) = a(free_dofs[static_cast<size_t>(r)], free_dofs[static_cast<size_t>(s)]);
    }
  }
  const Eigen::VectorXd dv_free = a_free.partialPivLu().solve(rhs_free);
  mesh::Points velocities = state.velocities;
  for (Eigen::Index r = 0; r < m; ++r) {
    velocities.data()[free_dofs[static_cast<size_t>(r)]] += dv_free(r);
  }
  return velocities;
}

TEST(MassSpringImplicit, StepIsTheLinearisedBackwardEulerStep) {
  const Lattice lattice = MakeLattice();
  MassSpringParameters p;
  p.spring_stiffness = 400.0;  // [N/m]
  p.node_mass = 1e-3;          // [kg]: dt² k / m = 0.4, far past the explicit limit at dt = 1 ms
  p.damping_ratio = 0.1;
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  p.cg_tolerance = 1e-13;
  const auto model = MassSpringModel::FromEdges(lattice.rest, lattice.edges, p);
  const auto state = model->MakeState();
  const int32_t n = model->num_nodes();
  const mesh::Points external = PointLoad(n, 4, Vector3d(0.0, 0.02, 0.0));
  const int32_t fixed[] = {0, 1};
  const int32_t prescribed[] = {17};
  mesh::Points targets = lattice.rest.col(17) + Vector3d(0.0, 0.0, 0.001);
  const Attachment grasp[] = {{13, lattice.rest.col(13) + Vector3d(0.002, 0.0, 0.0), 30.0}};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.external_forces = &external;
  inputs.fixed_nodes = fixed;
  inputs.prescribed_nodes = prescribed;
  inputs.prescribed_positions = &targets;
  inputs.attachments = grasp;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> speed(-0.05, 0.05);
  for (int round = 0; round < 5; ++round) {
    Perturb(state.get(), 0.002, static_cast<unsigned>(round));  // some springs stretched
    for (Eigen::Index i = 0; i < state->velocities.size(); ++i) {
      state->velocities.data()[i] = speed(rng);
    }
    for (const int32_t node : fixed) {
      state->positions.col(node) = lattice.rest.col(node);
      state->velocities.col(node).setZero();
    }
    const mesh::Points expected = DenseImplicitVelocities(
        *model, *state, lattice.edges, p.spring_stiffness, p.node_mass, p.damping_ratio, inputs);
    const mesh::Points before = state->velocities;
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    const double change = (expected - before).norm();
    ASSERT_GT(change, 0.0);
    for (const int32_t i : {2, 3, 4, 5, 8, 9, 12, 13, 16}) {  // free nodes
      EXPECT_LT((state->velocities.col(i) - expected.col(i)).norm(), 1e-9 * change)
          << "round " << round << " node " << i;
    }
    EXPECT_EQ(state->velocities.col(0), Vector3d::Zero());
  }
  EXPECT_EQ(state->counters.solver_unconverged, 0);
}

TEST(MassSpringImplicit, WarmStartGivesTheColdStepToTheTolerance) {
  // The state keeps the previous step's Δv as CG's first guess: a step from a state with that
  // history equals the step from a fresh state with the same positions and velocities, to the
  // tolerance, and two runs of the same inputs agree bit for bit.
  const mesh_gen::BuiltinOrgan kidney = mesh_gen::GenerateBuiltinOrgan("kidney424");
  MassSpringParameters p;
  p.youngs_modulus = 5e4;
  p.density = 1050.0;
  p.damping_ratio = 0.1;
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  p.cg_tolerance = 1e-10;
  const auto model = MassSpringModel::FromTetMesh(kidney.volume, p);
  const int32_t fixed[] = {0, 1, 2};
  const Attachment grasp[] = {{11, kidney.volume.vertices.col(11) + Vector3d(0, 0, 0.003), 50.0}};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;
  inputs.attachments = grasp;
  const auto warm = model->MakeState();
  const auto again = model->MakeState();
  for (int step = 0; step < 30; ++step) {
    ASSERT_EQ(model->Step(inputs, warm.get()), StepStatus::kOk);
    ASSERT_EQ(model->Step(inputs, again.get()), StepStatus::kOk);
  }
  EXPECT_EQ(warm->positions, again->positions);  // deterministic
  EXPECT_EQ(warm->velocities, again->velocities);
  const auto cold = model->MakeState();
  cold->positions = warm->positions;
  cold->velocities = warm->velocities;
  const mesh::Points before = warm->velocities;
  const int64_t iterations_before = warm->counters.solver_iterations;
  ASSERT_EQ(model->Step(inputs, warm.get()), StepStatus::kOk);
  ASSERT_EQ(model->Step(inputs, cold.get()), StepStatus::kOk);
  const double change = (cold->velocities - before).norm();
  ASSERT_GT(change, 0.0);
  EXPECT_LT((warm->velocities - cold->velocities).norm(), 1e-7 * change);
  // The guess saves iterations.
  EXPECT_LT(warm->counters.solver_iterations - iterations_before, cold->counters.solver_iterations);
  EXPECT_EQ(warm->counters.solver_unconverged, 0);
}

TEST(MassSpringImplicit, RecoversFromARejectedStep) {
  // A diverged step leaves a useless Δv behind; the next step drops it as a guess and converges.
  const auto model = [] {
    const mesh_gen::BuiltinOrgan plate = mesh_gen::GenerateBuiltinOrgan("plate192");
    MassSpringParameters p;
    p.youngs_modulus = 1e5;
    p.integrator = MassSpringIntegrator::kImplicitEuler;
    return MassSpringModel::FromTetMesh(plate.volume, p);
  }();
  const auto state = model->MakeState();
  const int32_t fixed[] = {0, 1, 2};
  StepInputs inputs;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;
  inputs.dt = 1e-3;
  for (int step = 0; step < 5; ++step) ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  const mesh::Points blow = PointLoad(model->num_nodes(), 50, Vector3d(0.0, 0.0, 1e6));
  inputs.external_forces = &blow;  // [N]: past the speed limit, rejected and rolled back
  EXPECT_NE(model->Step(inputs, state.get()), StepStatus::kOk);
  inputs.external_forces = nullptr;
  for (int step = 0; step < 5; ++step) ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_TRUE(state->positions.allFinite());
  EXPECT_EQ(state->counters.solver_unconverged, 0);
}
}  // namespace
}  // namespace somasim::models
