// The linear system EfgModel and EfgMssCoupledModel share: node I moves by u_I = R_I q (R = Φ,
// or the coupled model's G), K and M̂ on one lower block pattern, and the kernels of their
// implicit Euler step, static solve and condensed stiffness (docs/models.md, "Element-free
// Galerkin"). Internal to the meshless models. Pure: no I/O.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <Eigen/SparseLU>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/sparse_cholesky.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/meshless/mls.h"
#include "server/models/tissue_model.h"

namespace somasim::models::meshless {

// The values the kernels read: the system's own, or a cut's (EfgCutValues), on its patterns.
struct EfgValues {
  const double* rows;  // R's entries on its pattern
  const double* k;     // K's blocks, 9 × blocks
  const double* m;     // M̂'s coefficients, blocks
};

// The state an EfgSystem steps: its unknowns (the truth; positions are derived), the caches of
// the step's and the static factorisation, and every buffer a step needs, sized by SizeState.
class EfgSystemState : public TissueState {
 public:
  mesh::Points params, vparams;            // q [m], q̇ [m/s] (the EFG's û, v̂), 3 × num_nodes
  mesh::Points good_params, good_vparams;  // the last accepted step's
  mesh::Points u, v, h, rhs, dv, work;     // scratch, 3 × num_nodes
  mesh::Points springs;                    // Σ k (target - X) per node [N], 3 × num_nodes
  mesh::Points anchor;                     // [m] where each fixed node is held
  std::vector<uint8_t> fixed_now, fixed_prev;  // num_nodes
  std::vector<double> support;                 // the supports' s_I [N/m], num_nodes: this step's
  std::vector<double> stiffness;               // all springs' s_I [N/m], num_nodes: this step's
  std::vector<double> cached_stiffness;        // the s_I the step's factor was made with, num_nodes
  std::vector<double> cached_support;          // the s_I the static factor was made with, num_nodes
  double cached_dt = 0.0;
  bool factor_valid = false;
  bool static_current = false;   // static_factor (or its absence) matches cached_support
  bool static_valid = false;     // static_factor holds K + P_s (P_s non-zero)
  int64_t factorisations = 0;    // numeric factorisations, both factors
  std::vector<double> a_blocks;  // 9 × blocks: a system's blocks before the scalar gather
  fem::LowerCsc system;          // the scalar lower pattern, values per factorisation
  std::unique_ptr<fem::SparseCholesky> factor, static_factor;
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

// The tetrahedra's volumes [m³] (num_tets, each positive) and lumped masses ρV/4 per corner
// [kg] (num_nodes, each positive) of a checked mesh.
struct LumpedTetMesh {
  std::vector<double> volume;
  std::vector<double> mass;
};
// Throws std::invalid_argument(prefix + the fault) for an empty mesh, a non-finite vertex, a
// node index out of range, a flat or inverted tetrahedron, a node in no tetrahedron.
LumpedTetMesh CheckAndLumpTetMesh(const mesh::TetMesh& mesh, double density,
                                  const std::string& prefix);

// Lamé's λ and μ [Pa] of Young's modulus E [Pa] and Poisson's ratio ν.
inline double LameLambda(double e, double nu) { return e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)); }
inline double LameMu(double e, double nu) { return e / (2.0 * (1.0 + nu)); }

// The lower block pattern of the node pairs that share a point (num_points lists of nodes:
// point p's are nodes[start[p] .. start[p+1])), and every diagonal: column c's blocks are
// block_row[block_start[c] .. block_start[c+1]), sorted, the diagonal first.
void LowerBlockPattern(int32_t num_nodes, const std::vector<int64_t>& start,
                       const std::vector<int32_t>& nodes, std::vector<int64_t>* block_start,
                       std::vector<int32_t>* block_row);

struct EfgSystem;
// A system on the mesh's nodes with their lumped masses [kg] (num_nodes) and the parameters'
// Rayleigh damping; R, the pattern and the blocks are the caller's to build.
std::unique_ptr<EfgSystem> NewEfgSystem(const mesh::TetMesh& mesh, std::vector<double> mass,
                                        const EfgParameters& parameters);

struct EfgSystem {
  mesh::Points rest;         // X [m], 3 × num_nodes
  std::vector<double> mass;  // m_I [kg], num_nodes
  // R by rows: node I's row is row_col/row_value[row_start[I] .. row_start[I+1]) (sorted
  // columns).
  std::vector<int32_t> row_start, row_col;
  std::vector<double> row_value;
  // The lower block pattern of K and the step's systems: column c's blocks are
  // block_row[block_start[c] .. block_start[c+1]) (sorted rows >= c, the diagonal first); K's
  // 3 × 3 blocks column-major at 9 × block index; M̂'s scalar coefficient (times I) per block.
  std::vector<int64_t> block_start;
  std::vector<int32_t> block_row;
  std::vector<double> k_blocks;  // [N/m], 9 × blocks
  std::vector<double> m_blocks;  // [kg], blocks
  // The scalar lower CSC pattern (3N columns) and, per scalar entry, its block index and place
  // in the block (b * 9 + r + 3 c).
  std::vector<int32_t> csc_col_start, csc_rows;
  std::vector<int64_t> csc_source;
  // R's LU factors and Rᵀ's (num_nodes × num_nodes): q = R⁻¹ u and f = R⁻ᵀ f̂, for the state
  // reports (Energy, InternalForces), not for the step.
  Eigen::SparseLU<Eigen::SparseMatrix<double>> lu, lu_transposed;
  double rayleigh_mass = 0.0;       // α [1/s]: C = α M̂ + β K
  double rayleigh_stiffness = 0.0;  // β [s]
  double penalty = 0.0;             // κ [N/m]: the supports' penalty springs

  int32_t num_nodes() const { return static_cast<int32_t>(rest.cols()); }
  EfgValues own_values() const { return {row_value.data(), k_blocks.data(), m_blocks.data()}; }

  // --- Construction, once rest, mass, R and the block pattern are set ---
  // Sizes K's and M̂'s blocks (zero).
  void SizeBlocks();
  // Adds a point's stiffness w Bᵀ D B to `k_blocks` (9 × blocks): its MLS evaluation with
  // gradients, weight w [m³] (rule weight × volume; negative to take the point out) and Lamé
  // λ, μ [Pa].
  void AddGaussPoint(const MlsEvaluation& eval, double w, double lambda, double mu,
                     double* k_blocks_out) const;
  // M̂ = Rᵀ diag(m) R into m_blocks, the penalty κ = penalty_factor × max diag K, the scalar
  // pattern and R's LU factors. Throws std::invalid_argument(prefix + ...) when R is singular.
  void Finish(double penalty_factor, const std::string& prefix);

  // --- Kernels (x, y: 3 × num_nodes flat) ---
  int64_t BlockIndex(int32_t row, int32_t col) const;  // -1 when not in the pattern
  void MultiplyStiffness(const EfgValues& values, const double* x, double* y) const;  // y = K x
  void MultiplyRows(const EfgValues& values, const double* x, double* y) const;       // y = R x
  void MultiplyRowsTransposed(const EfgValues& values, const double* x, double* y) const;
  // k_scale K + m_scale M̂ + s_scale Σ_I s_I R_Iᵀ R_I (s: num_nodes [N/m]) into `blocks`
  // (9 × blocks) and gathered into `csc_values` (the scalar lower pattern).
  void AssembleSystem(const EfgValues& values, double k_scale, double m_scale, double s_scale,
                      const double* s, double* blocks, double* csc_values) const;
  // ½ qᵀ K q [J] for unknowns q (3 × num_nodes). Allocates.
  double ElasticEnergy(const EfgValues& values, const mesh::Points& q) const;

  // --- A state's step ---
  // Sizes a state's buffers and analyses its factors' pattern (allocates: MakeState).
  void SizeState(EfgSystemState* st) const;
  // The step's factor of A = (1 + dt α) M̂ + (dt² + dt β) K + dt² Σ s_I R_Iᵀ R_I for the springs'
  // stiffness `s` (num_nodes), made again only when dt or s changed: true when it was (then
  // st->factor_valid says whether A was positive definite).
  bool UpdateStepFactor(const EfgValues& values, double dt, const std::vector<double>& s,
                        EfgSystemState* st) const;
  // The static factor of K_s = K + P_s for the state's supports, made again only when they
  // changed (none without supports). When K_s is singular and `shift_if_singular` (a cut
  // severed a piece the supports do not hold), K_s + σ M̂ with σ = 1 /s².
  void UpdateStaticFactor(const EfgValues& values, bool shift_if_singular,
                          EfgSystemState* st) const;
  // Steps 3–5 of the implicit Euler step: u, v at the nodes, the node-point forces
  // h_I = f_ext + m_I (g - α v_I) + Σ k (t - X_I) - s_I (u_I + dt v_I) and the right-hand side
  // rhs = dt (Rᵀ h - K (q + (β + dt) q̇)), from the state's springs and stiffness.
  void StepRightHandSide(const EfgValues& values, const StepInputs& inputs,
                         EfgSystemState* st) const;
  // The step's last part, with the velocity change Δq̇ in st->dv: q̇ += Δq̇, q += dt q̇, and the
  // positions and velocities at the nodes.
  void ApplyVelocityChange(const EfgValues& values, double dt, EfgSystemState* st) const;
  // (R_I K_s⁻¹ R_Iᵀ)⁻¹ [N/m] from the state's static factor, cached per node. Zero without it.
  Eigen::Matrix3d LocalStiffness(const EfgValues& values, const EfgSystemState& st,
                                 int32_t node) const;
  // Static equilibrium (K + P) q = Rᵀ h (+ the loads' parameter_forces) for loads already
  // checked (CheckStaticLoads): one factorisation and solve (allocates). Writes q, zero q̇ and
  // velocities, the positions. Throws std::runtime_error("<model>: SolveStatic: ...") when the
  // system is not positive definite.
  void SolveStatic(const EfgValues& values, const EfgStaticLoads& loads, const std::string& model,
                   EfgSystemState* st) const;
};

}  // namespace somasim::models::meshless
