// Finite elements on linear tetrahedra (SPEC §4.4, issue 5) behind the tissue-model interface:
// linear, corotational (Müller & Gross 2004) and total-Lagrangian hyperelastic models
// (hyperelastic.h), QLV viscoelasticity, implicit Euler dynamics (Step), Newton statics
// (SolveStatic) and cutting (ApplyCut). Pure kernel. The formulas: docs/models.md, "Finite
// elements".
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/block_sparse.h"
#include "server/models/fem/hyperelastic.h"
#include "server/models/fem/tet_elements.h"
#include "server/models/tissue_model.h"

namespace somasim::models::fem {

enum class FemKind {
  kLinear,        // small strain: valid for displacements and rotations well below 0.1 rad
  kCorotational,  // large rotation, small strain: the real-time workhorse
  kHyperelastic,  // total Lagrangian, large strain: FemParameters::hyperelastic (seed 000)
};

struct PronyTerm {
  double gamma = 0.0;  // γ_k [-]
  double tau = 1.0;    // τ_k [s]
};
inline constexpr size_t kMaxPronyTerms = 4;
// Seed 000 table 1 (Nava et al. 2008): γ1 = 0.5054, τ1 = 0.5784 s, γ2 = 0.1485, τ2 = 6.8863 s.
std::vector<PronyTerm> LiverNava2008Prony();
// One Prony term over a step dt [s]: decay = e^{-dt/τ}, β = (τ / dt)(1 - e^{-dt/τ}) (see
// ViscousStep).
void PronyFactors(const PronyTerm& term, double dt, double* decay, double* beta);

struct FemParameters {
  FemKind kind = FemKind::kCorotational;
  double youngs_modulus = 0.0;  // E [Pa], > 0 (linear and corotational)
  double poisson_ratio = 0.45;  // ν [-], in (-1, 0.5); soft tissue is nearly incompressible
  HyperelasticMaterial hyperelastic = LiverNava2008();  // kHyperelastic only
  double density = 1000.0;                              // ρ [kg/m³], > 0
  // Quasi-linear viscoelasticity (Fung; SPEC §4.4): G(t) = γ∞ + Σ_k γ_k e^{-t/τ_k}, G(0) = 1,
  // so γ∞ = 1 - Σ γ_k (>= 0); γ_k >= 0, τ_k > 0 [s]; at most kMaxPronyTerms. Empty: elastic.
  std::vector<PronyTerm> prony;
  double rayleigh_mass = 0.0;       // α [1/s], >= 0: C = α M + β K
  double rayleigh_stiffness = 0.0;  // β [s], >= 0
  // Step: CG stops at |r| <= cg_tolerance |b| or after cg_max_iterations (> 0).
  double cg_tolerance = 1e-6;
  int cg_max_iterations = 500;
  // Run exactly cg_max_iterations per step whatever the residual (a fixed budget per step, as
  // SOFA's CPU benchmark scene does with 20).
  bool cg_fixed_iterations = false;
  double speed_limit = 100.0;  // [m/s], > 0: a faster node marks a diverged step
};

// One time step's viscoelastic context (QLV in recursive form, Simo 1987): with the elastic
// stress S^e (hyperelastic: second Piola–Kirchhoff, P = F S; linear and corotational: the
// rotated-frame stress σ, P = R S) and the internal variables h_k of the last step,
//   S(t + dt) = g S^e(F) + offset,   g = γ∞ + Σ γ_k β_k,   β_k = (τ_k / dt)(1 - e^{-dt/τ_k}),
//   offset = Σ_k (e^{-dt/τ_k} h_k - γ_k β_k S^e_last),
// exact for a strain history linear over the step. Elastic: g = 1, no offset.
struct ViscousStep {
  double g = 1.0;
  const double* offset = nullptr;  // 9 × num_tets (3 × 3 column-major), or null
};

// One coordinate of one node held at a value (a symmetry plane, a roller): position(axis, node)
// = value [m] at full load.
struct ComponentConstraint {
  int32_t node = 0;
  int axis = 0;  // 0, 1, 2 = x, y, z
  double value = 0.0;
};

// What SolveStatic holds and loads. Fixed and prescribed nodes as in StepInputs.
struct StaticLoads {
  const mesh::Points* external_forces = nullptr;       // [N], 3 × num_nodes, or none
  Eigen::Vector3d gravity = Eigen::Vector3d::Zero();   // [m/s²]
  std::span<const int32_t> fixed_nodes;                // held at their rest positions
  std::span<const int32_t> prescribed_nodes;           // moved to prescribed_positions
  const mesh::Points* prescribed_positions = nullptr;  // [m], 3 × prescribed_nodes.size()
  std::span<const ComponentConstraint> components;     // single coordinates held or moved
  int load_steps = 1;                                  // > 0: loads applied in equal increments
  // Newton stops at |residual| <= tolerance × |load| (> 0), or when its correction is below
  // step_tolerance × |displacement| (>= 0): the displacement has converged to 9 digits, and
  // the residual of a slender, ill-conditioned structure may not fall further (|r| ~ ε cond(K)
  // |load|). The linear model's tangent is constant: it is factorised once.
  double tolerance = 1e-8;
  double step_tolerance = 1e-9;
  int max_newton_iterations = 50;
  // Modified Newton, for a sequence of nearby solves (a quasi-static time history): keep using
  // the last factorised tangent — from an earlier call with the same workspace and held DOFs
  // too — while its steps shrink the residual by reuse_ratio (in (0, 1)) or better, and
  // refactorise after a step that does not. An iteration then costs a solve with the old factor
  // instead of an assembly and a factorisation (far dearer than a solve: docs/benchmarks.md);
  // convergence is linear instead of quadratic, to the same tolerance. A state that is the one
  // the last call with the workspace left also starts from its positions extrapolated along
  // that call's change (load_steps = 1).
  bool reuse_factorisation = false;
  double reuse_ratio = 0.5;
};

struct StaticResult {
  bool converged = false;
  int newton_iterations = 0;    // summed over load steps
  int factorisations = 0;       // tangents factorised (fewer than iterations with reuse)
  double final_residual = 0.0;  // |r| / |load| at the end (free DOFs)
  // Newton's relative residual after each iteration of the last load step (to see quadratic
  // convergence).
  std::vector<double> residual_history;
  mesh::Points reactions;  // [N], 3 × num_nodes: force the supports exert (0 on free nodes)
};

// What repeated static solves of one model keep between calls (SolveStatic, SolveQuasiStatic,
// NewtonIteration): the free-DOF numbering, the tangent and its scalar lower triangle with the map
// between them, CHOLMOD's symbolic analysis (ordering and supernodes, redone only when the held
// DOFs change) and scratch vectors. Opaque; one per model and thread.
class StaticWorkspace {
 public:
  StaticWorkspace();
  ~StaticWorkspace();
  StaticWorkspace(const StaticWorkspace&) = delete;
  StaticWorkspace& operator=(const StaticWorkspace&) = delete;

 private:
  friend class FemModel;
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

class FemModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the bad parameter or mesh fault.
  static std::unique_ptr<FemModel> FromTetMesh(const mesh::TetMesh& mesh,
                                               const FemParameters& parameters);

  int32_t num_nodes() const override { return elements_.num_nodes(); }
  int32_t num_tets() const { return elements_.num_tets(); }
  FemKind kind() const { return kind_; }
  std::unique_ptr<TissueState> MakeState() const override;
  // The warped stiffness's diagonal block at `node` [N/m] (plus nothing else: grasps are the
  // contact issue's).
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;

  // Static equilibrium from the state's positions (rest for a fresh state): writes the
  // equilibrium positions into state->positions and zeroes the velocities. Allocates (a
  // factorisation per Newton iteration): not for the real-time path. Throws
  // std::invalid_argument on bad loads (sizes, indices, NaN).
  // With a workspace, what does not change between calls (the symbolic analysis of the
  // tangent's pattern, buffers) is reused: a sequence of solves (a time history) runs faster.
  StaticResult SolveStatic(const StaticLoads& loads, TissueState* state,
                           StaticWorkspace* workspace = nullptr) const;
  // Quasi-static viscoelastic evolution (no inertia): equilibrium at t + dt under `loads` (their
  // full values at t + dt; load_steps ramps within the step) with the state's QLV internal
  // variables, which are then advanced to t + dt. A creep or relaxation test is a sequence of
  // these. Allocates.
  StaticResult SolveQuasiStatic(const StaticLoads& loads, double dt, TissueState* state,
                                StaticWorkspace* workspace = nullptr) const;
  // One iteration of SolveStatic's Newton loop at full load (for benchmarks and tests): the held
  // DOFs are put at their values, then the residual, the tangent (assembled and factorised),
  // the Newton correction and the line search, exactly as SolveStatic does them. Returns the
  // relative residual after the iteration in final_residual (converged when it is below
  // loads.tolerance) and newton_iterations = 1; no reactions. Elastic (no QLV context).
  StaticResult NewtonIteration(const StaticLoads& loads, TissueState* state,
                               StaticWorkspace* workspace) const;
  // The exact tangent -∂f/∂x at x, Σ_e ElementTangent(x, e, true) (the matrix SolveStatic
  // factorises, before the held DOFs are taken out), into `matrix` (the model's pattern,
  // overwritten). Allocates nothing when `matrix` has the model's pattern already.
  void AssembleTangent(const mesh::Points& x, BlockSparseMatrix* matrix) const;
  const BlockSparseMatrix& pattern() const { return pattern_; }
  // For tests: a linear or corotational Step takes its portable element pass even where the
  // AVX-512 one is available (equal up to rounding). Set it before stepping.
  void set_force_scalar_element_pass(bool scalar) { force_scalar_element_pass_ = scalar; }

  // The element tangent -∂f_e/∂x_e (12 × 12, corners a = 0..3 × xyz) of element e at positions
  // x: exact (with the derivative of R) or warped (R K_e Rᵀ; the hyperelastic model has only
  // the exact one). For tests and the static solver.
  Eigen::Matrix<double, 12, 12> ElementTangent(const mesh::Points& x, int32_t e, bool exact,
                                               const ViscousStep* viscous = nullptr) const;
  size_t num_prony_terms() const { return prony_.size(); }

  // Cutting (SPEC §5.3, seed 003; cutting::TetCutter decides what is cut, the server's session
  // calls this after each blade step). The cut is part of the state — its own copy of the rest
  // geometry (rest positions, shape-function gradients, volumes), made by MakeState — so the
  // model stays read-only and a snapshot carries the cut; a rejected step does not undo it.
  //  - `removed` elements (each in [0, num_tets), alive) leave the assembly: their volume in the
  //    state becomes 0, so they add no force, stiffness or energy (masses stay: the lumped mass
  //    of the organ is conserved, as the vertices are);
  //  - `moved` nodes were relocated in state->positions from `positions_before` (3 × num_nodes,
  //    the positions the cutter started from). Their rest positions follow, pulled back through
  //    the mean deformation gradient F̄ of their alive elements (ΔX = F̄⁻¹ Δx, first order; Δx
  //    itself where F̄ is near singular), so the relocation adds no strain; a rest move that
  //    would take an alive element below 5 % of its original rest volume is halved (up to 8
  //    times, then dropped), so no element is ever inverted at rest. The alive elements around
  //    a moved node get their gradients and volumes from the new rest positions, and the
  //    rollback copy of the positions takes the relocated ones.
  // Allocates nothing. Throws std::invalid_argument (before changing anything) for an index out
  // of range, an element already removed, or positions of the wrong size or not finite.
  void ApplyCut(std::span<const int32_t> removed, std::span<const int32_t> moved,
                const mesh::Points& positions_before, TissueState* state) const;
  // Whether element e is still in the state's assembly (not cut away).
  bool ElementAlive(const TissueState& state, int32_t e) const;
  // The state's rest positions [m] (3 × num_nodes): the model's until a cut relocates nodes.
  const mesh::Points& RestPositions(const TissueState& state) const;

  // The relative residual |b - A Δv| / |b| CG reached in the state's last step.
  double LastSolverResidual(const TissueState& state) const;

  const std::vector<double>& masses() const { return mass_; }  // [kg], num_nodes
  const mesh::Points& rest_positions() const { return rest_; }
  const TetElements& elements() const { return elements_; }
  const HyperelasticMaterial& material() const { return material_; }  // kHyperelastic
  const std::vector<PronyTerm>& prony() const { return prony_; }
  double lambda() const { return lambda_; }  // [Pa]
  double mu() const { return mu_; }          // [Pa]

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;

 private:
  FemModel() = default;
  // The rest geometry a computation uses: the model's (ModelShape), or a state's (ShapeOf: a
  // cut state's own copy). Topology (tets, node lists) is always the model's.
  struct Shape {
    const mesh::Points& rest;                                   // 3 × num_nodes [m]
    const Eigen::Matrix<double, 3, Eigen::Dynamic>& gradients;  // 3 × 4·num_tets [1/m]
    const std::vector<double>& volumes;                         // num_tets [m³], 0 = cut away
    const mesh::Tetrahedra& tets;
  };
  Shape ModelShape() const {
    return {rest_, elements_.gradients, elements_.volumes, elements_.tets};
  }
  Shape ShapeOf(const TissueState& state) const;
  static Eigen::Matrix3d DisplacementGradientOf(const Shape& sh, const mesh::Points& x, int32_t e);
  Eigen::Matrix<double, 12, 12> ElementTangentOf(const Shape& sh, const mesh::Points& x, int32_t e,
                                                 bool exact,
                                                 const ViscousStep* viscous = nullptr) const;
  // Element e's rotation at x (identity for the linear and hyperelastic models), its strain ε
  // (symmetric; zero for the hyperelastic model, whose callers do not need it) and the first
  // Piola–Kirchhoff stress P [Pa]. The corotational rotation is PolarRotationFrom's from the
  // identity.
  void ElementStress(const Shape& sh, const mesh::Points& x, int32_t e, Eigen::Matrix3d* rotation,
                     Eigen::Matrix3d* strain, Eigen::Matrix3d* stress,
                     const ViscousStep* viscous = nullptr) const;
  // forces (3 × num_nodes) = elastic forces at x; also stores the element rotations (9 ×
  // num_tets) when `rotations` is given.
  void ElasticForces(const Shape& sh, const mesh::Points& x, double* forces, double* rotations,
                     const ViscousStep* viscous = nullptr) const;
  // The elastic energy at x; with a viscous context, the potential whose gradient is the
  // viscous step's forces (hyperelastic: Σ V (g W + offset : E)).
  double ElasticEnergy(const Shape& sh, const mesh::Points& x, const ViscousStep* viscous) const;
  // The elastic stress S^e of element e at x (see ViscousStep), 3 × 3.
  Eigen::Matrix3d ElasticStress(const Shape& sh, const mesh::Points& x, int32_t e) const;
  // The viscous context for a step of dt from the state's internal variables (into `offset`,
  // 9 × num_tets), and the update of the internal variables once the step is accepted.
  ViscousStep BeginViscousStep(const TissueState& state, double dt, double* offset) const;
  void EndViscousStep(double dt, TissueState* state) const;
  // SolveStatic, SolveQuasiStatic (with a viscous context) and NewtonIteration (single_iteration)
  // run one StaticSolve (fem_statics.cc).
  class StaticSolve;
  StaticResult SolveStaticImpl(const StaticLoads& loads, TissueState* state,
                               const ViscousStep* viscous, StaticWorkspace* workspace,
                               bool single_iteration) const;
  // Assembles Σ_e R_e K_e R_eᵀ (rotations 9 × num_tets, or identity for the linear model; the
  // exact tangent at x for the hyperelastic one) scaled by `scale` into `matrix` (zeroed
  // first), then adds mass_scale · M on the diagonal.
  void AssembleWarped(const Shape& sh, const mesh::Points& x, const double* rotations, double scale,
                      double mass_scale, BlockSparseMatrix* matrix,
                      const ViscousStep* viscous = nullptr) const;
  // Σ_e ElementTangent(x, e, exact, viscous) into `matrix` (zeroed first).
  void AssembleElementTangents(const Shape& sh, const mesh::Points& x, bool exact,
                               const ViscousStep* viscous, BlockSparseMatrix* matrix) const;
  // Linear and corotational Step: ElasticForces and AssembleWarped fused into one pass over the
  // elements (equal up to rounding), each rotation warm-started from `quaternions` (4 × num_tets:
  // the last step's, updated). With AVX-512 the corotational kind does F, R, forces and blocks
  // of eight elements at a time in that one pass; otherwise the rotations are decomposed first
  // in batches (PolarRotations).
  void ForcesAndWarpedMatrix(const Shape& sh, const mesh::Points& x, double* forces,
                             double* rotations, double* quaternions, const ViscousStep* viscous,
                             double k_scale, double m_scale, BlockSparseMatrix* matrix) const;
  // The undeformed element stiffness block K_ab = V (λ ∇N_a ∇N_bᵀ + μ ∇N_b ∇N_aᵀ + μ ∇N_a·∇N_b I).
  Eigen::Matrix3d RestBlock(const Shape& sh, int32_t e, int a, int b) const;

  mesh::Points rest_;  // [m], 3 × num_nodes
  TetElements elements_;
  BlockSparseMatrix pattern_;  // the stiffness pattern (values unused)
  // Its upper blocks only: a linear or corotational Step's matrix (symmetric: warped K, M).
  BlockSparseMatrix upper_pattern_;
  std::vector<double> mass_;  // [kg]
  FemKind kind_ = FemKind::kCorotational;
  HyperelasticMaterial material_;
  std::vector<PronyTerm> prony_;
  double lambda_ = 0.0, mu_ = 0.0;  // Lamé [Pa]
  double rayleigh_mass_ = 0.0, rayleigh_stiffness_ = 0.0;
  double cg_tolerance_ = 1e-6;
  int cg_max_iterations_ = 500;
  bool cg_fixed_iterations_ = false;
  bool force_scalar_element_pass_ = false;
};

}  // namespace somasim::models::fem
