// Tests of the implicit mass-spring step's kernels (issue 4 speed work): the multicolour
// Gauss-Seidel-preconditioned CG solves the linearised backward Euler system to its tolerance
// (against a dense solve of the same system, with held nodes and an attachment), on the
// AVX-512 and on the scalar path, and the two paths agree on organs with and without massless
// nodes and anchors.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cmath>
#include <random>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/models/mass_spring_model.h"

namespace somasim::models {

void SetMassSpringImplicitAvx512ForTesting(bool enabled);

namespace {

using Eigen::Vector3d;

// Restores the AVX-512 path when a test ends.
struct ScalarPath {
  explicit ScalarPath(bool scalar) { SetMassSpringImplicitAvx512ForTesting(!scalar); }
  ~ScalarPath() { SetMassSpringImplicitAvx512ForTesting(true); }
  ScalarPath(const ScalarPath&) = delete;
  ScalarPath& operator=(const ScalarPath&) = delete;
};

std::vector<std::array<int32_t, 2>> TetEdges(const mesh::TetMesh& mesh) {
  std::set<std::pair<int32_t, int32_t>> unique;
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    for (int a = 0; a < 4; ++a) {
      for (int b = a + 1; b < 4; ++b) {
        const int32_t i = mesh.tetrahedra(a, t), j = mesh.tetrahedra(b, t);
        unique.insert({std::min(i, j), std::max(i, j)});
      }
    }
  }
  std::vector<std::array<int32_t, 2>> edges;
  edges.reserve(unique.size());
  for (const auto& [i, j] : unique) edges.push_back({i, j});
  return edges;
}

// Δv of the linearised backward Euler step, (M + dt C + dt² K) Δv = dt (f - dt K v) over the
// free nodes, assembled densely from the plain spring formulas (uniform k [N/m] and node mass
// m [kg]). 3 × n.
mesh::Points DenseDeltaV(const MassSpringModel& model, const TissueState& state,
                         const std::vector<std::array<int32_t, 2>>& edges, double k, double m,
                         double zeta, const StepInputs& inputs) {
  const Eigen::Index n = model.num_nodes();
  const double dt = inputs.dt;
  const double damping = 2.0 * zeta * std::sqrt(k * 0.5 * m);
  Eigen::MatrixXd a = Eigen::MatrixXd::Identity(3 * n, 3 * n) * m;
  Eigen::MatrixXd stiffness = Eigen::MatrixXd::Zero(3 * n, 3 * n);
  Eigen::VectorXd f = Eigen::VectorXd::Zero(3 * n);
  for (const auto& [i, j] : edges) {
    const Vector3d d = state.positions.col(j) - state.positions.col(i);
    const double length = d.norm();
    const Vector3d u = d / length;
    const double l0 = (model.rest_positions().col(j) - model.rest_positions().col(i)).norm();
    const double c = std::max(0.0, 1.0 - l0 / length);
    const Eigen::Matrix3d uu = u * u.transpose();
    const Eigen::Matrix3d ks = k * (c * Eigen::Matrix3d::Identity() + (1.0 - c) * uu);
    const Eigen::Matrix3d block = dt * damping * uu + dt * dt * ks;
    for (const auto& [r, s, sign] :
         {std::tuple{i, i, 1.0}, {j, j, 1.0}, {i, j, -1.0}, {j, i, -1.0}}) {
      a.block<3, 3>(3 * r, 3 * s) += sign * block;
      stiffness.block<3, 3>(3 * r, 3 * s) += sign * ks;
    }
    // Seed 002 eq. 1-3: k (l - l0) u plus damping along the spring, on i; minus that on j.
    const Vector3d dv = state.velocities.col(j) - state.velocities.col(i);
    const Vector3d pull = (k * (length - l0) + damping * dv.dot(u)) * u;
    f.segment<3>(3 * i) += pull;
    f.segment<3>(3 * j) -= pull;
  }
  for (Eigen::Index i = 0; i < n; ++i) f.segment<3>(3 * i) += m * inputs.gravity;
  for (const Attachment& at : inputs.attachments) {
    a.block<3, 3>(3 * at.node, 3 * at.node) += dt * dt * at.stiffness * Eigen::Matrix3d::Identity();
    stiffness.block<3, 3>(3 * at.node, 3 * at.node) += at.stiffness * Eigen::Matrix3d::Identity();
    f.segment<3>(3 * at.node) += at.stiffness * (at.target - state.positions.col(at.node));
  }
  const Eigen::VectorXd v = state.velocities.reshaped();
  const Eigen::VectorXd rhs = dt * (f - dt * stiffness * v);
  std::vector<bool> held(static_cast<size_t>(n), false);
  for (const int32_t node : inputs.fixed_nodes) held[static_cast<size_t>(node)] = true;
  std::vector<Eigen::Index> free_dofs;
  for (Eigen::Index i = 0; i < 3 * n; ++i) {
    if (!held[static_cast<size_t>(i / 3)]) free_dofs.push_back(i);
  }
  const auto count = static_cast<Eigen::Index>(free_dofs.size());
  Eigen::MatrixXd a_free(count, count);
  Eigen::VectorXd rhs_free(count);
  for (Eigen::Index r = 0; r < count; ++r) {
    rhs_free(r) = rhs(free_dofs[static_cast<size_t>(r)]);
    for (Eigen::Index s = 0; s < count; ++s) {
      a_free(r, s) = a(free_dofs[static_cast<size_t>(r)], free_dofs[static_cast<size_t>(s)]);
    }
  }
  const Eigen::VectorXd dv_free = a_free.llt().solve(rhs_free);
  mesh::Points dv = mesh::Points::Zero(3, n);
  for (Eigen::Index r = 0; r < count; ++r)
    dv.data()[free_dofs[static_cast<size_t>(r)]] = dv_free(r);
  return dv;
}

class ImplicitPaths : public ::testing::TestWithParam<bool> {};  // true: scalar path

TEST_P(ImplicitPaths, DeltaVSolvesTheAssembledSystemToTheTolerance) {
  const ScalarPath path(GetParam());
  const mesh::TetMesh plate = mesh_gen::GenerateBuiltinOrgan("plate192").volume;
  const std::vector<std::array<int32_t, 2>> edges = TetEdges(plate);
  MassSpringParameters p;
  p.spring_stiffness = 300.0;  // [N/m]
  p.node_mass = 2e-3;          // [kg]: dt² k / m = 0.15 per spring, far past the explicit limit
  p.damping_ratio = 0.1;
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  p.cg_tolerance = 1e-11;
  const auto model = MassSpringModel::FromEdges(plate.vertices, edges, p);
  const auto state = model->MakeState();
  const int32_t n = model->num_nodes();
  const int32_t fixed[] = {0, 1, 2};
  const Attachment grasp[] = {{n / 2, plate.vertices.col(n / 2) + Vector3d(0.0, 0.0, 0.004), 40.0}};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;
  inputs.attachments = grasp;
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> offset(-0.002, 0.002), speed(-0.05, 0.05);
  for (int round = 0; round < 4; ++round) {
    for (Eigen::Index i = 0; i < state->positions.size(); ++i) {
      state->positions.data()[i] = plate.vertices.data()[i] + offset(rng);
      state->velocities.data()[i] = speed(rng);
    }
    for (const int32_t node : fixed) {
      state->positions.col(node) = plate.vertices.col(node);
      state->velocities.col(node).setZero();
    }
    const mesh::Points before = state->velocities;
    const mesh::Points expected = DenseDeltaV(*model, *state, edges, p.spring_stiffness,
                                              p.node_mass, p.damping_ratio, inputs);
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    const mesh::Points dv = state->velocities - before;
    ASSERT_GT(expected.norm(), 0.0);
    EXPECT_LT((dv - expected).norm(), 1e-8 * expected.norm()) << "round " << round;
    for (const int32_t node : fixed) EXPECT_EQ(state->velocities.col(node), Vector3d::Zero());
  }
  EXPECT_EQ(state->counters.solver_unconverged, 0);
}

INSTANTIATE_TEST_SUITE_P(MassSpringImplicit, ImplicitPaths, ::testing::Values(false, true),
                         [](const ::testing::TestParamInfo<bool>& param) {
                           return std::string(param.param ? "Scalar" : "Avx512");
                         });

// Runs `steps` implicit steps on `model` with the given path; returns the final state.
std::unique_ptr<TissueState> RunSteps(const MassSpringModel& model, bool scalar, int steps,
                                      const StepInputs& inputs) {
  const ScalarPath path(scalar);
  auto state = model.MakeState();
  for (int step = 0; step < steps; ++step) {
    EXPECT_EQ(model.Step(inputs, state.get()), StepStatus::kOk);
  }
  return state;
}

TEST(MassSpringImplicit, ScalarAndAvx512PathsAgreeOnAnOrgan) {
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan("spleen600");
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;
  p.density = 1050.0;
  p.damping_ratio = 0.1;
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  p.cg_tolerance = 1e-12;
  const auto model = MassSpringModel::FromSurface(organ.surface, p);
  const int32_t fixed[] = {0, 1, 2};
  const Attachment grasp[] = {{40, organ.surface.vertices.col(40) + Vector3d(0, 0.003, 0), 20.0}};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;
  inputs.attachments = grasp;
  const auto vector = RunSteps(*model, false, 20, inputs);
  const auto scalar = RunSteps(*model, true, 20, inputs);
  const double scale = vector->velocities.norm();
  ASSERT_GT(scale, 0.0);
  EXPECT_LT((vector->velocities - scalar->velocities).norm(), 1e-9 * scale);
  EXPECT_LT((vector->positions - scalar->positions).norm(), 1e-12);
  EXPECT_EQ(vector->counters.solver_unconverged, 0);
  EXPECT_EQ(scalar->counters.solver_unconverged, 0);
}

TEST(MassSpringImplicit, ScalarAndAvx512PathsAgreeWhenCgStopsAtItsIterationCap) {
  // The AVX-512 path does CG's step (Δv += α p, r -= α q) inside the next preconditioner
  // application; stopped by the cap rather than the tolerance, Δv must still hold the last step.
  const mesh_gen::BuiltinOrgan organ = mesh_gen::GenerateBuiltinOrgan("spleen600");
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;
  p.density = 1050.0;
  p.damping_ratio = 0.1;
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  p.cg_tolerance = 1e-14;
  p.cg_max_iterations = 2;
  const auto model = MassSpringModel::FromSurface(organ.surface, p);
  const int32_t fixed[] = {0, 1, 2};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = fixed;
  const auto vector = RunSteps(*model, false, 5, inputs);
  const auto scalar = RunSteps(*model, true, 5, inputs);
  const double scale = vector->velocities.norm();
  ASSERT_GT(scale, 0.0);
  EXPECT_LT((vector->velocities - scalar->velocities).norm(), 1e-9 * scale);
  EXPECT_EQ(vector->counters.solver_iterations, scalar->counters.solver_iterations);
  EXPECT_EQ(vector->counters.solver_iterations, 10);
  EXPECT_EQ(vector->counters.solver_unconverged, 5);
}

TEST(MassSpringImplicit, ScalarAndAvx512PathsAgreeOnAGeneralisedSurface) {
  // Massless core nodes (the identity stands in for their inverse block) and anchors.
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;
  p.density = 1050.0;
  p.damping_ratio = 0.1;
  p.anchor_stiffness = 5.0;
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  p.cg_tolerance = 1e-12;
  const auto model = MassSpringModel::FromGeneralisedSurface(liver, p);
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  const auto vector = RunSteps(*model, false, 20, inputs);
  const auto scalar = RunSteps(*model, true, 20, inputs);
  const double scale = vector->velocities.norm();
  ASSERT_GT(scale, 0.0);
  EXPECT_LT((vector->velocities - scalar->velocities).norm(), 1e-9 * scale);
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    if (model->masses()[static_cast<size_t>(i)] > 0.0) continue;
    EXPECT_EQ(vector->positions.col(i), liver.vertices.col(i)) << "core node " << i;
  }
}

}  // namespace
}  // namespace somasim::models
