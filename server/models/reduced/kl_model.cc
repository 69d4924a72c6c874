#include "server/models/reduced/kl_model.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#include "common/checks/finite.h"
#include "server/models/particle_mesh.h"

namespace somasim::models::reduced {
namespace {

// The state: the reduced coordinates (ModalState), the creep bookkeeping and the step's
// scratch, sized by MakeState.
class KlState final : public ModalState {
 public:
  Eigen::VectorXd rhs, load;   // n: the step's right-hand side and the tool's part of it
  Eigen::MatrixXd system;      // n × n: Bᵀ K B plus the springs
  Eigen::MatrixXd springs;     // n × n: the springs' part
  Eigen::VectorXd spring_rhs;  // n
  Eigen::LLT<Eigen::MatrixXd> llt;
  double onset = -1.0;  // [s] when the tool's load came on; < 0: no load
  double multiplier = 1.0, good_multiplier = 1.0;
  double good_onset = -1.0;

 protected:
  void SaveGood() override {
    SaveModal();
    good_multiplier = multiplier;
    good_onset = onset;
  }
  // The base class has copied its last-good buffers (unused here) into x and v; they are
  // rebuilt from the last accepted ξ.
  void RestoreGood() override {
    multiplier = good_multiplier;
    onset = good_onset;
    RestoreModal();
  }
};

void Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("reduced model: " + what);
}

}  // namespace

std::unique_ptr<KlReducedModel> KlReducedModel::Create(KlModelData data) {
  CheckModalData(data.rest, data.masses, data.modes, "reduced model: ");
  const Eigen::Index nodes = data.rest.cols();
  const Eigen::Index n = data.modes.cols();
  Require(data.stiffness_modes.rows() == data.modes.rows() && data.stiffness_modes.cols() == n,
          "stiffness_modes (K B) must have the modes' shape");
  Require(data.stiffness_modes.allFinite(), "K B is not finite");
  Require(data.reduced_stiffness.rows() == n && data.reduced_stiffness.cols() == n,
          "reduced_stiffness must be n × n (n = " + std::to_string(n) + ")");
  Require(data.reduced_stiffness.allFinite(), "the reduced stiffness is not finite");
  const double scale = data.reduced_stiffness.cwiseAbs().maxCoeff();
  Require((data.reduced_stiffness - data.reduced_stiffness.transpose()).cwiseAbs().maxCoeff() <=
              1e-9 * scale,
          "the reduced stiffness is not symmetric");
  Require(checks::FiniteNonNegative(data.creep_radius), "creep_radius must be >= 0");
  Require(checks::FinitePositive(data.penalty_stiffness), "penalty_stiffness must be > 0");
  Require(checks::FinitePositive(data.max_local_stiffness), "max_local_stiffness must be > 0");
  std::vector<uint8_t> has_curve(static_cast<size_t>(nodes), 0);
  for (size_t c = 0; c < data.creep.size(); ++c) {
    const CreepCurve& curve = data.creep[c];
    const std::string which = "creep curve " + std::to_string(c) + ": ";
    Require(curve.node >= 0 && curve.node < nodes,
            which + "node " + std::to_string(curve.node) + " out of range");
    Require(has_curve[static_cast<size_t>(curve.node)] == 0,
            which + "node " + std::to_string(curve.node) + " has another curve");
    has_curve[static_cast<size_t>(curve.node)] = 1;
    Require(checks::FinitePositive(curve.interval), which + "interval must be > 0");
    Require(!curve.multiplier.empty(), which + "no sample");
    for (const double v : curve.multiplier) {
      Require(checks::FinitePositive(v), which + "a multiplier is not finite and > 0");
    }
    Require(std::abs(curve.multiplier.front() - 1.0) <= 1e-6, which + "c(0) must be 1");
  }
  auto model = std::unique_ptr<KlReducedModel>(new KlReducedModel(std::move(data)));
  Require(model->factor_.info() == Eigen::Success,
          "the reduced stiffness is not positive definite");
  return model;
}

KlReducedModel::KlReducedModel(KlModelData data) : data_(std::move(data)) {
  const Eigen::Index nodes = data_.rest.cols(), n = data_.modes.cols();
  factor_.compute(data_.reduced_stiffness);
  if (factor_.info() != Eigen::Success) return;  // Create refuses it
  gravity_modes_ = Eigen::MatrixXd::Zero(n, 3);
  compliance_.resize(static_cast<size_t>(nodes));
  moves_.assign(static_cast<size_t>(nodes), 0);
  const double mode_scale = data_.modes.cwiseAbs().maxCoeff();
  for (Eigen::Index i = 0; i < nodes; ++i) {
    const auto rows = data_.modes.middleRows(3 * i, 3);  // B_i: 3 × n
    for (int a = 0; a < 3; ++a) gravity_modes_.col(a) += data_.masses[i] * rows.row(a).transpose();
    const Eigen::MatrixXd y = factor_.solve(rows.transpose());  // n × 3
    compliance_[static_cast<size_t>(i)] = rows * y;
    moves_[static_cast<size_t>(i)] = rows.cwiseAbs().maxCoeff() > 1e-9 * mode_scale ? 1 : 0;
  }
  // Each node's creep curve: its own, else the nearest curve node's within creep_radius.
  curve_of_node_.assign(static_cast<size_t>(nodes), -1);
  for (Eigen::Index i = 0; i < nodes; ++i) {
    double best = data_.creep_radius;
    for (size_t c = 0; c < data_.creep.size(); ++c) {
      const double d = (data_.rest.col(i) - data_.rest.col(data_.creep[c].node)).norm();
      if (d <= best) {
        best = d;
        curve_of_node_[static_cast<size_t>(i)] = static_cast<int32_t>(c);
      }
    }
  }
  field_ = ModalField(data_.modes);
  // Quasi-static: a load that comes on moves the tissue within one step, so the velocities
  // (displacement / dt) say nothing about divergence; only non-finite values do.
  set_speed_limit(std::numeric_limits<double>::max());
}

std::unique_ptr<TissueState> KlReducedModel::MakeState() const {
  auto state = std::make_unique<KlState>();
  InitialiseState(data_.rest, state.get());
  const Eigen::Index n = data_.modes.cols();
  state->InitialiseModal(field_, data_.rest.data(), speed_limit());
  state->rhs = Eigen::VectorXd::Zero(n);
  state->load = Eigen::VectorXd::Zero(n);
  state->system = data_.reduced_stiffness;
  state->springs = Eigen::MatrixXd::Zero(n, n);
  state->spring_rhs = Eigen::VectorXd::Zero(n);
  state->llt = Eigen::LLT<Eigen::MatrixXd>(n);
  state->llt.compute(state->system);  // sizes its storage
  return state;
}

double KlReducedModel::CurveValue(int32_t curve, double t) const {
  const CreepCurve& c = data_.creep[static_cast<size_t>(curve)];
  const double k = std::max(0.0, t) / c.interval;
  const size_t last = c.multiplier.size() - 1;
  if (k >= static_cast<double>(last)) return c.multiplier[last];
  const auto i = static_cast<size_t>(k);
  const double w = k - static_cast<double>(i);
  return (1.0 - w) * c.multiplier[i] + w * c.multiplier[i + 1];
}

void KlReducedModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* s = static_cast<KlState*>(base);
  // Gravity, then the tool's load and the node it mostly acts on.
  s->rhs.noalias() = gravity_modes_ * inputs.gravity;
  s->load.setZero();
  const int32_t loaded = inputs.external_forces != nullptr
                             ? AddProjectedLoads(data_.modes, *inputs.external_forces, &s->load)
                             : -1;
  const double t = s->time + inputs.dt;  // the end of the step
  if (loaded < 0) {
    s->onset = -1.0;
    s->multiplier = 1.0;
  } else {
    if (s->onset < 0.0) s->onset = s->time;
    const int32_t curve = curve_of_node_[static_cast<size_t>(loaded)];
    s->multiplier = curve < 0 ? 1.0 : CurveValue(curve, t - s->onset);
  }
  s->rhs += s->multiplier * s->load;
  // Springs: grasps, prescribed nodes, fixed nodes the modes can move.
  const bool springs =
      SpringTerms(data_.modes, data_.modes, data_.rest, moves_.data(), data_.penalty_stiffness,
                  inputs, s->positions, &s->springs, &s->spring_rhs);
  if (springs) {
    s->system = data_.reduced_stiffness + s->springs;
    s->rhs += s->spring_rhs;
  }
  s->xi_prev = s->xi;  // the last accepted step's
  if (springs) {
    s->llt.compute(s->system);
    s->xi = s->rhs;
    s->llt.solveInPlace(s->xi);
  } else {
    s->xi = s->rhs;
    factor_.solveInPlace(s->xi);
  }
  // Reconstruction: x = X + B ξ, v = B (ξ − ξ_prev) / dt.
  s->dt = inputs.dt;
  s->Rebuild();
}

Eigen::Matrix3d KlReducedModel::LocalStiffness(const TissueState& state, int32_t node) const {
  if (node < 0 || node >= num_nodes()) return Eigen::Matrix3d::Zero();
  const Eigen::Matrix3d compliance =
      CreepMultiplier(state) * compliance_[static_cast<size_t>(node)];
  return CappedStiffness(compliance, data_.max_local_stiffness);
}

void KlReducedModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  forces->resize(3, num_nodes());
  Eigen::Map<Eigen::VectorXd>(forces->data(), forces->size()).noalias() =
      -(data_.stiffness_modes * Coordinates(state));
}

EnergyReport KlReducedModel::Energy(const TissueState& state,
                                    const Eigen::Vector3d& gravity) const {
  EnergyReport e;
  const Eigen::VectorXd& xi = Coordinates(state);
  e.elastic = 0.5 * xi.dot(data_.reduced_stiffness * xi);
  AddKineticAndGravity(data_.masses, state, gravity, &e);
  return e;
}

const Eigen::VectorXd& KlReducedModel::Coordinates(const TissueState& state) const {
  return static_cast<const KlState&>(state).xi;
}

double KlReducedModel::CreepMultiplier(const TissueState& state) const {
  return static_cast<const KlState&>(state).multiplier;
}

}  // namespace somasim::models::reduced
