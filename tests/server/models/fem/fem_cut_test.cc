// Cutting a FEM state (FemModel::ApplyCut, SPEC §5.3): cut elements leave the assembly exactly
// (forces, energy and stiffness equal those of a model built without them), relocated nodes carry
// their rest positions along so a relocation adds no strain, no rest element is inverted, the
// cut survives a rejected step, bad input is refused without a change, and a cut allocates
// nothing.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <random>
#include <stdexcept>
#include <vector>

#include "common/mesh_gen/structured_meshes.h"
#include "server/models/fem/fem_model.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

FemParameters Material(FemKind kind) {
  FemParameters p;
  p.kind = kind;
  p.youngs_modulus = 5000.0;  // [Pa]
  p.poisson_ratio = 0.3;
  p.density = 1055.0;
  if (kind == FemKind::kHyperelastic) p.hyperelastic = NeoHookean(5000.0 / 2.6 / 2.0, 1e-4);
  return p;
}

mesh::TetMesh Box() {
  return mesh_gen::BoxGridTets(3, 3, 4, Vector3d::Zero(), Vector3d(0.02, 0.02, 0.03));
}

mesh::Points Deformed(const mesh::Points& rest, unsigned seed) {
  const Matrix3d q = Eigen::AngleAxisd(0.7, Vector3d(1.0, 2.0, 0.5).normalized()).matrix();
  mesh::Points x = q * Vector3d(1.08, 0.96, 1.02).asDiagonal() * rest;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> noise(-4e-4, 4e-4);
  for (Eigen::Index i = 0; i < x.size(); ++i) x.data()[i] += noise(rng);
  return x;
}

// Every third element of the box's lower half: none of them leaves a node without an element
// (checked below), as the cutter guarantees.
std::vector<int32_t> SomeElements(const mesh::TetMesh& mesh) {
  std::vector<int32_t> removed;
  for (int32_t e = 0; e < static_cast<int32_t>(mesh.tetrahedra.cols()); e += 3) {
    if (mesh.vertices.col(mesh.tetrahedra(0, e)).z() < 0.015) removed.push_back(e);
  }
  return removed;
}

mesh::TetMesh Without(const mesh::TetMesh& mesh, const std::vector<int32_t>& removed) {
  mesh::TetMesh out;
  out.vertices = mesh.vertices;
  std::vector<uint8_t> gone(static_cast<size_t>(mesh.tetrahedra.cols()), 0);
  for (const int32_t e : removed) gone[static_cast<size_t>(e)] = 1;
  out.tetrahedra.resize(4, mesh.tetrahedra.cols() - static_cast<Eigen::Index>(removed.size()));
  Eigen::Index k = 0;
  for (Eigen::Index e = 0; e < mesh.tetrahedra.cols(); ++e) {
    if (gone[static_cast<size_t>(e)] == 0) out.tetrahedra.col(k++) = mesh.tetrahedra.col(e);
  }
  return out;
}

class FemCutKinds : public ::testing::TestWithParam<FemKind> {};

TEST_P(FemCutKinds, CutElementsLeaveTheAssemblyExactly) {
  const mesh::TetMesh mesh = Box();
  const std::vector<int32_t> removed = SomeElements(mesh);
  ASSERT_GT(removed.size(), 5U);
  const mesh::TetMesh reduced_mesh = Without(mesh, removed);
  std::vector<int> used(static_cast<size_t>(mesh.vertices.cols()), 0);
  for (Eigen::Index e = 0; e < reduced_mesh.tetrahedra.cols(); ++e) {
    for (int a = 0; a < 4; ++a) used[static_cast<size_t>(reduced_mesh.tetrahedra(a, e))] = 1;
  }
  for (const int u : used) ASSERT_EQ(u, 1) << "the test's removal orphans a node";

  const auto model = FemModel::FromTetMesh(mesh, Material(GetParam()));
  const auto reference = FemModel::FromTetMesh(reduced_mesh, Material(GetParam()));
  auto state = model->MakeState();
  auto ref_state = reference->MakeState();
  model->ApplyCut(removed, {}, state->positions, state.get());
  for (const int32_t e : removed) EXPECT_FALSE(model->ElementAlive(*state, e));
  EXPECT_TRUE(model->ElementAlive(*state, 1));

  state->positions = Deformed(mesh.vertices, 3);
  ref_state->positions = state->positions;
  mesh::Points f, f_ref;
  model->InternalForces(*state, &f);
  reference->InternalForces(*ref_state, &f_ref);
  EXPECT_LE((f - f_ref).norm(), 1e-10 * f_ref.norm());
  const double energy = model->Energy(*state, Vector3d::Zero()).elastic;
  const double energy_ref = reference->Energy(*ref_state, Vector3d::Zero()).elastic;
  EXPECT_NEAR(energy, energy_ref, 1e-10 * std::abs(energy_ref));
  for (const int32_t node : {0, 7, 20, 35}) {
    EXPECT_LE(
        (model->LocalStiffness(*state, node) - reference->LocalStiffness(*ref_state, node)).norm(),
        1e-9 * reference->LocalStiffness(*ref_state, node).norm())
        << "node " << node;
  }
  // Mass is conserved: the masses are the uncut model's.
  double mass = 0.0;
  for (const double m : model->masses()) mass += m;
  EXPECT_NEAR(mass, 1055.0 * 0.02 * 0.02 * 0.03, 1e-12);
}

TEST_P(FemCutKinds, ARelocationUnderAHomogeneousDeformationAddsNoStrain) {
  const mesh::TetMesh mesh = Box();
  const auto model = FemModel::FromTetMesh(mesh, Material(GetParam()));
  auto state = model->MakeState();
  // x = F X, homogeneous: interior nodes carry no force.
  const Matrix3d f = Eigen::AngleAxisd(0.4, Vector3d(0.0, 1.0, 1.0).normalized()).matrix() *
                     Vector3d(1.05, 0.97, 1.01).asDiagonal();
  state->positions = f * mesh.vertices;
  mesh::Points before = state->positions;
  // An interior node (the box's centre column) moved by 1 mm.
  int32_t node = -1;
  for (int32_t i = 0; i < mesh.vertices.cols(); ++i) {
    const Vector3d x = mesh.vertices.col(i);
    if (std::abs(x.x() - 0.01) < 1e-9 && std::abs(x.y() - 0.01) < 1e-9 &&
        std::abs(x.z() - 0.01) < 1e-9) {
      node = i;
    }
  }
  ASSERT_GE(node, 0);
  mesh::Points f0;
  model->InternalForces(*state, &f0);
  ASSERT_LE(f0.col(node).norm(), 1e-9);
  const double scale = f0.cwiseAbs().maxCoeff();
  state->positions.col(node) += Vector3d(1e-3, -0.5e-3, 0.3e-3);
  const int32_t moved[] = {node};
  model->ApplyCut({}, moved, before, state.get());
  mesh::Points f1;
  model->InternalForces(*state, &f1);
  EXPECT_LE((f1 - f0).cwiseAbs().maxCoeff(), 1e-9 * scale) << "the relocation strained the tissue";
  EXPECT_LE((model->RestPositions(*state).col(node) -
             (mesh.vertices.col(node) + f.inverse() * Vector3d(1e-3, -0.5e-3, 0.3e-3)))
                .norm(),
            1e-12);
}

INSTANTIATE_TEST_SUITE_P(Kinds, FemCutKinds,
                         ::testing::Values(FemKind::kLinear, FemKind::kCorotational,
                                           FemKind::kHyperelastic));

TEST(FemCut, ARestMoveThatWouldInvertAnElementIsShortened) {
  const mesh::TetMesh mesh = Box();
  const auto model = FemModel::FromTetMesh(mesh, Material(FemKind::kCorotational));
  auto state = model->MakeState();
  const mesh::Points before = state->positions;
  // A corner node moved far through the box: its rest move must stop short of inverting.
  state->positions.col(0) += Vector3d(0.03, 0.03, 0.03);
  const int32_t moved[] = {0};
  model->ApplyCut({}, moved, before, state.get());
  const mesh::Points& rest = model->RestPositions(*state);
  for (Eigen::Index e = 0; e < mesh.tetrahedra.cols(); ++e) {
    Matrix3d d;
    for (int c = 0; c < 3; ++c)
      d.col(c) = rest.col(mesh.tetrahedra(c + 1, e)) - rest.col(mesh.tetrahedra(0, e));
    Matrix3d d0;
    for (int c = 0; c < 3; ++c) {
      d0.col(c) =
          mesh.vertices.col(mesh.tetrahedra(c + 1, e)) - mesh.vertices.col(mesh.tetrahedra(0, e));
    }
    EXPECT_GE(d.determinant(), 0.05 * d0.determinant() * (1 - 1e-12)) << "element " << e;
  }
  mesh::Points forces;
  model->InternalForces(*state, &forces);
  EXPECT_TRUE(forces.allFinite());
}

TEST(FemCut, BadCutsAreRefusedWithoutAChange) {
  const mesh::TetMesh mesh = Box();
  const auto model = FemModel::FromTetMesh(mesh, Material(FemKind::kCorotational));
  auto state = model->MakeState();
  const mesh::Points before = state->positions;
  const int32_t out_of_range[] = {static_cast<int32_t>(mesh.tetrahedra.cols())};
  const int32_t negative[] = {-1};
  const int32_t good[] = {2};
  EXPECT_THROW(model->ApplyCut(out_of_range, {}, before, state.get()), std::invalid_argument);
  EXPECT_THROW(model->ApplyCut(good, negative, before, state.get()), std::invalid_argument);
  mesh::Points wrong(3, 2);
  wrong.setZero();
  EXPECT_THROW(model->ApplyCut(good, {}, wrong, state.get()), std::invalid_argument);
  mesh::Points nan = before;
  nan(1, 3) = std::nan("");
  EXPECT_THROW(model->ApplyCut(good, {}, nan, state.get()), std::invalid_argument);
  EXPECT_TRUE(model->ElementAlive(*state, 2)) << "a refused cut changed the state";
  model->ApplyCut(good, {}, before, state.get());
  EXPECT_FALSE(model->ElementAlive(*state, 2));
  try {
    model->ApplyCut(good, {}, before, state.get());
    FAIL() << "cutting an element twice was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("already cut"), std::string::npos) << e.what();
  }
}

TEST(FemCut, ACutSurvivesARejectedStepAndAllocatesNothing) {
  const mesh::TetMesh mesh = Box();
  FemParameters p = Material(FemKind::kCorotational);
  const auto model = FemModel::FromTetMesh(mesh, p);
  auto state = model->MakeState();
  StepInputs inputs;
  inputs.dt = 1e-3;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  const mesh::Points before = state->positions;
  state->positions.col(5) += Vector3d(2e-4, 0.0, 0.0);
  const int32_t removed[] = {4, 9};
  const int32_t moved[] = {5};
  {
    testing::AllocationCounter counter;
    model->ApplyCut(removed, moved, before, state.get());
    EXPECT_EQ(counter.count(), 0);
  }
  const Vector3d relocated = state->positions.col(5);
  // A step that diverges (a huge external force): rejected, the cut and the relocation stay.
  mesh::Points push = mesh::Points::Zero(3, mesh.vertices.cols());
  push(0, 30) = 1e12;
  inputs.external_forces = &push;
  EXPECT_NE(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_FALSE(model->ElementAlive(*state, 4));
  EXPECT_FALSE(model->ElementAlive(*state, 9));
  EXPECT_LE((state->positions.col(5) - relocated).norm(), 1e-15);
}

}  // namespace
}  // namespace somasim::models::fem
