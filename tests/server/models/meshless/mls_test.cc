// MLS shape functions (SPEC §4.6): partition of unity and linear reproduction at random points,
// gradients equal to finite differences, the gradient of a reproduced linear field is exact, the
// weight is the cubic spline, and bad nodes or points are refused with their names.
#include "server/models/meshless/mls.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>

#include "common/mesh_gen/structured_meshes.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

// A 6 × 5 × 7 grid over 5 × 4 × 6 cm with every node moved randomly by up to 20 % of the spacing
// (MLS must not rely on a regular layout).
mesh::Points IrregularNodes() {
  mesh::Points x =
      mesh_gen::BoxGridTets(6, 5, 7, Vector3d::Zero(), Vector3d(0.05, 0.04, 0.06)).vertices;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> offset(-0.002, 0.002);
  for (Eigen::Index k = 0; k < x.size(); ++k) x.data()[k] += offset(rng);
  return x;
}

std::vector<Vector3d> RandomPoints(int count, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> ux(0.003, 0.047), uy(0.003, 0.037), uz(0.003, 0.057);
  std::vector<Vector3d> points;
  points.reserve(static_cast<size_t>(count));
  for (int k = 0; k < count; ++k) {
    // Drawn in sequence: the order of evaluating function arguments differs between compilers.
    const double x = ux(rng);
    const double y = uy(rng);
    const double z = uz(rng);
    points.emplace_back(x, y, z);
  }
  return points;
}

TEST(MlsShapeFunctions, PartitionOfUnityAndLinearReproduction) {
  const mesh::Points nodes = IrregularNodes();
  const MlsShapeFunctions mls(nodes, MlsParameters{});
  MlsEvaluation eval;
  size_t most = 0, fewest = 1000;
  for (const Vector3d& x : RandomPoints(200, 11)) {
    mls.Evaluate(x, false, &eval);
    double sum = 0.0;
    Vector3d reproduced = Vector3d::Zero();
    for (size_t a = 0; a < eval.nodes.size(); ++a) {
      sum += eval.values[a];
      reproduced += eval.values[a] * nodes.col(eval.nodes[a]);
    }
    EXPECT_NEAR(sum, 1.0, 1e-10);
    EXPECT_LT((reproduced - x).norm(), 1e-10 * 0.06) << x.transpose();
    most = std::max(most, eval.nodes.size());
    fewest = std::min(fewest, eval.nodes.size());
  }
  std::printf("MLS supports per point: %zu .. %zu (scale 2, k = 4)\n", fewest, most);
}

TEST(MlsShapeFunctions, GradientsEqualCentralDifferences) {
  const mesh::Points nodes = IrregularNodes();
  const MlsShapeFunctions mls(nodes, MlsParameters{});
  MlsEvaluation eval, plus, minus;
  const double h = 1e-7;  // [m]: the spacing is 1 cm
  double worst = 0.0;
  for (const Vector3d& x : RandomPoints(40, 12)) {
    mls.Evaluate(x, true, &eval);
    for (int k = 0; k < 3; ++k) {
      Vector3d step = Vector3d::Zero();
      step[k] = h;
      mls.Evaluate(x + step, false, &plus);
      mls.Evaluate(x - step, false, &minus);
      // At ±h a node can enter or leave the support only where its weight is 0 with zero slope
      // (r = 1), so a node absent from a support set contributes the value 0 there.
      const auto value_of = [](const MlsEvaluation& e, int node) {
        const auto it = std::find(e.nodes.begin(), e.nodes.end(), node);
        return it == e.nodes.end() ? 0.0 : e.values[static_cast<size_t>(it - e.nodes.begin())];
      };
      const double scale = eval.gradients.cwiseAbs().maxCoeff();
      for (size_t a = 0; a < eval.nodes.size(); ++a) {
        const double fd =
            (value_of(plus, eval.nodes[a]) - value_of(minus, eval.nodes[a])) / (2.0 * h);
        const double analytic = eval.gradients(k, static_cast<Eigen::Index>(a));
        worst = std::max(worst, std::abs(fd - analytic) / scale);
        EXPECT_NEAR(analytic, fd, 1e-6 * scale) << "node " << eval.nodes[a] << " axis " << k;
      }
      for (const MlsEvaluation* e : {&plus, &minus}) {
        for (size_t b = 0; b < e->nodes.size(); ++b) {
          if (std::find(eval.nodes.begin(), eval.nodes.end(), e->nodes[b]) == eval.nodes.end()) {
            EXPECT_LT(std::abs(e->values[b]), 1e-12) << "node " << e->nodes[b] << " entered";
          }
        }
      }
    }
  }
  std::printf("MLS gradient vs central difference: worst relative error %.2e\n", worst);
}

TEST(MlsShapeFunctions, GradientOfReproducedLinearFieldIsExact) {
  const mesh::Points nodes = IrregularNodes();
  const MlsShapeFunctions mls(nodes, MlsParameters{});
  Matrix3d g;
  g << 0.1, -0.3, 0.05, 0.2, 0.02, -0.1, -0.07, 0.4, 0.3;
  const Vector3d c(1e-3, -2e-3, 5e-4);
  MlsEvaluation eval;
  for (const Vector3d& x : RandomPoints(100, 13)) {
    mls.Evaluate(x, true, &eval);
    Matrix3d grad = Matrix3d::Zero();
    Vector3d sum_gradients = Vector3d::Zero();
    for (size_t a = 0; a < eval.nodes.size(); ++a) {
      const Vector3d u = c + g * nodes.col(eval.nodes[a]);
      grad += u * eval.gradients.col(static_cast<Eigen::Index>(a)).transpose();
      sum_gradients += eval.gradients.col(static_cast<Eigen::Index>(a));
    }
    EXPECT_LT((grad - g).cwiseAbs().maxCoeff(), 1e-10) << x.transpose();
    EXPECT_LT(sum_gradients.norm(), 1e-8) << x.transpose();  // [1/m]: ∇Σφ = 0
  }
}

TEST(MlsShapeFunctions, WeightIsTheCubicSpline) {
  EXPECT_DOUBLE_EQ(CubicSplineWeight(0.0), 2.0 / 3.0);
  EXPECT_DOUBLE_EQ(CubicSplineWeight(1.0), 0.0);
  EXPECT_DOUBLE_EQ(CubicSplineWeight(1.5), 0.0);
  EXPECT_NEAR(CubicSplineWeight(0.5 - 1e-12), CubicSplineWeight(0.5 + 1e-12), 1e-10);
  for (double r = 0.01; r < 1.0; r += 0.0731) {
    const double h = 1e-6;
    const double fd = (CubicSplineWeight(r + h) - CubicSplineWeight(r - h)) / (2.0 * h);
    EXPECT_NEAR(CubicSplineWeightDerivative(r), fd, 1e-8) << r;
  }
  EXPECT_DOUBLE_EQ(CubicSplineWeightDerivative(0.0), 0.0);
  EXPECT_NEAR(CubicSplineWeightDerivative(1.0 - 1e-9), 0.0, 1e-12);
}

TEST(MlsShapeFunctions, SupportRadiusIsScaleTimesKthNeighbourDistance) {
  // A regular grid of spacing h = 1 cm: an inside node has 6 neighbours at h, so d_4 = h; a
  // corner has 3 at h, then 3 at √2 h, so d_4 = √2 h.
  const mesh::Points nodes =
      mesh_gen::BoxGridTets(5, 5, 5, Vector3d::Zero(), Vector3d(0.04, 0.04, 0.04)).vertices;
  const MlsShapeFunctions mls(nodes, MlsParameters{});
  const int32_t corner = 0, centre = 2 + 5 * (2 + 5 * 2);
  EXPECT_NEAR(mls.support_radii()[corner], 2.0 * std::sqrt(2.0) * 0.01, 1e-12);
  EXPECT_NEAR(mls.support_radii()[centre], 2.0 * 0.01, 1e-12);
}

TEST(MlsShapeFunctions, BadInputIsRefusedByName) {
  mesh::Points nodes = IrregularNodes();
  const auto message = [](const auto& make) {
    try {
      make();
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("no exception");
  };
  mesh::Points bad = nodes;
  bad(1, 3) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(message([&] { MlsShapeFunctions m(bad, MlsParameters{}); }).find("node 3"),
            std::string::npos);
  MlsParameters p;
  p.support_scale = 0.5;
  EXPECT_NE(message([&] { MlsShapeFunctions m(nodes, p); }).find("support_scale"),
            std::string::npos);
  p = MlsParameters{};
  p.support_neighbours = 0;
  EXPECT_NE(message([&] { MlsShapeFunctions m(nodes, p); }).find("support_neighbours"),
            std::string::npos);
  // Far outside the nodes: no support covers the point, and the point is named.
  const MlsShapeFunctions mls(nodes, MlsParameters{});
  MlsEvaluation eval;
  const std::string far = message([&] { mls.Evaluate(Vector3d(1.0, 1.0, 1.0), false, &eval); });
  EXPECT_NE(far.find("(1, 1, 1)"), std::string::npos) << far;
  // Coplanar nodes: the moment matrix is singular at every point.
  mesh::Points flat = nodes.leftCols(30);  // the bottom layer of the grid, flattened
  flat.row(2).setZero();
  const MlsShapeFunctions planar(flat, MlsParameters{});
  const std::string singular =
      message([&] { planar.Evaluate(Vector3d(0.02, 0.02, 0.0), false, &eval); });
  EXPECT_NE(singular.find("ill-conditioned"), std::string::npos) << singular;
  EXPECT_NE(singular.find("(0.02, 0.02, 0)"), std::string::npos) << singular;
}

}  // namespace
}  // namespace somasim::models::meshless
