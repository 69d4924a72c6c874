// EfgModel's construction (efg_model.h): the MLS shape functions, Φ, the Gauss points, the
// stiffness and mass blocks on their patterns, the penalty, the scalar pattern and Φ's LU.
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
#include "server/models/meshless/efg_internal.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/meshless/efg_shared.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using Eigen::Vector4d;

[[noreturn]] void Refuse(const std::string& what) { throw std::invalid_argument("efg: " + what); }

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
  const auto n = static_cast<int32_t>(mesh.vertices.cols());
  const auto num_tets = static_cast<int32_t>(mesh.tetrahedra.cols());
  if (n == 0 || num_tets == 0) Refuse("mesh: empty (no nodes or no tetrahedra)");
  for (int32_t i = 0; i < n; ++i) {
    if (!mesh.vertices.col(i).allFinite()) {
      Refuse("mesh: vertex " + std::to_string(i) + " has a non-finite coordinate");
    }
  }
  std::unique_ptr<EfgModel> model(new EfgModel());
  model->rest_ = mesh.vertices;
  const double e = parameters.youngs_modulus, nu = parameters.poisson_ratio;
  model->lambda_ = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
  model->mu_ = e / (2.0 * (1.0 + nu));
  model->rayleigh_mass_ = parameters.rayleigh_mass;
  model->rayleigh_stiffness_ = parameters.rayleigh_stiffness;
  model->set_speed_limit(parameters.speed_limit);
  model->max_low_rank_nodes_ = parameters.max_low_rank_nodes;

  // Tetrahedra: indices, volumes (positive), lumped masses ρV/4 per corner, longest edges.
  std::vector<double> volume(static_cast<size_t>(num_tets));
  std::vector<double> longest(static_cast<size_t>(n), 0.0);
  model->mass_.assign(size_t(n), 0.0);
  for (int32_t t = 0; t < num_tets; ++t) {
    for (int a = 0; a < 4; ++a) {
      const int32_t i = mesh.tetrahedra(a, t);
      if (i < 0 || i >= n) {
        Refuse("mesh: tetrahedron " + std::to_string(t) + " has node index " + std::to_string(i) +
               " out of range");
      }
    }
    const auto x = [&](int a) { return mesh.vertices.col(mesh.tetrahedra(a, t)); };
    const double v = (x(1) - x(0)).dot((x(2) - x(0)).cross(x(3) - x(0))) / 6.0;
    const double scale =
        std::max({(x(1) - x(0)).norm(), (x(2) - x(0)).norm(), (x(3) - x(0)).norm()});
    if (!(v > 1e-12 * scale * scale * scale)) {
      Refuse("mesh: tetrahedron " + std::to_string(t) + " is flat or inverted (volume " +
             std::to_string(v) + " m^3)");
    }
    volume[size_t(t)] = v;
    for (int a = 0; a < 4; ++a) {
      const int32_t i = mesh.tetrahedra(a, t);
      model->mass_[size_t(i)] += parameters.density * v / 4.0;
      for (int b = 0; b < 4; ++b) {
        longest[size_t(i)] = std::max(longest[size_t(i)], (x(a) - x(b)).norm());
      }
    }
  }
  for (int32_t i = 0; i < n; ++i) {
    if (!(model->mass_[size_t(i)] > 0.0)) {
      Refuse("mesh: node " + std::to_string(i) + " belongs to no tetrahedron");
    }
    longest[size_t(i)] *= parameters.min_support_edge_factor;
  }
  model->shape_ = std::make_unique<MlsShapeFunctions>(mesh.vertices, parameters.mls, longest);

  // Φ by rows: φ_J(X_I).
  MlsEvaluation eval;
  model->phi_start_.assign(size_t(n) + 1, 0);
  for (int32_t i = 0; i < n; ++i) {
    model->shape_->Evaluate(mesh.vertices.col(i), false, &eval);
    model->phi_node_.insert(model->phi_node_.end(), eval.nodes.begin(), eval.nodes.end());
    model->phi_value_.insert(model->phi_value_.end(), eval.values.begin(), eval.values.end());
    model->phi_start_[size_t(i) + 1] = static_cast<int32_t>(model->phi_node_.size());
  }

  // Gauss points (tet by tet) and, for the pattern, the nodes covering each one.
  const TetRule rule = MakeTetRule(parameters.gauss_points);
  const auto gauss_of_tet = static_cast<int64_t>(rule.points.size());
  model->num_gauss_ = gauss_of_tet * num_tets;
  const auto gauss_point = [&](int32_t t, size_t g) {
    Vector3d p = Vector3d::Zero();
    for (int a = 0; a < 4; ++a) p += rule.points[g][a] * mesh.vertices.col(mesh.tetrahedra(a, t));
    return p;
  };
  // Points: the Gauss points, then the node points (Φ's rows: M̂ = Φᵀ m Φ and P share them).
  std::vector<int64_t> point_start{0};
  std::vector<int32_t> point_nodes;
  model->gauss_x_.resize(3, model->num_gauss_);
  model->gauss_w_.resize(size_t(model->num_gauss_));
  for (int32_t t = 0; t < num_tets; ++t) {
    for (size_t g = 0; g < rule.points.size(); ++g) {
      const int64_t index = gauss_of_tet * t + static_cast<int64_t>(g);
      model->gauss_x_.col(index) = gauss_point(t, g);
      model->gauss_w_[size_t(index)] = rule.weights[g] * volume[size_t(t)];
      model->shape_->Evaluate(model->gauss_x_.col(index), false, &eval);
      point_nodes.insert(point_nodes.end(), eval.nodes.begin(), eval.nodes.end());
      point_start.push_back(static_cast<int64_t>(point_nodes.size()));
    }
  }
  for (int32_t i = 0; i < n; ++i) {
    point_nodes.insert(point_nodes.end(), model->phi_node_.begin() + model->phi_start_[size_t(i)],
                       model->phi_node_.begin() + model->phi_start_[size_t(i) + 1]);
    point_start.push_back(static_cast<int64_t>(point_nodes.size()));
  }
  // The lower block pattern: column c holds every node >= c sharing a point with c.
  {
    const size_t num_points = point_start.size() - 1;
    std::vector<int64_t> of_node_start(size_t(n) + 1, 0);
    for (const int32_t j : point_nodes) ++of_node_start[size_t(j) + 1];
    for (size_t j = 1; j <= size_t(n); ++j) of_node_start[j] += of_node_start[j - 1];
    std::vector<int64_t> fill(of_node_start.begin(), of_node_start.end() - 1);
    std::vector<int32_t> points_of_node(point_nodes.size());
    for (size_t p = 0; p < num_points; ++p) {
      for (int64_t k = point_start[p]; k < point_start[p + 1]; ++k) {
        points_of_node[size_t(fill[size_t(point_nodes[size_t(k)])]++)] = static_cast<int32_t>(p);
      }
    }
    std::vector<int32_t> mark(size_t(n), -1), column;
    model->block_start_.assign(size_t(n) + 1, 0);
    for (int32_t c = 0; c < n; ++c) {
      column.clear();
      for (int64_t k = of_node_start[size_t(c)]; k < of_node_start[size_t(c) + 1]; ++k) {
        const auto p = size_t(points_of_node[size_t(k)]);
        for (int64_t q = point_start[p]; q < point_start[p + 1]; ++q) {
          const int32_t j = point_nodes[size_t(q)];
          if (j >= c && mark[size_t(j)] != c) {
            mark[size_t(j)] = c;
            column.push_back(j);
          }
        }
      }
      if (mark[size_t(c)] != c) column.push_back(c);  // a node outside every support of its own
      std::sort(column.begin(), column.end());
      model->block_row_.insert(model->block_row_.end(), column.begin(), column.end());
      model->block_start_[size_t(c) + 1] = static_cast<int64_t>(model->block_row_.size());
    }
  }
  point_nodes = {};
  point_start = {};
  const size_t blocks = model->block_row_.size();
  model->k_blocks_.assign(9 * blocks, 0.0);
  model->m_blocks_.assign(blocks, 0.0);

  for (int64_t g = 0; g < model->num_gauss_; ++g) {
    model->shape_->Evaluate(model->gauss_x_.col(g), true, &eval);
    model->AddGaussPoint(eval, model->gauss_w_[size_t(g)], 1.0, model->k_blocks_.data());
  }
  // M̂ = Φᵀ diag(m) Φ.
  for (int32_t i = 0; i < n; ++i) {
    const int32_t begin = model->phi_start_[size_t(i)], end = model->phi_start_[size_t(i) + 1];
    for (int32_t b = begin; b < end; ++b) {
      const int32_t col = model->phi_node_[size_t(b)];
      int64_t slot = model->block_start_[size_t(col)];
      for (int32_t a = b; a < end; ++a) {
        while (model->block_row_[size_t(slot)] != model->phi_node_[size_t(a)]) ++slot;
        model->m_blocks_[size_t(slot)] +=
            model->mass_[size_t(i)] * model->phi_value_[size_t(a)] * model->phi_value_[size_t(b)];
      }
    }
  }
  model->penalty_ =
      parameters.penalty_factor * MaxBlockDiagonal(model->block_start_, model->k_blocks_);

  // The scalar lower CSC pattern of the 3N × 3N systems and each entry's block source.
  ScalarLowerPattern(model->block_start_, model->block_row_, &model->csc_col_start_,
                     &model->csc_rows_, &model->csc_source_);

  // Φ's LU factors (for the reports' û = Φ⁻¹ u).
  model->factors_ = std::make_unique<Factors>();
  if (!FactorNodeValueMatrix(model->phi_start_, model->phi_node_, model->phi_value_,
                             &model->factors_->phi, &model->factors_->phi_transposed)) {
    Refuse("the node-value matrix Φ (φ_J(X_I)) is singular: nodes too close together?");
  }
  return model;
}

void EfgModel::AddGaussPoint(const MlsEvaluation& eval, double w, double sign,
                             double* k_blocks) const {
  // K = Σ_gauss w |J| B_Jᵀ D B_K, block (J, K) = w (λ ∇φ_J ∇φ_Kᵀ + μ ∇φ_K ∇φ_Jᵀ
  //     + μ ∇φ_J·∇φ_K I) (the FEM rest block with ∇φ for ∇N).
  const double sw = sign * w;
  const size_t m = eval.nodes.size();
  for (size_t b = 0; b < m; ++b) {
    const int32_t col = eval.nodes[b];
    const Vector3d gb = eval.gradients.col(static_cast<Eigen::Index>(b));
    int64_t slot = block_start_[size_t(col)];
    for (size_t a = b; a < m; ++a) {
      const int32_t row = eval.nodes[a];
      while (block_row_[size_t(slot)] != row) ++slot;  // both sorted
      const Vector3d ga = eval.gradients.col(static_cast<Eigen::Index>(a));
      Eigen::Map<Matrix3d> block(k_blocks + 9 * slot);
      block.noalias() += sw * (lambda_ * ga * gb.transpose() + mu_ * gb * ga.transpose());
      block.diagonal().array() += sw * mu_ * ga.dot(gb);
    }
  }
}

}  // namespace somasim::models::meshless
