// Molecular model (seed 002 §2.2, SPEC §4.2), on the 45-node tissue patch so that the tests
// are fast in sanitizer builds too: each energy term's force is its exact negative gradient, the
// local stiffness is the force Jacobian, the rest shape and its rigid motions are force-free, the
// integrator keeps energy and momentum, steps allocate nothing, bad parameters are refused by
// name.
#include "server/models/molecular_model.h"

#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

constexpr uint32_t kTermSets[] = {MolecularModel::kBond, MolecularModel::kAngle,
                                  MolecularModel::kStretchBend, MolecularModel::kAllTerms};

std::unique_ptr<MolecularModel> OrganModel(const std::string& name, double damping_ratio,
                                           double stretch_bend_factor = 0.02) {
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan(name);
  MolecularParameters p;
  p.youngs_modulus = 3000.0;  // soft tissue [Pa]
  p.density = 1050.0;
  p.damping_ratio = damping_ratio;
  p.stretch_bend_factor = stretch_bend_factor;
  return MolecularModel::FromSurface(organ.surface, p);
}

// Moves every node by a seeded random offset of up to `amplitude` [m].
void Perturb(TissueState* state, double amplitude, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> offset(-amplitude, amplitude);
  for (Eigen::Index i = 0; i < state->positions.size(); ++i) {
    state->positions.data()[i] += offset(rng);
  }
}

// A time step at `fraction` of a bound on the explicit stability limit 2/ω_max, with
// ω_max² <= max_i 4 trace(K_ii)/m_i, as in the mass-spring test. It is conservative with the
// angle terms too: measured on tissue45 and spleen600 (perturbed, undamped), symplectic Euler
// stays stable for 5000 steps at 2× this step and diverges within 4 steps at 3×.
double SafeStep(const MolecularModel& model, double fraction) {
  const auto state = model.MakeState();
  double omega2 = 0.0;
  for (int32_t i = 0; i < model.num_nodes(); ++i) {
    const double k = model.LocalStiffness(*state, i).trace();
    omega2 = std::max(omega2, 4.0 * k / model.masses()[static_cast<size_t>(i)]);
  }
  return fraction * 2.0 / std::sqrt(omega2);
}

TEST(MolecularModel, ForcesAreNegativeEnergyGradient) {
  const auto model = OrganModel("tissue45", 0.0, 0.2);  // a strong coupling, to test it
  const auto state = model->MakeState();
  Perturb(state.get(), 0.001, 1);
  mesh::Points forces(3, model->num_nodes());
  for (const uint32_t terms : kTermSets) {
    EXPECT_GT(std::abs(model->TermEnergy(*state, terms)), 0.0) << "terms " << terms;
    model->TermForces(*state, terms, &forces);
    double worst = 0.0;
    for (int32_t node = 0; node < model->num_nodes(); ++node) {
      for (int axis = 0; axis < 3; ++axis) {
        const double h = 1e-7;
        const double x0 = state->positions(axis, node);
        state->positions(axis, node) = x0 + h;
        const double plus = model->TermEnergy(*state, terms);
        state->positions(axis, node) = x0 - h;
        const double minus = model->TermEnergy(*state, terms);
        state->positions(axis, node) = x0;
        const double gradient = (plus - minus) / (2 * h);
        const double scale =
            std::max(std::abs(forces(axis, node)), 1e-3 * forces.cwiseAbs().maxCoeff());
        worst = std::max(worst, std::abs(forces(axis, node) + gradient) / scale);
      }
    }
    EXPECT_LT(worst, 1e-6) << "terms " << terms;
  }
  // The full model is the sum of its terms.
  model->InternalForces(*state, &forces);
  mesh::Points sum = mesh::Points::Zero(3, model->num_nodes()), part(3, model->num_nodes());
  for (const uint32_t terms :
       {MolecularModel::kBond, MolecularModel::kAngle, MolecularModel::kStretchBend}) {
    model->TermForces(*state, terms, &part);
    sum += part;
  }
  EXPECT_LT((sum - forces).norm(), 1e-12 * forces.norm());
  EXPECT_NEAR(model->Energy(*state, Vector3d::Zero()).elastic,
              model->TermEnergy(*state, MolecularModel::kAllTerms), 0.0);
}

// The per-step triangle kernels (portable scalar and, on this CPU, the vector one) give the
// straightforward per-bond, per-angle forces to round-off, damping included, and repeat
// themselves bit for bit. tissue45 has 66 triangles (8 full blocks and a tail of 2).
TEST(MolecularModel, TriangleKernelsMatchTheReference) {
  for (const std::string organ : {"tissue45", "spleen600"}) {
    const auto model = OrganModel(organ, 0.3, 0.2);
    const auto state = model->MakeState();
    Perturb(state.get(), 0.001, 6);
    std::mt19937 rng(7);
    std::normal_distribution<double> speed(0.0, 0.05);
    for (Eigen::Index i = 0; i < state->velocities.size(); ++i) {
      state->velocities.data()[i] = speed(rng);
    }
    const Eigen::Index n = model->num_nodes();
    mesh::Points reference(3, n), scalar(3, n), vector(3, n), again(3, n);
    for (const uint32_t terms : kTermSets) {
      model->ReferenceTermForces(*state, terms, &reference);
      model->KernelTermForces(*state, terms, false, &scalar);
      model->KernelTermForces(*state, terms, true, &vector);
      const double scale = reference.cwiseAbs().maxCoeff();
      ASSERT_GT(scale, 0.0);
      EXPECT_LT((scalar - reference).cwiseAbs().maxCoeff(), 1e-12 * scale)
          << organ << " terms " << terms;
      EXPECT_LT((vector - reference).cwiseAbs().maxCoeff(), 1e-12 * scale)
          << organ << " terms " << terms << " vector kernel " << MolecularModel::HasVectorKernel();
      model->TermForces(*state, terms, &again);
      EXPECT_EQ(again, vector);
      model->KernelTermForces(*state, terms, false, &again);
      EXPECT_EQ(again, scalar);
    }
  }
}

TEST(MolecularModel, LocalStiffnessIsTheForceJacobian) {
  const auto model = OrganModel("tissue45", 0.0, 0.2);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.001, 2);
  mesh::Points plus(3, model->num_nodes()), minus(3, model->num_nodes());
  for (const uint32_t terms : kTermSets) {
    for (const int32_t node : {0, 22, 44}) {
      const Matrix3d k = model->TermLocalStiffness(*state, node, terms);
      Matrix3d fd;
      for (int axis = 0; axis < 3; ++axis) {
        const double h = 1e-7;
        const double x0 = state->positions(axis, node);
        state->positions(axis, node) = x0 + h;
        model->TermForces(*state, terms, &plus);
        state->positions(axis, node) = x0 - h;
        model->TermForces(*state, terms, &minus);
        state->positions(axis, node) = x0;
        fd.col(axis) = -(plus.col(node) - minus.col(node)) / (2 * h);
      }
      EXPECT_LT((fd - k).norm(), 1e-6 * k.norm()) << "terms " << terms << " node " << node << "\n"
                                                  << fd << "\n"
                                                  << k;
      EXPECT_LT((k - k.transpose()).norm(), 1e-12 * k.norm());
    }
  }
}

TEST(MolecularModel, RestShapeIsInEquilibrium) {
  const auto model = OrganModel("tissue45", 0.1);
  const auto state = model->MakeState();
  mesh::Points forces(3, model->num_nodes());
  model->InternalForces(*state, &forces);
  EXPECT_EQ(model->Energy(*state, Vector3d::Zero()).elastic, 0.0);
  // A node moved by 0.1 mm feels a restoring force; at rest every force is round-off of it.
  const Matrix3d k0 = model->LocalStiffness(*state, 0);
  EXPECT_GT(k0.eigenvalues().real().minCoeff(), 0.0);
  const double probe = k0.norm() * 1e-4;  // [N]
  EXPECT_LT(forces.cwiseAbs().maxCoeff(), 1e-9 * probe);

  // A rigid rotation and translation of the rest shape is force-free and energy-free too, and
  // a rigid velocity is not damped.
  const Matrix3d rotation =
      Eigen::AngleAxisd(0.7, Vector3d(1.0, 2.0, -0.5).normalized()).toRotationMatrix();
  const Vector3d shift(0.03, -0.01, 0.2);
  const Vector3d omega(0.3, -0.2, 0.5);  // [rad/s]
  for (Eigen::Index i = 0; i < state->positions.cols(); ++i) {
    state->positions.col(i) = rotation * state->positions.col(i) + shift;
    state->velocities.col(i) = Vector3d(0.01, 0.0, -0.02) + omega.cross(state->positions.col(i));
  }
  model->InternalForces(*state, &forces);
  EXPECT_LT(forces.cwiseAbs().maxCoeff(), 1e-9 * probe);
  EXPECT_LT(model->Energy(*state, Vector3d::Zero()).elastic, 1e-18);
}

TEST(MolecularModel, MomentumIsConservedWithoutExternalForce) {
  const auto model = OrganModel("tissue45", 0.3);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.001, 4);
  std::mt19937 rng(5);
  std::normal_distribution<double> speed(0.0, 0.01);
  for (Eigen::Index i = 0; i < state->velocities.size(); ++i) {
    state->velocities.data()[i] = speed(rng);
  }
  StepInputs inputs;
  inputs.dt = SafeStep(*model, 0.3);
  const EnergyReport before = model->Energy(*state, inputs.gravity);
  double mass = 0.0;
  for (const double m : model->masses()) mass += m;
  for (int step = 0; step < 500; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  }
  const EnergyReport after = model->Energy(*state, inputs.gravity);
  EXPECT_LT((after.momentum - before.momentum).norm(), 1e-12 * mass);
  EXPECT_LT(after.total(), before.total());  // the bond damping took energy out
}

TEST(MolecularModel, UndampedEnergyStaysWithinOnePercent) {
  const auto model = OrganModel("tissue45", 0.0);
  const auto state = model->MakeState();
  Perturb(state.get(), 0.0005, 3);
  StepInputs inputs;
  // Symplectic Euler conserves a modified energy; the true energy wobbles by about ω·dt/2 of the
  // fastest mode, and the wobble scales with dt. Checked after every step: at 5 % of the
  // stability bound (68 µs) the worst is 1.6 %, at 2 % 0.65 %; this 1 % (14 µs) gives 0.33 %.
  inputs.dt = SafeStep(*model, 0.01);
  const double e0 = model->Energy(*state, inputs.gravity).total();
  ASSERT_GT(e0, 0.0);
  double worst = 0.0;
  for (int step = 0; step < 10000; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    worst = std::max(worst, std::abs(model->Energy(*state, inputs.gravity).total() - e0));
  }
  EXPECT_LT(worst, 0.01 * e0);
}

TEST(MolecularModel, StepAllocatesNothing) {
  const auto model = OrganModel("tissue45", 0.1);
  const auto state = model->MakeState();
  // 10 mN on node 5 [N], 3 × num_nodes.
  const mesh::Points external =
      Vector3d(0.0, 0.0, 0.01) * Eigen::RowVectorXd::Unit(model->num_nodes(), 5);
  const int32_t fixed[] = {0, 1, 2};
  const int32_t prescribed[] = {7};
  mesh::Points targets = state->positions.col(7);
  const Attachment grasp[] = {{11, state->positions.col(11) + Vector3d(0, 0, 0.001), 5.0}};
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
    const Matrix3d k = model->LocalStiffness(*state, 5);
    const EnergyReport energy = model->Energy(*state, inputs.gravity);
    EXPECT_EQ(allocations.count(), 0);
    EXPECT_GT(k.trace(), 0.0);
    EXPECT_GT(energy.kinetic, 0.0);
  }
  EXPECT_EQ(state->counters.steps, 101);
  EXPECT_EQ(state->positions.col(7), targets.col(0));
  {
    // A diverging step, rolled back, allocates nothing either.
    inputs.dt = 1e6;
    const testing::AllocationCounter allocations;
    const StepStatus status = model->Step(inputs, state.get());
    EXPECT_EQ(allocations.count(), 0);
    EXPECT_NE(status, StepStatus::kOk);
  }
}

TEST(MolecularModel, BadParametersAreRefusedNamingThem) {
  const mesh_gen::BuiltinOrgan tissue = mesh_gen::GenerateBuiltinOrgan("tissue45");
  const auto message = [&](const MolecularParameters& p) -> std::string {
    try {
      MolecularModel::FromSurface(tissue.surface, p);
    } catch (const std::invalid_argument& error) {
      return error.what();
    }
    return "accepted";
  };
  const auto refused = [&](const MolecularParameters& p, const std::string& name) {
    return message(p).find(name) != std::string::npos;
  };
  MolecularParameters good;
  good.youngs_modulus = 1e4;
  EXPECT_EQ(message(good), "accepted");
  MolecularParameters p = good;
  p.youngs_modulus = -1.0;
  EXPECT_TRUE(refused(p, "youngs_modulus"));
  p.youngs_modulus = std::nan("");
  EXPECT_TRUE(refused(p, "youngs_modulus"));
  p.bond_stiffness = 10.0;  // a raw bond stiffness makes E unnecessary
  EXPECT_EQ(message(p), "accepted");
  p = good;
  p.density = 0.0;
  EXPECT_TRUE(refused(p, "density"));
  p = good;
  p.damping_ratio = -0.1;
  EXPECT_TRUE(refused(p, "damping_ratio"));
  p = good;
  p.thickness = 0.0;
  EXPECT_TRUE(refused(p, "thickness"));
  p = good;
  p.bend_factor = -0.1;
  EXPECT_TRUE(refused(p, "bend_factor"));
  p = good;
  p.stretch_bend_factor = std::numeric_limits<double>::infinity();
  EXPECT_TRUE(refused(p, "stretch_bend_factor"));
  p = good;
  p.bond_stiffness = -1.0;
  EXPECT_TRUE(refused(p, "bond_stiffness"));
  p = good;
  p.angle_stiffness = -1.0;
  EXPECT_TRUE(refused(p, "angle_stiffness"));
  p = good;
  p.stretch_bend_stiffness = std::nan("");
  EXPECT_TRUE(refused(p, "stretch_bend_stiffness"));
  p = good;
  p.node_mass = -1.0;
  EXPECT_TRUE(refused(p, "node_mass"));
  p = good;
  p.speed_limit = 0.0;
  EXPECT_TRUE(refused(p, "speed_limit"));

  mesh::SurfaceMesh broken = tissue.surface;
  broken.triangles(2, 7) = 500;
  EXPECT_THROW(MolecularModel::FromSurface(broken, good), std::invalid_argument);
  broken = tissue.surface;
  broken.vertices(0, 3) = std::nan("");
  EXPECT_THROW(MolecularModel::FromSurface(broken, good), std::invalid_argument);
  broken = tissue.surface;
  broken.triangles(1, 0) = broken.triangles(0, 0);  // a zero-length bond
  EXPECT_THROW(MolecularModel::FromSurface(broken, good), std::invalid_argument);
  broken.triangles.resize(3, 0);
  EXPECT_THROW(MolecularModel::FromSurface(broken, good), std::invalid_argument);
}

TEST(MolecularModel, RawConstantsReplaceThePhysicalRules) {
  const mesh_gen::BuiltinOrgan tissue = mesh_gen::GenerateBuiltinOrgan("tissue45");
  MolecularParameters p;
  p.bond_stiffness = 20.0;           // [N/m]
  p.angle_stiffness = 0.003;         // [J]
  p.stretch_bend_stiffness = 0.004;  // [N]
  p.node_mass = 0.002;               // [kg]
  const auto model = MolecularModel::FromSurface(tissue.surface, p);
  EXPECT_EQ(model->num_nodes(), 45);
  EXPECT_EQ(model->num_angles(), 3 * 66);
  for (const double k : model->bond_stiffness()) EXPECT_EQ(k, 20.0);
  for (const double k : model->angle_stiffness()) EXPECT_EQ(k, 0.003);
  for (const double k : model->stretch_bend()) EXPECT_EQ(k, 0.004);
  for (const double m : model->masses()) EXPECT_EQ(m, 0.002);
}

}  // namespace
}  // namespace somasim::models
