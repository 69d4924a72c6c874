#include "server/models/reduced/nonlinear_model.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#include "common/checks/finite.h"
#include "server/models/fem/tet_elements.h"
#include "server/models/particle_mesh.h"

namespace somasim::models::reduced {
namespace {

using Eigen::Matrix3d;

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

void Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("nonlinear reduced model: " + what);
}

// The step's QLV context: g and each element's offset (9 × m) from the state's variables.
double BeginViscous(const std::vector<fem::PronyTerm>& prony, double dt,
                    const Eigen::VectorXd& history, const Eigen::VectorXd& elastic_last,
                    Eigen::VectorXd* offset) {
  if (prony.empty() || !(dt > 0.0)) {
    offset->setZero();
    return 1.0;
  }
  const size_t terms = prony.size();
  double decay[fem::kMaxPronyTerms] = {}, weight[fem::kMaxPronyTerms] = {};
  double g = 1.0;
  for (size_t k = 0; k < terms; ++k) {
    double beta = 0.0;
    fem::PronyFactors(prony[k], dt, &decay[k], &beta);
    weight[k] = prony[k].gamma * beta;
    g += weight[k] - prony[k].gamma;  // γ∞ + Σ γ_k β_k
  }
  const Eigen::Index m = offset->size() / 9;
  for (Eigen::Index e = 0; e < m; ++e) {
    auto out = offset->segment<9>(9 * e);
    out = -(weight[0] * elastic_last.segment<9>(9 * e));
    for (size_t k = 1; k < terms; ++k) out -= weight[k] * elastic_last.segment<9>(9 * e);
    for (size_t k = 0; k < terms; ++k) {
      out += decay[k] * history.segment<9>(9 * (e * static_cast<Eigen::Index>(terms) +
                                                static_cast<Eigen::Index>(k)));
    }
  }
  return g;
}

}  // namespace

Eigen::Matrix<double, 9, Eigen::Dynamic> ElementGradientMap(
    const Eigen::MatrixXd& modes, const Eigen::Ref<const Eigen::Matrix<int32_t, 4, 1>>& corners,
    const Eigen::Ref<const Eigen::Matrix<double, 3, 4>>& gradients) {
  Eigen::Matrix<double, 9, Eigen::Dynamic> d = Eigen::MatrixXd::Zero(9, modes.cols());
  for (int a = 0; a < 4; ++a) {
    const auto rows = modes.middleRows(3 * corners(a), 3);
    for (int j = 0; j < 3; ++j) d.middleRows(3 * j, 3) += gradients(j, a) * rows;
  }
  return d;
}

std::unique_ptr<NonlinearReducedModel> NonlinearReducedModel::Create(NonlinearModelData data) {
  CheckModalData(data.rest, data.masses, data.modes, "nonlinear reduced model: ");
  const Eigen::Index nodes = data.rest.cols();
  const Eigen::Index n = data.modes.cols();
  Require(data.test_modes.size() == 0 ||
              (data.test_modes.rows() == data.modes.rows() && data.test_modes.cols() == n),
          "test_modes must be empty or 3N × n like the modes, got " +
              std::to_string(data.test_modes.rows()) + " × " +
              std::to_string(data.test_modes.cols()));
  Require(data.test_modes.allFinite(), "a test mode is not finite");
  const Eigen::Index m = data.tets.cols();
  Require(m >= 1, "no sampled element");
  Require(static_cast<Eigen::Index>(data.weights.size()) == m,
          "weights: " + std::to_string(data.weights.size()) + " for " + std::to_string(m) +
              " elements");
  for (const double w : data.weights) Require(checks::FinitePositive(w), "a weight is not > 0");
  Require(data.elements.empty() || static_cast<Eigen::Index>(data.elements.size()) == m,
          "elements: " + std::to_string(data.elements.size()) + " for " + std::to_string(m) +
              " sampled elements");
  for (const int32_t e : data.elements) Require(e >= 0, "an element index is negative");
  for (Eigen::Index e = 0; e < m; ++e) {
    for (int a = 0; a < 4; ++a) {
      Require(data.tets(a, e) >= 0 && data.tets(a, e) < nodes,
              "sampled element " + std::to_string(e) + ": corner " +
                  std::to_string(data.tets(a, e)) + " out of range");
    }
  }
  try {
    fem::CheckMaterial(data.material);
  } catch (const std::invalid_argument& error) {
    Require(false, std::string("material: ") + error.what());
  }
  Require(data.prony.size() <= fem::kMaxPronyTerms, "more than 4 Prony terms");
  double gamma_sum = 0.0;
  for (const fem::PronyTerm& t : data.prony) {
    Require(checks::FiniteNonNegative(t.gamma) && checks::FinitePositive(t.tau),
            "a Prony term needs gamma >= 0 and tau > 0");
    gamma_sum += t.gamma;
  }
  Require(gamma_sum <= 1.0, "the Prony gammas sum above 1");
  Require(checks::FinitePositive(data.penalty_stiffness), "penalty_stiffness must be > 0");
  Require(checks::FinitePositive(data.max_local_stiffness), "max_local_stiffness must be > 0");
  Require(checks::FinitePositive(data.newton_tolerance), "newton_tolerance must be > 0");
  Require(data.max_newton_iterations >= 1, "max_newton_iterations must be >= 1");
  const auto c = static_cast<Eigen::Index>(data.correction_nodes.size());
  Require(data.corrections.size() == 0
              ? c == 0
              : data.corrections.rows() == 3 * nodes && data.corrections.cols() == 3 * c,
          "corrections must be 3N × 3c for c = " + std::to_string(c) + " correction nodes, got " +
              std::to_string(data.corrections.rows()) + " × " +
              std::to_string(data.corrections.cols()));
  Require(data.corrections.allFinite(), "a correction is not finite");
  const auto magnitudes = static_cast<Eigen::Index>(data.correction_magnitudes.size());
  Require(magnitudes == 0
              ? data.correction_scales.size() == 0
              : data.correction_scales.rows() == magnitudes && data.correction_scales.cols() == c,
          "correction_scales must be M × c for M = " + std::to_string(magnitudes) +
              " magnitudes and c = " + std::to_string(c) + " nodes");
  for (size_t k = 0; k < data.correction_magnitudes.size(); ++k) {
    const double f = data.correction_magnitudes[k];
    Require(checks::FinitePositive(f) && (k == 0 || f > data.correction_magnitudes[k - 1]),
            "correction_magnitudes must be finite, > 0 and increasing");
  }
  Require(data.correction_scales.allFinite() && (data.correction_scales.array() >= 0.0).all(),
          "a correction scale is not finite and >= 0");
  Require(data.correction_coefficients.size() == 0 ||
              (data.correction_coefficients.rows() == data.modes.cols() &&
               data.correction_coefficients.cols() == 4 * magnitudes * c && magnitudes > 0),
          "correction_coefficients must be n × 4Mc for n = " + std::to_string(data.modes.cols()) +
              " modes, M = " + std::to_string(magnitudes) + " magnitudes and c = " +
              std::to_string(c) + " nodes (and needs the magnitudes), got " +
              std::to_string(data.correction_coefficients.rows()) + " × " +
              std::to_string(data.correction_coefficients.cols()));
  Require(data.correction_coefficients.allFinite(), "a correction coefficient is not finite");
  {
    std::vector<uint8_t> seen(static_cast<size_t>(nodes), 0);
    for (const int32_t p : data.correction_nodes) {
      Require(p >= 0 && p < nodes, "correction node " + std::to_string(p) + " out of range");
      Require(seen[static_cast<size_t>(p)] == 0,
              "correction node " + std::to_string(p) + " listed twice");
      seen[static_cast<size_t>(p)] = 1;
    }
  }
  // The sampled elements' geometry (throws for an inverted or flat one).
  mesh::TetMesh sampled;
  sampled.vertices = data.rest;
  sampled.tetrahedra = data.tets;
  fem::TetElements elements;
  try {
    elements = fem::BuildTetElements(sampled, "sampled elements");
  } catch (const std::invalid_argument& error) {
    Require(false, error.what());
  }
  return std::unique_ptr<NonlinearReducedModel>(
      new NonlinearReducedModel(std::move(data), elements));
}

NonlinearReducedModel::NonlinearReducedModel(NonlinearModelData data,
                                             const fem::TetElements& elements)
    : data_(std::move(data)) {
  const Eigen::Index nodes = data_.rest.cols(), n = data_.modes.cols(), m = data_.tets.cols();
  // D_ê (9 × n): vec(F − I) = Σ_a u_a ∇N_aᵀ with u_a = B_a ξ, so row i + 3j of D_ê is
  // Σ_a ∇N_a[j] B(3 node_a + i, :).
  gradient_map_ = Eigen::MatrixXd::Zero(9 * m, n);
  scale_.resize(m);
  for (Eigen::Index e = 0; e < m; ++e) {
    scale_(e) = data_.weights[static_cast<size_t>(e)] * elements.volumes[static_cast<size_t>(e)];
    gradient_map_.middleRows(9 * e, 9) =
        ElementGradientMap(data_.modes, data_.tets.col(e), elements.gradients.middleCols<4>(4 * e));
  }
  if (petrov_galerkin()) {
    test_map_ = Eigen::MatrixXd::Zero(9 * m, n);
    for (Eigen::Index e = 0; e < m; ++e) {
      test_map_.middleRows(9 * e, 9) = ElementGradientMap(data_.test_modes, data_.tets.col(e),
                                                          elements.gradients.middleCols<4>(4 * e));
    }
  }
  gravity_modes_ = Eigen::MatrixXd::Zero(n, 3);
  moves_.assign(static_cast<size_t>(nodes), 0);
  const double mode_scale = data_.modes.cwiseAbs().maxCoeff();
  for (Eigen::Index i = 0; i < nodes; ++i) {
    const auto rows = data_.modes.middleRows(3 * i, 3);
    const auto test_rows = TestModes().middleRows(3 * i, 3);
    for (int a = 0; a < 3; ++a) {
      gravity_modes_.col(a) += data_.masses[i] * test_rows.row(a).transpose();
    }
    moves_[static_cast<size_t>(i)] = rows.cwiseAbs().maxCoeff() > 1e-9 * mode_scale ? 1 : 0;
  }
  field_ = ModalField(data_.modes);
  // Quasi-static, as the KL model: only non-finite values reject a step.
  set_speed_limit(std::numeric_limits<double>::max());
}

bool NonlinearReducedModel::Stresses(const double* h, double g, const double* offset,
                                     double* p) const {
  const Eigen::Index m = data_.tets.cols();
  for (Eigen::Index e = 0; e < m; ++e) {
    const Matrix3d f = Matrix3d::Identity() + Eigen::Map<const Matrix3d>(h + 9 * e);
    if (!(f.determinant() > 0.0)) return false;
    Matrix3d stress = g * fem::FirstPiolaStress(data_.material, f);
    if (offset != nullptr) stress.noalias() += f * Eigen::Map<const Matrix3d>(offset + 9 * e);
    Eigen::Map<Matrix3d>(p + 9 * e) = scale_(e) * stress;
  }
  return true;
}

void NonlinearReducedModel::TangentFactors(const double* h, double g, const double* offset,
                                           double* t) const {
  const Eigen::Index m = data_.tets.cols(), n = data_.modes.cols();
  Eigen::Map<Eigen::MatrixXd> out(t, 9 * m, n);
  for (Eigen::Index e = 0; e < m; ++e) {
    const Matrix3d f = Matrix3d::Identity() + Eigen::Map<const Matrix3d>(h + 9 * e);
    const fem::StressPoint point = fem::PrepareStressDifferential(data_.material, f);
    Eigen::Matrix<double, 9, 9> c;  // ∂vec P / ∂vec F, column c + 3d for dF = e_c e_dᵀ
    for (int d = 0; d < 3; ++d) {
      for (int r = 0; r < 3; ++r) {
        Matrix3d df = Matrix3d::Zero();
        df(r, d) = 1.0;
        Matrix3d dp = g * fem::StressDifferential(point, df);
        if (offset != nullptr) {  // d(F O) = dF O: row r of O's row d
          dp.row(r) += Eigen::Map<const Matrix3d>(offset + 9 * e).row(d);
        }
        c.col(r + 3 * d) = scale_(e) * Eigen::Map<const Eigen::Matrix<double, 9, 1>>(dp.data());
      }
    }
    out.middleRows(9 * e, 9).noalias() = c.lazyProduct(gradient_map_.middleRows(9 * e, 9));
  }
}

std::unique_ptr<TissueState> NonlinearReducedModel::MakeState() const {
  auto state = std::make_unique<NonlinearState>();
  InitialiseState(data_.rest, state.get());
  const Eigen::Index n = data_.modes.cols(), m = data_.tets.cols();
  const auto terms = static_cast<Eigen::Index>(data_.prony.size());
  state->InitialiseModal(field_, data_.rest.data(), speed_limit());
  const auto c = static_cast<Eigen::Index>(data_.correction_nodes.size());
  state->corr_elastic = Eigen::MatrixXd::Zero(3, c);
  state->corr_history = Eigen::MatrixXd::Zero(3, c * terms);
  state->good_corr_elastic = state->corr_elastic;
  state->good_corr_history = state->corr_history;
  state->corr_field = Eigen::VectorXd::Zero(c > 0 ? data_.modes.rows() : 0);
  state->corr_xi = Eigen::VectorXd::Zero(data_.correction_coefficients.size() > 0 ? n : 0);
  state->corr_field_prev = state->corr_field;
  state->good_corr_field = state->corr_field;
  state->good_corr_field_prev = state->corr_field;
  state->history = Eigen::VectorXd::Zero(9 * m * terms);
  state->good_history = state->history;
  state->elastic_last = Eigen::VectorXd::Zero(9 * m);
  state->good_elastic_last = state->elastic_last;
  state->grad = Eigen::VectorXd::Zero(9 * m);
  state->stress = state->grad;
  state->offset = state->grad;
  state->factors = Eigen::MatrixXd::Zero(9 * m, n);
  state->springs = Eigen::MatrixXd::Zero(n, n);
  state->external = Eigen::VectorXd::Zero(n);
  state->internal = state->external;
  state->residual = state->external;
  state->delta = state->external;
  state->spring_rhs = state->external;
  state->trial = state->external;
  state->local = Eigen::MatrixXd::Zero(n, 3);
  // The tangent at rest, factorised: the first step's Newton and LocalStiffness start from it.
  TangentFactors(state->grad.data(), 1.0, nullptr, state->factors.data());
  state->tangent.noalias() = TestMap().transpose() * state->factors;
  state->tissue_tangent = state->tangent;
  state->petrov = petrov_galerkin();
  if (state->petrov) {
    state->lu = Eigen::PartialPivLU<Eigen::MatrixXd>(n);
  } else {
    state->llt = Eigen::LLT<Eigen::MatrixXd>(n);
  }
  state->Factorise();
  return state;
}

// One step's Newton iteration on r(ξ) = 0: the step's QLV context and springs, the residual and
// the tangent's factor at a point, and the loop.
struct NonlinearReducedModel::Newton {
  const NonlinearReducedModel& model;
  NonlinearState* s;
  bool springs;           // springs act this step (s->springs, s->spring_rhs)
  double g;               // QLV's g (1: elastic)
  const double* offset;   // QLV's offsets (9 × m), or nullptr without Prony terms
  double residual_floor;  // tol × the largest load carried so far
  double scale = 0.0;     // |Ψᵀ f_ext| + |Ψᵀ f_int| (+ |springs|) at the last evaluation

  // r at ξ (into s->residual; s->grad and s->stress follow ξ); false if an element inverts or
  // a value is not finite.
  bool Evaluate(const Eigen::VectorXd& xi, double* norm) {
    s->grad.noalias() = model.gradient_map_ * xi;
    if (!model.Stresses(s->grad.data(), g, offset, s->stress.data())) return false;
    s->internal.noalias() = -(model.TestMap().transpose() * s->stress);
    s->residual = s->external + s->internal;
    scale = s->external.norm() + s->internal.norm();
    if (springs) {
      s->residual += s->spring_rhs;
      s->residual.noalias() -= s->springs * xi;
      scale += s->spring_rhs.norm();
    }
    *norm = s->residual.norm();
    return std::isfinite(*norm);
  }
  // The factor of the tissue's tangent plus the springs: with `assemble`, the tissue's tangent
  // at ξ first (s->grad must be ξ's; O(|E| (81 n + 9 n²)), the expensive part), else the last
  // one assembled (an n × n factorisation, O(n³ / 3): what a change of springs costs).
  bool Refactor(bool assemble) {
    if (assemble) {
      model.TangentFactors(s->grad.data(), g, offset, s->factors.data());
      s->tissue_tangent.noalias() = model.TestMap().transpose() * s->factors;
    }
    s->tangent = s->tissue_tangent;
    if (springs) s->tangent += s->springs;
    return s->Factorise();
  }
  bool Met(double norm) const {
    return norm <= std::max(model.data_.newton_tolerance * scale, residual_floor);
  }

  // Newton's method from s->xi (or the predictor s->trial, when `extrapolate` and its residual
  // is the smaller), reusing the last factor while it halves the residual, with a backtracking
  // line search on |r| (a correction that inverts an element or raises |r| is halved; with a
  // reused factor, the tangent is refreshed first). Adds its iterations to the state's
  // counters. False when the step must be rejected; *converged when |r| met the tolerance.
  bool Solve(const StepInputs& inputs, bool extrapolate, bool* converged) {
    double norm = 0.0;
    bool ok = Evaluate(s->xi, &norm);
    double predicted = 0.0;
    if (ok && extrapolate && Evaluate(s->trial, &predicted)) {
      if (predicted < norm) {  // the buffers hold the predictor's r, grad and stress
        s->xi = s->trial;
        norm = predicted;
      } else {
        ok = Evaluate(s->xi, &norm);
      }
    } else if (ok && extrapolate) {
      ok = Evaluate(s->xi, &norm);
    }
    *converged = false;
    // When the springs differ from those of the factor (their stiffness dwarfs the tissue's: a
    // factor without them barely helps), the factor is remade with them on the last tissue
    // tangent — cheap; the same springs with moved targets (a grasp being pulled) keep it.
    double signature = 0.0;
    if (springs) {
      for (const Attachment& a : inputs.attachments) {
        signature += (a.node + 1.0) * (1.0 + 1e-3 * a.stiffness);
      }
      signature += 7.0 * static_cast<double>(inputs.prescribed_nodes.size());
      signature += 1e-9 * s->springs.trace();
    }
    if (ok && signature != s->factor_springs) {
      s->factor_springs = signature;
      ok = Refactor(false);
    }
    bool refresh = false, fresh = false;
    int iterations = 0;
    while (ok) {
      if (Met(norm) || norm == 0.0) {
        *converged = true;
        break;
      }
      if (iterations >= model.data_.max_newton_iterations) break;
      if (refresh && !fresh) {
        if (!Refactor(true)) {
          ok = false;
          break;
        }
        fresh = true;
      }
      s->delta = s->residual;
      s->SolveInPlace(s->delta);
      double alpha = 1.0, trial_norm = 0.0;
      int halvings = 0;
      while (true) {
        s->trial = s->xi + alpha * s->delta;
        const bool trial_ok = Evaluate(s->trial, &trial_norm);
        if (trial_ok && (trial_norm < norm || Met(trial_norm))) break;
        if (!fresh) {  // a stale factor's direction: refresh it at ξ and start again
          double again = 0.0;
          ok = Evaluate(s->xi, &again) && Refactor(true);
          if (!ok) break;
          fresh = true;
          s->delta = s->residual;
          s->SolveInPlace(s->delta);
          alpha = 1.0;
          continue;
        }
        if (++halvings > 12) break;  // no progress (rounding): keep ξ, unconverged
        alpha *= 0.5;
      }
      if (!ok) break;
      if (halvings > 12) {
        double again = 0.0;
        ok = Evaluate(s->xi, &again);  // grad and stress back at ξ
        break;
      }
      s->xi = s->trial;  // s->residual, grad and stress are the trial's
      ++iterations;
      refresh = trial_norm > 0.5 * norm;
      fresh = false;
      norm = trial_norm;
    }
    s->counters.solver_iterations += iterations;
    return ok;
  }
};

void NonlinearReducedModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* s = static_cast<NonlinearState*>(base);
  // Loads: gravity and the tool's forces (projected), then the springs' constant part.
  s->external.noalias() = gravity_modes_ * inputs.gravity;
  if (inputs.external_forces != nullptr) {
    AddProjectedLoads(TestModes(), *inputs.external_forces, &s->external);
  }
  const bool springs =
      SpringTerms(data_.modes, TestModes(), data_.rest, moves_.data(), data_.penalty_stiffness,
                  inputs, s->positions, &s->springs, &s->spring_rhs);
  const double g = BeginViscous(data_.prony, inputs.dt, s->history, s->elastic_last, &s->offset);
  const double* offset = data_.prony.empty() ? nullptr : s->offset.data();
  // Converged at |r| <= tol × max(|Ψᵀ f_ext| + |Ψᵀ f_int| (+ springs), the largest load of a
  // converged step so far): with no load at all (a release, the tissue recovering) the first
  // alone cannot be met but in rounding, and each step would run to its limit.
  const double applied = s->external.norm() + (springs ? s->spring_rhs.norm() : 0.0);
  Newton newton{*this, s, springs, g, offset, data_.newton_tolerance * s->load_scale};
  // The predictor: the last step's change again (a smooth load history at 1 kHz then starts
  // Newton next to the answer), when the step is as long as the last one.
  const bool extrapolate = s->dt == inputs.dt;
  s->trial = s->xi + (s->xi - s->xi_prev);
  s->xi_prev = s->xi;
  s->dt = inputs.dt;
  bool converged = false;
  if (!newton.Solve(inputs, extrapolate, &converged)) {
    s->xi.setConstant(std::numeric_limits<double>::quiet_NaN());  // rejected: rolled back
    s->Rebuild();
    return;
  }
  if (converged) {
    s->load_scale = std::max(s->load_scale, applied);
  } else {
    ++s->counters.solver_unconverged;
  }
  if (!data_.prony.empty()) AdvanceProny(inputs.dt, s);
  if (!data_.correction_nodes.empty()) Correct(inputs, s);
  s->Rebuild();
  s->ApplyCorrection();
}

void NonlinearReducedModel::AdvanceProny(double dt, TissueState* base) const {
  auto* s = static_cast<NonlinearState*>(base);
  // The Prony variables advance with the accepted elastic stresses S^e = F⁻¹ P^e.
  const size_t terms = data_.prony.size();
  double decay[fem::kMaxPronyTerms] = {}, weight[fem::kMaxPronyTerms] = {};
  for (size_t k = 0; k < terms; ++k) {
    double beta = 0.0;
    fem::PronyFactors(data_.prony[k], dt, &decay[k], &beta);
    weight[k] = data_.prony[k].gamma * beta;
  }
  const Eigen::Index m = data_.tets.cols();
  for (Eigen::Index e = 0; e < m; ++e) {
    const Matrix3d f = Matrix3d::Identity() + Eigen::Map<const Matrix3d>(s->grad.data() + 9 * e);
    const Matrix3d now = f.inverse() * fem::FirstPiolaStress(data_.material, f);
    Eigen::Map<Matrix3d> last(s->elastic_last.data() + 9 * e);
    for (size_t k = 0; k < terms; ++k) {
      Eigen::Map<Matrix3d> h(s->history.data() + 9 * (e * static_cast<Eigen::Index>(terms) +
                                                      static_cast<Eigen::Index>(k)));
      h = decay[k] * h + weight[k] * (now - last);
    }
    last = now;
  }
}

NonlinearReducedModel::Bracket NonlinearReducedModel::MagnitudeBracket(double magnitude) const {
  // Piecewise linear through the origin's value and (f_m, value_m), held beyond the last.
  const std::vector<double>& f = data_.correction_magnitudes;
  double f0 = 0.0;
  for (size_t m = 0; m < f.size(); ++m) {
    if (magnitude <= f[m]) {
      const double w = (magnitude - f0) / (f[m] - f0);  // f[m] > f0 >= 0
      return {static_cast<Eigen::Index>(m) - 1, 1.0 - w, static_cast<Eigen::Index>(m), w};
    }
    f0 = f[m];
  }
  return {-1, 0.0, static_cast<Eigen::Index>(f.size()) - 1, 1.0};
}

double NonlinearReducedModel::CorrectionScale(Eigen::Index node, double magnitude) const {
  if (data_.correction_magnitudes.empty()) return 1.0;
  const Bracket b = MagnitudeBracket(magnitude);  // κ through (0, 1)
  return b.low_weight * (b.low < 0 ? 1.0 : data_.correction_scales(b.low, node)) +
         b.high_weight * data_.correction_scales(b.high, node);
}

void NonlinearReducedModel::Correct(const StepInputs& inputs, TissueState* base) const {
  auto* s = static_cast<NonlinearState*>(base);
  // Each correction node's effective force e: the external force through the QLV recursion of
  // the elements' stresses (BeginViscous and the history update above, on a 3-vector), then
  // δ = Σ_p R_p e_p over the nodes whose e is not negligible.
  const size_t terms = data_.prony.size();
  double decay[fem::kMaxPronyTerms] = {}, weight[fem::kMaxPronyTerms] = {};
  double g = 1.0;
  const bool viscous = terms > 0 && inputs.dt > 0.0;
  if (viscous) {
    for (size_t k = 0; k < terms; ++k) {
      double beta = 0.0;
      fem::PronyFactors(data_.prony[k], inputs.dt, &decay[k], &beta);
      weight[k] = data_.prony[k].gamma * beta;
      g += weight[k] - data_.prony[k].gamma;
    }
  }
  // δ_prev ← δ, δ ← 0 (the 3N vectors touched only when one is non-zero; same sizes).
  if (s->corr_nonzero) {
    s->corr_field_prev = s->corr_field;
    s->corr_field.setZero();
  } else if (s->corr_prev_nonzero) {
    s->corr_field_prev.setZero();
  }
  s->corr_prev_nonzero = s->corr_nonzero;
  s->corr_nonzero = false;
  const bool in_modes = s->corr_xi.size() > 0;
  if (in_modes) s->corr_xi.setZero();
  for (Eigen::Index k = 0; k < static_cast<Eigen::Index>(data_.correction_nodes.size()); ++k) {
    const int32_t p = data_.correction_nodes[static_cast<size_t>(k)];
    Eigen::Vector3d f = Eigen::Vector3d::Zero();
    if (inputs.external_forces != nullptr) f = inputs.external_forces->col(p);
    auto last = s->corr_elastic.col(k);
    Eigen::Vector3d e = f;
    if (viscous) {
      Eigen::Vector3d offset = Eigen::Vector3d::Zero();
      for (size_t t = 0; t < terms; ++t) {
        offset += decay[t] * s->corr_history.col(k * static_cast<Eigen::Index>(terms) +
                                                 static_cast<Eigen::Index>(t)) -
                  weight[t] * last;
      }
      e = (f - offset) / g;
      for (size_t t = 0; t < terms; ++t) {
        auto h = s->corr_history.col(k * static_cast<Eigen::Index>(terms) +
                                     static_cast<Eigen::Index>(t));
        h = decay[t] * h + weight[t] * (e - last);
      }
    }
    last = e;
    const double magnitude = e.norm();
    if (magnitude > 1e-9) {  // [N]: below it the dent is ~1e-11 m
      const double kappa = CorrectionScale(k, magnitude);
      s->corr_field.noalias() += data_.corrections.middleCols<3>(3 * k) * (kappa * e);
      if (in_modes) AddCoefficientCorrection(k, e, magnitude, &s->corr_xi);
      s->corr_nonzero = true;
    }
  }
  if (in_modes && s->corr_nonzero) s->corr_field.noalias() += data_.modes * s->corr_xi;
}

void NonlinearReducedModel::AddCoefficientCorrection(Eigen::Index node, const Eigen::Vector3d& e,
                                                     double magnitude, Eigen::VectorXd* xi) const {
  // G_p(|e|) φ(e), G_p through (0, 0) (MagnitudeBracket).
  const auto count = static_cast<Eigen::Index>(data_.correction_magnitudes.size());
  const Eigen::Vector4d phi = CorrectionFeatures(e);
  const Bracket b = MagnitudeBracket(magnitude);
  xi->noalias() += data_.correction_coefficients.middleCols<4>(4 * (node * count + b.high)) *
                   (b.high_weight * phi);
  if (b.low >= 0) {
    xi->noalias() += data_.correction_coefficients.middleCols<4>(4 * (node * count + b.low)) *
                     (b.low_weight * phi);
  }
}

void NonlinearReducedModel::ReducedForces(const TissueState& state, const Eigen::VectorXd& xi,
                                          double dt, Eigen::VectorXd* force,
                                          Eigen::MatrixXd* tangent) const {
  const auto& s = static_cast<const NonlinearState&>(state);
  const Eigen::Index m = data_.tets.cols();
  Eigen::VectorXd offset(9 * m), grad = gradient_map_ * xi, stress(9 * m);
  const double g = BeginViscous(data_.prony, dt, s.history, s.elastic_last, &offset);
  const double* off = data_.prony.empty() || !(dt > 0.0) ? nullptr : offset.data();
  if (!Stresses(grad.data(), g, off, stress.data())) {
    force->setConstant(xi.size(), std::numeric_limits<double>::quiet_NaN());
  } else {
    *force = -(TestMap().transpose() * stress);
  }
  if (tangent != nullptr) {
    Eigen::MatrixXd factors(9 * m, xi.size());
    TangentFactors(grad.data(), g, off, factors.data());
    *tangent = TestMap().transpose() * factors;
  }
}

Eigen::Matrix3d NonlinearReducedModel::LocalStiffness(const TissueState& state,
                                                      int32_t node) const {
  if (node < 0 || node >= num_nodes()) return Eigen::Matrix3d::Zero();
  const auto& s = static_cast<const NonlinearState&>(state);
  const auto rows = data_.modes.middleRows(3 * node, 3);  // B_i: 3 × n
  s.local = TestModes().middleRows(3 * node, 3).transpose();
  s.SolveInPlace(s.local);
  Matrix3d compliance = rows * s.local;
  compliance = 0.5 * (compliance + compliance.transpose()).eval();
  return CappedStiffness(compliance, data_.max_local_stiffness);
}

void NonlinearReducedModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  // Bᵀ f_int (with either projection: the part of the forces the modes see).
  const Eigen::VectorXd grad = gradient_map_ * Coordinates(state);
  Eigen::VectorXd stress(grad.size()), reduced;
  if (Stresses(grad.data(), 1.0, nullptr, stress.data())) {
    reduced = -(gradient_map_.transpose() * stress);
  } else {
    reduced.setConstant(num_modes(), std::numeric_limits<double>::quiet_NaN());
  }
  forces->resize(3, num_nodes());
  Eigen::Map<Eigen::VectorXd>(forces->data(), forces->size()).noalias() = data_.modes * reduced;
}

EnergyReport NonlinearReducedModel::Energy(const TissueState& state,
                                           const Eigen::Vector3d& gravity) const {
  EnergyReport report;
  report.elastic = ElasticEnergyAt(Coordinates(state));
  AddKineticAndGravity(data_.masses, state, gravity, &report);
  return report;
}

double NonlinearReducedModel::ElasticEnergyAt(const Eigen::VectorXd& xi) const {
  const Eigen::VectorXd grad = gradient_map_ * xi;
  double energy = 0.0;
  for (Eigen::Index e = 0; e < data_.tets.cols(); ++e) {
    const Matrix3d f = Matrix3d::Identity() + Eigen::Map<const Matrix3d>(grad.data() + 9 * e);
    energy += scale_(e) * fem::StrainEnergy(data_.material, f);
  }
  return energy;
}

const Eigen::VectorXd& NonlinearReducedModel::Coordinates(const TissueState& state) const {
  return static_cast<const NonlinearState&>(state).xi;
}

}  // namespace somasim::models::reduced
