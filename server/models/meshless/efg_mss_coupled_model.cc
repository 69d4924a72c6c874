#include "server/models/meshless/efg_mss_coupled_model.h"

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

#include "common/checks/finite.h"
#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/efg_shared.h"
#include "server/models/particle_mesh.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using Eigen::Vector4d;

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("efg-mss: " + what);
}

void CheckParameters(const EfgMssCoupledParameters& parameters) {
  CheckEfgParameters(parameters.efg, "efg-mss: efg.");
  const auto finite_non_negative = [](double value, const char* what) {
    if (!checks::FiniteNonNegative(value)) {
      Refuse(std::string(what) + " must be a finite value >= 0");
    }
  };
  finite_non_negative(parameters.region_radius, "region_radius [m]");
  if (!parameters.region_centre.allFinite()) Refuse("region_centre [m] must be finite");
}

// The state: the unknowns (the truth; positions are derived), the factors and every buffer a
// step needs, sized by MakeState.
class CoupledState final : public TissueState {
 public:
  mesh::Points q, vq;                          // q [m], q̇ [m/s], 3 × num_nodes
  mesh::Points good_q, good_vq;                // the last accepted step's
  mesh::Points u, v, h, rhs, dv, work;         // scratch, 3 × num_nodes
  mesh::Points springs;                        // Σ k (target - X) per node [N], 3 × num_nodes
  mesh::Points anchor;                         // [m] where each fixed node is held
  std::vector<uint8_t> fixed_now, fixed_prev;  // num_nodes
  std::vector<double> support;                 // the supports' s_I [N/m], num_nodes
  std::vector<double> stiffness;               // every spring's s_I [N/m], num_nodes
  std::vector<double> cached_stiffness;        // the s_I the step's factor was made with
  std::vector<double> cached_support;          // the s_I the static factor was made with
  double cached_dt = 0.0;
  bool factor_valid = false;
  bool static_current = false;
  bool static_valid = false;
  int64_t factorisations = 0;
  std::vector<double> a_blocks;  // 9 × blocks
  fem::LowerCsc system;
  std::unique_ptr<fem::SparseCholesky> factor, static_factor;
  // LocalStiffness: scratch (3N each) and its per-node cache (9 × num_nodes; flags, num_nodes).
  mutable std::vector<double> local_rhs, local_solution;
  mutable std::vector<double> local_stiffness;
  mutable std::vector<uint8_t> local_valid;

 protected:
  void SaveGood() override {
    good_q = q;  // same sizes: no allocation
    good_vq = vq;
  }
  void RestoreGood() override {
    q = good_q;
    vq = good_vq;
  }
};

// (column, coefficient) pairs of a node's G row.
using Row = std::vector<std::pair<int32_t, double>>;

}  // namespace

struct EfgMssCoupledModel::Factors {
  Eigen::SparseLU<Eigen::SparseMatrix<double>> g, g_transposed;
};

EfgMssCoupledModel::EfgMssCoupledModel() = default;
EfgMssCoupledModel::~EfgMssCoupledModel() = default;

std::unique_ptr<EfgMssCoupledModel> EfgMssCoupledModel::FromTetMesh(
    const mesh::TetMesh& mesh, const EfgMssCoupledParameters& parameters) {
  CheckParameters(parameters);
  const EfgParameters& efg = parameters.efg;
  const auto n = static_cast<int32_t>(mesh.vertices.cols());
  const auto num_tets = static_cast<int32_t>(mesh.tetrahedra.cols());
  if (n == 0 || num_tets == 0) Refuse("mesh: empty (no nodes or no tetrahedra)");
  for (int32_t i = 0; i < n; ++i) {
    if (!mesh.vertices.col(i).allFinite()) {
      Refuse("mesh: vertex " + std::to_string(i) + " has a non-finite coordinate");
    }
  }
  std::unique_ptr<EfgMssCoupledModel> model(new EfgMssCoupledModel());
  model->rest_ = mesh.vertices;
  model->rayleigh_mass_ = efg.rayleigh_mass;
  model->rayleigh_stiffness_ = efg.rayleigh_stiffness;
  model->set_speed_limit(efg.speed_limit);

  // 1. Tetrahedra: checks, volumes, lumped masses ρV/4, and which are meshless (a corner within
  // the region).
  std::vector<double> volume(static_cast<size_t>(num_tets));
  std::vector<uint8_t> meshless(size_t(num_tets), 0);
  model->mass_.assign(size_t(n), 0.0);
  const double r2 = parameters.region_radius * parameters.region_radius;
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
      model->mass_[size_t(mesh.tetrahedra(a, t))] += efg.density * v / 4.0;
      if ((x(a) - parameters.region_centre).squaredNorm() <= r2) meshless[size_t(t)] = 1;
    }
  }
  for (int32_t i = 0; i < n; ++i) {
    if (!(model->mass_[size_t(i)] > 0.0)) {
      Refuse("mesh: node " + std::to_string(i) + " belongs to no tetrahedron");
    }
  }

  // 2. The region's nodes E (increasing node order: unknowns 0..|E|-1), the interface, the
  // MSS-only nodes (the following unknowns), and E's longest meshless edges.
  std::vector<uint8_t> in_meshless(size_t(n), 0), in_mss(size_t(n), 0);
  std::vector<int32_t> meshless_tets, mss_tets;
  for (int32_t t = 0; t < num_tets; ++t) {
    (meshless[size_t(t)] != 0 ? meshless_tets : mss_tets).push_back(t);
    for (int a = 0; a < 4; ++a) {
      (meshless[size_t(t)] != 0 ? in_meshless : in_mss)[size_t(mesh.tetrahedra(a, t))] = 1;
    }
  }
  model->num_meshless_tets_ = static_cast<int32_t>(meshless_tets.size());
  model->efg_of_node_.assign(size_t(n), -1);
  std::vector<int32_t> unknown_of_node(size_t(n), -1), efg_nodes;
  for (int32_t i = 0; i < n; ++i) {
    if (in_meshless[size_t(i)] == 0) continue;
    model->efg_of_node_[size_t(i)] = static_cast<int32_t>(efg_nodes.size());
    unknown_of_node[size_t(i)] = static_cast<int32_t>(efg_nodes.size());
    efg_nodes.push_back(i);
    if (in_mss[size_t(i)] != 0) ++model->num_interface_;
  }
  const auto num_efg = static_cast<int32_t>(efg_nodes.size());
  model->num_efg_ = num_efg;
  if (num_efg > 0 && num_efg <= efg.mls.support_neighbours) {
    Refuse("region_radius: the region holds " + std::to_string(num_efg) +
           " nodes; the EFG needs more than efg.mls.support_neighbours (" +
           std::to_string(efg.mls.support_neighbours) + ")");
  }
  {
    int32_t next = num_efg;
    for (int32_t i = 0; i < n; ++i) {
      if (unknown_of_node[size_t(i)] < 0) unknown_of_node[size_t(i)] = next++;
    }
  }

  // 3. MLS on E (sub-mesh coordinates) and G's rows: Φ_I for E, the unit row otherwise.
  std::unique_ptr<MlsShapeFunctions> shape;
  mesh::Points sub_nodes(3, num_efg);
  for (int32_t e = 0; e < num_efg; ++e) sub_nodes.col(e) = mesh.vertices.col(efg_nodes[size_t(e)]);
  MlsEvaluation eval;
  std::vector<Row> rows(static_cast<size_t>(n));
  if (num_efg > 0) {
    std::vector<double> longest(size_t(num_efg), 0.0);
    for (const int32_t t : meshless_tets) {
      for (int a = 0; a < 4; ++a) {
        const auto e = size_t(model->efg_of_node_[size_t(mesh.tetrahedra(a, t))]);
        for (int b = 0; b < 4; ++b) {
          longest[e] = std::max(longest[e], (mesh.vertices.col(mesh.tetrahedra(a, t)) -
                                             mesh.vertices.col(mesh.tetrahedra(b, t)))
                                                .norm());
        }
      }
    }
    for (double& l : longest) l *= efg.min_support_edge_factor;
    shape = std::make_unique<MlsShapeFunctions>(sub_nodes, efg.mls, longest);
  }
  for (int32_t i = 0; i < n; ++i) {
    if (model->efg_of_node_[size_t(i)] < 0) {
      rows[size_t(i)] = {{unknown_of_node[size_t(i)], 1.0}};
      continue;
    }
    shape->Evaluate(mesh.vertices.col(i), false, &eval);
    for (size_t a = 0; a < eval.nodes.size(); ++a) {
      rows[size_t(i)].emplace_back(eval.nodes[a], eval.values[a]);  // sorted sub indices
    }
  }
  model->g_start_.assign(size_t(n) + 1, 0);
  for (int32_t i = 0; i < n; ++i) {
    for (const auto& [col, value] : rows[size_t(i)]) {
      model->g_col_.push_back(col);
      model->g_value_.push_back(value);
    }
    model->g_start_[size_t(i) + 1] = static_cast<int32_t>(model->g_col_.size());
  }

  // 4. The springs: the MSS tetrahedra's unique edges, Van Gelder's k = E Σ V / |e|²
  // (MassSpringModel's rule), each with its coefficient row G_b - G_a (merged, sorted).
  std::vector<Row> spring_rows;
  if (!mss_tets.empty()) {
    mesh::TetMesh mss;
    mss.vertices = mesh.vertices;
    mss.tetrahedra.resize(4, static_cast<Eigen::Index>(mss_tets.size()));
    for (size_t k = 0; k < mss_tets.size(); ++k) {
      mss.tetrahedra.col(static_cast<Eigen::Index>(k)) = mesh.tetrahedra.col(mss_tets[k]);
    }
    const MeshEdges edges = TetMeshEdges(mss, "efg-mss");
    const auto m = static_cast<Eigen::Index>(edges.edges.size());
    model->spring_dir_.resize(3, m);
    for (Eigen::Index s = 0; s < m; ++s) {
      const auto [a, b] = edges.edges[size_t(s)];
      const Vector3d d = mesh.vertices.col(b) - mesh.vertices.col(a);
      const double length = d.norm();
      if (!(length > 0.0)) {
        Refuse("mesh: nodes " + std::to_string(a) + " and " + std::to_string(b) + " coincide");
      }
      model->spring_a_.push_back(a);
      model->spring_b_.push_back(b);
      model->spring_k_.push_back(efg.youngs_modulus * edges.edge_size[size_t(s)] /
                                 (length * length));
      model->spring_dir_.col(s) = d / length;
      Row row;
      for (const auto& [col, value] : rows[size_t(b)]) row.emplace_back(col, value);
      for (const auto& [col, value] : rows[size_t(a)]) row.emplace_back(col, -value);
      std::sort(row.begin(), row.end(),
                [](const auto& x, const auto& y) { return x.first < y.first; });
      Row merged;
      for (const auto& entry : row) {
        if (!merged.empty() && merged.back().first == entry.first) {
          merged.back().second += entry.second;
        } else {
          merged.push_back(entry);
        }
      }
      spring_rows.push_back(std::move(merged));
    }
  }

  // 5. The lower block pattern over the unknowns: every pair sharing a Gauss point, a node's G
  // row, or a spring's row; every diagonal.
  const TetRule rule = MakeTetRule(efg.gauss_points);
  model->num_gauss_ = static_cast<int64_t>(rule.points.size() * meshless_tets.size());
  const auto gauss_point = [&](int32_t t, size_t g) {
    Vector3d p = Vector3d::Zero();
    for (int a = 0; a < 4; ++a) p += rule.points[g][a] * mesh.vertices.col(mesh.tetrahedra(a, t));
    return p;
  };
  std::vector<int64_t> keys;  // col · n + row, row >= col
  const auto compact = [&keys] {
    std::sort(keys.begin(), keys.end());
    keys.erase(std::unique(keys.begin(), keys.end()), keys.end());
  };
  size_t compacted = 0;  // keys' size after the last compaction (bounds the memory on big organs)
  const auto add_pairs = [&](const std::vector<int32_t>& cols) {
    for (const int32_t c : cols) {
      for (const int32_t r : cols) {
        if (r >= c) keys.push_back(int64_t{c} * n + r);
      }
    }
    if (keys.size() > compacted + (size_t{1} << 23)) {
      compact();
      compacted = keys.size();
    }
  };
  std::vector<int32_t> cols;
  for (const int32_t t : meshless_tets) {
    for (size_t g = 0; g < rule.points.size(); ++g) {
      shape->Evaluate(gauss_point(t, g), false, &eval);
      add_pairs(eval.nodes);
    }
  }
  for (const std::vector<Row>* list : {&rows, &spring_rows}) {
    for (const Row& row : *list) {
      cols.clear();
      for (const auto& entry : row) cols.push_back(entry.first);
      add_pairs(cols);
    }
  }
  for (int32_t c = 0; c < n; ++c) keys.push_back(int64_t{c} * n + c);
  compact();
  model->block_start_.assign(size_t(n) + 1, 0);
  model->block_row_.reserve(keys.size());
  for (const int64_t key : keys) {
    model->block_row_.push_back(static_cast<int32_t>(key % n));
    ++model->block_start_[size_t(key / n) + 1];
  }
  for (size_t c = 0; c < size_t(n); ++c) model->block_start_[c + 1] += model->block_start_[c];
  keys = {};
  const size_t blocks = model->block_row_.size();
  model->k_blocks_.assign(9 * blocks, 0.0);
  model->m_blocks_.assign(blocks, 0.0);

  // 6. K_E = Σ_gauss w |J| B_Jᵀ D B_K (efg_model.cc's blocks), then the springs
  // k c_J c_L e eᵀ, then M̂ = Gᵀ diag(m) G.
  const double e_mod = efg.youngs_modulus, nu = efg.poisson_ratio;
  const double lambda = e_mod * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
  const double mu = e_mod / (2.0 * (1.0 + nu));
  for (const int32_t t : meshless_tets) {
    for (size_t g = 0; g < rule.points.size(); ++g) {
      shape->Evaluate(gauss_point(t, g), true, &eval);
      const double w = rule.weights[g] * volume[size_t(t)];
      const size_t m = eval.nodes.size();
      for (size_t b = 0; b < m; ++b) {
        const int32_t col = eval.nodes[b];
        const Vector3d gb = eval.gradients.col(static_cast<Eigen::Index>(b));
        int64_t slot = model->block_start_[size_t(col)];
        for (size_t a = b; a < m; ++a) {
          while (model->block_row_[size_t(slot)] != eval.nodes[a]) ++slot;  // both sorted
          const Vector3d ga = eval.gradients.col(static_cast<Eigen::Index>(a));
          Eigen::Map<Matrix3d> block(model->k_blocks_.data() + 9 * slot);
          block.noalias() += w * (lambda * ga * gb.transpose() + mu * gb * ga.transpose());
          block.diagonal().array() += w * mu * ga.dot(gb);
        }
      }
    }
  }
  for (size_t s = 0; s < spring_rows.size(); ++s) {
    const Vector3d e = model->spring_dir_.col(static_cast<Eigen::Index>(s));
    const Matrix3d kee = model->spring_k_[s] * e * e.transpose();
    const Row& row = spring_rows[s];
    for (size_t b = 0; b < row.size(); ++b) {
      int64_t slot = model->block_start_[size_t(row[b].first)];
      for (size_t a = b; a < row.size(); ++a) {
        while (model->block_row_[size_t(slot)] != row[a].first) ++slot;
        Eigen::Map<Matrix3d>(model->k_blocks_.data() + 9 * slot) +=
            (row[a].second * row[b].second) * kee;
      }
    }
  }
  for (int32_t i = 0; i < n; ++i) {
    const Row& row = rows[size_t(i)];
    for (size_t b = 0; b < row.size(); ++b) {
      int64_t slot = model->block_start_[size_t(row[b].first)];
      for (size_t a = b; a < row.size(); ++a) {
        while (model->block_row_[size_t(slot)] != row[a].first) ++slot;
        model->m_blocks_[size_t(slot)] += model->mass_[size_t(i)] * row[a].second * row[b].second;
      }
    }
  }
  model->penalty_ = efg.penalty_factor * MaxBlockDiagonal(model->block_start_, model->k_blocks_);

  // 7. The scalar lower CSC pattern of the 3N × 3N systems and each entry's block source.
  ScalarLowerPattern(model->block_start_, model->block_row_, &model->csc_col_start_,
                     &model->csc_rows_, &model->csc_source_);

  // 8. G's LU factors (for the reports' q = G⁻¹ u).
  model->factors_ = std::make_unique<Factors>();
  if (!FactorNodeValueMatrix(model->g_start_, model->g_col_, model->g_value_, &model->factors_->g,
                             &model->factors_->g_transposed)) {
    Refuse("the node-value matrix Φ (φ_J(X_I)) is singular: nodes too close together?");
  }
  return model;
}

int64_t EfgMssCoupledModel::BlockIndex(int32_t row, int32_t col) const {
  const auto begin = block_row_.begin() + block_start_[size_t(col)];
  const auto end = block_row_.begin() + block_start_[size_t(col) + 1];
  const auto it = std::lower_bound(begin, end, row);
  return it != end && *it == row ? static_cast<int64_t>(it - block_row_.begin()) : -1;
}

std::unique_ptr<TissueState> EfgMssCoupledModel::MakeState() const {
  auto state = std::make_unique<CoupledState>();
  InitialiseState(rest_, state.get());
  const Eigen::Index n = num_nodes();
  for (mesh::Points* p :
       {&state->q, &state->vq, &state->good_q, &state->good_vq, &state->u, &state->v, &state->h,
        &state->rhs, &state->dv, &state->work, &state->springs}) {
    *p = mesh::Points::Zero(3, n);
  }
  state->anchor = rest_;
  state->fixed_now.assign(size_t(n), 0);
  state->fixed_prev.assign(size_t(n), 0);
  state->support.assign(size_t(n), 0.0);
  state->stiffness.assign(size_t(n), 0.0);
  state->cached_stiffness.assign(size_t(n), 0.0);
  state->cached_support.assign(size_t(n), 0.0);
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

int64_t EfgMssCoupledModel::Factorisations(const TissueState& state) const {
  return static_cast<const CoupledState&>(state).factorisations;
}

const mesh::Points& EfgMssCoupledModel::Unknowns(const TissueState& state) const {
  return static_cast<const CoupledState&>(state).q;
}

void EfgMssCoupledModel::MultiplyStiffness(const double* x, double* y) const {
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

void EfgMssCoupledModel::MultiplyG(const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  for (size_t i = 0; i < n; ++i) {
    Vector3d sum = Vector3d::Zero();
    for (auto k = size_t(g_start_[i]); k < size_t(g_start_[i + 1]); ++k) {
      sum += g_value_[k] * Eigen::Map<const Vector3d>(x + 3 * size_t(g_col_[k]));
    }
    Eigen::Map<Vector3d>(y + 3 * i) = sum;
  }
}

void EfgMssCoupledModel::MultiplyGTransposed(const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  std::fill(y, y + 3 * n, 0.0);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Map<const Vector3d> xi(x + 3 * i);
    for (auto k = size_t(g_start_[i]); k < size_t(g_start_[i + 1]); ++k) {
      Eigen::Map<Vector3d>(y + 3 * size_t(g_col_[k])) += g_value_[k] * xi;
    }
  }
}

void EfgMssCoupledModel::AssembleSystem(double k_scale, double m_scale, double s_scale,
                                        const double* s, double* blocks, double* values) const {
  const size_t num_blocks = block_row_.size();
  for (size_t b = 0; b < num_blocks; ++b) {
    Eigen::Map<Matrix3d> block(blocks + 9 * b);
    block = k_scale * Eigen::Map<const Matrix3d>(k_blocks_.data() + 9 * b);
    block.diagonal().array() += m_scale * m_blocks_[b];
  }
  const auto n = num_nodes();
  for (int32_t i = 0; i < n; ++i) {
    if (s[size_t(i)] == 0.0) continue;
    const int32_t begin = g_start_[size_t(i)], end = g_start_[size_t(i) + 1];
    for (int32_t b = begin; b < end; ++b) {
      for (int32_t a = b; a < end; ++a) {
        const int64_t slot = BlockIndex(g_col_[size_t(a)], g_col_[size_t(b)]);
        Eigen::Map<Matrix3d>(blocks + 9 * slot).diagonal().array() +=
            s_scale * s[size_t(i)] * g_value_[size_t(a)] * g_value_[size_t(b)];
      }
    }
  }
  for (size_t k = 0; k < csc_source_.size(); ++k) values[k] = blocks[size_t(csc_source_[k])];
}

Matrix3d EfgMssCoupledModel::LocalStiffness(const TissueState& base, int32_t node) const {
  const auto& st = static_cast<const CoupledState&>(base);
  if (!st.static_valid || node < 0 || node >= num_nodes()) return Matrix3d::Zero();
  double* cached = st.local_stiffness.data() + 9 * size_t(node);
  if (st.local_valid[size_t(node)] != 0) return Eigen::Map<const Matrix3d>(cached);
  // Column k of the compliance G_I K_s⁻¹ G_Iᵀ: a unit force along k at the node point.
  const int32_t begin = g_start_[size_t(node)], end = g_start_[size_t(node) + 1];
  Matrix3d compliance;
  for (int k = 0; k < 3; ++k) {
    for (int32_t a = begin; a < end; ++a) {
      st.local_rhs[3 * size_t(g_col_[size_t(a)]) + size_t(k)] = g_value_[size_t(a)];
    }
    st.static_factor->Solve(st.local_rhs.data(), st.local_solution.data());
    Vector3d sum = Vector3d::Zero();
    for (int32_t a = begin; a < end; ++a) {
      const auto j = 3 * size_t(g_col_[size_t(a)]);
      sum += g_value_[size_t(a)] * Eigen::Map<const Vector3d>(st.local_solution.data() + j);
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

// q = G⁻¹ (x - X) for a state's positions (3 × num_nodes), by G's LU.
mesh::Points UnknownsOf(const Eigen::SparseLU<Eigen::SparseMatrix<double>>& g,
                        const mesh::Points& positions, const mesh::Points& rest) {
  const Eigen::MatrixXd u = (positions - rest).transpose();  // num_nodes × 3
  const Eigen::MatrixXd q = g.solve(u);
  return q.transpose();
}

}  // namespace

double EfgMssCoupledModel::ElasticEnergyOfUnknowns(const mesh::Points& unknowns) const {
  mesh::Points k_q(3, num_nodes());
  MultiplyStiffness(unknowns.data(), k_q.data());
  return 0.5 * unknowns.cwiseProduct(k_q).sum();
}

void EfgMssCoupledModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  const mesh::Points q = UnknownsOf(factors_->g, state.positions, rest_);
  mesh::Points k_q(3, num_nodes());
  MultiplyStiffness(q.data(), k_q.data());
  // Gᵀ f = -K q: the node-point forces whose virtual work on δu = G δq is -δqᵀ K q.
  const Eigen::MatrixXd rhs = -k_q.transpose();
  const Eigen::MatrixXd f = factors_->g_transposed.solve(rhs);
  *forces = f.transpose();
}

EnergyReport EfgMssCoupledModel::Energy(const TissueState& state, const Vector3d& gravity) const {
  EnergyReport report;
  report.elastic = ElasticEnergyOfUnknowns(UnknownsOf(factors_->g, state.positions, rest_));
  AddKineticAndGravity(mass_, state, gravity, &report);
  return report;
}

void EfgMssCoupledModel::SolveStatic(const EfgStaticLoads& loads, TissueState* base) const {
  auto* st = static_cast<CoupledState*>(base);
  const int32_t n = num_nodes();
  CheckStaticLoads(loads, n, "efg-mss");
  if (loads.parameter_forces != nullptr) {
    throw std::invalid_argument("efg-mss: SolveStatic: parameter_forces is not supported");
  }
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
  MultiplyGTransposed(h.data(), rhs.data());

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
        "efg-mss: SolveStatic: K + penalties is not positive definite "
        "(too few held nodes to remove the rigid motions)");
  }
  cholesky.Solve(rhs.data(), solution.data());
  st->q = solution;
  st->vq.setZero();
  MultiplyG(st->q.data(), st->u.data());
  st->positions = rest_ + st->u;
  st->velocities.setZero();
}

bool EfgMssCoupledModel::PrepareFactors(double dt, TissueState* base) const {
  auto* st = static_cast<CoupledState*>(base);
  const double alpha = rayleigh_mass_, beta = rayleigh_stiffness_;
  if (!st->factor_valid || dt != st->cached_dt ||
      !std::equal(st->stiffness.begin(), st->stiffness.end(), st->cached_stiffness.begin())) {
    AssembleSystem(dt * dt + dt * beta, 1.0 + dt * alpha, dt * dt, st->stiffness.data(),
                   st->a_blocks.data(), st->system.values.data());
    st->factor_valid = st->factor->Factorise(st->system);
    ++st->factorisations;
    st->cached_dt = dt;
    std::copy(st->stiffness.begin(), st->stiffness.end(), st->cached_stiffness.begin());
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
  return true;
}

void EfgMssCoupledModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<CoupledState*>(base);
  const auto n = size_t(num_nodes());
  const double dt = inputs.dt;
  const double alpha = rayleigh_mass_, beta = rayleigh_stiffness_;

  // 1. Springs at the node points: the supports' and all springs' summed stiffness per node and
  // Σ k (target - X_I).
  GatherSupportSprings(inputs, rest_, penalty_, st);
  std::copy(st->support.begin(), st->support.end(), st->stiffness.begin());
  for (const Attachment& grasp : inputs.attachments) {
    st->stiffness[size_t(grasp.node)] += grasp.stiffness;
    st->springs.col(grasp.node) += grasp.stiffness * (grasp.target - rest_.col(grasp.node));
  }

  // 2. The factors (re-made only when dt or a node's spring stiffness changed).
  if (!PrepareFactors(dt, st)) {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
    return;
  }

  // 3. Physical displacements and velocities at the nodes.
  MultiplyG(st->q.data(), st->u.data());
  MultiplyG(st->vq.data(), st->v.data());

  // 4. Node-point forces h_I = f_ext + m_I (g - α v_I) + Σ k (t - X_I) - s_I (u_I + dt v_I).
  const mesh::Points* external = inputs.external_forces;
  for (size_t i = 0; i < n; ++i) {
    const auto c = static_cast<Eigen::Index>(i);
    Vector3d f = mass_[i] * (inputs.gravity - alpha * st->v.col(c)) + st->springs.col(c) -
                 st->stiffness[i] * (st->u.col(c) + dt * st->v.col(c));
    if (external != nullptr) f += external->col(c);
    st->h.col(c) = f;
  }
  // 5. b = dt (Gᵀ h - K (q + (β + dt) q̇)).
  st->work = st->q + (beta + dt) * st->vq;
  MultiplyStiffness(st->work.data(), st->dv.data());
  MultiplyGTransposed(st->h.data(), st->rhs.data());
  st->rhs = dt * (st->rhs - st->dv);

  // 6. Solve, update the unknowns, then the physical positions and velocities.
  st->factor->Solve(st->rhs.data(), st->dv.data());
  ++st->counters.solver_iterations;
  st->vq += st->dv;
  st->q += dt * st->vq;
  MultiplyG(st->q.data(), st->u.data());
  MultiplyG(st->vq.data(), st->velocities.data());
  st->positions = rest_ + st->u;
}

}  // namespace somasim::models::meshless
