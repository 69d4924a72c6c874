// Internal to NonlinearReducedModel's translation units (nonlinear_model.cc,
// nonlinear_model_step.cc): its state and the QLV context both use. Not part of the model's
// interface.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <Eigen/LU>
#include <vector>

#include "server/models/fem/fem_model.h"
#include "server/models/reduced/modal_field.h"

namespace somasim::models::reduced::nonlinear_internal {

// The state: the reduced coordinates (ModalState) and the Prony variables of the sampled
// elements, their last good copies, and the step's scratch, sized by MakeState.
class NonlinearState final : public ModalState {
 public:
  // QLV (fem_model.h's ViscousStep) per sampled element: h_k (9 × terms × m, term-minor) and
  // the elastic stress S^e of the last step (9 × m) [Pa].
  Eigen::VectorXd history, good_history, elastic_last, good_elastic_last;
  // Scratch.
  Eigen::VectorXd grad, stress, offset;     // 9m: vec(F − I), w V vec(P), the step's offset
  Eigen::MatrixXd factors;                  // 9m × n: blockdiag(w V ∂P/∂F) D
  Eigen::MatrixXd tangent, springs;         // n × n: the factor's matrix, the springs' part
  Eigen::MatrixXd tissue_tangent;           // n × n: the tissue's, as last assembled
  Eigen::LLT<Eigen::MatrixXd> llt;          // of the last tangent (plus springs), Galerkin
  Eigen::PartialPivLU<Eigen::MatrixXd> lu;  // the same, Petrov–Galerkin (not symmetric)
  bool petrov = false;
  Eigen::VectorXd external, internal, residual, delta, spring_rhs, trial;  // n
  mutable Eigen::MatrixXd local;  // n × 3: LocalStiffness's K̂⁻¹ B_iᵀ (or K̂⁻¹ Ψ_iᵀ)
  double factor_springs = 0.0;    // the springs the factor holds (a signature; 0: none)
  // The largest load the tissue has carried, |r|'s units (|Ψᵀ f_ext| + |springs' part|): Newton's
  // floor (a released tissue's recovery has no load to be relative to).
  double load_scale = 0.0;
  // The static correction (c correction nodes): each node's effective force e of the last
  // step and its QLV variables [N] (3 × c, 3 × c·terms, term-minor), their good copies; the
  // field it adds, δ = Σ_p R_p e_p, and the last step's (3N [m]), with their good copies;
  // whether δ and δ_prev are non-zero (while neither is, nothing touches the 3N vectors).
  Eigen::MatrixXd corr_elastic, corr_history, good_corr_elastic, good_corr_history;
  Eigen::VectorXd corr_field, corr_field_prev, good_corr_field, good_corr_field_prev;
  Eigen::VectorXd corr_xi;  // n: the correction's part in the modes, δξ = Σ_p G_p e_p (scratch)
  bool corr_nonzero = false, corr_prev_nonzero = false;
  bool good_corr_nonzero = false, good_corr_prev_nonzero = false;
  bool corr_active() const { return corr_nonzero || corr_prev_nonzero; }

  // Factorises `tangent` (true: it is regular / positive definite) and solves with the factor
  // in place (allocation-free: the factors are sized by MakeState).
  bool Factorise() {
    if (petrov) {
      lu.compute(tangent);
      // PartialPivLU does not report singularity: a zero or non-finite pivot is the sign.
      const auto diagonal = lu.matrixLU().diagonal();
      return diagonal.allFinite() && diagonal.cwiseAbs().minCoeff() > 0.0;
    }
    llt.compute(tangent);
    return llt.info() == Eigen::Success;
  }
  template <typename Derived>
  void SolveInPlace(Eigen::MatrixBase<Derived>& v) const {
    if (petrov) {
      v = lu.solve(v);
    } else {
      llt.solveInPlace(v);
    }
  }

  // Adds δ to the positions and (δ − δ_prev) / dt to the velocities just rebuilt from ξ.
  void ApplyCorrection() {
    if (!corr_active()) return;
    Eigen::Map<Eigen::VectorXd>(positions.data(), positions.size()) += corr_field;
    if (dt > 0.0) {
      Eigen::Map<Eigen::VectorXd>(velocities.data(), velocities.size()) +=
          (corr_field - corr_field_prev) / dt;
    }
    checked_non_finite_ = checked_non_finite_ || !corr_field.allFinite();
  }

 protected:
  void SaveGood() override {
    SaveModal();
    good_history = history;
    good_elastic_last = elastic_last;
    if (corr_elastic.size() > 0) {  // same sizes: no allocation
      good_corr_elastic = corr_elastic;
      good_corr_history = corr_history;
    }
    if (corr_active() || good_corr_nonzero || good_corr_prev_nonzero) {
      good_corr_field = corr_field;
      good_corr_field_prev = corr_field_prev;
    }
    good_corr_nonzero = corr_nonzero;
    good_corr_prev_nonzero = corr_prev_nonzero;
  }
  void RestoreGood() override {
    history = good_history;
    elastic_last = good_elastic_last;
    if (corr_elastic.size() > 0) {
      corr_elastic = good_corr_elastic;
      corr_history = good_corr_history;
    }
    if (corr_active() || good_corr_nonzero || good_corr_prev_nonzero) {
      corr_field = good_corr_field;
      corr_field_prev = good_corr_field_prev;
    }
    corr_nonzero = good_corr_nonzero;
    corr_prev_nonzero = good_corr_prev_nonzero;
    RestoreModal();
    ApplyCorrection();
  }
};

// The step's QLV context: g and each element's offset (9 × m) from the state's variables.
double BeginViscous(const std::vector<fem::PronyTerm>& prony, double dt,
                    const Eigen::VectorXd& history, const Eigen::VectorXd& elastic_last,
                    Eigen::VectorXd* offset);

}  // namespace somasim::models::reduced::nonlinear_internal
