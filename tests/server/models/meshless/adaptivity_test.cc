// Seed 001's adaptivity (eq. 1–9, adaptivity.h) and the adaptive hybrid: the cells' mesh
// intensity is zero for a homogeneous strain, converges to the analytic |∇DSE| / DM for a
// quadratic field, peaks at a point load; the adaptive hybrid refines its region where the
// intensity is high, keeps pure EFG's statics, settles (stops rebuilding) and refuses bad
// thresholds.
#include "server/models/meshless/adaptivity.h"

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <stdexcept>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"
#include "server/models/meshless/efg_hybrid_model.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

constexpr double kLambda = 3000.0, kMu = 1000.0;  // [Pa]

mesh::TetMesh Box() {
  return mesh_gen::BoxGridTets(6, 6, 6, Vector3d::Zero(), Vector3d(0.05, 0.05, 0.05));
}

TEST(CellIntensity, HomogeneousStrainHasNoGradientAndNoIntensity) {
  const mesh::TetMesh mesh = Box();
  const MlsShapeFunctions shape(mesh.vertices, MlsParameters{});
  Matrix3d g;
  g << 0.01, 0.002, -0.003, 0.001, -0.02, 0.004, 0.0, 0.005, 0.015;
  const mesh::Points params = g * mesh.vertices;  // MLS reproduces a linear field exactly
  const CellIntensity cells = ComputeCellIntensity(shape, mesh.tetrahedra, params, kLambda, kMu);
  const Matrix3d strain = 0.5 * (g + g.transpose());
  const Matrix3d stress = kLambda * strain.trace() * Matrix3d::Identity() + 2.0 * kMu * strain;
  const double density = 0.5 * stress.cwiseProduct(strain).sum();
  double worst_density = 0.0, worst_gradient = 0.0;
  for (size_t t = 0; t < cells.gradient.size(); ++t) {
    worst_density = std::max(worst_density, std::abs(cells.energy_density[t] / density - 1.0));
    worst_gradient = std::max(worst_gradient, cells.gradient[t]);
  }
  EXPECT_LT(worst_density, 1e-8);
  // |∇DSE| relative to DSE over the box size: zero up to rounding.
  EXPECT_LT(worst_gradient * 0.05 / density, 1e-6);
}

// u = c (x², 0, 0): ε_xx = 2 c x, DSE = ½ (λ + 2μ) (2 c x)², ∇DSE = (4 (λ + 2μ) c² x, 0, 0).
// With û = u(X) the MLS field (linear basis) is the quadratic up to its approximation error,
// and the indicator's error on interior cells falls under refinement.
double QuadraticGradientError(int nodes_per_side) {
  const mesh::TetMesh mesh = mesh_gen::BoxGridTets(nodes_per_side, nodes_per_side, nodes_per_side,
                                                   Vector3d::Zero(), Vector3d(0.05, 0.05, 0.05));
  const MlsShapeFunctions shape(mesh.vertices, MlsParameters{});
  const double c = 0.5;  // [1/m]
  mesh::Points params = mesh::Points::Zero(3, mesh.vertices.cols());
  for (Eigen::Index i = 0; i < mesh.vertices.cols(); ++i) {
    params(0, i) = c * mesh.vertices(0, i) * mesh.vertices(0, i);
  }
  const CellIntensity cells = ComputeCellIntensity(shape, mesh.tetrahedra, params, kLambda, kMu);
  double worst = 0.0;
  int checked = 0;
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    Vector3d centroid = Vector3d::Zero();
    for (int a = 0; a < 4; ++a) centroid += 0.25 * mesh.vertices.col(mesh.tetrahedra(a, t));
    if ((centroid.array() < 0.015).any() || (centroid.array() > 0.035).any()) continue;
    const double exact = 4.0 * (kLambda + 2.0 * kMu) * c * c * centroid.x();
    worst = std::max(worst, std::abs(cells.gradient[size_t(t)] / exact - 1.0));
    // r_d = GSED / DM, DM = 4 / V (eq. 5–6).
    EXPECT_NEAR(cells.intensity[size_t(t)] * cells.node_density[size_t(t)],
                cells.gradient[size_t(t)], 1e-12 * cells.gradient[size_t(t)]);
    ++checked;
  }
  EXPECT_GT(checked, 20);
  std::printf("quadratic field, %d^3 nodes: %d interior cells, worst |grad DSE| error %.2f %%\n",
              nodes_per_side, checked, 100 * worst);
  return worst;
}

TEST(CellIntensity, QuadraticFieldGradientConvergesToTheAnalyticOne) {
  const double coarse = QuadraticGradientError(6);
  const double fine = QuadraticGradientError(11);
  // First order: the linear fit through four Gauss values of a DSE that is quadratic in x has an
  // O(h) error in its slope, on top of the field's own approximation error.
  EXPECT_LT(fine, 0.7 * coarse);
  EXPECT_LT(fine, 0.05);
}

struct Liver {
  mesh::TetMesh mesh;
  int32_t top = 0;
  std::vector<int32_t> fixed;
};

Liver Liver288() {
  Liver c;
  c.mesh = mesh_gen::GenerateBuiltinOrgan("liver288").volume;
  const mesh::Points& x = c.mesh.vertices;
  const double lo = x.row(2).minCoeff(), hi = x.row(2).maxCoeff();
  Eigen::Index top = 0;
  x.row(2).maxCoeff(&top);
  c.top = static_cast<int32_t>(top);
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(2, i) <= lo + 0.15 * (hi - lo)) c.fixed.push_back(static_cast<int32_t>(i));
  }
  return c;
}

TEST(CellIntensity, APointLoadPutsTheHighestIntensityAtTheLoadedNode) {
  const Liver liver = Liver288();
  const auto model = EfgModel::FromTetMesh(liver.mesh, EfgParameters{});
  auto state = model->MakeState();
  mesh::Points forces = mesh::Points::Zero(3, model->num_nodes());
  forces(2, liver.top) = 5.7;
  EfgStaticLoads loads;
  loads.external_forces = &forces;
  loads.fixed_nodes = liver.fixed;
  model->SolveStatic(loads, state.get());
  const CellIntensity cells = ComputeCellIntensity(model->shape_functions(), liver.mesh.tetrahedra,
                                                   model->NodalParameters(*state), kLambda, kMu);
  const auto worst = std::max_element(cells.intensity.begin(), cells.intensity.end());
  const auto cell = static_cast<Eigen::Index>(worst - cells.intensity.begin());
  bool touches = false;
  for (int a = 0; a < 4; ++a) touches |= liver.mesh.tetrahedra(a, cell) == liver.top;
  EXPECT_TRUE(touches) << "cell " << cell;
  EXPECT_DOUBLE_EQ(cells.r_max, *worst);
  EXPECT_DOUBLE_EQ(*std::max_element(cells.normalised.begin(), cells.normalised.end()), 1.0);
  EXPECT_DOUBLE_EQ(*std::min_element(cells.normalised.begin(), cells.normalised.end()), 0.0);
}

TEST(CellIntensity, RefusesMismatchedSizesIndicesAndNaN) {
  const mesh::TetMesh mesh = Box();
  const MlsShapeFunctions shape(mesh.vertices, MlsParameters{});
  const mesh::Points good = mesh::Points::Zero(3, mesh.vertices.cols());
  EXPECT_THROW(ComputeCellIntensity(shape, mesh.tetrahedra, mesh::Points::Zero(3, 5), 1, 1),
               std::invalid_argument);
  mesh::Points nan = good;
  nan(1, 3) = std::nan("");
  EXPECT_THROW(ComputeCellIntensity(shape, mesh.tetrahedra, nan, 1, 1), std::invalid_argument);
  mesh::Tetrahedra bad = mesh.tetrahedra;
  bad(2, 7) = static_cast<int32_t>(mesh.vertices.cols());
  EXPECT_THROW(ComputeCellIntensity(shape, bad, good, 1, 1), std::invalid_argument);
  mesh::Tetrahedra flat = mesh.tetrahedra;
  flat(3, 0) = flat(0, 0);  // a repeated corner: zero volume
  EXPECT_THROW(CellIntensityEvaluator(shape, flat), std::invalid_argument);
  // One evaluator serves many fields and refuses a wrong one too.
  const CellIntensityEvaluator evaluator(shape, mesh.tetrahedra);
  EXPECT_THROW(evaluator.Compute(mesh::Points::Zero(3, 5), 1, 1), std::invalid_argument);
  EXPECT_NO_THROW(evaluator.Compute(good, 1, 1));
}

// Seed 001's adaptive hybrid under its 5.7 N pull: the region grows where the intensity is
// high (around the load and along the held underside's edge), stops changing once the field
// settles, and the statics stay pure EFG's.
TEST(AdaptiveHybrid, RefinesWhereTheIntensityIsHighSettlesAndKeepsEfgStatics) {
  const Liver liver = Liver288();
  mesh::Points forces = mesh::Points::Zero(3, liver.mesh.vertices.cols());
  forces(2, liver.top) = 5.7;
  EfgHybridParameters p;
  p.region_radius = 0.035;
  p.adaptive = true;
  p.adapt_interval = 50;
  p.efg.rayleigh_mass = 20.0;
  const auto model = EfgHybridModel::FromTetMesh(liver.mesh, p);
  auto state = model->MakeState();
  StepInputs in;
  in.dt = 0.01;
  in.external_forces = &forces;
  in.fixed_nodes = liver.fixed;
  ASSERT_EQ(model->Step(in, state.get()), StepStatus::kOk);
  const int32_t ball = model->RegionNodes(*state);
  for (int k = 0; k < 400; ++k) ASSERT_EQ(model->Step(in, state.get()), StepStatus::kOk);
  const int32_t adapted = model->RegionNodes(*state);
  const int64_t partitions = model->Partitions(*state);
  for (int k = 0; k < 200; ++k) ASSERT_EQ(model->Step(in, state.get()), StepStatus::kOk);
  std::printf("adaptive hybrid: region %d -> %d nodes, %lld partitions, %lld adaptations\n", ball,
              adapted, static_cast<long long>(partitions),
              static_cast<long long>(model->Adaptations(*state)));
  EXPECT_GT(adapted, ball);
  EXPECT_EQ(model->Partitions(*state), partitions) << "the region kept changing";
  EXPECT_GE(model->Adaptations(*state), 12);
  // Statics: pure EFG's.
  const auto efg = EfgModel::FromTetMesh(liver.mesh, p.efg);
  auto efg_state = efg->MakeState();
  EfgStaticLoads loads;
  loads.external_forces = &forces;
  loads.fixed_nodes = liver.fixed;
  efg->SolveStatic(loads, efg_state.get());
  EXPECT_LT((state->positions - efg_state->positions).cwiseAbs().maxCoeff(), 1e-6);  // [m]
}

TEST(AdaptiveHybrid, BadThresholdsAreRefusedByName) {
  const mesh::TetMesh mesh = Box();
  const auto refused = [&](const EfgHybridParameters& p, const char* name) {
    try {
      EfgHybridModel::FromTetMesh(mesh, p);
      ADD_FAILURE() << name << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(name), std::string::npos) << e.what();
    }
  };
  EfgHybridParameters p;
  p.adapt_interval = 0;
  refused(p, "adapt_interval");
  p = {};
  p.refine_threshold = 0.0;
  refused(p, "refine_threshold");
  p = {};
  p.refine_threshold = 1.5;
  refused(p, "refine_threshold");
  p = {};
  p.coarsen_threshold = 0.5;  // above refine_threshold
  refused(p, "coarsen_threshold");
  p = {};
  p.coarsen_threshold = std::nan("");
  refused(p, "coarsen_threshold");
}

}  // namespace
}  // namespace somasim::models::meshless
