// Mass-spring model (seed 002 §2.1, SPEC §4.1): forces are exact energy gradients, the local
// stiffness is the force Jacobian, the integrator keeps energy and momentum, a spring rings at
// √(k/m), divergence is caught and rolled back, steps allocate nothing, bad input is refused.
#include "server/models/mass_spring_model.h"

#include <gtest/gtest.h>

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

}  // namespace
}  // namespace somasim::models
