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

}  // namespace

std::vector<PronyTerm> LiverNava2008Prony() { return {{0.5054, 0.5784}, {0.1485, 6.8863}}; }

// e^{-dt/τ} and β = (τ/dt)(1 - e^{-dt/τ}) of a Prony term (β → 1 as dt/τ → 0).
void PronyFactors(const PronyTerm& term, double dt, double* decay, double* beta) {
  const double x = dt / term.tau;
  *decay = std::exp(-x);
  *beta = x > 1e-8 ? -std::expm1(-x) / x : 1.0 - 0.5 * x;
}

ViscousStep FemModel::BeginViscousStep(const TissueState& base, double dt, double* offset) const {
  const auto& state = static_cast<const FemState&>(base);
  ViscousStep step;
  double gamma_sum = 0.0;
  step.g = 0.0;
  for (const PronyTerm& t : prony_) {
    double decay = 0.0, beta = 0.0;
    PronyFactors(t, dt, &decay, &beta);
    step.g += t.gamma * beta;
    gamma_sum += t.gamma;
  }
  step.g += 1.0 - gamma_sum;  // γ∞
  const size_t m = static_cast<size_t>(num_tets()), terms = prony_.size();
  // e^{-dt/τ_k} and γ_k β_k, the same for every element (at most kMaxPronyTerms).
  double decay[kMaxPronyTerms] = {}, weight[kMaxPronyTerms] = {};
  for (size_t k = 0; k < terms; ++k) {
    double beta = 0.0;
    PronyFactors(prony_[k], dt, &decay[k], &beta);
    weight[k] = prony_[k].gamma * beta;
  }
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
  for (size_t k = 0; k < terms; ++k) {
    double beta = 0.0;
    PronyFactors(prony_[k], dt, &decay[k], &beta);
    weight[k] = prony_[k].gamma * beta;
  }
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
