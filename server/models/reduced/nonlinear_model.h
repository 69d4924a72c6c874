// The nonlinear reduced model that beats seed 000's (issue 12, SPEC §4.5): U = B ξ on the modes
// as in seed 000, but ξ solves the Galerkin (or Petrov–Galerkin) projection of the full
// hyperelastic–viscoelastic equilibrium, its forces and tangent by an ECSW cubature (ecsw.h) with
// the Prony variables on the sampled elements; quasi-static Newton per step, and a static
// correction of the field under point forces at the builder's region nodes. Derivations:
// docs/reduced.md, "The nonlinear model". Allocation-free steps; cannot be cut. Pure: no I/O.
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
  // The static correction (docs/reduced.md; optional): its nodes (c, distinct, in [0, N)) and R
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
  // Galerkin, Ψ = B). The builder's is Ψ = K0⁻¹ B (docs/reduced.md, "Petrov–Galerkin").
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
