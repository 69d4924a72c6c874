// EfgModel's construction (efg_model.h): the MLS shape functions, Φ, the Gauss points, the
// stiffness and mass blocks on their patterns, the penalty, the scalar pattern and Φ's LU; and
// the parameter checks and Gauss rules the EFG models share (efg_shared.h).
#include <Eigen/LU>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <algorithm>
#include <array>
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/checks/finite.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/meshless/efg_shared.h"
#include "server/models/meshless/efg_system.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using Eigen::Vector4d;

}  // namespace

void CheckEfgParameters(const EfgParameters& p, const std::string& prefix) {
  const auto fail = [&prefix](const std::string& what) {
    throw std::invalid_argument(prefix + what);
  };
  const auto finite_positive = [&fail](double value, const char* what) {
    if (!checks::FinitePositive(value)) fail(std::string(what) + " must be a finite value > 0");
  };
  const auto finite_non_negative = [&fail](double value, const char* what) {
    if (!checks::FiniteNonNegative(value)) fail(std::string(what) + " must be a finite value >= 0");
  };
  finite_positive(p.youngs_modulus, "youngs_modulus [Pa]");
  if (!(p.poisson_ratio > -1.0 && p.poisson_ratio < 0.5))
    fail("poisson_ratio must lie in (-1, 0.5)");
  finite_positive(p.density, "density [kg/m^3]");
  finite_non_negative(p.rayleigh_mass, "rayleigh_mass [1/s]");
  finite_non_negative(p.rayleigh_stiffness, "rayleigh_stiffness [s]");
  if (!(p.min_support_edge_factor >= 1.0) || !std::isfinite(p.min_support_edge_factor)) {
    fail("min_support_edge_factor must be finite and >= 1");
  }
  if (p.gauss_points != 4 && p.gauss_points != 14) fail("gauss_points must be 4 or 14");
  finite_positive(p.penalty_factor, "penalty_factor");
  finite_positive(p.speed_limit, "speed_limit [m/s]");
  if (!(p.max_low_rank_nodes >= 0 && p.max_low_rank_nodes <= EfgParameters::kMaxLowRankNodes)) {
    fail("max_low_rank_nodes must lie in 0.." + std::to_string(EfgParameters::kMaxLowRankNodes));
  }
}

namespace {

void AddOrbit(TetRule* rule, double weight, double a, double b, bool two_two) {
  if (!two_two) {  // the 4 permutations of (a, a, a, b)
    for (int k = 0; k < 4; ++k) {
      Vector4d p = Vector4d::Constant(a);
      p[k] = b;
      rule->points.push_back(p);
      rule->weights.push_back(weight);
    }
    return;
  }
  // the 6 permutations of (a, a, b, b)
  constexpr std::array<std::array<int, 2>, 6> kPairs = {
      {{0, 1}, {0, 2}, {0, 3}, {1, 2}, {1, 3}, {2, 3}}};
  for (const auto& pair : kPairs) {
    Vector4d p = Vector4d::Constant(b);
    p[pair[0]] = a;
    p[pair[1]] = a;
    rule->points.push_back(p);
    rule->weights.push_back(weight);
  }
}

}  // namespace

// 4 points: exact for polynomials of degree 2. 14 points: degree 5, all weights positive
// (Walkington's rule; checked: every monomial of degree <= 5 on the unit tetrahedron to 2e-15).
TetRule MakeTetRule(int points) {
  TetRule rule;
  if (points == 4) {
    AddOrbit(&rule, 0.25, 0.1381966011250105, 0.5854101966249685, false);
  } else {
    AddOrbit(&rule, 0.0734930431163619, 0.0927352503108912, 1.0 - 3.0 * 0.0927352503108912, false);
    AddOrbit(&rule, 0.1126879257180162, 0.3108859192633006, 1.0 - 3.0 * 0.3108859192633006, false);
    AddOrbit(&rule, 0.0425460207770812, 0.0455037041256496, 0.5 - 0.0455037041256496, true);
  }
  return rule;
}

std::unique_ptr<EfgModel> EfgModel::FromTetMesh(const mesh::TetMesh& mesh,
                                                const EfgParameters& parameters) {
  CheckEfgParameters(parameters, "efg: ");
  LumpedTetMesh lumped = CheckAndLumpTetMesh(mesh, parameters.density, "efg: ");
  std::unique_ptr<EfgModel> model(new EfgModel());
  model->system_ = NewEfgSystem(mesh, std::move(lumped.mass), parameters);
  model->lambda_ = LameLambda(parameters.youngs_modulus, parameters.poisson_ratio);
  model->mu_ = LameMu(parameters.youngs_modulus, parameters.poisson_ratio);
  model->set_speed_limit(parameters.speed_limit);
  model->max_low_rank_nodes_ = parameters.max_low_rank_nodes;
  model->BuildShapeFunctions(mesh, parameters);
  model->BuildGaussPointsAndPattern(mesh, lumped.volume, parameters.gauss_points);
  model->BuildStiffness();
  model->system_->Finish(parameters.penalty_factor, "efg: ");
  return model;
}

void EfgModel::BuildShapeFunctions(const mesh::TetMesh& mesh, const EfgParameters& parameters) {
  // Every node's support covers min_support_edge_factor × its longest incident tet edge.
  const int32_t n = num_nodes();
  std::vector<double> longest(static_cast<size_t>(n), 0.0);
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    const auto x = [&](int a) { return mesh.vertices.col(mesh.tetrahedra(a, t)); };
    for (int a = 0; a < 4; ++a) {
      const int32_t i = mesh.tetrahedra(a, t);
      for (int b = 0; b < 4; ++b) {
        longest[size_t(i)] = std::max(longest[size_t(i)], (x(a) - x(b)).norm());
      }
    }
  }
  for (double& l : longest) l *= parameters.min_support_edge_factor;
  shape_ = std::make_unique<MlsShapeFunctions>(mesh.vertices, parameters.mls, longest);

  // Φ by rows: φ_J(X_I).
  EfgSystem& system = *system_;
  MlsEvaluation eval;
  system.row_start.assign(size_t(n) + 1, 0);
  for (int32_t i = 0; i < n; ++i) {
    shape_->Evaluate(mesh.vertices.col(i), false, &eval);
    system.row_col.insert(system.row_col.end(), eval.nodes.begin(), eval.nodes.end());
    system.row_value.insert(system.row_value.end(), eval.values.begin(), eval.values.end());
    system.row_start[size_t(i) + 1] = static_cast<int32_t>(system.row_col.size());
  }
}

void EfgModel::BuildGaussPointsAndPattern(const mesh::TetMesh& mesh,
                                          const std::vector<double>& volume, int gauss_points) {
  const int32_t n = num_nodes();
  const auto num_tets = static_cast<int32_t>(mesh.tetrahedra.cols());
  EfgSystem& system = *system_;
  // Gauss points (tet by tet) and, for the pattern, the nodes covering each one.
  const TetRule rule = MakeTetRule(gauss_points);
  const auto gauss_of_tet = static_cast<int64_t>(rule.points.size());
  num_gauss_ = gauss_of_tet * num_tets;
  const auto gauss_point = [&](int32_t t, size_t g) {
    Vector3d p = Vector3d::Zero();
    for (int a = 0; a < 4; ++a) p += rule.points[g][a] * mesh.vertices.col(mesh.tetrahedra(a, t));
    return p;
  };
  // Points: the Gauss points, then the node points (Φ's rows: M̂ = Φᵀ m Φ and P share them).
  std::vector<int64_t> point_start{0};
  std::vector<int32_t> point_nodes;
  MlsEvaluation eval;
  gauss_x_.resize(3, num_gauss_);
  gauss_w_.resize(size_t(num_gauss_));
  for (int32_t t = 0; t < num_tets; ++t) {
    for (size_t g = 0; g < rule.points.size(); ++g) {
      const int64_t index = gauss_of_tet * t + static_cast<int64_t>(g);
      gauss_x_.col(index) = gauss_point(t, g);
      gauss_w_[size_t(index)] = rule.weights[g] * volume[size_t(t)];
      shape_->Evaluate(gauss_x_.col(index), false, &eval);
      point_nodes.insert(point_nodes.end(), eval.nodes.begin(), eval.nodes.end());
      point_start.push_back(static_cast<int64_t>(point_nodes.size()));
    }
  }
  for (int32_t i = 0; i < n; ++i) {
    point_nodes.insert(point_nodes.end(), system.row_col.begin() + system.row_start[size_t(i)],
                       system.row_col.begin() + system.row_start[size_t(i) + 1]);
    point_start.push_back(static_cast<int64_t>(point_nodes.size()));
  }
  LowerBlockPattern(n, point_start, point_nodes, &system.block_start, &system.block_row);
}

void EfgModel::BuildStiffness() {
  system_->SizeBlocks();
  MlsEvaluation eval;
  for (int64_t g = 0; g < num_gauss_; ++g) {
    shape_->Evaluate(gauss_x_.col(g), true, &eval);
    AddGaussPoint(eval, gauss_w_[size_t(g)], 1.0, system_->k_blocks.data());
  }
}

void EfgModel::AddGaussPoint(const MlsEvaluation& eval, double w, double sign,
                             double* k_blocks) const {
  system_->AddGaussPoint(eval, sign * w, lambda_, mu_, k_blocks);
}

}  // namespace somasim::models::meshless
