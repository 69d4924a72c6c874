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
#include "server/models/meshless/efg_system.h"
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

// (column, coefficient) pairs of a node's G row.
using Row = std::vector<std::pair<int32_t, double>>;

}  // namespace

// FromTetMesh's stages and what they pass on.
struct EfgMssCoupledModel::Build {
  Build(const mesh::TetMesh& mesh, const EfgMssCoupledParameters& coupled,
        EfgMssCoupledModel* owner, std::vector<double> volumes)
      : tet_mesh(mesh),
        parameters(coupled),
        model(owner),
        system(*owner->system_),
        volume(std::move(volumes)) {}

  const mesh::TetMesh& tet_mesh;
  const EfgMssCoupledParameters& parameters;
  EfgMssCoupledModel* model;
  EfgSystem& system;
  std::vector<double> volume;  // [m³], num_tets
  std::vector<int32_t> meshless_tets, mss_tets;
  std::vector<int32_t> efg_nodes;            // E, increasing
  std::vector<int32_t> unknown_of_node;      // num_nodes
  std::unique_ptr<MlsShapeFunctions> shape;  // on E (sub-mesh indices = unknowns 0..|E|-1)
  std::vector<Row> spring_rows;              // G_b - G_a per spring (merged, sorted)

  int32_t num_nodes() const { return static_cast<int32_t>(tet_mesh.vertices.cols()); }
  Eigen::Vector3d GaussPoint(const TetRule& rule, int32_t t, size_t g) const {
    Vector3d p = Vector3d::Zero();
    for (int a = 0; a < 4; ++a)
      p += rule.points[g][a] * tet_mesh.vertices.col(tet_mesh.tetrahedra(a, t));
    return p;
  }

  // 1. The region's tetrahedra (a corner within the radius); its nodes E (increasing node
  // order: unknowns 0..|E|-1), the interface, the MSS-only nodes (the following unknowns).
  void SplitRegion() {
    const int32_t n = num_nodes();
    const auto num_tets = static_cast<int32_t>(tet_mesh.tetrahedra.cols());
    const double r2 = parameters.region_radius * parameters.region_radius;
    std::vector<uint8_t> in_meshless(size_t(n), 0), in_mss(size_t(n), 0);
    for (int32_t t = 0; t < num_tets; ++t) {
      bool meshless = false;
      for (int a = 0; a < 4; ++a) {
        const auto corner = tet_mesh.vertices.col(tet_mesh.tetrahedra(a, t));
        if ((corner - parameters.region_centre).squaredNorm() <= r2) meshless = true;
      }
      (meshless ? meshless_tets : mss_tets).push_back(t);
      for (int a = 0; a < 4; ++a) {
        (meshless ? in_meshless : in_mss)[size_t(tet_mesh.tetrahedra(a, t))] = 1;
      }
    }
    model->num_meshless_tets_ = static_cast<int32_t>(meshless_tets.size());
    model->efg_of_node_.assign(size_t(n), -1);
    unknown_of_node.assign(size_t(n), -1);
    for (int32_t i = 0; i < n; ++i) {
      if (in_meshless[size_t(i)] == 0) continue;
      model->efg_of_node_[size_t(i)] = static_cast<int32_t>(efg_nodes.size());
      unknown_of_node[size_t(i)] = static_cast<int32_t>(efg_nodes.size());
      efg_nodes.push_back(i);
      if (in_mss[size_t(i)] != 0) ++model->num_interface_;
    }
    const auto num_efg = static_cast<int32_t>(efg_nodes.size());
    model->num_efg_ = num_efg;
    const int32_t neighbours = parameters.efg.mls.support_neighbours;
    if (num_efg > 0 && num_efg <= neighbours) {
      Refuse("region_radius: the region holds " + std::to_string(num_efg) +
             " nodes; the EFG needs more than efg.mls.support_neighbours (" +
             std::to_string(neighbours) + ")");
    }
    int32_t next = num_efg;
    for (int32_t i = 0; i < n; ++i) {
      if (unknown_of_node[size_t(i)] < 0) unknown_of_node[size_t(i)] = next++;
    }
  }

  // 2. MLS on E (sub-mesh coordinates, supports of at least min_support_edge_factor × the
  // node's longest meshless edge) and G's rows: Φ_I for E, the unit row otherwise.
  void BuildRows() {
    const int32_t n = num_nodes();
    const auto num_efg = static_cast<int32_t>(efg_nodes.size());
    mesh::Points sub_nodes(3, num_efg);
    for (int32_t e = 0; e < num_efg; ++e)
      sub_nodes.col(e) = tet_mesh.vertices.col(efg_nodes[size_t(e)]);
    if (num_efg > 0) {
      std::vector<double> longest(size_t(num_efg), 0.0);
      for (const int32_t t : meshless_tets) {
        for (int a = 0; a < 4; ++a) {
          const auto e = size_t(model->efg_of_node_[size_t(tet_mesh.tetrahedra(a, t))]);
          for (int b = 0; b < 4; ++b) {
            longest[e] = std::max(longest[e], (tet_mesh.vertices.col(tet_mesh.tetrahedra(a, t)) -
                                               tet_mesh.vertices.col(tet_mesh.tetrahedra(b, t)))
                                                  .norm());
          }
        }
      }
      for (double& l : longest) l *= parameters.efg.min_support_edge_factor;
      shape = std::make_unique<MlsShapeFunctions>(sub_nodes, parameters.efg.mls, longest);
    }
    MlsEvaluation eval;
    system.row_start.assign(size_t(n) + 1, 0);
    for (int32_t i = 0; i < n; ++i) {
      if (model->efg_of_node_[size_t(i)] < 0) {
        system.row_col.push_back(unknown_of_node[size_t(i)]);
        system.row_value.push_back(1.0);
      } else {
        shape->Evaluate(tet_mesh.vertices.col(i), false, &eval);  // sorted sub indices
        system.row_col.insert(system.row_col.end(), eval.nodes.begin(), eval.nodes.end());
        system.row_value.insert(system.row_value.end(), eval.values.begin(), eval.values.end());
      }
      system.row_start[size_t(i) + 1] = static_cast<int32_t>(system.row_col.size());
    }
  }

  // 3. The springs: the MSS tetrahedra's unique edges, Van Gelder's k = E Σ V / |e|²
  // (MassSpringModel's rule), each with its coefficient row G_b - G_a (merged, sorted).
  void BuildSprings() {
    if (mss_tets.empty()) return;
    mesh::TetMesh mss;
    mss.vertices = tet_mesh.vertices;
    mss.tetrahedra.resize(4, static_cast<Eigen::Index>(mss_tets.size()));
    for (size_t k = 0; k < mss_tets.size(); ++k) {
      mss.tetrahedra.col(static_cast<Eigen::Index>(k)) = tet_mesh.tetrahedra.col(mss_tets[k]);
    }
    const MeshEdges edges = TetMeshEdges(mss, "efg-mss");
    const auto m = static_cast<Eigen::Index>(edges.edges.size());
    model->spring_dir_.resize(3, m);
    const auto row_of = [this](int32_t node, double sign, Row* row) {
      for (int32_t k = system.row_start[size_t(node)]; k < system.row_start[size_t(node) + 1];
           ++k) {
        row->emplace_back(system.row_col[size_t(k)], sign * system.row_value[size_t(k)]);
      }
    };
    for (Eigen::Index s = 0; s < m; ++s) {
      const auto [a, b] = edges.edges[size_t(s)];
      const Vector3d d = tet_mesh.vertices.col(b) - tet_mesh.vertices.col(a);
      const double length = d.norm();
      if (!(length > 0.0)) {
        Refuse("mesh: nodes " + std::to_string(a) + " and " + std::to_string(b) + " coincide");
      }
      model->spring_a_.push_back(a);
      model->spring_b_.push_back(b);
      model->spring_k_.push_back(parameters.efg.youngs_modulus * edges.edge_size[size_t(s)] /
                                 (length * length));
      model->spring_dir_.col(s) = d / length;
      Row row;
      row_of(b, 1.0, &row);
      row_of(a, -1.0, &row);
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

  // 4. The lower block pattern over the unknowns: every pair sharing a Gauss point, a node's G
  // row, or a spring's row; every diagonal.
  void BuildPattern(const TetRule& rule) {
    std::vector<int64_t> start{0};
    std::vector<int32_t> nodes;
    MlsEvaluation eval;
    for (const int32_t t : meshless_tets) {
      for (size_t g = 0; g < rule.points.size(); ++g) {
        shape->Evaluate(GaussPoint(rule, t, g), false, &eval);
        nodes.insert(nodes.end(), eval.nodes.begin(), eval.nodes.end());
        start.push_back(static_cast<int64_t>(nodes.size()));
      }
    }
    for (int32_t i = 0; i < num_nodes(); ++i) {
      nodes.insert(nodes.end(), system.row_col.begin() + system.row_start[size_t(i)],
                   system.row_col.begin() + system.row_start[size_t(i) + 1]);
      start.push_back(static_cast<int64_t>(nodes.size()));
    }
    for (const Row& row : spring_rows) {
      for (const auto& entry : row) nodes.push_back(entry.first);
      start.push_back(static_cast<int64_t>(nodes.size()));
    }
    LowerBlockPattern(num_nodes(), start, nodes, &system.block_start, &system.block_row);
  }

  // 5. K_E = Σ_gauss w |J| B_Jᵀ D B_K (the EFG's blocks), then the springs k c_J c_L e eᵀ.
  void BuildStiffness(const TetRule& rule) {
    system.SizeBlocks();
    const double lambda = LameLambda(parameters.efg.youngs_modulus, parameters.efg.poisson_ratio);
    const double mu = LameMu(parameters.efg.youngs_modulus, parameters.efg.poisson_ratio);
    MlsEvaluation eval;
    for (const int32_t t : meshless_tets) {
      for (size_t g = 0; g < rule.points.size(); ++g) {
        shape->Evaluate(GaussPoint(rule, t, g), true, &eval);
        const double w = rule.weights[g] * volume[size_t(t)];
        system.AddGaussPoint(eval, w, lambda, mu, system.k_blocks.data());
      }
    }
    for (size_t s = 0; s < spring_rows.size(); ++s) {
      const Vector3d e = model->spring_dir_.col(static_cast<Eigen::Index>(s));
      const Matrix3d kee = model->spring_k_[s] * e * e.transpose();
      const Row& row = spring_rows[s];
      for (size_t b = 0; b < row.size(); ++b) {
        int64_t slot = system.block_start[size_t(row[b].first)];
        for (size_t a = b; a < row.size(); ++a) {
          while (system.block_row[size_t(slot)] != row[a].first) ++slot;
          Eigen::Map<Matrix3d>(system.k_blocks.data() + 9 * slot) +=
              (row[a].second * row[b].second) * kee;
        }
      }
    }
  }
};

EfgMssCoupledModel::EfgMssCoupledModel() = default;
EfgMssCoupledModel::~EfgMssCoupledModel() = default;

std::unique_ptr<EfgMssCoupledModel> EfgMssCoupledModel::FromTetMesh(
    const mesh::TetMesh& mesh, const EfgMssCoupledParameters& parameters) {
  CheckParameters(parameters);
  const EfgParameters& efg = parameters.efg;
  LumpedTetMesh lumped = CheckAndLumpTetMesh(mesh, efg.density, "efg-mss: ");
  std::unique_ptr<EfgMssCoupledModel> model(new EfgMssCoupledModel());
  model->system_ = NewEfgSystem(mesh, std::move(lumped.mass), efg);
  model->set_speed_limit(efg.speed_limit);
  Build build(mesh, parameters, model.get(), std::move(lumped.volume));
  build.SplitRegion();
  build.BuildRows();
  build.BuildSprings();
  const TetRule rule = MakeTetRule(efg.gauss_points);
  model->num_gauss_ = static_cast<int64_t>(rule.points.size() * build.meshless_tets.size());
  build.BuildPattern(rule);
  build.BuildStiffness(rule);
  // M̂ = Gᵀ diag(m) G, the penalty, the scalar pattern and G's LU factors (q = G⁻¹ u).
  model->system_->Finish(efg.penalty_factor, "efg-mss: ");
  return model;
}

int32_t EfgMssCoupledModel::num_nodes() const { return system_->num_nodes(); }
const std::vector<double>& EfgMssCoupledModel::masses() const { return system_->mass; }
const mesh::Points& EfgMssCoupledModel::rest_positions() const { return system_->rest; }
double EfgMssCoupledModel::penalty() const { return system_->penalty; }
int64_t EfgMssCoupledModel::stiffness_blocks() const {
  return static_cast<int64_t>(system_->block_row.size());
}

std::unique_ptr<TissueState> EfgMssCoupledModel::MakeState() const {
  auto state = std::make_unique<EfgSystemState>();
  InitialiseState(system_->rest, state.get());
  system_->SizeState(state.get());
  return state;
}

int64_t EfgMssCoupledModel::Factorisations(const TissueState& state) const {
  return static_cast<const EfgSystemState&>(state).factorisations;
}

const mesh::Points& EfgMssCoupledModel::Unknowns(const TissueState& state) const {
  return static_cast<const EfgSystemState&>(state).params;
}

Matrix3d EfgMssCoupledModel::LocalStiffness(const TissueState& base, int32_t node) const {
  return system_->LocalStiffness(system_->own_values(), static_cast<const EfgSystemState&>(base),
                                 node);
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
  return system_->ElasticEnergy(system_->own_values(), unknowns);
}

void EfgMssCoupledModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  const mesh::Points q = UnknownsOf(system_->lu, state.positions, system_->rest);
  mesh::Points k_q(3, num_nodes());
  system_->MultiplyStiffness(system_->own_values(), q.data(), k_q.data());
  // Gᵀ f = -K q: the node-point forces whose virtual work on δu = G δq is -δqᵀ K q.
  const Eigen::MatrixXd rhs = -k_q.transpose();
  const Eigen::MatrixXd f = system_->lu_transposed.solve(rhs);
  *forces = f.transpose();
}

EnergyReport EfgMssCoupledModel::Energy(const TissueState& state, const Vector3d& gravity) const {
  EnergyReport report;
  report.elastic = ElasticEnergyOfUnknowns(UnknownsOf(system_->lu, state.positions, system_->rest));
  AddKineticAndGravity(system_->mass, state, gravity, &report);
  return report;
}

void EfgMssCoupledModel::SolveStatic(const EfgStaticLoads& loads, TissueState* base) const {
  CheckStaticLoads(loads, num_nodes(), "efg-mss");
  if (loads.parameter_forces != nullptr) {
    throw std::invalid_argument("efg-mss: SolveStatic: parameter_forces is not supported");
  }
  system_->SolveStatic(system_->own_values(), loads, "efg-mss", static_cast<EfgSystemState*>(base));
}

bool EfgMssCoupledModel::PrepareFactors(double dt, TissueState* base) const {
  auto* st = static_cast<EfgSystemState*>(base);
  const EfgValues values = system_->own_values();
  if (system_->UpdateStepFactor(values, dt, st->stiffness, st) && !st->factor_valid) {
    return false;  // cannot happen for a positive mass
  }
  // The static K_s = K + P_s for LocalStiffness (nothing holds a body without supports).
  system_->UpdateStaticFactor(values, false, st);
  return true;
}

void EfgMssCoupledModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* st = static_cast<EfgSystemState*>(base);
  const mesh::Points& rest = system_->rest;
  // 1. Springs at the node points: the supports' and all springs' summed stiffness per node and
  // Σ k (target - X_I).
  GatherSupportSprings(inputs, rest, system_->penalty, st);
  std::copy(st->support.begin(), st->support.end(), st->stiffness.begin());
  for (const Attachment& grasp : inputs.attachments) {
    st->stiffness[size_t(grasp.node)] += grasp.stiffness;
    st->springs.col(grasp.node) += grasp.stiffness * (grasp.target - rest.col(grasp.node));
  }
  // 2. The factors (re-made only when dt or a node's spring stiffness changed).
  if (!PrepareFactors(inputs.dt, st)) {
    st->positions.setConstant(std::numeric_limits<double>::quiet_NaN());  // marks it diverged
    return;
  }
  // 3–5. The node-point loads and the right-hand side b = dt (Gᵀ h - K (q + (β + dt) q̇)).
  const EfgValues values = system_->own_values();
  system_->StepRightHandSide(values, inputs, st);
  // 6. Solve, update the unknowns, then the physical positions and velocities.
  st->factor->Solve(st->rhs.data(), st->dv.data());
  system_->ApplyVelocityChange(values, inputs.dt, st);
}

}  // namespace somasim::models::meshless
