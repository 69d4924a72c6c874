// NonlinearReducedModel's step (nonlinear_model.h): the loads and springs, Newton on the reduced
// equilibrium, the sampled elements' Prony variables, and the static correction of the field.
#include <algorithm>
#include <cmath>
#include <limits>

#include "server/models/fem/hyperelastic.h"
#include "server/models/reduced/nonlinear_internal.h"
#include "server/models/reduced/nonlinear_model.h"

namespace somasim::models::reduced {

using Eigen::Matrix3d;
using nonlinear_internal::BeginViscous;
using nonlinear_internal::NonlinearState;

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

}  // namespace somasim::models::reduced
