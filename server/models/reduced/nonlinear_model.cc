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
#include "server/models/reduced/nonlinear_internal.h"

namespace somasim::models::reduced {

using Eigen::Matrix3d;
using nonlinear_internal::BeginViscous;
using nonlinear_internal::NonlinearState;

namespace {

void Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("nonlinear reduced model: " + what);
}

}  // namespace

double nonlinear_internal::BeginViscous(const std::vector<fem::PronyTerm>& prony, double dt,
                                        const Eigen::VectorXd& history,
                                        const Eigen::VectorXd& elastic_last,
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
