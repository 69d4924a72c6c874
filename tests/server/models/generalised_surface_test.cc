// Seed 001's generalised surface mesh (SPEC §4.1): the outer shell is the outer fraction of the
// organ's thickness, measured by exact distances to the boundary; only shell edges become
// springs and only shell nodes carry mass.
#include "server/models/generalised_surface.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>

#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"
#include "server/models/mass_spring_model.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models {
namespace {

using Eigen::Vector3d;

TEST(PointTriangleDistance, MatchesDenseSamplingOfTheTriangle) {
  const Vector3d a(0.0, 0.0, 0.0), b(1.0, 0.0, 0.0), c(0.2, 0.8, 0.1);
  std::mt19937 random(7);
  std::uniform_real_distribution<double> coordinate(-1.0, 2.0);
  for (int trial = 0; trial < 60; ++trial) {
    const Vector3d p(coordinate(random), coordinate(random), coordinate(random));
    double sampled = 1e300;
    const int n = 200;
    for (int i = 0; i <= n; ++i) {
      for (int j = 0; i + j <= n; ++j) {
        const double u = double(i) / n, v = double(j) / n;
        sampled = std::min(sampled, (p - (a + u * (b - a) + v * (c - a))).norm());
      }
    }
    const double exact = PointTriangleDistance(p, a, b, c);
    EXPECT_LE(exact, sampled + 1e-12) << "point " << p.transpose();
    EXPECT_NEAR(exact, sampled, 1e-2) << "point " << p.transpose();  // sampling resolution
  }
}

TEST(PointTriangleDistance, CornerEdgeAndFaceRegions) {
  const Vector3d a(0.0, 0.0, 0.0), b(2.0, 0.0, 0.0), c(0.0, 2.0, 0.0);
  EXPECT_DOUBLE_EQ(PointTriangleDistance(Vector3d(0.5, 0.5, 3.0), a, b, c), 3.0);    // face
  EXPECT_DOUBLE_EQ(PointTriangleDistance(Vector3d(1.0, -4.0, 3.0), a, b, c), 5.0);   // edge ab
  EXPECT_DOUBLE_EQ(PointTriangleDistance(Vector3d(-3.0, -4.0, 0.0), a, b, c), 5.0);  // corner a
  EXPECT_DOUBLE_EQ(PointTriangleDistance(Vector3d(2.0, 2.0, 0.0), a, b, c), std::sqrt(2.0));
}

TEST(SelectOuterShell, DepthIsTheDistanceToTheNearestFaceOfABox) {
  // Unit cube, 11³ nodes, spacing 0.1: depth = distance to the nearest of the six faces.
  const mesh::TetMesh cube = mesh_gen::BoxGridTets(11, 11, 11, Vector3d::Zero(), Vector3d::Ones());
  const OuterShell shell = SelectOuterShell(cube, 0.25);
  EXPECT_NEAR(shell.thickness, 1.0, 1e-12);  // the centre node is 0.5 deep
  for (Eigen::Index i = 0; i < cube.vertices.cols(); ++i) {
    const Vector3d p = cube.vertices.col(i);
    const double expected = std::min({p.x(), p.y(), p.z(), 1.0 - p.x(), 1.0 - p.y(), 1.0 - p.z()});
    ASSERT_NEAR(shell.depth[static_cast<size_t>(i)], expected, 1e-12) << "node " << i;
  }
  // depth <= 0.25: the outer three layers on each side; the core is the 5³ nodes 0.3..0.7.
  EXPECT_EQ(shell.num_shell_nodes, 11 * 11 * 11 - 5 * 5 * 5);
}

TEST(SelectOuterShell, KeepsTheWholeBoundaryAndDropsTheCoreOfAnOrgan) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  const OuterShell shell = SelectOuterShell(liver, 0.2);
  const mesh::SurfaceMesh boundary = mesh::ExtractBoundarySurface(liver);
  for (Eigen::Index f = 0; f < boundary.triangles.cols(); ++f) {
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(shell.in_shell[static_cast<size_t>(boundary.triangles(k, f))], 1);
    }
  }
  EXPECT_GT(shell.num_shell_nodes, 0);
  EXPECT_LT(shell.num_shell_nodes, liver.vertices.cols());  // a core exists and is dropped
  for (size_t i = 0; i < shell.depth.size(); ++i) {
    EXPECT_EQ(shell.in_shell[i] != 0, shell.depth[i] <= 0.2 * shell.thickness) << "node " << i;
  }
}

TEST(ShellEdges, OnlyShellNodesCarrySpringsAndMass) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  const OuterShell shell = SelectOuterShell(liver, 0.2);
  const MeshEdges edges = ShellEdges(liver, shell);
  const MeshEdges all = TetMeshEdges(liver, "test");
  EXPECT_LT(edges.edges.size(), all.edges.size());
  for (const auto& [i, j] : edges.edges) {
    EXPECT_EQ(shell.in_shell[static_cast<size_t>(i)], 1);
    EXPECT_EQ(shell.in_shell[static_cast<size_t>(j)], 1);
  }
  for (size_t i = 0; i < edges.node_size.size(); ++i) {
    if (shell.in_shell[i] != 0) {
      EXPECT_DOUBLE_EQ(edges.node_size[i], all.node_size[i]);
    } else {
      EXPECT_EQ(edges.node_size[i], 0.0);
    }
  }
}

TEST(SelectOuterShell, RefusesBadFractionsAndBadMeshesWithAMessage) {
  const mesh::TetMesh cube = mesh_gen::BoxGridTets(3, 3, 3, Vector3d::Zero(), Vector3d::Ones());
  for (const double fraction : {0.0, -0.1, 0.6, std::nan("")}) {
    try {
      SelectOuterShell(cube, fraction);
      ADD_FAILURE() << "fraction " << fraction << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("shell fraction"), std::string::npos) << e.what();
    }
  }
  mesh::TetMesh broken = cube;
  broken.tetrahedra(2, 0) = 99;
  EXPECT_THROW(SelectOuterShell(broken, 0.2), std::invalid_argument);
  broken = cube;
  broken.vertices(0, 4) = std::nan("");
  EXPECT_THROW(SelectOuterShell(broken, 0.2), std::invalid_argument);
  OuterShell wrong = SelectOuterShell(cube, 0.2);
  wrong.in_shell.pop_back();
  EXPECT_THROW(ShellEdges(cube, wrong), std::invalid_argument);
}

// External forces [N] on a two-node model: `force` on node 0.
mesh::Points PointLoad2(const Vector3d& force) {
  mesh::Points forces(3, 2);
  forces.col(0) = force;
  forces.col(1) = Vector3d::Zero();
  return forces;
}

MassSpringParameters ShellMaterial(MassSpringIntegrator integrator) {
  MassSpringParameters p;
  p.youngs_modulus = 3000.0;  // [Pa]
  p.density = 1050.0;         // [kg/m³]
  p.damping_ratio = 0.1;
  p.anchor_stiffness = 5.0;  // k_s [N/m]
  p.integrator = integrator;
  return p;
}

// Positions moved off rest by a deterministic pattern of amplitude `amplitude` [m].
mesh::Points Jiggled(const mesh::Points& rest, double amplitude) {
  mesh::Points x = rest;
  std::mt19937 random(3);
  std::uniform_real_distribution<double> offset(-amplitude, amplitude);
  for (Eigen::Index i = 0; i < x.size(); ++i) x.data()[i] += offset(random);
  return x;
}

TEST(GeneralisedSurfaceModel, OnlyTheShellHasMassAndTheCoreStaysAtRest) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  const auto model = MassSpringModel::FromGeneralisedSurface(
      liver, ShellMaterial(MassSpringIntegrator::kSymplecticEuler));
  const OuterShell shell = SelectOuterShell(liver, 0.2);
  ASSERT_EQ(model->anchored_nodes().size(), static_cast<size_t>(shell.num_shell_nodes));
  for (size_t i = 0; i < shell.in_shell.size(); ++i) {
    EXPECT_EQ(model->masses()[i] > 0.0, shell.in_shell[i] != 0) << "node " << i;
  }
  const auto state = model->MakeState();
  StepInputs inputs;
  inputs.dt = 1e-4;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  for (int step = 0; step < 200; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  }
  double shell_moved = 0.0;
  for (size_t i = 0; i < shell.in_shell.size(); ++i) {
    const double moved = (state->positions.col(static_cast<Eigen::Index>(i)) -
                          liver.vertices.col(static_cast<Eigen::Index>(i)))
                             .norm();
    if (shell.in_shell[i] == 0) {
      EXPECT_EQ(moved, 0.0) << "core node " << i;
    } else {
      shell_moved = std::max(shell_moved, moved);
    }
  }
  EXPECT_GT(shell_moved, 0.0);
}

TEST(GeneralisedSurfaceModel, ForcesAndStiffnessAreDerivativesOfTheEnergyWithAnchors) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  const auto model = MassSpringModel::FromGeneralisedSurface(
      liver, ShellMaterial(MassSpringIntegrator::kSymplecticEuler));
  const auto state = model->MakeState();
  state->positions = Jiggled(liver.vertices, 0.002);
  const int32_t n = model->num_nodes();
  mesh::Points forces(3, n), plus(3, n), minus(3, n);
  model->InternalForces(*state, &forces);
  const Vector3d g = Vector3d::Zero();
  for (const int32_t node : {model->anchored_nodes().front(), model->anchored_nodes().back()}) {
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
    EXPECT_LT((fd - k).norm(), 1e-6 * k.norm()) << "node " << node;
  }
}

TEST(GeneralisedSurfaceModel, TwoAnchoredNodesSettleAtTheAnalyticEquilibrium) {
  // Two nodes, one spring k, both anchored with k_s; a force F pulls node 0 along x. Static
  // balance: k_s u1 = k (u0 - u1) and k_s u0 + k (u0 - u1) = F, so
  // u0 = F (k + k_s) / (k_s (k_s + 2k)), u1 = F k / (k_s (k_s + 2k)).
  mesh::Points rest(3, 2);
  rest.col(0) = Vector3d(0.0, 0.0, 0.0);
  rest.col(1) = Vector3d(0.01, 0.0, 0.0);
  const double k = 20.0, ks = 5.0, force = -0.01;
  const double u0 = force * (k + ks) / (ks * (ks + 2 * k));
  const double u1 = force * k / (ks * (ks + 2 * k));
  for (const auto integrator :
       {MassSpringIntegrator::kSymplecticEuler, MassSpringIntegrator::kImplicitEuler}) {
    MassSpringParameters p;
    p.spring_stiffness = k;
    p.node_mass = 1e-3;
    p.damping_ratio = 0.5;
    p.anchor_stiffness = ks;
    p.integrator = integrator;
    p.cg_tolerance = 1e-12;
    const auto model = MassSpringModel::FromEdges(rest, {{0, 1}}, p);
    const auto state = model->MakeState();
    const mesh::Points load = PointLoad2(Vector3d(force, 0.0, 0.0));
    StepInputs inputs;
    inputs.dt = 1e-3;
    inputs.external_forces = &load;
    for (int step = 0; step < 20000; ++step) {
      ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    }
    EXPECT_NEAR(state->positions(0, 0) - rest(0, 0), u0, 1e-9);
    EXPECT_NEAR(state->positions(0, 1) - rest(0, 1), u1, 1e-9);
  }
}

TEST(GeneralisedSurfaceModel, StepsAllocateNothing) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  for (const auto integrator :
       {MassSpringIntegrator::kSymplecticEuler, MassSpringIntegrator::kImplicitEuler}) {
    const auto model = MassSpringModel::FromGeneralisedSurface(liver, ShellMaterial(integrator));
    const auto state = model->MakeState();
    StepInputs inputs;
    inputs.dt = 1e-4;
    inputs.gravity = Vector3d(0.0, 0.0, -9.81);
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    testing::AllocationCounter counter;
    for (int step = 0; step < 10; ++step) {
      ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    }
    EXPECT_EQ(counter.count(), 0);
  }
}

TEST(GeneralisedSurfaceModel, BadAnchorsAreRefusedNamingThem) {
  const mesh::TetMesh liver = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  MassSpringParameters p = ShellMaterial(MassSpringIntegrator::kSymplecticEuler);
  p.anchor_stiffness = 0.0;
  try {
    MassSpringModel::FromGeneralisedSurface(liver, p);
    ADD_FAILURE() << "no anchors accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("anchor_stiffness"), std::string::npos) << e.what();
  }
  for (const double bad : {-1.0, std::nan(""), std::numeric_limits<double>::infinity()}) {
    p.anchor_stiffness = bad;
    EXPECT_THROW(MassSpringModel::FromGeneralisedSurface(liver, p), std::invalid_argument);
  }
  p.anchor_stiffness = 5.0;
  p.shell_fraction = 0.7;
  EXPECT_THROW(MassSpringModel::FromGeneralisedSurface(liver, p), std::invalid_argument);
}

}  // namespace
}  // namespace somasim::models
