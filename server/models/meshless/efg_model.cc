#include "server/models/meshless/efg_model.h"

#include <Eigen/LU>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/small_cholesky.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using Eigen::Vector4d;

[[noreturn]] void Refuse(const std::string& what) { throw std::invalid_argument("efg: " + what); }

void CheckParameters(const EfgParameters& p) {
  const auto finite_positive = [](double value, const char* what) {
    if (!(value > 0.0) || !std::isfinite(value)) {
      Refuse(std::string(what) + " must be a finite value > 0");
    }
  };
  const auto finite_non_negative = [](double value, const char* what) {
    if (!(value >= 0.0) || !std::isfinite(value)) {
      Refuse(std::string(what) + " must be a finite value >= 0");
    }
  };
  finite_positive(p.youngs_modulus, "youngs_modulus [Pa]");
  if (!(p.poisson_ratio > -1.0 && p.poisson_ratio < 0.5)) {
    Refuse("poisson_ratio must lie in (-1, 0.5)");
  }
  finite_positive(p.density, "density [kg/m^3]");
  finite_non_negative(p.rayleigh_mass, "rayleigh_mass [1/s]");
  finite_non_negative(p.rayleigh_stiffness, "rayleigh_stiffness [s]");
  if (!(p.min_support_edge_factor >= 1.0) || !std::isfinite(p.min_support_edge_factor)) {
    Refuse("min_support_edge_factor must be finite and >= 1");
  }
  if (p.gauss_points != 4 && p.gauss_points != 14) Refuse("gauss_points must be 4 or 14");
  finite_positive(p.penalty_factor, "penalty_factor");
  finite_positive(p.speed_limit, "speed_limit [m/s]");
  if (!(p.max_low_rank_nodes >= 0 && p.max_low_rank_nodes <= EfgParameters::kMaxLowRankNodes)) {
    Refuse("max_low_rank_nodes must lie in 0.." + std::to_string(EfgParameters::kMaxLowRankNodes));
  }
}

// A symmetric Gauss rule on a tetrahedron: barycentric points (4 each) and weights summing to 1
// (multiply by the volume).
struct TetRule {
  std::vector<Vector4d> points;
  std::vector<double> weights;
};

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

}  // namespace

// Φ's sparse LU (num_nodes × num_nodes) and Φᵀ's: û = Φ⁻¹ u and f = Φ⁻ᵀ f̂, for the state
// reports (Energy, InternalForces), not for the step.
struct EfgModel::Factors {
  Eigen::SparseLU<Eigen::SparseMatrix<double>> phi;
  Eigen::SparseLU<Eigen::SparseMatrix<double>> phi_transposed;
};

namespace {

// The state of an EFG model: the nodal parameters (the truth; positions are derived), the
// caches of the step's factorisation and of the attachments' low-rank update, and every buffer
// a step needs, sized by MakeState.
class EfgState final : public TissueState {
 public:
  mesh::Points params, vparams;                // û [m], v̂ [m/s], 3 × num_nodes
  mesh::Points good_params, good_vparams;      // the last accepted step's
  mesh::Points u, v, h, rhs, dv, work;         // scratch, 3 × num_nodes
  mesh::Points springs;                        // Σ k (target - X) per node [N], 3 × num_nodes
  mesh::Points anchor;                         // [m] where each fixed node is held
  std::vector<uint8_t> fixed_now, fixed_prev;  // num_nodes
  std::vector<double> support;                 // the supports' s_I [N/m], num_nodes: this step's
  std::vector<double> stiffness;               // all springs' s_I [N/m], num_nodes: this step's
  // This step's distinct attached nodes with a summed stiffness k > 0, in order of first
  // appearance: node and k [N/m] (num_attached of num_nodes used), and per node the summed k
  // while the step gathers them (num_nodes; zero between steps).
  std::vector<int32_t> attached_nodes;
  std::vector<double> attached_stiffness, attached_sum;
  int32_t num_attached = 0;
  std::vector<double> cached_stiffness;  // the s_I the step's factor was made with, num_nodes
  std::vector<double> cached_support;    // the s_I the static factor was made with, num_nodes
  double cached_dt = 0.0;
  bool factor_valid = false;
  bool static_current = false;   // static_factor (or its absence) matches cached_support
  bool static_valid = false;     // static_factor holds K + P_s (P_s non-zero)
  int64_t factorisations = 0;    // numeric factorisations, both factors
  std::vector<double> a_blocks;  // 9 × blocks: a system's blocks before the scalar gather
  fem::LowerCsc system;          // the model's scalar pattern, values per factorisation
  std::unique_ptr<fem::SparseCholesky> factor, static_factor;
  // The low-rank slots (capacity c = max_low_rank_nodes), valid while the step's factor holds
  // A0: slot s holds node slot_node[s] (-1: free) with Z's columns 3s..3s+2 and G's rows and
  // columns 3s..3s+2; slot_of_node maps back (num_nodes, -1: none); slot_stamp[s] the last step
  // (stamp) that used it.
  Eigen::MatrixXd z;                                            // A0⁻¹ U, 3N × 3c
  Eigen::MatrixXd gram;                                         // Uᵀ A0⁻¹ U, 3c × 3c
  std::vector<int32_t> slot_node, slot_of_node, attached_slot;  // c, num_nodes, c
  std::vector<int64_t> slot_stamp;                              // c
  int64_t stamp = 0;
  Eigen::MatrixXd small;         // I + W G W for this step's nodes (leading 3m × 3m), 3c × 3c
  Eigen::VectorXd small_rhs;     // 3c
  std::vector<double> unit_rhs;  // Φ_Iᵀ e_k, zero between uses, 3N
  // LocalStiffness: scratch (3N each) and its per-node cache (9 × num_nodes, column-major
  // 3 × 3 blocks; valid flags, num_nodes), cleared when the static factor changes.
  mutable std::vector<double> local_rhs, local_solution;
  mutable std::vector<double> local_stiffness;
  mutable std::vector<uint8_t> local_valid;

 protected:
  void SaveGood() override {
    good_params = params;  // same sizes: no allocation
    good_vparams = vparams;
  }
  void RestoreGood() override {
    params = good_params;
    vparams = good_vparams;
  }
};

}  // namespace

EfgModel::EfgModel() = default;
EfgModel::~EfgModel() = default;

std::unique_ptr<EfgModel> EfgModel::FromTetMesh(const mesh::TetMesh& mesh,
                                                const EfgParameters& parameters) {
  CheckParameters(parameters);
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
  for (int32_t t = 0; t < num_tets; ++t) {
    for (size_t g = 0; g < rule.points.size(); ++g) {
      model->shape_->Evaluate(gauss_point(t, g), false, &eval);
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

  // K = Σ_gauss w |J| B_Jᵀ D B_K, block (J, K) = w (λ ∇φ_J ∇φ_Kᵀ + μ ∇φ_K ∇φ_Jᵀ
  //     + μ ∇φ_J·∇φ_K I) (the FEM rest block with ∇φ for ∇N).
  const double lambda = model->lambda_, mu = model->mu_;
  for (int32_t t = 0; t < num_tets; ++t) {
    for (size_t g = 0; g < rule.points.size(); ++g) {
      model->shape_->Evaluate(gauss_point(t, g), true, &eval);
      const double w = rule.weights[g] * volume[size_t(t)];
      const size_t m = eval.nodes.size();
      for (size_t b = 0; b < m; ++b) {
        const int32_t col = eval.nodes[b];
        const Vector3d gb = eval.gradients.col(static_cast<Eigen::Index>(b));
        int64_t slot = model->block_start_[size_t(col)];
        for (size_t a = b; a < m; ++a) {
          const int32_t row = eval.nodes[a];
          while (model->block_row_[size_t(slot)] != row) ++slot;  // both sorted
          const Vector3d ga = eval.gradients.col(static_cast<Eigen::Index>(a));
          Eigen::Map<Matrix3d> block(model->k_blocks_.data() + 9 * slot);
          block.noalias() += w * (lambda * ga * gb.transpose() + mu * gb * ga.transpose());
          block.diagonal().array() += w * mu * ga.dot(gb);
        }
      }
    }
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
  double max_diagonal = 0.0;
  for (int32_t c = 0; c < n; ++c) {
    const int64_t slot = model->block_start_[size_t(c)];  // the diagonal block comes first
    const Eigen::Map<const Matrix3d> block(model->k_blocks_.data() + 9 * slot);
    max_diagonal = std::max(max_diagonal, block.diagonal().maxCoeff());
  }
  model->penalty_ = parameters.penalty_factor * max_diagonal;

  // The scalar lower CSC pattern of the 3N × 3N systems and each entry's block source.
  model->csc_col_start_.assign(3 * size_t(n) + 1, 0);
  for (int32_t c = 0; c < n; ++c) {
    const int64_t begin = model->block_start_[size_t(c)], end = model->block_start_[size_t(c) + 1];
    for (int cc = 0; cc < 3; ++cc) {
      for (int64_t slot = begin; slot < end; ++slot) {
        const int32_t row = model->block_row_[size_t(slot)];
        for (int r = row == c ? cc : 0; r < 3; ++r) {
          model->csc_rows_.push_back(3 * row + r);
          model->csc_source_.push_back(9 * slot + r + 3 * cc);
        }
      }
      model->csc_col_start_[3 * size_t(c) + size_t(cc) + 1] =
          static_cast<int32_t>(model->csc_rows_.size());
    }
  }

  // Φ's LU factors (for the reports' û = Φ⁻¹ u).
  {
    std::vector<Eigen::Triplet<double>> triplets;
    triplets.reserve(model->phi_value_.size());
    for (int32_t i = 0; i < n; ++i) {
      for (int32_t k = model->phi_start_[size_t(i)]; k < model->phi_start_[size_t(i) + 1]; ++k) {
        triplets.emplace_back(i, model->phi_node_[size_t(k)], model->phi_value_[size_t(k)]);
      }
    }
    Eigen::SparseMatrix<double> phi(n, n);
    phi.setFromTriplets(triplets.begin(), triplets.end());
    model->factors_ = std::make_unique<Factors>();
    model->factors_->phi.compute(phi);
    Eigen::SparseMatrix<double> phi_t = phi.transpose();
    model->factors_->phi_transposed.compute(phi_t);
    if (model->factors_->phi.info() != Eigen::Success ||
        model->factors_->phi_transposed.info() != Eigen::Success) {
      Refuse("the node-value matrix Φ (φ_J(X_I)) is singular: nodes too close together?");
    }
  }
  return model;
}

int64_t EfgModel::BlockIndex(int32_t row, int32_t col) const {
  const auto begin = block_row_.begin() + block_start_[size_t(col)];
  const auto end = block_row_.begin() + block_start_[size_t(col) + 1];
  const auto it = std::lower_bound(begin, end, row);
  return it != end && *it == row ? static_cast<int64_t>(it - block_row_.begin()) : -1;
}

std::unique_ptr<TissueState> EfgModel::MakeState() const {
  auto state = std::make_unique<EfgState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = num_nodes();
  for (mesh::Points* p :
       {&state->params, &state->vparams, &state->good_params, &state->good_vparams, &state->u,
        &state->v, &state->h, &state->rhs, &state->dv, &state->work, &state->springs}) {
    *p = mesh::Points::Zero(3, n);
  }
  state->anchor = rest_;
  state->fixed_now.assign(size_t(n), 0);
  state->fixed_prev.assign(size_t(n), 0);
  state->support.assign(size_t(n), 0.0);
  state->stiffness.assign(size_t(n), 0.0);
  state->attached_nodes.assign(size_t(n), 0);
  state->attached_stiffness.assign(size_t(n), 0.0);
  state->attached_sum.assign(size_t(n), 0.0);
  state->cached_stiffness.assign(size_t(n), 0.0);
  state->cached_support.assign(size_t(n), 0.0);
  const auto slots = static_cast<Eigen::Index>(max_low_rank_nodes_);
  state->z = Eigen::MatrixXd::Zero(3 * n, 3 * slots);
  state->gram = Eigen::MatrixXd::Zero(3 * slots, 3 * slots);
  state->small = Eigen::MatrixXd::Zero(3 * slots, 3 * slots);
  state->small_rhs = Eigen::VectorXd::Zero(3 * slots);
  state->slot_node.assign(size_t(slots), -1);
  state->slot_of_node.assign(size_t(n), -1);
  state->attached_slot.assign(size_t(slots), -1);
  state->slot_stamp.assign(size_t(slots), -1);
  state->unit_rhs.assign(3 * size_t(n), 0.0);
  state->a_blocks.assign(k_blocks_.size(), 0.0);
  state->system.size = 3 * static_cast<int32_t>(n);
  state->system.col_start = csc_col_start_;
  state->system.rows = csc_rows_;
  state->system.values.assign(csc_rows_.size(), 0.0);
  state->factor = std::make_unique<fem::SparseCholesky>();
  state->factor->Analyse(state->system);
  state->static_factor = std::make_unique<fem::SparseCholesky>();
  state->static_factor->Analyse(state->system);
  state->local_rhs.assign(3 * size_t(n), 0.0);
  state->local_solution.assign(3 * size_t(n), 0.0);
  state->local_stiffness.assign(9 * size_t(n), 0.0);
  state->local_valid.assign(size_t(n), 0);
  return state;
}

int64_t EfgModel::Factorisations(const TissueState& state) const {
  return static_cast<const EfgState&>(state).factorisations;
}

const mesh::Points& EfgModel::NodalParameters(const TissueState& state) const {
  return static_cast<const EfgState&>(state).params;
}

void EfgModel::MultiplyStiffness(const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  std::fill(y, y + 3 * n, 0.0);
  for (size_t c = 0; c < n; ++c) {
    const Eigen::Map<const Vector3d> xc(x + 3 * c);
    Eigen::Map<Vector3d> yc(y + 3 * c);
    const auto begin = size_t(block_start_[c]), end = size_t(block_start_[c + 1]);
    yc.noalias() += Eigen::Map<const Matrix3d>(k_blocks_.data() + 9 * begin) * xc;  // diagonal
    for (size_t slot = begin + 1; slot < end; ++slot) {
      const auto r = size_t(block_row_[slot]);
      const Eigen::Map<const Matrix3d> block(k_blocks_.data() + 9 * slot);
      Eigen::Map<Vector3d>(y + 3 * r).noalias() += block * xc;
      yc.noalias() += block.transpose() * Eigen::Map<const Vector3d>(x + 3 * r);
    }
  }
}

void EfgModel::MultiplyPhi(const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  for (size_t i = 0; i < n; ++i) {
    Vector3d sum = Vector3d::Zero();
    for (auto k = size_t(phi_start_[i]); k < size_t(phi_start_[i + 1]); ++k) {
      sum += phi_value_[k] * Eigen::Map<const Vector3d>(x + 3 * size_t(phi_node_[k]));
    }
    Eigen::Map<Vector3d>(y + 3 * i) = sum;
  }
}

void EfgModel::MultiplyPhiTransposed(const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  std::fill(y, y + 3 * n, 0.0);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Map<const Vector3d> xi(x + 3 * i);
    for (auto k = size_t(phi_start_[i]); k < size_t(phi_start_[i + 1]); ++k) {
      Eigen::Map<Vector3d>(y + 3 * size_t(phi_node_[k])) += phi_value_[k] * xi;
    }
  }
}

void EfgModel::AssembleSystem(double k_scale, double m_scale, double s_scale, const double* s,
                              double* blocks, double* values) const {
  // Blocks first (k_scale K + m_scale M̂ + s_scale Σ s_I Φ_Iᵀ Φ_I), then gathered into the scalar
  // CSC.
  const size_t num_blocks = block_row_.size();
  for (size_t b = 0; b < num_blocks; ++b) {
    Eigen::Map<Matrix3d> block(blocks + 9 * b);
    block = k_scale * Eigen::Map<const Matrix3d>(k_blocks_.data() + 9 * b);
    block.diagonal().array() += m_scale * m_blocks_[b];
  }
  const auto n = num_nodes();
  for (int32_t i = 0; i < n; ++i) {
    if (s[size_t(i)] == 0.0) continue;
    const int32_t begin = phi_start_[size_t(i)], end = phi_start_[size_t(i) + 1];
    for (int32_t b = begin; b < end; ++b) {
      for (int32_t a = b; a < end; ++a) {
        const int64_t slot = BlockIndex(phi_node_[size_t(a)], phi_node_[size_t(b)]);
        Eigen::Map<Matrix3d>(blocks + 9 * slot).diagonal().array() +=
            s_scale * s[size_t(i)] * phi_value_[size_t(a)] * phi_value_[size_t(b)];
      }
    }
  }
  for (size_t k = 0; k < csc_source_.size(); ++k) values[k] = blocks[size_t(csc_source_[k])];
}

void EfgModel::NodeDisplacements(const mesh::Points& parameters,
                                 mesh::Points* displacements) const {
  displacements->resize(3, num_nodes());
  MultiplyPhi(parameters.data(), displacements->data());
}

void EfgModel::DisplacementAt(const TissueState& state, const Vector3d& x, Vector3d* u,
                              Matrix3d* gradient) const {
  const mesh::Points& params = static_cast<const EfgState&>(state).params;
  MlsEvaluation eval;
  shape_->Evaluate(x, gradient != nullptr, &eval);
  Vector3d sum = Vector3d::Zero();
  Matrix3d grad = Matrix3d::Zero();
  for (size_t a = 0; a < eval.nodes.size(); ++a) {
    const auto col = static_cast<Eigen::Index>(a);
    sum += eval.values[a] * params.col(eval.nodes[a]);
    if (gradient != nullptr)
      grad += params.col(eval.nodes[a]) * eval.gradients.col(col).transpose();
  }
  if (u != nullptr) *u = sum;
  if (gradient != nullptr) *gradient = grad;
}

Matrix3d EfgModel::LocalStiffness(const TissueState& base, int32_t node) const {
  const auto& st = static_cast<const EfgState&>(base);
  if (!st.static_valid || node < 0 || node >= num_nodes()) return Matrix3d::Zero();
  double* cached = st.local_stiffness.data() + 9 * size_t(node);
  if (st.local_valid[size_t(node)] != 0) return Eigen::Map<const Matrix3d>(cached);
  // Column k of the compliance Φ_I K_s⁻¹ Φ_Iᵀ: a unit force along k at the node point.
  const int32_t begin = phi_start_[size_t(node)], end = phi_start_[size_t(node) + 1];
  Matrix3d compliance;
  for (int k = 0; k < 3; ++k) {
    for (int32_t a = begin; a < end; ++a) {
      st.local_rhs[3 * size_t(phi_node_[size_t(a)]) + size_t(k)] = phi_value_[size_t(a)];
    }
    st.static_factor->Solve(st.local_rhs.data(), st.local_solution.data());
    Vector3d sum = Vector3d::Zero();
    for (int32_t a = begin; a < end; ++a) {
      const auto j = 3 * size_t(phi_node_[size_t(a)]);
      sum += phi_value_[size_t(a)] * Eigen::Map<const Vector3d>(st.local_solution.data() + j);
      st.local_rhs[j + size_t(k)] = 0.0;
    }
    compliance.col(k) = sum;
  }
  const Matrix3d stiffness = compliance.inverse();
  Eigen::Map<Matrix3d> out(cached);
  out = 0.5 * (stiffness + stiffness.transpose());
  st.local_valid[size_t(node)] = 1;
  return Eigen::Map<const Matrix3d>(cached);
}

namespace {

// û = Φ⁻¹ (x - X) for a state's positions (3 × num_nodes), by Φ's LU.
mesh::Points ParametersOf(const Eigen::SparseLU<Eigen::SparseMatrix<double>>& phi,
                          const mesh::Points& positions, const mesh::Points& rest) {
  const Eigen::MatrixXd u = (positions - rest).transpose();  // num_nodes × 3
  const Eigen::MatrixXd params = phi.solve(u);
  return params.transpose();
}

}  // namespace

void EfgModel::ForcesOfParameters(const mesh::Points& params, mesh::Points* forces) const {
  mesh::Points k_params(3, num_nodes());
  MultiplyStiffness(params.data(), k_params.data());
  // Φᵀ f = -K û: the physical forces whose virtual work on δu = Φ δû is -δûᵀ K û.
  const Eigen::MatrixXd rhs = -k_params.transpose();
  const Eigen::MatrixXd f = factors_->phi_transposed.solve(rhs);
  *forces = f.transpose();
}

double EfgModel::ElasticEnergyOfParameters(const mesh::Points& params) const {
  mesh::Points k_params(3, num_nodes());
  MultiplyStiffness(params.data(), k_params.data());
  return 0.5 * params.cwiseProduct(k_params).sum();
}

void EfgModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  ForcesOfParameters(ParametersOf(factors_->phi, state.positions, rest_), forces);
}

EnergyReport EfgModel::Energy(const TissueState& state, const Vector3d& gravity) const {
  EnergyReport report;
  report.elastic = ElasticEnergyOfParameters(ParametersOf(factors_->phi, state.positions, rest_));
  for (Eigen::Index i = 0; i < state.positions.cols(); ++i) {
    const double m = mass_[size_t(i)];
    report.kinetic += 0.5 * m * state.velocities.col(i).squaredNorm();
    report.gravity -= m * gravity.dot(state.positions.col(i));
    report.momentum += m * state.velocities.col(i);
  }
  return report;
}

void CheckStaticLoads(const EfgStaticLoads& loads, int32_t n, const std::string& model) {
  const auto refuse = [&model](const std::string& what) {
    throw std::invalid_argument(model + ": SolveStatic: " + what);
  };
  const auto in_range = [n](int32_t node) { return node >= 0 && node < n; };
  if (loads.external_forces != nullptr &&
      (loads.external_forces->cols() != n || !loads.external_forces->allFinite())) {
    refuse("external_forces must be finite, 3 x num_nodes");
  }
  if (loads.parameter_forces != nullptr &&
      (loads.parameter_forces->cols() != n || !loads.parameter_forces->allFinite())) {
    refuse("parameter_forces must be finite, 3 x num_nodes");
  }
  if (!loads.gravity.allFinite()) refuse("gravity must be finite");
  for (const int32_t node : loads.fixed_nodes) {
    if (!in_range(node)) refuse("fixed node " + std::to_string(node) + " out of range");
  }
  for (const int32_t node : loads.prescribed_nodes) {
    if (!in_range(node)) {
      refuse("prescribed node " + std::to_string(node) + " out of range");
    }
  }
  if (!loads.prescribed_nodes.empty() &&
      (loads.prescribed_positions == nullptr ||
       loads.prescribed_positions->cols() !=
           static_cast<Eigen::Index>(loads.prescribed_nodes.size()) ||
       !loads.prescribed_positions->allFinite())) {
    refuse("prescribed_positions must be finite, 3 x prescribed_nodes.size()");
  }
  if (loads.fixed_nodes.empty() && loads.prescribed_nodes.empty()) {
    refuse("needs fixed or prescribed nodes (a free body has no equilibrium)");
  }
}

void EfgModel::SolveStatic(const EfgStaticLoads& loads, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const int32_t n = num_nodes();
  CheckStaticLoads(loads, n, "efg");
  // Penalty springs κ: fixed at rest (target displacement 0), prescribed at their positions.
  std::vector<double> s(size_t(n), 0.0);
  mesh::Points h = mesh::Points::Zero(3, n);
  for (const int32_t node : loads.fixed_nodes) s[size_t(node)] += penalty_;
  for (size_t k = 0; k < loads.prescribed_nodes.size(); ++k) {
    const int32_t node = loads.prescribed_nodes[k];
    s[size_t(node)] += penalty_;
    h.col(node) += penalty_ * (loads.prescribed_positions->col(static_cast<Eigen::Index>(k)) -
                               rest_.col(node));
  }
  for (int32_t i = 0; i < n; ++i) h.col(i) += mass_[size_t(i)] * loads.gravity;
  if (loads.external_forces != nullptr) h += *loads.external_forces;
  mesh::Points rhs(3, n), solution(3, n);
  MultiplyPhiTransposed(h.data(), rhs.data());
  if (loads.parameter_forces != nullptr) rhs += *loads.parameter_forces;

  fem::LowerCsc system;
  system.size = 3 * n;
  system.col_start = csc_col_start_;
  system.rows = csc_rows_;
  system.values.assign(csc_rows_.size(), 0.0);
  std::vector<double> blocks(k_blocks_.size());
  AssembleSystem(1.0, 0.0, 1.0, s.data(), blocks.data(), system.values.data());
  fem::SparseCholesky cholesky;
  cholesky.Analyse(system);
  if (!cholesky.Factorise(system)) {
    throw std::runtime_error(
        "efg: SolveStatic: K + penalties is not positive definite "
        "(too few held nodes to remove the rigid motions)");
  }
  cholesky.Solve(rhs.data(), solution.data());
  st->params = solution;
  st->vparams.setZero();
  MultiplyPhi(st->params.data(), st->u.data());
  st->positions = rest_ + st->u;
  st->velocities.setZero();
}

bool EfgModel::PrepareFactors(double dt, bool low_rank, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const double alpha = rayleigh_mass_, beta = rayleigh_stiffness_;
  // The step's system: A0 (supports only) on the low-rank path, else A with the attachments.
  const std::vector<double>& key = low_rank ? st->support : st->stiffness;
  if (!st->factor_valid || dt != st->cached_dt ||
      !std::equal(key.begin(), key.end(), st->cached_stiffness.begin())) {
    AssembleSystem(dt * dt + dt * beta, 1.0 + dt * alpha, dt * dt, key.data(), st->a_blocks.data(),
                   st->system.values.data());
    st->factor_valid = st->factor->Factorise(st->system);
    ++st->factorisations;
    st->cached_dt = dt;
    std::copy(key.begin(), key.end(), st->cached_stiffness.begin());
    // Z = A0⁻¹ U belongs to the old factor: every slot is free again.
    for (int32_t& node : st->slot_node) {
      if (node >= 0) st->slot_of_node[size_t(node)] = -1;
      node = -1;
    }
    std::fill(st->slot_stamp.begin(), st->slot_stamp.end(), int64_t{-1});
    if (!st->factor_valid) return false;  // cannot happen for a positive mass
  }
  // The static K_s = K + P_s for LocalStiffness (nothing holds a body without supports).
  if (!st->static_current ||
      !std::equal(st->support.begin(), st->support.end(), st->cached_support.begin())) {
    st->static_valid = false;
    if (std::any_of(st->support.begin(), st->support.end(), [](double s) { return s > 0; })) {
      AssembleSystem(1.0, 0.0, 1.0, st->support.data(), st->a_blocks.data(),
                     st->system.values.data());
      st->static_valid = st->static_factor->Factorise(st->system);
      ++st->factorisations;
    }
    st->static_current = true;
    std::copy(st->support.begin(), st->support.end(), st->cached_support.begin());
    std::fill(st->local_valid.begin(), st->local_valid.end(), uint8_t{0});
  }
  if (!low_rank || st->num_attached == 0) return true;
  // The attached nodes' slots: those already cached are kept (stamped), each new node takes the
  // least recently used slot, which no node of this step holds (num_attached <= slots).
  ++st->stamp;
  const auto m = size_t(st->num_attached);
  for (size_t j = 0; j < m; ++j) {
    const int32_t slot = st->slot_of_node[size_t(st->attached_nodes[j])];
    st->attached_slot[j] = slot;
    if (slot >= 0) st->slot_stamp[size_t(slot)] = st->stamp;
  }
  for (size_t j = 0; j < m; ++j) {
    if (st->attached_slot[j] >= 0) continue;
    const auto oldest = std::min_element(st->slot_stamp.begin(), st->slot_stamp.end());
    const auto slot = static_cast<int32_t>(oldest - st->slot_stamp.begin());
    if (st->slot_node[size_t(slot)] >= 0) {
      st->slot_of_node[size_t(st->slot_node[size_t(slot)])] = -1;
    }
    FillLowRankSlot(slot, st->attached_nodes[j], st);
    st->slot_stamp[size_t(slot)] = st->stamp;
    st->attached_slot[j] = slot;
  }
  return true;
}

void EfgModel::FillLowRankSlot(int32_t slot, int32_t node, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const auto s = static_cast<Eigen::Index>(slot);
  // Z's columns: A0⁻¹ Φ_Iᵀ e_k, three solves.
  const int32_t begin = phi_start_[size_t(node)], end = phi_start_[size_t(node) + 1];
  for (int k = 0; k < 3; ++k) {
    for (int32_t a = begin; a < end; ++a) {
      st->unit_rhs[3 * size_t(phi_node_[size_t(a)]) + size_t(k)] = phi_value_[size_t(a)];
    }
    st->factor->Solve(st->unit_rhs.data(), st->z.col(3 * s + k).data());
    for (int32_t a = begin; a < end; ++a) {
      st->unit_rhs[3 * size_t(phi_node_[size_t(a)]) + size_t(k)] = 0.0;
    }
  }
  st->slot_node[size_t(slot)] = node;
  st->slot_of_node[size_t(node)] = slot;
  // G's blocks with every held slot t (this one included): Φ_{I_t} Z_s (3 × 3), mirrored (G
  // is symmetric; the diagonal block is symmetrised).
  for (size_t t = 0; t < st->slot_node.size(); ++t) {
    const int32_t other = st->slot_node[t];
    if (other < 0) continue;
    Matrix3d block = Matrix3d::Zero();
    for (int32_t a = phi_start_[size_t(other)]; a < phi_start_[size_t(other) + 1]; ++a) {
      const Eigen::Index row = 3 * static_cast<Eigen::Index>(phi_node_[size_t(a)]);
      block += phi_value_[size_t(a)] * st->z.block<3, 3>(row, 3 * s);
    }
    const auto tt = static_cast<Eigen::Index>(t);
    if (tt == s) block = 0.5 * (block + block.transpose()).eval();
    st->gram.block<3, 3>(3 * tt, 3 * s) = block;
    st->gram.block<3, 3>(3 * s, 3 * tt) = block.transpose();
  }
}

bool EfgModel::CorrectForAttachments(double dt, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const auto m = static_cast<Eigen::Index>(st->num_attached);
  const Eigen::Index r = 3 * m;
  // W Uᵀ x0 (W = S^½: dt √k_j per node) and the lower triangle of I + W G W.
  for (Eigen::Index i = 0; i < m; ++i) {
    const int32_t node = st->attached_nodes[size_t(i)];
    const double wi = dt * std::sqrt(st->attached_stiffness[size_t(i)]);
    Vector3d ux = Vector3d::Zero();
    for (int32_t a = phi_start_[size_t(node)]; a < phi_start_[size_t(node) + 1]; ++a) {
      ux += phi_value_[size_t(a)] *
            Eigen::Map<const Vector3d>(st->dv.data() + 3 * size_t(phi_node_[size_t(a)]));
    }
    st->small_rhs.segment<3>(3 * i) = wi * ux;
    const auto si = static_cast<Eigen::Index>(st->attached_slot[size_t(i)]);
    for (Eigen::Index j = 0; j <= i; ++j) {
      const double wj = dt * std::sqrt(st->attached_stiffness[size_t(j)]);
      const auto sj = static_cast<Eigen::Index>(st->attached_slot[size_t(j)]);
      st->small.block<3, 3>(3 * i, 3 * j) = (wi * wj) * st->gram.block<3, 3>(3 * si, 3 * sj);
    }
    st->small.block<3, 3>(3 * i, 3 * i).diagonal().array() += 1.0;
  }
  const auto ld = static_cast<int>(st->small.rows());
  if (!CholeskyInPlace(st->small.data(), static_cast<int>(r), ld)) return false;
  CholeskySolveInPlace(st->small.data(), static_cast<int>(r), ld, st->small_rhs.data());
  // dv = x0 - Σ_j Z_j (W y)_j.
  Eigen::Map<Eigen::VectorXd> dv(st->dv.data(), st->dv.size());
  for (Eigen::Index j = 0; j < m; ++j) {
    const double wj = dt * std::sqrt(st->attached_stiffness[size_t(j)]);
    const auto sj = static_cast<Eigen::Index>(st->attached_slot[size_t(j)]);
    const Vector3d y = wj * st->small_rhs.segment<3>(3 * j);
    dv.noalias() -= st->z.middleCols<3>(3 * sj) * y;
  }
  return true;
}

void EfgModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<EfgState*>(base);
  const auto n = size_t(num_nodes());
  const double dt = inputs.dt;
  const double alpha = rayleigh_mass_, beta = rayleigh_stiffness_;

  // 1. Springs at the node points: per node the supports' summed stiffness, every spring's
  // Σ k (target - X_I), and the distinct attached nodes with their summed stiffness.
  std::fill(st->support.begin(), st->support.end(), 0.0);
  st->springs.setZero();
  std::fill(st->fixed_now.begin(), st->fixed_now.end(), uint8_t{0});
  for (const int32_t node : inputs.fixed_nodes) {
    const auto i = size_t(node);
    if (st->fixed_now[i] != 0) continue;  // listed twice
    st->fixed_now[i] = 1;
    if (st->fixed_prev[i] == 0) st->anchor.col(node) = st->positions.col(node);
    st->support[i] += penalty_;
    st->springs.col(node) += penalty_ * (st->anchor.col(node) - rest_.col(node));
  }
  std::swap(st->fixed_now, st->fixed_prev);  // no allocation
  for (size_t k = 0; k < inputs.prescribed_nodes.size(); ++k) {
    const int32_t node = inputs.prescribed_nodes[k];
    st->support[size_t(node)] += penalty_;
    st->springs.col(node) +=
        penalty_ *
        (inputs.prescribed_positions->col(static_cast<Eigen::Index>(k)) - rest_.col(node));
  }
  for (const Attachment& grasp : inputs.attachments) {
    st->attached_sum[size_t(grasp.node)] += grasp.stiffness;
    st->springs.col(grasp.node) += grasp.stiffness * (grasp.target - rest_.col(grasp.node));
  }
  std::copy(st->support.begin(), st->support.end(), st->stiffness.begin());
  st->num_attached = 0;
  for (const Attachment& grasp : inputs.attachments) {  // in order; each node once
    const auto i = size_t(grasp.node);
    const double k = st->attached_sum[i];
    if (k > 0.0) {
      st->attached_nodes[size_t(st->num_attached)] = grasp.node;
      st->attached_stiffness[size_t(st->num_attached)] = k;
      ++st->num_attached;
      st->stiffness[i] += k;
    }
    st->attached_sum[i] = 0.0;  // marks the node taken and leaves the sums zero
  }

  // 2. The factors: A0 and the attached nodes' slots, or A with the attachments inside.
  const bool low_rank = st->num_attached <= max_low_rank_nodes_;
  if (!PrepareFactors(dt, low_rank, st)) {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
    return;
  }

  // 3. Physical displacements and velocities at the nodes.
  MultiplyPhi(st->params.data(), st->u.data());
  MultiplyPhi(st->vparams.data(), st->v.data());

  // 4. Node-point forces h_I = f_ext + m_I (g - α v_I) + Σ k (t - X_I) - s_I (u_I + dt v_I).
  const mesh::Points* external = inputs.external_forces;
  for (size_t i = 0; i < n; ++i) {
    const auto c = static_cast<Eigen::Index>(i);
    Vector3d f = mass_[i] * (inputs.gravity - alpha * st->v.col(c)) + st->springs.col(c) -
                 st->stiffness[i] * (st->u.col(c) + dt * st->v.col(c));
    if (external != nullptr) f += external->col(c);
    st->h.col(c) = f;
  }
  // 5. b = dt (Φᵀ h - K (û + (β + dt) v̂)).
  st->work = st->params + (beta + dt) * st->vparams;
  MultiplyStiffness(st->work.data(), st->dv.data());
  MultiplyPhiTransposed(st->h.data(), st->rhs.data());
  st->rhs = dt * (st->rhs - st->dv);

  // 6. Solve, update the parameters, then the physical positions and velocities.
  st->factor->Solve(st->rhs.data(), st->dv.data());
  if (low_rank && st->num_attached > 0 && !CorrectForAttachments(dt, st)) {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
    return;
  }
  ++st->counters.solver_iterations;
  st->vparams += st->dv;
  st->params += dt * st->vparams;
  MultiplyPhi(st->params.data(), st->u.data());
  MultiplyPhi(st->vparams.data(), st->velocities.data());
  st->positions = rest_ + st->u;
}

}  // namespace somasim::models::meshless
