// EFG coupled to a mass-spring system (SPEC §4.6; seed 001's table 1 "耦合模型"): with the region
// covering every node it is the EfgModel, statics and dynamics; covering none, a linear MSS
// assembled independently here with MassSpringModel's spring constants; forces are energy
// gradients, rigid motions cost nothing and the internal forces have no resultant (the two
// regions balance); seed 001's liver pull and press stays within a measured bound of pure EFG;
// dynamics settle on the static solution; a steady step allocates nothing and changing tool
// springs re-factorise while moving targets do not; bad parameters are refused by name.
#include "server/models/meshless/efg_mss_coupled_model.h"

#include <gtest/gtest.h>

#include <Eigen/Cholesky>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <random>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"
#include "server/models/mass_spring_model.h"
#include "server/models/meshless/efg_model.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

// 80 nodes, 3 × 3 × 4 cells.
mesh::TetMesh SmallBox() {
  return mesh_gen::BoxGridTets(4, 4, 5, Vector3d::Zero(), Vector3d(0.03, 0.03, 0.04));
}

// The box's nodes at z = 0.
std::vector<int32_t> BoxBottom(const mesh::TetMesh& box) {
  std::vector<int32_t> fixed;
  for (Eigen::Index i = 0; i < box.vertices.cols(); ++i) {
    if (box.vertices(2, i) < 1e-9) fixed.push_back(static_cast<int32_t>(i));
  }
  return fixed;
}

// A region around the box's top corner that leaves both kinds of tetrahedra.
EfgMssCoupledParameters MixedBoxRegion() {
  EfgMssCoupledParameters p;
  p.region_centre = Vector3d(0.03, 0.03, 0.04);
  p.region_radius = 0.025;
  return p;
}

std::string InvalidArgumentOf(const mesh::TetMesh& mesh, const EfgMssCoupledParameters& p) {
  try {
    EfgMssCoupledModel::FromTetMesh(mesh, p);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "no exception";
}

double MaxGap(const mesh::Points& x, const mesh::Points& y) {
  double worst = 0.0;
  for (Eigen::Index i = 0; i < x.cols(); ++i) worst = std::max(worst, (x.col(i) - y.col(i)).norm());
  return worst;
}

// Seed 001's liver as in efg_model_test.cc: the top node loaded, the underside held.
struct LiverCase {
  mesh::TetMesh mesh;
  int32_t load_node = 0;       // the top node (largest z)
  std::vector<int32_t> fixed;  // the underside: z <= min z + 15 % of the height
};

LiverCase Liver288() {
  LiverCase c;
  c.mesh = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  const mesh::Points& x = c.mesh.vertices;
  const double lo = x.row(2).minCoeff(), hi = x.row(2).maxCoeff();
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  c.load_node = static_cast<int32_t>(top);
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(2, i) <= lo + 0.15 * (hi - lo)) c.fixed.push_back(static_cast<int32_t>(i));
  }
  return c;
}

EfgMssCoupledParameters RegionAt(const Vector3d& centre, double radius) {
  EfgMssCoupledParameters p;
  p.region_centre = centre;
  p.region_radius = radius;
  return p;
}

// The coupled model's largest deviation from pure EFG [m] in seed 001's pull and press on
// liver288 (Liver288PullAndPressStaysNearPureEfg): measured 4.78 mm (3.00 mm at the load node;
// pure EFG's largest displacement 78.3 mm), rounded up. The seed reports ±0.18 mm for its own
// coupled model; ours is as far off as a Van Gelder spring network is from the continuum.
constexpr double kLiver288PullPressBound = 5e-3;

// ---- Limits: all EFG, all MSS -----------------------------------------------------------------

TEST(EfgMssCoupledModel, RegionCoveringEveryNodeIsTheEfgModel) {
  const mesh::TetMesh box = SmallBox();
  const auto coupled = EfgMssCoupledModel::FromTetMesh(box, RegionAt(Vector3d::Zero(), 1.0));
  const auto efg = EfgModel::FromTetMesh(box, EfgParameters{});
  ASSERT_EQ(coupled->num_efg_nodes(), coupled->num_nodes());
  ASSERT_EQ(coupled->num_springs(), 0);
  EXPECT_EQ(coupled->penalty(), efg->penalty());
  EXPECT_EQ(coupled->num_gauss_points(), efg->num_gauss_points());
  const std::vector<int32_t> fixed = BoxBottom(box);
  const auto top = static_cast<int32_t>(box.vertices.cols() - 1);
  mesh::Points forces = mesh::Points::Zero(3, box.vertices.cols());
  forces.col(top) = Vector3d(0.2, -0.1, 0.3);  // [N]

  // Statics.
  EfgStaticLoads loads;
  loads.external_forces = &forces;
  loads.gravity = Vector3d(0.0, 0.0, -9.81);
  loads.fixed_nodes = fixed;
  auto coupled_state = coupled->MakeState();
  auto efg_state = efg->MakeState();
  coupled->SolveStatic(loads, coupled_state.get());
  efg->SolveStatic(loads, efg_state.get());
  const double scale = MaxGap(efg_state->positions, box.vertices);
  ASSERT_GT(scale, 1e-4);
  EXPECT_LT(MaxGap(coupled_state->positions, efg_state->positions), 1e-9 * scale);

  // Dynamics, with a grasp whose target moves (the EFG's low-rank path; factorised in here).
  coupled_state = coupled->MakeState();
  efg_state = efg->MakeState();
  Attachment grasp{top, box.vertices.col(top), 200.0};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = loads.gravity;
  inputs.external_forces = &forces;
  inputs.fixed_nodes = fixed;
  inputs.attachments = {&grasp, 1};
  for (int step = 0; step < 30; ++step) {
    grasp.target = box.vertices.col(top) + Vector3d(0.0, 1e-4 * step, 0.0);
    ASSERT_EQ(coupled->Step(inputs, coupled_state.get()), StepStatus::kOk);
    ASSERT_EQ(efg->Step(inputs, efg_state.get()), StepStatus::kOk);
  }
  const double moved = MaxGap(efg_state->positions, box.vertices);
  ASSERT_GT(moved, 1e-5);
  EXPECT_LT(MaxGap(coupled_state->positions, efg_state->positions), 1e-9 * moved);
  EXPECT_LT(MaxGap(coupled_state->velocities, efg_state->velocities),
            1e-9 * efg_state->velocities.cwiseAbs().maxCoeff());
}

TEST(EfgMssCoupledModel, RegionCoveringNoNodeIsALinearMassSpringSystem) {
  const mesh::TetMesh box = SmallBox();
  const auto coupled =
      EfgMssCoupledModel::FromTetMesh(box, RegionAt(Vector3d(1.0, 1.0, 1.0), 0.01));
  ASSERT_EQ(coupled->num_efg_nodes(), 0);
  ASSERT_EQ(coupled->num_gauss_points(), 0);

  // The spring constants are MassSpringModel's (Van Gelder's rule), spring by spring (both list
  // the unique edges sorted by their nodes).
  MassSpringParameters mss;
  mss.youngs_modulus = 5000.0;
  mss.density = 1055.0;
  const auto springs = MassSpringModel::FromTetMesh(box, mss);
  ASSERT_EQ(coupled->num_springs(), springs->num_springs());
  for (int32_t s = 0; s < springs->num_springs(); ++s) {
    EXPECT_NEAR(coupled->spring_stiffness()[size_t(s)], springs->stiffness()[size_t(s)],
                1e-12 * springs->stiffness()[size_t(s)]);
  }
  for (Eigen::Index i = 0; i < box.vertices.cols(); ++i) {
    EXPECT_NEAR(coupled->masses()[size_t(i)], springs->masses()[size_t(i)], 1e-15);
  }

  // An independent linear MSS: K = Σ k e eᵀ over the unique edges (each edge's k from the summed
  // volumes of its tetrahedra), the bottom held exactly (its rows and columns removed).
  const auto n = static_cast<Eigen::Index>(box.vertices.cols());
  std::map<std::pair<int32_t, int32_t>, double> edge_volume;
  for (Eigen::Index t = 0; t < box.tetrahedra.cols(); ++t) {
    const auto x = [&](int a) { return box.vertices.col(box.tetrahedra(a, t)); };
    const double v = (x(1) - x(0)).dot((x(2) - x(0)).cross(x(3) - x(0))) / 6.0;
    for (int a = 0; a < 4; ++a) {
      for (int b = a + 1; b < 4; ++b) {
        const int32_t i = box.tetrahedra(a, t), j = box.tetrahedra(b, t);
        edge_volume[{std::min(i, j), std::max(i, j)}] += v;
      }
    }
  }
  Eigen::MatrixXd k = Eigen::MatrixXd::Zero(3 * n, 3 * n);
  for (const auto& [edge, v] : edge_volume) {
    const Vector3d d = box.vertices.col(edge.second) - box.vertices.col(edge.first);
    const Matrix3d block = 5000.0 * v / d.squaredNorm() * (d * d.transpose()) / d.squaredNorm();
    for (const auto& [a, b, sign] : {std::tuple{edge.first, edge.first, 1.0},
                                     {edge.second, edge.second, 1.0},
                                     {edge.first, edge.second, -1.0},
                                     {edge.second, edge.first, -1.0}}) {
      k.block<3, 3>(3 * a, 3 * b) += sign * block;
    }
  }
  const std::vector<int32_t> fixed = BoxBottom(box);
  std::vector<Eigen::Index> free_dofs;
  for (Eigen::Index i = 0; i < n; ++i) {
    if (std::find(fixed.begin(), fixed.end(), i) != fixed.end()) continue;
    for (int c = 0; c < 3; ++c) free_dofs.push_back(3 * i + c);
  }
  const auto top = static_cast<int32_t>(n - 1);
  mesh::Points forces = mesh::Points::Zero(3, n);
  forces.col(top) = Vector3d(0.2, -0.1, 0.3);  // [N]
  const Vector3d gravity(0.0, 0.0, -9.81);
  const auto m = static_cast<Eigen::Index>(free_dofs.size());
  Eigen::MatrixXd k_free(m, m);
  Eigen::VectorXd f_free(m);
  for (Eigen::Index a = 0; a < m; ++a) {
    const Eigen::Index node = free_dofs[size_t(a)] / 3, c = free_dofs[size_t(a)] % 3;
    f_free[a] = forces(c, node) + coupled->masses()[size_t(node)] * gravity[c];
    for (Eigen::Index b = 0; b < m; ++b)
      k_free(a, b) = k(free_dofs[size_t(a)], free_dofs[size_t(b)]);
  }
  const Eigen::VectorXd u_free = k_free.ldlt().solve(f_free);
  mesh::Points expected = box.vertices;
  for (Eigen::Index a = 0; a < m; ++a) {
    expected(free_dofs[size_t(a)] % 3, free_dofs[size_t(a)] / 3) += u_free[a];
  }

  EfgStaticLoads loads;
  loads.external_forces = &forces;
  loads.gravity = gravity;
  loads.fixed_nodes = fixed;
  auto state = coupled->MakeState();
  coupled->SolveStatic(loads, state.get());
  const double scale = u_free.cwiseAbs().maxCoeff();
  ASSERT_GT(scale, 1e-4);
  // The supports are penalty springs (κ = 1e5 × max diagonal): met to ~1e-5 of the response.
  EXPECT_LT(MaxGap(state->positions, expected), 1e-4 * scale);
}

// ---- Energy, forces, balance -----------------------------------------------------------------

TEST(EfgMssCoupledModel, MixedRegionHasBothKindsAndAnInterface) {
  const auto model = EfgMssCoupledModel::FromTetMesh(SmallBox(), MixedBoxRegion());
  EXPECT_GT(model->num_efg_nodes(), 10);
  EXPECT_LT(model->num_efg_nodes(), model->num_nodes() - 10);
  EXPECT_GT(model->num_interface_nodes(), 0);
  EXPECT_GT(model->num_springs(), 0);
  EXPECT_GT(model->num_meshless_tets(), 0);
}

TEST(EfgMssCoupledModel, ForcesAreMinusTheEnergyGradient) {
  const auto model = EfgMssCoupledModel::FromTetMesh(SmallBox(), MixedBoxRegion());
  auto state = model->MakeState();
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> offset(-1e-3, 1e-3);
  for (Eigen::Index k = 0; k < state->positions.size(); ++k) {
    state->positions.data()[k] += offset(rng);
  }
  mesh::Points forces;
  model->InternalForces(*state, &forces);
  const double h = 1e-7;
  for (Eigen::Index k = 0; k < forces.size(); k += 3) {
    const double x0 = state->positions.data()[k];
    state->positions.data()[k] = x0 + h;
    const double plus = model->Energy(*state, Vector3d::Zero()).elastic;
    state->positions.data()[k] = x0 - h;
    const double minus = model->Energy(*state, Vector3d::Zero()).elastic;
    state->positions.data()[k] = x0;
    EXPECT_NEAR(forces.data()[k], -(plus - minus) / (2.0 * h), 1e-6 * forces.cwiseAbs().maxCoeff())
        << "dof " << k;
  }
  // The two regions balance: the internal forces have no resultant and no moment.
  Vector3d resultant = Vector3d::Zero(), moment = Vector3d::Zero();
  for (Eigen::Index i = 0; i < forces.cols(); ++i) {
    resultant += forces.col(i);
    moment += model->rest_positions().col(i).cross(forces.col(i));
  }
  EXPECT_LT(resultant.norm(), 1e-9 * forces.cwiseAbs().maxCoeff());
  EXPECT_LT(moment.norm(), 1e-9 * 0.05 * forces.cwiseAbs().maxCoeff());
}

// Linear elasticity: a translation and an infinitesimal rotation u = ω × X store no energy (the
// EFG reproduces linear fields; a linear spring sees e·(ω × (X_b - X_a)) = 0).
TEST(EfgMssCoupledModel, RigidMotionsCostNoElasticEnergy) {
  const auto model = EfgMssCoupledModel::FromTetMesh(SmallBox(), MixedBoxRegion());
  auto state = model->MakeState();
  const mesh::Points& rest = model->rest_positions();
  // A reference: a 0.1 % stretch along z.
  state->positions = rest;
  state->positions.row(2) *= 1.001;
  const double stretch = model->Energy(*state, Vector3d::Zero()).elastic;
  ASSERT_GT(stretch, 0.0);
  state->positions = rest.colwise() + Vector3d(1e-3, -2e-3, 5e-4);
  EXPECT_LT(model->Energy(*state, Vector3d::Zero()).elastic, 1e-12 * stretch);
  const Vector3d omega(0.01, -0.02, 0.015);  // [rad]
  for (Eigen::Index i = 0; i < rest.cols(); ++i) {
    state->positions.col(i) = rest.col(i) + omega.cross(rest.col(i));
  }
  EXPECT_LT(model->Energy(*state, Vector3d::Zero()).elastic, 1e-12 * stretch);
  mesh::Points forces;
  model->InternalForces(*state, &forces);
  EXPECT_LT(forces.cwiseAbs().maxCoeff(), 1e-9);
}

// ---- Seed 001's liver ------------------------------------------------------------------------

// Seed 001 §2 and Fig. 5/6: 5.7 N at the top node in 0.3 N steps, pulled and pressed, underside
// held; the seed's coupled model stays within ±0.018 cm of pure EFG. Here the region is the 5 cm
// ball around the load node (the default radius). Measured (this build): see the printout; the
// bound asserted is that measurement rounded up, not a tuned value.
TEST(EfgMssCoupledModel, Liver288PullAndPressStaysNearPureEfg) {
  if (somasim::testing::kUnderSanitizer) GTEST_SKIP() << "heavy validation: Release build only";
  const LiverCase liver = Liver288();
  const auto efg = EfgModel::FromTetMesh(liver.mesh, EfgParameters{});
  const auto coupled = EfgMssCoupledModel::FromTetMesh(
      liver.mesh, RegionAt(liver.mesh.vertices.col(liver.load_node), 0.05));
  auto efg_state = efg->MakeState();
  auto coupled_state = coupled->MakeState();
  double worst = 0.0, worst_at_load = 0.0, largest = 0.0;
  for (const double sign : {1.0, -1.0}) {
    for (int k = 1; k <= 19; ++k) {
      mesh::Points forces = mesh::Points::Zero(3, liver.mesh.vertices.cols());
      forces(2, liver.load_node) = sign * 0.3 * k;  // [N]
      EfgStaticLoads loads;
      loads.external_forces = &forces;
      loads.fixed_nodes = liver.fixed;
      efg->SolveStatic(loads, efg_state.get());
      coupled->SolveStatic(loads, coupled_state.get());
      ASSERT_TRUE(coupled_state->positions.allFinite());
      worst = std::max(worst, MaxGap(coupled_state->positions, efg_state->positions));
      worst_at_load = std::max(worst_at_load, (coupled_state->positions.col(liver.load_node) -
                                               efg_state->positions.col(liver.load_node))
                                                  .norm());
      largest = std::max(largest, MaxGap(efg_state->positions, liver.mesh.vertices));
    }
  }
  std::printf(
      "liver288 coupled EFG+MSS (radius 5 cm: %d EFG nodes, %d interface, %d springs) vs pure "
      "EFG, pull and press to 5.7 N: max |dx| %.3f mm (at the load node %.3f mm); EFG's largest "
      "displacement %.2f mm\n",
      coupled->num_efg_nodes(), coupled->num_interface_nodes(), coupled->num_springs(), 1e3 * worst,
      1e3 * worst_at_load, 1e3 * largest);
  EXPECT_GT(coupled->num_springs(), 0);
  EXPECT_LT(worst, kLiver288PullPressBound);
}

// The springs are what differs from the continuum: the larger the EFG region around the load,
// the closer to pure EFG (and equal once it covers the organ).
TEST(EfgMssCoupledModel, DeviationFromPureEfgShrinksAsTheRegionGrows) {
  if (somasim::testing::kUnderSanitizer) GTEST_SKIP() << "heavy validation: Release build only";
  const LiverCase liver = Liver288();
  const auto efg = EfgModel::FromTetMesh(liver.mesh, EfgParameters{});
  mesh::Points forces = mesh::Points::Zero(3, liver.mesh.vertices.cols());
  forces(2, liver.load_node) = 5.7;  // [N]
  EfgStaticLoads loads;
  loads.external_forces = &forces;
  loads.fixed_nodes = liver.fixed;
  auto efg_state = efg->MakeState();
  efg->SolveStatic(loads, efg_state.get());
  const double largest = MaxGap(efg_state->positions, liver.mesh.vertices);
  double last = std::numeric_limits<double>::infinity();
  std::printf("liver288 coupled vs pure EFG at 5.7 N, by region radius:");
  // Radius 0 far from the organ: no region at all (pure springs).
  for (const double radius : {0.0, 0.03, 0.05, 0.08, 0.12, 1.0}) {
    const Vector3d centre =
        radius > 0.0 ? Vector3d(liver.mesh.vertices.col(liver.load_node)) : Vector3d::Constant(1e3);
    const auto coupled = EfgMssCoupledModel::FromTetMesh(liver.mesh, RegionAt(centre, radius));
    auto state = coupled->MakeState();
    coupled->SolveStatic(loads, state.get());
    const double gap = MaxGap(state->positions, efg_state->positions);
    std::printf(
        " %.0f cm (%d EFG nodes): %.3f mm (load node u_z %.2f mm);", 100.0 * radius,
        coupled->num_efg_nodes(), 1e3 * gap,
        1e3 * (state->positions(2, liver.load_node) - liver.mesh.vertices(2, liver.load_node)));
    EXPECT_LT(gap, last) << radius;
    last = gap;
  }
  std::printf(
      " pure EFG: load node u_z %.2f mm\n",
      1e3 * (efg_state->positions(2, liver.load_node) - liver.mesh.vertices(2, liver.load_node)));
  EXPECT_LT(last, 1e-9 * largest);  // the whole organ: pure EFG
}

// ---- Dynamics ---------------------------------------------------------------------------------

TEST(EfgMssCoupledModel, ImplicitDynamicsSettlesOnTheStaticSolution) {
  const mesh::TetMesh box = SmallBox();
  EfgMssCoupledParameters p = MixedBoxRegion();
  p.efg.rayleigh_mass = 20.0;
  const auto model = EfgMssCoupledModel::FromTetMesh(box, p);
  const std::vector<int32_t> fixed = BoxBottom(box);
  const Vector3d gravity(0.0, 0.0, -9.81);
  auto statics = model->MakeState();
  EfgStaticLoads loads;
  loads.gravity = gravity;
  loads.fixed_nodes = fixed;
  model->SolveStatic(loads, statics.get());
  const double sag = MaxGap(statics->positions, box.vertices);
  ASSERT_GT(sag, 1e-6);
  auto state = model->MakeState();
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = gravity;
  inputs.fixed_nodes = fixed;
  double first_total = 0.0;
  for (int step = 0; step < 2000; ++step) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk) << step;
    if (step == 0) first_total = model->Energy(*state, gravity).total();
  }
  EXPECT_LT(MaxGap(state->positions, statics->positions), 1e-3 * sag);
  EXPECT_LT(model->Energy(*state, gravity).total(), first_total);
  EXPECT_EQ(model->Factorisations(*state), 2);  // the step's and the static factor, once
}

TEST(EfgMssCoupledModel, SteadyStepAllocatesNothing) {
  const LiverCase liver = Liver288();
  const auto model = EfgMssCoupledModel::FromTetMesh(
      liver.mesh, RegionAt(liver.mesh.vertices.col(liver.load_node), 0.05));
  auto state = model->MakeState();
  mesh::Points forces = mesh::Points::Zero(3, model->num_nodes());
  forces(2, liver.load_node) = 0.5;
  Attachment grasp{liver.load_node, liver.mesh.vertices.col(liver.load_node), 50.0};
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.external_forces = &forces;
  inputs.fixed_nodes = liver.fixed;
  inputs.attachments = {&grasp, 1};
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);  // factorises: may allocate
  (void)model->LocalStiffness(*state, liver.load_node);
  const int64_t factorised = model->Factorisations(*state);
  int64_t allocations = 0;
  {
    const somasim::testing::AllocationCounter counter;
    for (int k = 0; k < 5; ++k) {
      forces(0, liver.load_node) = 0.1 * k;  // the load and the grasp's target move
      grasp.target.x() += 1e-4;
      ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    }
    (void)model->LocalStiffness(*state, liver.load_node);
    allocations = counter.count();
  }
  EXPECT_EQ(allocations, 0);
  EXPECT_EQ(model->Factorisations(*state), factorised);
  // A change of the grasp's stiffness is factorised in (and only the step's factor).
  grasp.stiffness = 80.0;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_EQ(model->Factorisations(*state), factorised + 1);
  const Matrix3d k = model->LocalStiffness(*state, liver.load_node);
  EXPECT_LT((k - k.transpose()).norm(), 1e-12 * k.norm());
  EXPECT_GT(k.diagonal().minCoeff(), 0.0);
}

TEST(EfgMssCoupledModel, RejectedAndBadStepsLeaveTheStateUnchanged) {
  const auto model = EfgMssCoupledModel::FromTetMesh(SmallBox(), MixedBoxRegion());
  auto state = model->MakeState();
  StepInputs inputs;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  const std::vector<int32_t> fixed = BoxBottom(SmallBox());
  inputs.fixed_nodes = fixed;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  const mesh::Points before = state->positions;
  mesh::Points huge = mesh::Points::Zero(3, model->num_nodes());
  huge(2, model->num_nodes() - 1) = 1e12;  // [N]: far beyond the speed limit
  inputs.external_forces = &huge;
  EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kRejectedTooFast);
  EXPECT_EQ(state->positions, before);
  inputs.external_forces = nullptr;
  inputs.dt = -1.0;
  EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kBadInput);
  EXPECT_EQ(state->positions, before);
}

// ---- Bad input -------------------------------------------------------------------------------

TEST(EfgMssCoupledModel, BadParametersAreRefusedByName) {
  const mesh::TetMesh box = SmallBox();
  EfgMssCoupledParameters p = MixedBoxRegion();
  p.region_radius = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(InvalidArgumentOf(box, p).find("region_radius"), std::string::npos);
  p.region_radius = -0.01;
  EXPECT_NE(InvalidArgumentOf(box, p).find("region_radius"), std::string::npos);
  p = MixedBoxRegion();
  p.region_centre = Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  EXPECT_NE(InvalidArgumentOf(box, p).find("region_centre"), std::string::npos);
  EXPECT_NE(InvalidArgumentOf(box, EfgMssCoupledParameters{}).find("region_centre"),
            std::string::npos);  // the default: no centre given
  p = MixedBoxRegion();
  p.efg.youngs_modulus = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(InvalidArgumentOf(box, p).find("youngs_modulus"), std::string::npos);
  p = MixedBoxRegion();
  p.efg.poisson_ratio = 0.5;
  EXPECT_NE(InvalidArgumentOf(box, p).find("poisson_ratio"), std::string::npos);
  p = MixedBoxRegion();
  p.efg.gauss_points = 5;
  EXPECT_NE(InvalidArgumentOf(box, p).find("gauss_points"), std::string::npos);
  EXPECT_NE(InvalidArgumentOf(mesh::TetMesh{}, MixedBoxRegion()).find("empty"), std::string::npos);
  mesh::TetMesh bad = box;
  bad.vertices(1, 5) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(InvalidArgumentOf(bad, MixedBoxRegion()).find("vertex 5"), std::string::npos);
  bad = box;
  std::swap(bad.tetrahedra(0, 3), bad.tetrahedra(1, 3));  // inverted
  EXPECT_NE(InvalidArgumentOf(bad, MixedBoxRegion()).find("tetrahedron 3"), std::string::npos);

  // A region of one tetrahedron (4 nodes) cannot carry the MLS (4 neighbours per support).
  mesh::TetMesh two;
  two.vertices.resize(3, 5);
  two.vertices << 0.0, 0.01, 0.0, 0.0, 0.01,  //
      0.0, 0.0, 0.01, 0.0, 0.01,              //
      0.0, 0.0, 0.0, 0.01, 0.01;
  two.tetrahedra.resize(4, 2);
  two.tetrahedra << 0, 4, 1, 2, 3, 3, 2, 1;
  for (Eigen::Index t = 0; t < 2; ++t) {  // orient positively
    const auto x = [&](int a) { return two.vertices.col(two.tetrahedra(a, t)); };
    if ((x(1) - x(0)).dot((x(2) - x(0)).cross(x(3) - x(0))) < 0.0) {
      std::swap(two.tetrahedra(0, t), two.tetrahedra(1, t));
    }
  }
  EfgMssCoupledParameters one = RegionAt(Vector3d::Zero(), 1e-3);  // node 0: only tet 0
  EXPECT_NE(InvalidArgumentOf(two, one).find("region_radius"), std::string::npos)
      << InvalidArgumentOf(two, one);
}

TEST(EfgMssCoupledModel, StaticSolveRefusesBadLoads) {
  const auto model = EfgMssCoupledModel::FromTetMesh(SmallBox(), MixedBoxRegion());
  auto state = model->MakeState();
  EfgStaticLoads loads;  // nothing held
  EXPECT_THROW(model->SolveStatic(loads, state.get()), std::invalid_argument);
  const std::vector<int32_t> fixed = BoxBottom(SmallBox());
  loads.fixed_nodes = fixed;
  const mesh::Points wrong = mesh::Points::Zero(3, 3);
  loads.external_forces = &wrong;
  EXPECT_THROW(model->SolveStatic(loads, state.get()), std::invalid_argument);
}

}  // namespace
}  // namespace somasim::models::meshless
