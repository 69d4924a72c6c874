// The cut's geometry: which segments cross a blade's swept quad.
#include "server/models/cut_geometry.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"
#include "server/models/mass_spring_model.h"
#include "server/models/molecular_model.h"
#include "server/models/position_based_model.h"

namespace somasim::models {
namespace {

using Eigen::Vector3d;

// A blade from z = 0.01 down to z = -0.01 along x = 0, moved along y from 0 to 0.02: the sweep
// is the part of the plane x = 0 with y in [0, 0.02] and z in [-0.01, 0.01].
SweptQuad Blade() {
  SweptQuad sweep;
  sweep.p0 = Vector3d(0.0, 0.0, 0.01);
  sweep.q0 = Vector3d(0.0, 0.0, -0.01);
  sweep.p1 = Vector3d(0.0, 0.02, 0.01);
  sweep.q1 = Vector3d(0.0, 0.02, -0.01);
  return sweep;
}

TEST(CutGeometry, SegmentsCrossingThePlaneInsideTheQuadAreCut) {
  const SweptQuad sweep = Blade();
  EXPECT_TRUE(SegmentCrossesSweep(Vector3d(-0.001, 0.01, 0.0), Vector3d(0.001, 0.01, 0.0), sweep));
  EXPECT_TRUE(
      SegmentCrossesSweep(Vector3d(0.003, 0.005, 0.008), Vector3d(-0.001, 0.015, -0.009), sweep));
  // Beyond the blade's reach (z), before its start (y < 0), or not reaching the plane.
  EXPECT_FALSE(
      SegmentCrossesSweep(Vector3d(-0.001, 0.01, 0.02), Vector3d(0.001, 0.01, 0.02), sweep));
  EXPECT_FALSE(
      SegmentCrossesSweep(Vector3d(-0.001, -0.01, 0.0), Vector3d(0.001, -0.01, 0.0), sweep));
  EXPECT_FALSE(SegmentCrossesSweep(Vector3d(0.001, 0.01, 0.0), Vector3d(0.003, 0.01, 0.0), sweep));
  // In the plane of the sweep: separates nothing.
  EXPECT_FALSE(SegmentCrossesSweep(Vector3d(0.0, 0.005, 0.0), Vector3d(0.0, 0.015, 0.0), sweep));
}

TEST(CutGeometry, AgreesWithThePlaneCrossingOfRandomSegments) {
  // For the planar sweep, a segment crosses iff its ends are on opposite sides of x = 0 and the
  // crossing point lies in the rectangle.
  const SweptQuad sweep = Blade();
  std::mt19937 random(11);
  std::uniform_real_distribution<double> coordinate(-0.03, 0.03);
  int crossings = 0;
  for (int trial = 0; trial < 2000; ++trial) {
    const Vector3d a(coordinate(random), coordinate(random), coordinate(random));
    const Vector3d b(coordinate(random), coordinate(random), coordinate(random));
    bool expected = false;
    if (a.x() * b.x() < 0.0) {
      const double s = a.x() / (a.x() - b.x());
      const Vector3d c = a + s * (b - a);
      expected = c.y() >= 0.0 && c.y() <= 0.02 && c.z() >= -0.01 && c.z() <= 0.01;
    }
    crossings += expected ? 1 : 0;
    EXPECT_EQ(SegmentCrossesSweep(a, b, sweep), expected) << "trial " << trial;
  }
  EXPECT_GT(crossings, 50);
}

TEST(CutGeometry, ABladeThatDidNotMoveCutsNothing) {
  SweptQuad still = Blade();
  still.p1 = still.p0;
  still.q1 = still.q0;
  EXPECT_FALSE(SegmentCrossesSweep(Vector3d(-0.001, 0.0, 0.0), Vector3d(0.001, 0.0, 0.0), still));
}

}  // namespace
}  // namespace somasim::models

namespace somasim::models {
namespace {

// A plate 192 (seed 003: 200 × 200 × 10 mm) cut through its middle from one edge to the other:
// the springs / constraints crossing x = 0.1 go, and the two halves come apart under gravity when
// held at opposite ends.
template <typename Model, typename Parameters>
void CheckCutSeparatesThePlate(const Parameters& parameters) {
  const mesh::TetMesh plate = mesh_gen::Plate192();
  const auto model = Model::FromTetMesh(plate, parameters);
  ASSERT_TRUE(model->SupportsCutting());
  const auto state = model->MakeState();
  const Eigen::Vector3d low = plate.vertices.rowwise().minCoeff();
  const Eigen::Vector3d high = plate.vertices.rowwise().maxCoeff();
  const double middle = 0.5 * (low.x() + high.x()) + 1e-4;  // between node columns
  SweptQuad sweep;
  sweep.p0 = Eigen::Vector3d(middle, low.y() - 0.01, high.z() + 0.01);
  sweep.q0 = Eigen::Vector3d(middle, low.y() - 0.01, low.z() - 0.01);
  sweep.p1 = Eigen::Vector3d(middle, high.y() + 0.01, high.z() + 0.01);
  sweep.q1 = Eigen::Vector3d(middle, high.y() + 0.01, low.z() - 0.01);
  const int32_t removed = model->Cut(sweep, state.get());
  EXPECT_GT(removed, 0);
  EXPECT_EQ(model->Cut(sweep, state.get()), 0);  // nothing left to cut there
  // Hold the left edge and the right edge; under gravity the two halves hang apart: no force
  // crosses the cut, so the nodes next to it on either side are free to sag.
  std::vector<int32_t> held;
  for (int32_t i = 0; i < plate.vertices.cols(); ++i) {
    if (plate.vertices(0, i) < low.x() + 1e-6 || plate.vertices(0, i) > high.x() - 1e-6) {
      held.push_back(i);
    }
  }
  // With no force across the cut, the internal forces of the rest state are zero and remain
  // zero at any displacement of one half alone: move the right half rigidly, and the left half
  // feels nothing.
  mesh::Points moved = state->positions;
  for (int32_t i = 0; i < moved.cols(); ++i) {
    if (moved(0, i) > middle) moved(2, i) += 0.01;
  }
  state->positions = moved;
  mesh::Points forces(3, model->num_nodes());
  model->InternalForces(*state, &forces);
  EXPECT_LT(forces.cwiseAbs().maxCoeff(), 1e-9) << "a force crosses the cut";
  StepInputs inputs;
  inputs.dt = 1e-4;
  inputs.gravity = Eigen::Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = held;
  for (int step = 0; step < 20; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  }
}

TEST(CutHook, MassSpringSpringsCrossingTheSweepStopActing) {
  MassSpringParameters p;
  p.youngs_modulus = 1e5;
  p.density = 1000.0;
  CheckCutSeparatesThePlate<MassSpringModel>(p);
  p.integrator = MassSpringIntegrator::kImplicitEuler;
  CheckCutSeparatesThePlate<MassSpringModel>(p);
}

TEST(CutHook, PositionBasedConstraintsCrossingTheSweepStopActing) {
  PositionBasedParameters p;
  p.youngs_modulus = 1e5;
  p.density = 1000.0;
  p.iterations = 10;
  CheckCutSeparatesThePlate<PositionBasedModel>(p);
}

TEST(CutHook, ModelsWithoutCuttingRemoveNothing) {
  const mesh::SurfaceMesh patch = mesh_gen::GenerateBuiltinOrgan("tissue45").surface;
  MolecularParameters p;
  p.youngs_modulus = 3000.0;
  p.density = 1000.0;
  const auto model = MolecularModel::FromSurface(patch, p);
  const auto state = model->MakeState();
  EXPECT_FALSE(model->SupportsCutting());
  SweptQuad sweep = Blade();
  EXPECT_EQ(model->Cut(sweep, state.get()), 0);
}

TEST(CutHook, NonFiniteSweepsCutNothing) {
  MassSpringParameters p;
  p.youngs_modulus = 1e5;
  p.density = 1000.0;
  const auto model = MassSpringModel::FromTetMesh(mesh_gen::Plate192(), p);
  const auto state = model->MakeState();
  SweptQuad sweep = Blade();
  sweep.q1.x() = std::nan("");
  EXPECT_EQ(model->Cut(sweep, state.get()), 0);
}

}  // namespace
}  // namespace somasim::models
