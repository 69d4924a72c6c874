#include "server/models/meshless/efg_system.h"

#include <Eigen/LU>
#include <algorithm>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "server/models/meshless/efg_shared.h"

namespace somasim::models::meshless {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

// σ [1/s²]: the mass shift of the static K_s when a cut has severed an unsupported piece (the
// held piece's stiffness changes by σ/ω² of its own, ~1 % for a liver).
constexpr double kSeveredShift = 1.0;

}  // namespace

LumpedTetMesh CheckAndLumpTetMesh(const mesh::TetMesh& mesh, double density,
                                  const std::string& prefix) {
  const auto refuse = [&prefix](const std::string& what) {
    throw std::invalid_argument(prefix + what);
  };
  const auto n = static_cast<int32_t>(mesh.vertices.cols());
  const auto num_tets = static_cast<int32_t>(mesh.tetrahedra.cols());
  if (n == 0 || num_tets == 0) refuse("mesh: empty (no nodes or no tetrahedra)");
  for (int32_t i = 0; i < n; ++i) {
    if (!mesh.vertices.col(i).allFinite()) {
      refuse("mesh: vertex " + std::to_string(i) + " has a non-finite coordinate");
    }
  }
  LumpedTetMesh out;
  out.volume.resize(static_cast<size_t>(num_tets));
  out.mass.assign(size_t(n), 0.0);
  for (int32_t t = 0; t < num_tets; ++t) {
    for (int a = 0; a < 4; ++a) {
      const int32_t i = mesh.tetrahedra(a, t);
      if (i < 0 || i >= n) {
        refuse("mesh: tetrahedron " + std::to_string(t) + " has node index " + std::to_string(i) +
               " out of range");
      }
    }
    const auto x = [&](int a) { return mesh.vertices.col(mesh.tetrahedra(a, t)); };
    const double v = (x(1) - x(0)).dot((x(2) - x(0)).cross(x(3) - x(0))) / 6.0;
    const double scale =
        std::max({(x(1) - x(0)).norm(), (x(2) - x(0)).norm(), (x(3) - x(0)).norm()});
    if (!(v > 1e-12 * scale * scale * scale)) {
      refuse("mesh: tetrahedron " + std::to_string(t) + " is flat or inverted (volume " +
             std::to_string(v) + " m^3)");
    }
    out.volume[size_t(t)] = v;
    for (int a = 0; a < 4; ++a) out.mass[size_t(mesh.tetrahedra(a, t))] += density * v / 4.0;
  }
  for (int32_t i = 0; i < n; ++i) {
    if (!(out.mass[size_t(i)] > 0.0)) {
      refuse("mesh: node " + std::to_string(i) + " belongs to no tetrahedron");
    }
  }
  return out;
}

void LowerBlockPattern(int32_t n, const std::vector<int64_t>& start,
                       const std::vector<int32_t>& nodes, std::vector<int64_t>* block_start,
                       std::vector<int32_t>* block_row) {
  // The points of each node (CSR), then per column c every node >= c sharing one with c.
  const size_t num_points = start.size() - 1;
  std::vector<int64_t> of_node_start(size_t(n) + 1, 0);
  for (const int32_t j : nodes) ++of_node_start[size_t(j) + 1];
  for (size_t j = 1; j <= size_t(n); ++j) of_node_start[j] += of_node_start[j - 1];
  std::vector<int64_t> fill(of_node_start.begin(), of_node_start.end() - 1);
  std::vector<int32_t> points_of_node(nodes.size());
  for (size_t p = 0; p < num_points; ++p) {
    for (int64_t k = start[p]; k < start[p + 1]; ++k) {
      points_of_node[size_t(fill[size_t(nodes[size_t(k)])]++)] = static_cast<int32_t>(p);
    }
  }
  std::vector<int32_t> mark(size_t(n), -1), column;
  block_start->assign(size_t(n) + 1, 0);
  block_row->clear();
  for (int32_t c = 0; c < n; ++c) {
    column.clear();
    for (int64_t k = of_node_start[size_t(c)]; k < of_node_start[size_t(c) + 1]; ++k) {
      const auto p = size_t(points_of_node[size_t(k)]);
      for (int64_t q = start[p]; q < start[p + 1]; ++q) {
        const int32_t j = nodes[size_t(q)];
        if (j >= c && mark[size_t(j)] != c) {
          mark[size_t(j)] = c;
          column.push_back(j);
        }
      }
    }
    if (mark[size_t(c)] != c) column.push_back(c);  // a node in no point of its own
    std::sort(column.begin(), column.end());
    block_row->insert(block_row->end(), column.begin(), column.end());
    (*block_start)[size_t(c) + 1] = static_cast<int64_t>(block_row->size());
  }
}

std::unique_ptr<EfgSystem> NewEfgSystem(const mesh::TetMesh& mesh, std::vector<double> mass,
                                        const EfgParameters& parameters) {
  auto system = std::make_unique<EfgSystem>();
  system->rest = mesh.vertices;
  system->mass = std::move(mass);
  system->rayleigh_mass = parameters.rayleigh_mass;
  system->rayleigh_stiffness = parameters.rayleigh_stiffness;
  return system;
}

void EfgSystem::SizeBlocks() {
  const size_t blocks = block_row.size();
  k_blocks.assign(9 * blocks, 0.0);
  m_blocks.assign(blocks, 0.0);
}

void EfgSystem::AddGaussPoint(const MlsEvaluation& eval, double w, double lambda, double mu,
                              double* k_blocks_out) const {
  // K = Σ_gauss w |J| B_Jᵀ D B_K, block (J, K) = w (λ ∇φ_J ∇φ_Kᵀ + μ ∇φ_K ∇φ_Jᵀ
  //     + μ ∇φ_J·∇φ_K I) (the FEM rest block with ∇φ for ∇N).
  const size_t m = eval.nodes.size();
  for (size_t b = 0; b < m; ++b) {
    const int32_t col = eval.nodes[b];
    const Vector3d gb = eval.gradients.col(static_cast<Eigen::Index>(b));
    int64_t slot = block_start[size_t(col)];
    for (size_t a = b; a < m; ++a) {
      const int32_t row = eval.nodes[a];
      while (block_row[size_t(slot)] != row) ++slot;  // both sorted
      const Vector3d ga = eval.gradients.col(static_cast<Eigen::Index>(a));
      Eigen::Map<Matrix3d> block(k_blocks_out + 9 * slot);
      block.noalias() += w * (lambda * ga * gb.transpose() + mu * gb * ga.transpose());
      block.diagonal().array() += w * mu * ga.dot(gb);
    }
  }
}

void EfgSystem::Finish(double penalty_factor, const std::string& prefix) {
  // M̂ = Rᵀ diag(m) R.
  const int32_t n = num_nodes();
  for (int32_t i = 0; i < n; ++i) {
    const int32_t begin = row_start[size_t(i)], end = row_start[size_t(i) + 1];
    for (int32_t b = begin; b < end; ++b) {
      int64_t slot = block_start[size_t(row_col[size_t(b)])];
      for (int32_t a = b; a < end; ++a) {
        while (block_row[size_t(slot)] != row_col[size_t(a)]) ++slot;
        m_blocks[size_t(slot)] += mass[size_t(i)] * row_value[size_t(a)] * row_value[size_t(b)];
      }
    }
  }
  penalty = penalty_factor * MaxBlockDiagonal(block_start, k_blocks);
  ScalarLowerPattern(block_start, block_row, &csc_col_start, &csc_rows, &csc_source);
  if (!FactorNodeValueMatrix(row_start, row_col, row_value, &lu, &lu_transposed)) {
    throw std::invalid_argument(
        prefix + "the node-value matrix Φ (φ_J(X_I)) is singular: nodes too close together?");
  }
}

int64_t EfgSystem::BlockIndex(int32_t row, int32_t col) const {
  const auto begin = block_row.begin() + block_start[size_t(col)];
  const auto end = block_row.begin() + block_start[size_t(col) + 1];
  const auto it = std::lower_bound(begin, end, row);
  return it != end && *it == row ? static_cast<int64_t>(it - block_row.begin()) : -1;
}

void EfgSystem::MultiplyStiffness(const EfgValues& values, const double* x, double* y) const {
  // By the symmetric lower block storage: each off-diagonal block acts twice.
  const double* k = values.k;
  const auto n = size_t(num_nodes());
  std::fill(y, y + 3 * n, 0.0);
  for (size_t c = 0; c < n; ++c) {
    const Eigen::Map<const Vector3d> xc(x + 3 * c);
    Eigen::Map<Vector3d> yc(y + 3 * c);
    const auto begin = size_t(block_start[c]), end = size_t(block_start[c + 1]);
    yc.noalias() += Eigen::Map<const Matrix3d>(k + 9 * begin) * xc;  // diagonal
    for (size_t slot = begin + 1; slot < end; ++slot) {
      const auto r = size_t(block_row[slot]);
      const Eigen::Map<const Matrix3d> block(k + 9 * slot);
      Eigen::Map<Vector3d>(y + 3 * r).noalias() += block * xc;
      yc.noalias() += block.transpose() * Eigen::Map<const Vector3d>(x + 3 * r);
    }
  }
}

void EfgSystem::MultiplyRows(const EfgValues& values, const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  const double* value = values.rows;
  for (size_t i = 0; i < n; ++i) {
    Vector3d sum = Vector3d::Zero();
    for (auto k = size_t(row_start[i]); k < size_t(row_start[i + 1]); ++k) {
      sum += value[k] * Eigen::Map<const Vector3d>(x + 3 * size_t(row_col[k]));
    }
    Eigen::Map<Vector3d>(y + 3 * i) = sum;
  }
}

void EfgSystem::MultiplyRowsTransposed(const EfgValues& values, const double* x, double* y) const {
  const auto n = size_t(num_nodes());
  const double* value = values.rows;
  std::fill(y, y + 3 * n, 0.0);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Map<const Vector3d> xi(x + 3 * i);
    for (auto k = size_t(row_start[i]); k < size_t(row_start[i + 1]); ++k) {
      Eigen::Map<Vector3d>(y + 3 * size_t(row_col[k])) += value[k] * xi;
    }
  }
}

void EfgSystem::AssembleSystem(const EfgValues& values, double k_scale, double m_scale,
                               double s_scale, const double* s, double* blocks,
                               double* csc_values) const {
  // Blocks first (k_scale K + m_scale M̂ + s_scale Σ s_I R_Iᵀ R_I), then gathered into the
  // scalar CSC.
  const size_t num_blocks = block_row.size();
  for (size_t b = 0; b < num_blocks; ++b) {
    Eigen::Map<Matrix3d> block(blocks + 9 * b);
    block = k_scale * Eigen::Map<const Matrix3d>(values.k + 9 * b);
    block.diagonal().array() += m_scale * values.m[b];
  }
  const int32_t n = num_nodes();
  const double* value = values.rows;
  for (int32_t i = 0; i < n; ++i) {
    if (s[size_t(i)] == 0.0) continue;
    const int32_t begin = row_start[size_t(i)], end = row_start[size_t(i) + 1];
    for (int32_t b = begin; b < end; ++b) {
      for (int32_t a = b; a < end; ++a) {
        const int64_t slot = BlockIndex(row_col[size_t(a)], row_col[size_t(b)]);
        Eigen::Map<Matrix3d>(blocks + 9 * slot).diagonal().array() +=
            s_scale * s[size_t(i)] * value[size_t(a)] * value[size_t(b)];
      }
    }
  }
  for (size_t k = 0; k < csc_source.size(); ++k) csc_values[k] = blocks[size_t(csc_source[k])];
}

double EfgSystem::ElasticEnergy(const EfgValues& values, const mesh::Points& q) const {
  mesh::Points k_q(3, num_nodes());
  MultiplyStiffness(values, q.data(), k_q.data());
  return 0.5 * q.cwiseProduct(k_q).sum();
}

void EfgSystem::SizeState(EfgSystemState* st) const {
  const Eigen::Index n = num_nodes();
  for (mesh::Points* p : {&st->params, &st->vparams, &st->good_params, &st->good_vparams, &st->u,
                          &st->v, &st->h, &st->rhs, &st->dv, &st->work, &st->springs}) {
    *p = mesh::Points::Zero(3, n);
  }
  st->anchor = rest;
  st->fixed_now.assign(size_t(n), 0);
  st->fixed_prev.assign(size_t(n), 0);
  st->support.assign(size_t(n), 0.0);
  st->stiffness.assign(size_t(n), 0.0);
  st->cached_stiffness.assign(size_t(n), 0.0);
  st->cached_support.assign(size_t(n), 0.0);
  st->a_blocks.assign(k_blocks.size(), 0.0);
  st->system.size = 3 * static_cast<int32_t>(n);
  st->system.col_start = csc_col_start;
  st->system.rows = csc_rows;
  st->system.values.assign(csc_rows.size(), 0.0);
  st->factor = std::make_unique<fem::SparseCholesky>();
  st->factor->Analyse(st->system);
  st->static_factor = std::make_unique<fem::SparseCholesky>();
  st->static_factor->Analyse(st->system);
  st->local_rhs.assign(3 * size_t(n), 0.0);
  st->local_solution.assign(3 * size_t(n), 0.0);
  st->local_stiffness.assign(9 * size_t(n), 0.0);
  st->local_valid.assign(size_t(n), 0);
}

bool EfgSystem::UpdateStepFactor(const EfgValues& values, double dt, const std::vector<double>& s,
                                 EfgSystemState* st) const {
  if (st->factor_valid && dt == st->cached_dt &&
      std::equal(s.begin(), s.end(), st->cached_stiffness.begin())) {
    return false;
  }
  const double alpha = rayleigh_mass, beta = rayleigh_stiffness;
  AssembleSystem(values, dt * dt + dt * beta, 1.0 + dt * alpha, dt * dt, s.data(),
                 st->a_blocks.data(), st->system.values.data());
  st->factor_valid = st->factor->Factorise(st->system);
  ++st->factorisations;
  st->cached_dt = dt;
  std::copy(s.begin(), s.end(), st->cached_stiffness.begin());
  return true;
}

void EfgSystem::UpdateStaticFactor(const EfgValues& values, bool shift_if_singular,
                                   EfgSystemState* st) const {
  if (st->static_current &&
      std::equal(st->support.begin(), st->support.end(), st->cached_support.begin())) {
    return;
  }
  st->static_valid = false;
  if (std::any_of(st->support.begin(), st->support.end(), [](double s) { return s > 0; })) {
    AssembleSystem(values, 1.0, 0.0, 1.0, st->support.data(), st->a_blocks.data(),
                   st->system.values.data());
    st->static_valid = st->static_factor->Factorise(st->system);
    ++st->factorisations;
    if (!st->static_valid && shift_if_singular) {
      AssembleSystem(values, 1.0, kSeveredShift, 1.0, st->support.data(), st->a_blocks.data(),
                     st->system.values.data());
      st->static_valid = st->static_factor->Factorise(st->system);
      ++st->factorisations;
    }
  }
  st->static_current = true;
  std::copy(st->support.begin(), st->support.end(), st->cached_support.begin());
  std::fill(st->local_valid.begin(), st->local_valid.end(), uint8_t{0});
}

void EfgSystem::StepRightHandSide(const EfgValues& values, const StepInputs& inputs,
                                  EfgSystemState* st) const {
  const auto n = size_t(num_nodes());
  const double dt = inputs.dt;
  const double alpha = rayleigh_mass, beta = rayleigh_stiffness;
  // Physical displacements and velocities at the nodes.
  MultiplyRows(values, st->params.data(), st->u.data());
  MultiplyRows(values, st->vparams.data(), st->v.data());
  // Node-point forces h_I = f_ext + m_I (g - α v_I) + Σ k (t - X_I) - s_I (u_I + dt v_I).
  const mesh::Points* external = inputs.external_forces;
  for (size_t i = 0; i < n; ++i) {
    const auto c = static_cast<Eigen::Index>(i);
    Vector3d f = mass[i] * (inputs.gravity - alpha * st->v.col(c)) + st->springs.col(c) -
                 st->stiffness[i] * (st->u.col(c) + dt * st->v.col(c));
    if (external != nullptr) f += external->col(c);
    st->h.col(c) = f;
  }
  // b = dt (Rᵀ h - K (q + (β + dt) q̇)).
  st->work = st->params + (beta + dt) * st->vparams;
  MultiplyStiffness(values, st->work.data(), st->dv.data());
  MultiplyRowsTransposed(values, st->h.data(), st->rhs.data());
  st->rhs = dt * (st->rhs - st->dv);
}

void EfgSystem::ApplyVelocityChange(const EfgValues& values, double dt, EfgSystemState* st) const {
  ++st->counters.solver_iterations;
  st->vparams += st->dv;
  st->params += dt * st->vparams;
  MultiplyRows(values, st->params.data(), st->u.data());
  MultiplyRows(values, st->vparams.data(), st->velocities.data());
  st->positions = rest + st->u;
}

Matrix3d EfgSystem::LocalStiffness(const EfgValues& values, const EfgSystemState& st,
                                   int32_t node) const {
  if (!st.static_valid || node < 0 || node >= num_nodes()) return Matrix3d::Zero();
  double* cached = st.local_stiffness.data() + 9 * size_t(node);
  if (st.local_valid[size_t(node)] != 0) return Eigen::Map<const Matrix3d>(cached);
  // Column k of the compliance R_I K_s⁻¹ R_Iᵀ: a unit force along k at the node point.
  const double* value = values.rows;
  const int32_t begin = row_start[size_t(node)], end = row_start[size_t(node) + 1];
  Matrix3d compliance;
  for (int k = 0; k < 3; ++k) {
    for (int32_t a = begin; a < end; ++a) {
      st.local_rhs[3 * size_t(row_col[size_t(a)]) + size_t(k)] = value[size_t(a)];
    }
    st.static_factor->Solve(st.local_rhs.data(), st.local_solution.data());
    Vector3d sum = Vector3d::Zero();
    for (int32_t a = begin; a < end; ++a) {
      const auto j = 3 * size_t(row_col[size_t(a)]);
      sum += value[size_t(a)] * Eigen::Map<const Vector3d>(st.local_solution.data() + j);
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

void EfgSystem::SolveStatic(const EfgValues& values, const EfgStaticLoads& loads,
                            const std::string& model, EfgSystemState* st) const {
  const int32_t n = num_nodes();
  // Penalty springs κ: fixed at rest (target displacement 0), prescribed at their positions.
  std::vector<double> s(size_t(n), 0.0);
  mesh::Points h = mesh::Points::Zero(3, n);
  AddStaticSupports(loads, rest, penalty, &s, &h);
  for (int32_t i = 0; i < n; ++i) h.col(i) += mass[size_t(i)] * loads.gravity;
  if (loads.external_forces != nullptr) h += *loads.external_forces;
  mesh::Points rhs(3, n), solution(3, n);
  MultiplyRowsTransposed(values, h.data(), rhs.data());
  if (loads.parameter_forces != nullptr) rhs += *loads.parameter_forces;

  fem::LowerCsc system;
  system.size = 3 * n;
  system.col_start = csc_col_start;
  system.rows = csc_rows;
  system.values.assign(csc_rows.size(), 0.0);
  std::vector<double> blocks(k_blocks.size());
  AssembleSystem(values, 1.0, 0.0, 1.0, s.data(), blocks.data(), system.values.data());
  fem::SparseCholesky cholesky;
  cholesky.Analyse(system);
  if (!cholesky.Factorise(system)) {
    throw std::runtime_error(model +
                             ": SolveStatic: K + penalties is not positive definite "
                             "(too few held nodes to remove the rigid motions)");
  }
  cholesky.Solve(rhs.data(), solution.data());
  st->params = solution;
  st->vparams.setZero();
  MultiplyRows(values, st->params.data(), st->u.data());
  st->positions = rest + st->u;
  st->velocities.setZero();
}

}  // namespace somasim::models::meshless
