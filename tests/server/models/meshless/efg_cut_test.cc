// Cutting the element-free Galerkin model by the visibility criterion (issue 13; seed 001:
// meshless regions suit cutting): a cut through a bar separates it cleanly (no stiffness, shape
// function or mass couples the two sides, and the severed piece falls freely while the held
// one stays), a sweep that misses the body changes nothing, a partial cut weakens the body and
// keeps forces the exact energy gradient, the physical field does not jump at a cut, the
// sweep is pulled back to the reference configuration, bad sweeps are ignored, and the hybrid
// cuts as the EFG does.
#include <gtest/gtest.h>

#include <Eigen/Core>
#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "common/mesh_gen/structured_meshes.h"
#include "server/models/meshless/efg_hybrid_model.h"
#include "server/models/meshless/efg_model.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

// A bar 8 cm along x (nodes every 1 cm), 2 × 2 cm across.
mesh::TetMesh Bar() {
  return mesh_gen::BoxGridTets(9, 3, 3, Vector3d::Zero(), Vector3d(0.08, 0.02, 0.02));
}

constexpr double kCutX = 0.0451;  // [m] between the node layers x = 0.04 and 0.05

// A blade across the whole section at x = `x`, swept through z from below to above; `depth` in
// (0, 1] the fraction of the height it reaches from the bottom (1: the whole section).
SweptQuad SweepAt(double x, double depth = 1.0, const Vector3d& offset = Vector3d::Zero()) {
  const double z_top = -0.005 + depth * 0.03;
  return {Vector3d(x, -0.01, -0.005) + offset, Vector3d(x, 0.03, -0.005) + offset,
          Vector3d(x, -0.01, z_top) + offset, Vector3d(x, 0.03, z_top) + offset};
}

std::vector<int32_t> NodesWhere(const mesh::Points& x, bool (*keep)(const Vector3d&)) {
  std::vector<int32_t> nodes;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (keep(x.col(i))) nodes.push_back(static_cast<int32_t>(i));
  }
  return nodes;
}

bool LeftEnd(const Vector3d& x) { return x.x() < 1e-9; }
bool RightEnd(const Vector3d& x) { return x.x() > 0.08 - 1e-9; }
bool LeftOfCut(const Vector3d& x) { return x.x() < kCutX; }

// A stiffer tissue than the liver's 5 kPa (the bar's first bending mode at ~70 rad/s instead of
// 7, so the uncut bar sags mm while the severed piece falls cm in 0.1 s), without mass damping:
// free fall is then exactly g (β K does not act on a rigid motion).
EfgParameters StiffBar() {
  EfgParameters p;
  p.youngs_modulus = 5e5;  // [Pa]
  p.rayleigh_mass = 0.0;
  return p;
}

TEST(EfgCut, ACutThroughTheBarSeparatesItCleanly) {
  const auto model = EfgModel::FromTetMesh(Bar(), StiffBar());
  const auto state = model->MakeState();
  const mesh::Points& rest = model->rest_positions();
  const int32_t hidden = model->Cut(SweepAt(kCutX), state.get());
  EXPECT_GT(hidden, 0);
  const EfgCutValues* cut = model->CutOf(*state);
  ASSERT_NE(cut, nullptr);
  EXPECT_EQ(cut->hidden_pairs, hidden);
  EXPECT_EQ(cut->triangles.size(), 6u);
  // No coupling left across the cut: Φ's entries exactly, K's and M̂'s blocks to round-off of
  // the subtraction (their old contributions left).
  const int32_t n = model->num_nodes();
  // Probe K by the energy of fields living on one side: E(a + b) = E(a) + E(b) when no block
  // couples the sides.
  mesh::Points left = mesh::Points::Zero(3, n), right = mesh::Points::Zero(3, n);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> draw(-1e-3, 1e-3);
  for (int32_t i = 0; i < n; ++i) {
    mesh::Points& side = LeftOfCut(rest.col(i)) ? left : right;
    side.col(i) = Vector3d(draw(rng), draw(rng), draw(rng));
  }
  const double e_left = model->ElasticEnergyOfParameters(left, cut);
  const double e_right = model->ElasticEnergyOfParameters(right, cut);
  const double e_both = model->ElasticEnergyOfParameters(left + right, cut);
  EXPECT_GT(e_left, 0.0);
  EXPECT_GT(e_right, 0.0);
  EXPECT_NEAR(e_both, e_left + e_right, 1e-10 * (e_left + e_right));
  // Uncut, the sides are coupled: the same probe sees it.
  const double uncut_both = model->ElasticEnergyOfParameters(left + right);
  const double uncut_sum =
      model->ElasticEnergyOfParameters(left) + model->ElasticEnergyOfParameters(right);
  EXPECT_GT(std::abs(uncut_both - uncut_sum), 1e-3 * uncut_sum);
  // Φ: no node point sees a node on the other side.
  mesh::Points u;
  model->NodeDisplacements(right, &u, cut);
  for (int32_t i = 0; i < n; ++i) {
    if (LeftOfCut(rest.col(i))) {
      EXPECT_EQ(u.col(i).norm(), 0.0) << "node " << i;
    }
  }
  EXPECT_EQ(cut->dropped_points, 0);
  EXPECT_EQ(cut->detached_rows, 0);
}

TEST(EfgCut, TheSeveredPieceFallsFreelyAndTheHeldOneStays) {
  const auto model = EfgModel::FromTetMesh(Bar(), StiffBar());
  const auto state = model->MakeState();
  const mesh::Points& rest = model->rest_positions();
  const std::vector<int32_t> held = NodesWhere(rest, LeftEnd);
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = held;
  // Uncut for reference, then the same with the cut.
  const auto uncut = model->MakeState();
  ASSERT_GT(model->Cut(SweepAt(kCutX), state.get()), 0);
  constexpr int kSteps = 100;
  for (int k = 0; k < kSteps; ++k) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk) << "step " << k;
    ASSERT_EQ(model->Step(inputs, uncut.get()), StepStatus::kOk);
  }
  const double t = kSteps * inputs.dt;
  // Implicit Euler's free fall after n steps: Σ_k dt (k dt g) = g dt² n (n + 1) / 2.
  const double fall = 9.81 * inputs.dt * inputs.dt * kSteps * (kSteps + 1) / 2.0;
  double right_z = 0.0, left_max = 0.0, uncut_right = 0.0;
  int right_count = 0;
  for (Eigen::Index i = 0; i < rest.cols(); ++i) {
    const double dz = state->positions(2, i) - rest(2, i);
    if (LeftOfCut(rest.col(i))) {
      left_max = std::max(left_max, (state->positions.col(i) - uncut->positions.col(i)).norm());
    } else {
      right_z += dz;
      ++right_count;
      uncut_right = std::min(uncut_right, uncut->positions(2, i) - rest(2, i));
    }
  }
  right_z /= right_count;
  EXPECT_NEAR(right_z, -fall, 0.02 * fall) << "t = " << t << " s";
  // Uncut, the bar's end sags by far less than it falls when severed.
  EXPECT_GT(uncut_right, -0.2 * fall);
  // The held piece moves as a shorter cantilever: not far from the uncut bar's left half.
  EXPECT_LT(left_max, 0.2 * fall);
}

TEST(EfgCut, ASweepMissingTheBodyChangesNothing) {
  const auto model = EfgModel::FromTetMesh(Bar(), EfgParameters{});
  const auto state = model->MakeState();
  EXPECT_EQ(model->Cut(SweepAt(0.2), state.get()), 0);  // 12 cm beyond the bar's end
  const SweptQuad still{Vector3d(0.04, 0.0, 0.0), Vector3d(0.04, 0.02, 0.0),
                        Vector3d(0.04, 0.0, 0.0), Vector3d(0.04, 0.02, 0.0)};
  EXPECT_EQ(model->Cut(still, state.get()), 0);  // a blade that did not move
  const EfgCutValues* cut = model->CutOf(*state);
  ASSERT_NE(cut, nullptr);
  EXPECT_EQ(cut->version, 0);
  EXPECT_EQ(cut->hidden_pairs, 0);
  EXPECT_TRUE(cut->triangles.empty());  // a sweep that hid nothing is not kept
  // The cut state's values equal the model's: steps equal an uncut state's exactly.
  const auto plain = model->MakeState();
  const std::vector<int32_t> held = NodesWhere(model->rest_positions(), LeftEnd);
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = held;
  for (int k = 0; k < 5; ++k) {
    model->Step(inputs, state.get());
    model->Step(inputs, plain.get());
  }
  EXPECT_EQ(state->positions, plain->positions);
}

TEST(EfgCut, NonFiniteSweepsAreIgnored) {
  const auto model = EfgModel::FromTetMesh(Bar(), EfgParameters{});
  const auto state = model->MakeState();
  SweptQuad bad = SweepAt(kCutX);
  bad.q1.x() = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(model->Cut(bad, state.get()), 0);
  bad = SweepAt(kCutX);
  bad.p0.y() = std::numeric_limits<double>::infinity();
  EXPECT_EQ(model->Cut(bad, state.get()), 0);
  EXPECT_EQ(model->CutOf(*state), nullptr);
  EXPECT_EQ(state->positions, model->rest_positions());
}

// Static tip displacement along +x (opening the cut) under a pull at the right end.
double PullOpening(const EfgModel& model, TissueState* state) {
  const mesh::Points& rest = model.rest_positions();
  const std::vector<int32_t> held = NodesWhere(rest, LeftEnd);
  const std::vector<int32_t> pulled = NodesWhere(rest, RightEnd);
  mesh::Points forces = mesh::Points::Zero(3, rest.cols());
  for (const int32_t i : pulled) forces(0, i) = 0.05 / double(pulled.size());  // [N]
  EfgStaticLoads loads;
  loads.external_forces = &forces;
  loads.fixed_nodes = held;
  model.SolveStatic(loads, state);
  double sum = 0.0;
  for (const int32_t i : pulled) sum += state->positions(0, i) - rest(0, i);
  return sum / double(pulled.size());
}

TEST(EfgCut, APartialCutWeakensTheBarAndKeepsForcesTheEnergyGradient) {
  const auto model = EfgModel::FromTetMesh(Bar(), EfgParameters{});
  const auto uncut = model->MakeState();
  const auto state = model->MakeState();
  ASSERT_GT(model->Cut(SweepAt(kCutX, 0.6), state.get()), 0);  // 60 % of the height
  const double before = PullOpening(*model, uncut.get());
  const double after = PullOpening(*model, state.get());
  EXPECT_GT(after, 1.2 * before);  // the ligament carries the pull: the bar is softer
  EXPECT_TRUE(std::isfinite(after));
  // Forces = -∂E/∂x at a perturbed state of the cut body.
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> offset(-1e-3, 1e-3);
  for (Eigen::Index k = 0; k < state->positions.size(); ++k) {
    state->positions.data()[k] += offset(rng);
  }
  mesh::Points forces;
  model->InternalForces(*state, &forces);
  const double h = 1e-7;
  double worst = 0.0, scale = forces.cwiseAbs().maxCoeff();
  for (Eigen::Index k = 0; k < forces.size(); k += 7) {
    const double x0 = state->positions.data()[k];
    state->positions.data()[k] = x0 + h;
    const double plus = model->Energy(*state, Vector3d::Zero()).elastic;
    state->positions.data()[k] = x0 - h;
    const double minus = model->Energy(*state, Vector3d::Zero()).elastic;
    state->positions.data()[k] = x0;
    worst = std::max(worst, std::abs(forces.data()[k] + (plus - minus) / (2 * h)));
  }
  EXPECT_LT(worst, 1e-6 * scale);
}

TEST(EfgCut, TheBodyDoesNotJumpWhenCut) {
  const auto model = EfgModel::FromTetMesh(Bar(), EfgParameters{});
  const auto state = model->MakeState();
  PullOpening(*model, state.get());  // a deformed state
  const mesh::Points before = state->positions;
  ASSERT_GT(model->Cut(SweepAt(kCutX, 0.5), state.get()), 0);
  EXPECT_LT((state->positions - before).cwiseAbs().maxCoeff(), 1e-12);
  // The parameters follow: Φ_cut û reproduces the positions.
  mesh::Points u;
  model->NodeDisplacements(model->NodalParameters(*state), &u, model->CutOf(*state));
  EXPECT_LT((model->rest_positions() + u - before).cwiseAbs().maxCoeff(), 1e-12);
}

TEST(EfgCut, TheSweepIsPulledBackToTheReferenceConfiguration) {
  const auto model = EfgModel::FromTetMesh(Bar(), EfgParameters{});
  const Vector3d moved(0.013, -0.004, 0.021);  // [m] a rigid translation of the body
  const auto at_rest = model->MakeState();
  const auto translated = model->MakeState();
  translated->positions.colwise() += moved;
  const SweptQuad swept = model->PullBack(SweepAt(kCutX, 0.7, moved), translated->positions);
  EXPECT_LT((swept.p0 - SweepAt(kCutX, 0.7).p0).norm(), 1e-12);
  EXPECT_LT((swept.q1 - SweepAt(kCutX, 0.7).q1).norm(), 1e-12);
  EXPECT_EQ(model->Cut(SweepAt(kCutX, 0.7, moved), translated.get()),
            model->Cut(SweepAt(kCutX, 0.7), at_rest.get()));
}

TEST(EfgCut, AnIncisionInManySmallSweepsEqualsOneSweep) {
  // A blade moving 1 mm per tick (the session's sweeps) hides the same pairs as one sweep.
  const auto model = EfgModel::FromTetMesh(Bar(), EfgParameters{});
  const auto once = model->MakeState();
  const auto ticks = model->MakeState();
  const int32_t total = model->Cut(SweepAt(kCutX), once.get());
  int64_t sum = 0;
  const SweptQuad whole = SweepAt(kCutX);
  constexpr int kTicks = 30;
  for (int k = 0; k < kTicks; ++k) {
    const double a = double(k) / kTicks, b = double(k + 1) / kTicks;
    const SweptQuad tick{whole.p0 + a * (whole.p1 - whole.p0), whole.q0 + a * (whole.q1 - whole.q0),
                         whole.p0 + b * (whole.p1 - whole.p0),
                         whole.q0 + b * (whole.q1 - whole.q0)};
    sum += model->Cut(tick, ticks.get());
  }
  EXPECT_EQ(sum, total);
  const EfgCutValues& a = *model->CutOf(*once);
  const EfgCutValues& b = *model->CutOf(*ticks);
  double worst = 0.0, scale = 0.0;
  for (size_t k = 0; k < a.k_blocks.size(); ++k) {
    worst = std::max(worst, std::abs(a.k_blocks[k] - b.k_blocks[k]));
    scale = std::max(scale, std::abs(a.k_blocks[k]));
  }
  EXPECT_LT(worst, 1e-10 * scale);
}

TEST(EfgHybridCut, TheHybridCutsAsTheEfg) {
  // The hybrid's region covers the cut; both models cut alike and, held at the left end under
  // gravity, the severed piece falls in both.
  EfgHybridParameters parameters;
  parameters.efg = StiffBar();
  parameters.region_radius = 0.03;
  parameters.region_centre = Vector3d(0.06, 0.01, 0.01);
  parameters.follow_tool = false;
  const auto hybrid = EfgHybridModel::FromTetMesh(Bar(), parameters);
  const auto efg = EfgModel::FromTetMesh(Bar(), parameters.efg);
  const auto hs = hybrid->MakeState();
  const auto es = efg->MakeState();
  const mesh::Points& rest = efg->rest_positions();
  const std::vector<int32_t> held = NodesWhere(rest, LeftEnd);
  StepInputs inputs;
  inputs.dt = 1e-3;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.fixed_nodes = held;
  ASSERT_EQ(hybrid->Step(inputs, hs.get()), StepStatus::kOk);  // partitions first
  ASSERT_EQ(efg->Step(inputs, es.get()), StepStatus::kOk);
  const int32_t h_hidden = hybrid->Cut(SweepAt(kCutX), hs.get());
  const int32_t e_hidden = efg->Cut(SweepAt(kCutX), es.get());
  EXPECT_GT(h_hidden, 0);
  EXPECT_EQ(h_hidden, e_hidden);
  ASSERT_NE(hybrid->CutOf(*hs), nullptr);
  constexpr int kSteps = 100;
  for (int k = 0; k < kSteps; ++k) {
    ASSERT_EQ(hybrid->Step(inputs, hs.get()), StepStatus::kOk) << "step " << k;
    ASSERT_EQ(efg->Step(inputs, es.get()), StepStatus::kOk);
  }
  const double fall = 9.81 * inputs.dt * inputs.dt * (kSteps + 1) * (kSteps + 2) / 2.0;
  double hybrid_z = 0.0, efg_z = 0.0;
  int count = 0;
  for (Eigen::Index i = 0; i < rest.cols(); ++i) {
    if (LeftOfCut(rest.col(i))) continue;
    hybrid_z += hs->positions(2, i) - rest(2, i);
    efg_z += es->positions(2, i) - rest(2, i);
    ++count;
  }
  hybrid_z /= count;
  efg_z /= count;
  EXPECT_NEAR(efg_z, -fall, 0.03 * fall);
  EXPECT_NEAR(hybrid_z, efg_z, 0.03 * fall);
}

}  // namespace
}  // namespace somasim::models::meshless
