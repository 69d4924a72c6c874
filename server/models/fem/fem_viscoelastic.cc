// FemModel's quasi-linear viscoelasticity (QLV, Fung): the Prony factors of a step, each step's
// viscous context from the internal variables, and their update once the step is accepted
// (recursive form, Simo 1987; docs/models.md).
#include <Eigen/Core>
#include <cmath>
#include <cstddef>
#include <vector>

#include "server/models/fem/fem_model.h"
#include "server/models/fem/fem_model_internal.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using internal::FemState;

// e^{-dt/τ_k} and γ_k β_k of every term over a step of dt, the same for every element.
void StepFactors(const std::vector<PronyTerm>& prony, double dt, double* decay, double* weight) {
  for (size_t k = 0; k < prony.size(); ++k) {
    double beta = 0.0;
    PronyFactors(prony[k], dt, &decay[k], &beta);
    weight[k] = prony[k].gamma * beta;
  }
}

}  // namespace

std::vector<PronyTerm> LiverNava2008Prony() { return {{0.5054, 0.5784}, {0.1485, 6.8863}}; }

void PronyFactors(const PronyTerm& term, double dt, double* decay, double* beta) {
  const double x = dt / term.tau;
  *decay = std::exp(-x);
  *beta = x > 1e-8 ? -std::expm1(-x) / x : 1.0 - 0.5 * x;  // β → 1 as dt/τ → 0
}

ViscousStep FemModel::BeginViscousStep(const TissueState& base, double dt, double* offset) const {
  const auto& state = static_cast<const FemState&>(base);
  const size_t m = static_cast<size_t>(num_tets()), terms = prony_.size();
  double decay[kMaxPronyTerms] = {}, weight[kMaxPronyTerms] = {};
  StepFactors(prony_, dt, decay, weight);
  // g = γ∞ + Σ γ_k β_k, γ∞ = 1 - Σ γ_k.
  ViscousStep step;
  double gamma_sum = 0.0;
  step.g = 0.0;
  for (size_t k = 0; k < terms; ++k) {
    step.g += weight[k];
    gamma_sum += prony_[k].gamma;
  }
  step.g += 1.0 - gamma_sum;
  // offset = Σ_k (e^{-dt/τ_k} h_k - γ_k β_k S^e_last).
  for (size_t e = 0; e < m; ++e) {
    Eigen::Map<Matrix3d> out(offset + 9 * e);
    out.setZero();
    const Eigen::Map<const Matrix3d> last(state.elastic_last.data() + 9 * e);
    for (size_t k = 0; k < terms; ++k) {
      out += decay[k] * Eigen::Map<const Matrix3d>(state.history.data() + 9 * (e * terms + k)) -
             weight[k] * last;
    }
  }
  step.offset = offset;
  return step;
}

void FemModel::EndViscousStep(double dt, TissueState* base) const {
  auto* state = static_cast<FemState*>(base);
  const Shape sh = ShapeOf(*state);
  const size_t m = static_cast<size_t>(num_tets()), terms = prony_.size();
  double decay[kMaxPronyTerms] = {}, weight[kMaxPronyTerms] = {};
  StepFactors(prony_, dt, decay, weight);
  for (size_t e = 0; e < m; ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const Matrix3d now = ElasticStress(sh, state->positions, static_cast<int32_t>(e));
    Eigen::Map<Matrix3d> last(state->elastic_last.data() + 9 * e);
    for (size_t k = 0; k < terms; ++k) {
      Eigen::Map<Matrix3d> h(state->history.data() + 9 * (e * terms + k));
      h = decay[k] * h + weight[k] * (now - last);  // exact for linear S^e over dt
    }
    last = now;
  }
}

}  // namespace somasim::models::fem
