// The nonlinear reduced model that beats seed 000's (issue 12, SPEC §4.5; docs/reduced.md): the
// displacement is U = B ξ on modes B (3N × n) as in seed 000, but instead of one linear reduced
// stiffness it solves the Galerkin projection of the full hyperelastic–viscoelastic equilibrium
//   r(ξ) = Bᵀ f_ext + Bᵀ f_int(X + B ξ) = 0,
// with the reduced internal force and tangent evaluated by energy-conserving sampling and
// weighting (ECSW; Farhat, Avery, Chapman & Cortial 2014): a few elements ê with weights w_ê > 0
// (ecsw.h) stand in for the sum over all elements,
//   Bᵀ f_int ≈ −Σ_ê w_ê V_ê D_êᵀ vec P(F_ê),   K̂ = Σ_ê w_ê V_ê D_êᵀ (∂P/∂F)_ê D_ê,
// where D_ê (9 × n) maps ξ to the element's displacement gradient, vec(F_ê − I) = D_ê ξ, so an
// element costs O(9 n) for its force and O(81 n + 9 n²) for its tangent, independently of N.
// The weights are positive, so the reduced forces stay the gradient of a positive-weighted sum
// of element energies (Lagrangian structure, stability).
// Material: the full model's hyperelastic law (hyperelastic.h) and QLV (fem_model.h's
// ViscousStep: S = g S^e(F) + offset, P = F S) with the Prony internal variables kept on the
// sampled elements only — the viscoelasticity lives in the reduced space, not in a creep
// multiplier, so loads that vary, move or are released relax as the full model does.
//
// Quasi-static, as the full model's SolveQuasiStatic and seed 000's model (no inertia; the
// velocities are the step's displacement over dt, for display): each step solves r(ξ) = 0 by
// Newton's method with the reduced tangent (an n × n Cholesky factorisation), reusing the last
// factor while it shrinks the residual at least twofold per iteration (modified Newton: a held
// or slowly moving load costs one or two force evaluations and no tangent), with a backtracking
// line search on |r| (a correction that would invert an element or raise |r| is halved, after
// refreshing a reused factor); a load too large to balance ends the step unconverged (counted)
// at the last iterate, no element inverted. Each step starts from the last step's change
// (a predictor) when that leaves the smaller residual. Grasps, prescribed nodes and fixed nodes
// the modes can move are springs (penalty_stiffness) in r and K̂; a change of springs (a probe's
// contact moving over the surface) re-factors the last assembled tissue tangent plus the new
// springs (O(n³/3)) without assembling it again. The Prony variables advance once the step has
// converged. Allocation-free; the full field is
// reconstructed once per step (modal_field.h). A reduced model cannot be cut.
//
// Static correction (residual flexibility; the "static correction" of mode truncation, e.g.
// Craig & Kurdila 2006 §14.4, Géradin & Rixen 2015 §5.3): a Galerkin model on modes B is stiffer
// than the full one — the local dent under a point force is not in span(B) — so the reduced
// displacement under a tool's push falls short (measured on the liver: 5–29 % at the loaded
// node). For point forces at the correction nodes (the builder's region nodes) the field gets
// the linear response the modes miss,
//   U = B ξ + Σ_p R_p e_p,   R_p = K0⁻¹ E_p − B K̂0⁻¹ Bᵀ E_p   (3N × 3, E_p the unit forces at p),
// K0 the full tangent at rest and K̂0 the reduced one (the cubature's, at ξ = 0), so that in the
// linear range the corrected model IS the full one for such loads. e_p [N] is the external force
// at p passed through the same QLV recursion as the elements' stresses (in the linear range the
// full model's stress history is that of K u, so its displacement is K⁻¹ e with e the force's
// recursion): held forces creep, released ones recover, as the full model's. The correction
// acts on external forces only; its amplitude follows the material's stiffening through a
// calibrated scale κ_p(|e|) (below) (a grasp's or probe's spring is not corrected, nor is
// LocalStiffness), and costs one 3N pass per loaded correction node per step.
// Under large forces the reduced equilibrium itself drifts from the full one inside span(B) —
// on the liver under a held 0.7 N (long-term ~2 N elastic) the field's in-span error is 17 %
// against a 3 % basis floor, while the out-of-span part is at the floor. (Likely the volume: the
// full field's projection onto the modes changes the elements' volumes 1.4× as much as the
// full field does — combinations of nearly isochoric large-strain snapshots are not isochoric —
// and with the near-incompressible material, K ≈ 50 G, Galerkin trades the soft motion's
// accuracy for volume.)
// The correction then also carries the offset in the modes, B G_p(|e|) (e, |e|) (fitted by the
// builder per node and magnitude, affine in the force's direction; one more n-vector and one
// 3N × n pass per step while a correction node is loaded). ξ itself (the dynamics, the haptic
// stiffness) is the reduced equilibrium's; the field shown and reported is corrected.
//
// Petrov–Galerkin (optional: a scene's `nonlinear_projection: PETROV_GALERKIN`; docs/reduced.md
// compares it with Galerkin on the liver): the equations are tested with Ψ instead of B,
//   r(ξ) = Ψᵀ f_ext + Ψᵀ f_int(X + B ξ) = 0,   Ψ = K0⁻¹ B,
// so that for a linear K0 the reduced solution is ξ = (BᵀB)⁻¹ Bᵀ u: the L2 projection of the
// full solution u = K0⁻¹ f onto the modes — the best field the basis holds — where Galerkin's is
// the best in K0's energy norm, which weighs the stiff dent under the tool and leaves the soft
// motion of the organ around it (most of the field's L2 norm) 2–4× the basis's floor (measured on
// the liver). Nonlinear: the residual's linearised displacement K0⁻¹ r has no component in
// span(B). Each sampled element carries a second gradient map D̃_ê (from Ψ) and
//   Ψᵀ f_int ≈ −Σ_ê w_ê V_ê D̃_êᵀ vec P(F_ê),   K̂ = Σ_ê w_ê V_ê D̃_êᵀ (∂P/∂F)_ê D_ê,
// the cubature trained on Ψᵀ f (ecsw.h). K̂ is not symmetric (an LU instead of a Cholesky
// factor; at rest K̂ = BᵀB, the identity for orthonormal modes) and the forces are no longer an
// energy's gradient: under large strain K̂ can turn singular (a 6 cm beam pushed 1.5 cm: an
// eigenvalue of −1e-3 against 1 at rest) where Galerkin's, positive definite, cannot — Newton
// then stops unconverged (counted). Galerkin stays the default for that. Loads, springs and gravity
// are tested with Ψ: a spring's term is k Ψ_iᵀ (target − X_i − B_i ξ). The static correction is
// then R_p = K0⁻¹ E_p − B K̂0⁻¹ Ψ_pᵀ (in the linear range still the full model for point forces at
// p), and LocalStiffness the inverse of the symmetric part of the compliance B_i K̂⁻¹ Ψ_iᵀ.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <Eigen/LU>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/fem_model.h"
#include "server/models/fem/hyperelastic.h"
#include "server/models/fem/tet_elements.h"
#include "server/models/reduced/modal_field.h"
#include "server/models/tissue_model.h"

namespace somasim::models::reduced {

struct NonlinearModelData {
  mesh::Points rest;           // X [m], 3 × N (N >= 1), finite
  std::vector<double> masses;  // [kg], N, each > 0 (gravity, energy, momentum)
  Eigen::MatrixXd modes;       // B [-], 3N × n (1 <= n <= 3N), row 3i + axis
  // The sampled elements (ECSW): their corners (4 × m, m >= 1, indices in [0, N), positively
  // oriented at rest) and weights w (m, each finite and > 0). `elements` (m, optional: empty or
  // m values) are their indices in the full mesh, for people and files.
  mesh::Tetrahedra tets;
  std::vector<double> weights;
  std::vector<int32_t> elements;
  fem::HyperelasticMaterial material = fem::LiverNava2008();
  std::vector<fem::PronyTerm> prony;  // QLV as in FemParameters::prony; empty: elastic
  double penalty_stiffness = 1e5;     // [N/m], > 0 (as KlModelData)
  double max_local_stiffness = 1e4;   // [N/m], > 0 (as KlModelData)
  // Newton stops at |r| <= newton_tolerance × max(|Bᵀ f_ext| + |Bᵀ f_int|, the largest |Bᵀ f_ext|
  // the tissue has carried) (> 0) or after max_newton_iterations (>= 1), accepting the last
  // iterate (counted as unconverged).
  double newton_tolerance = 1e-6;
  int max_newton_iterations = 30;
  // The static correction (above; optional): its nodes (c, distinct, in [0, N)) and R
  // (3N × 3c [m/N], node k's columns 3k..3k+2 the responses to unit x, y, z forces), finite.
  std::vector<int32_t> correction_nodes;
  Eigen::MatrixXd corrections;
  // Its amplitude under large forces (optional): the stiffening material makes the linear R_p an
  // over-estimate, so node p's correction is κ_p(|e|) R_p e with κ_p piecewise linear through
  // (0, 1) and (correction_magnitudes[m] [N], correction_scales(m, p)), held beyond the last.
  // The builder fits κ on its own training solves (the full model's static dents at the region
  // nodes against the reduced model's). Magnitudes increasing, > 0; scales M × c, finite, >= 0.
  std::vector<double> correction_magnitudes;
  Eigen::MatrixXd correction_scales;
  // The correction's part in the modes (optional; needs the magnitudes): the reduced
  // equilibrium's systematic offset from the full model under large forces at node p, in the
  // modes' coordinates, affine in the force's direction: δξ_p = G_p(|e|) φ(e), φ(e) = (e, |e|)
  // (4), with G_p piecewise linear in |e| through (0, 0) and (correction_magnitudes[m], G_{p,m}),
  // held beyond the last; the field gets B δξ_p. The n × 4 blocks G_{p,m} [1/N] side by side,
  // node-major: columns 4 (p M + m) .. +3 (n × 4Mc, finite). The builder fits them on its own
  // training solves (builder.h).
  Eigen::MatrixXd correction_coefficients;
  // The Petrov–Galerkin test basis Ψ [m/N per unit mode], 3N × n, finite (optional: empty is
  // Galerkin, Ψ = B). The builder's is Ψ = K0⁻¹ B (below).
  Eigen::MatrixXd test_modes;
};

// The correction's part in the modes is affine in the force's direction: G φ(e), φ = (e, |e|).
inline Eigen::Vector4d CorrectionFeatures(const Eigen::Vector3d& e) {
  return Eigen::Vector4d(e(0), e(1), e(2), e.norm());
}

// D (9 × n) of one element: vec(F − I) = D ξ for u = B ξ, row i + 3j = Σ_a ∇N_a[j] B(3 c_a + i, :)
// with corners c (4) and shape-function gradients ∇N_a (column a of `gradients`, 3 × 4).
Eigen::Matrix<double, 9, Eigen::Dynamic> ElementGradientMap(
    const Eigen::MatrixXd& modes, const Eigen::Ref<const Eigen::Matrix<int32_t, 4, 1>>& corners,
    const Eigen::Ref<const Eigen::Matrix<double, 3, 4>>& gradients);

class NonlinearReducedModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the field that is wrong (sizes, a non-finite value, an
  // element index out of range, an inverted or flat element, a weight not > 0, a bad material or
  // Prony term).
  static std::unique_ptr<NonlinearReducedModel> Create(NonlinearModelData data);

  int32_t num_nodes() const override { return static_cast<int32_t>(data_.masses.size()); }
  int32_t num_modes() const { return static_cast<int32_t>(data_.modes.cols()); }
  int32_t num_elements() const { return static_cast<int32_t>(data_.weights.size()); }
  std::unique_ptr<TissueState> MakeState() const override;
  // The condensed stiffness at `node` from the reduced tangent of the state's last
  // factorisation: (B_i K̂⁻¹ B_iᵀ)⁻¹ (Petrov–Galerkin: of the symmetric part of B_i K̂⁻¹ Ψ_iᵀ),
  // eigenvalues capped at max_local_stiffness (directions the modes do not move the node in).
  // O(n²).
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  // B (Bᵀ f_int) [N]: the internal forces' projection onto the modes (for orthonormal modes,
  // the part of the full model's internal forces the reduced model sees), elastic part.
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  // Elastic: Σ_ê w_ê V_ê W(F_ê).
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;

  bool petrov_galerkin() const { return data_.test_modes.size() > 0; }
  // The reduced internal force Bᵀ f_int (Petrov–Galerkin: Ψᵀ f_int) at ξ (n) with the state's Prony
  // variables as if for a step of dt (dt <= 0: elastic), and the reduced tangent −∂/∂ξ of it (n ×
  // n) when `tangent` is given. For tests (finite differences) and the builder. Allocates.
  void ReducedForces(const TissueState& state, const Eigen::VectorXd& xi, double dt,
                     Eigen::VectorXd* force, Eigen::MatrixXd* tangent) const;

  // Σ_ê w_ê V_ê W(F_ê) [J] at ξ (n).
  double ElasticEnergyAt(const Eigen::VectorXd& xi) const;
  const Eigen::VectorXd& Coordinates(const TissueState& state) const;
  const NonlinearModelData& data() const { return data_; }

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;
  // The state is ξ and the Prony variables: a rejected step rebuilds x and v from the last
  // accepted ones (as the KL model).
  bool SavesGoodStateItself() const override { return true; }
  // The reconstruction checks x and v as it writes them (modal_field.h).
  bool ChecksStateItself() const override { return true; }

 private:
  NonlinearReducedModel(NonlinearModelData data, const fem::TetElements& elements);
  // Advance's Newton iteration on r(ξ) = 0 (nonlinear_model.cc), and the sampled elements'
  // Prony variables after an accepted step of dt [s].
  struct Newton;
  void AdvanceProny(double dt, TissueState* state) const;
  // Stresses P of every sampled element at the state's gradient buffer (vec(F − I), 9 × m)
  // into p (9 × m), scaled by w V; false if an element is inverted (det F <= 0) or not finite.
  bool Stresses(const double* h, double g, const double* offset, double* p) const;
  // The static correction of an accepted step: the correction nodes' effective forces, their
  // QLV variables and the field δ in the state (allocation-free).
  void Correct(const StepInputs& inputs, TissueState* state) const;
  // κ of correction node `node` (index into correction_nodes) at |e| = magnitude [N].
  double CorrectionScale(Eigen::Index node, double magnitude) const;
  // Adds G_p(|e|) (e, |e|) of correction node `node` to xi (n); magnitude = |e|.
  void AddCoefficientCorrection(Eigen::Index node, const Eigen::Vector3d& e, double magnitude,
                                Eigen::VectorXd* xi) const;
  // Where |e| [N] falls among correction_magnitudes: value(|e|) = low_weight × value(low) +
  // high_weight × value(high), low = -1 standing for the value at 0 (held beyond the last).
  struct Bracket {
    Eigen::Index low = -1;
    double low_weight = 0.0;
    Eigen::Index high = 0;
    double high_weight = 0.0;
  };
  Bracket MagnitudeBracket(double magnitude) const;
  // T (9m × n) = blockdiag(w V ∂P/∂F) D at the gradients h.
  void TangentFactors(const double* h, double g, const double* offset, double* t) const;
  // The maps the equations are tested with: Ψ and D̃ (Petrov–Galerkin), else B and D.
  const Eigen::MatrixXd& TestModes() const {
    return petrov_galerkin() ? data_.test_modes : data_.modes;
  }
  const Eigen::MatrixXd& TestMap() const { return petrov_galerkin() ? test_map_ : gradient_map_; }

  NonlinearModelData data_;
  Eigen::MatrixXd gradient_map_;   // D: 9m × n, rows 9ê..9ê+8 = D_ê
  Eigen::MatrixXd test_map_;       // D̃: 9m × n from Ψ (Petrov–Galerkin), else empty
  Eigen::VectorXd scale_;          // m: w_ê V_ê [m³]
  Eigen::MatrixXd gravity_modes_;  // n × 3: column a = Bᵀ (m e_a) (Petrov–Galerkin: Ψᵀ)
  std::vector<uint8_t> moves_;     // N: 1 when the modes move the node
  ModalField field_;
};

}  // namespace somasim::models::reduced
