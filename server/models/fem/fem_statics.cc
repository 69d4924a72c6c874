// FemModel's static and quasi-static solves: Newton's method on the total potential with load
// stepping, a predictor per load step, a backtracking line search and CHOLMOD factorisations,
// one solve at a time in a FemModel::StaticSolve; the workspace that solves keep between calls.
#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/checks/finite.h"
#include "server/models/fem/fem_model.h"
#include "server/models/fem/fem_model_internal.h"
#include "server/models/fem/sparse_cholesky.h"

namespace somasim::models::fem {

using internal::Refuse;

struct StaticWorkspace::Impl {
  const FemModel* owner = nullptr;  // the model the pattern below belongs to
  std::vector<int32_t> dof;         // 3 × num_nodes: free DOF number, or -1 where held
  std::vector<int32_t> lower_dof;   // the numbering k_free (and the analysis) is for
  BlockSparseMatrix tangent;        // the model's pattern
  LowerCsc k_free;                  // the tangent on the free DOFs, scalar lower triangle
  std::vector<int32_t> k_source;    // k_free.values[k] = tangent value k_source[k]
  SparseCholesky cholesky;
  bool analysed = false;       // cholesky holds the analysis of k_free's pattern
  bool factorised = false;     // and a factor of a tangent on these free DOFs
  std::vector<double> offset;  // a QLV step's offset stress, 9 × num_tets
  // The last converged call's result and its change from where it started (time-history mode,
  // StaticLoads::reuse_factorisation), 3 × num_nodes.
  bool has_history = false;
  mesh::Points last_solution, last_change;
};

StaticWorkspace::StaticWorkspace() : impl_(std::make_unique<Impl>()) {}
StaticWorkspace::~StaticWorkspace() = default;

// One SolveStaticImpl call: the loads checked and the free DOFs numbered, then per load step the
// Dirichlet values, a predictor and Newton iterations (each a factorised or reused tangent, its
// correction and a line search), then the reactions. `state` holds the positions throughout.
class FemModel::StaticSolve {
 public:
  StaticSolve(const FemModel& model, const StaticLoads& loads, TissueState* state,
              const ViscousStep* viscous, StaticWorkspace::Impl* ws, bool single_iteration)
      : model_(model),
        sh_(model.ShapeOf(*state)),
        loads_(loads),
        state_(state),
        viscous_(viscous),
        ws_(*ws),
        dof_(ws->dof),
        single_iteration_(single_iteration),
        n_(static_cast<size_t>(model.num_nodes())) {}

  StaticResult Run();

 private:
  // A fresh workspace, or one another model used: start over.
  void AdoptWorkspace();
  // Refuses bad loads (sizes, indices, NaN) and numbers the free DOFs (dof_, num_dofs_); new held
  // DOFs get a new reduced pattern and a new analysis.
  void CheckLoadsAndNumberDofs();
  // The positions this load step puts the held DOFs at (the free ones where they are).
  mesh::Points LoadStepTarget(double scale) const;
  // Newton at one load step from the last one's equilibrium: whether it converged.
  bool SolveLoadStep(double scale);
  // Moves to `target`, the free DOFs following the held ones through the tangent.
  void Predict(double scale, const mesh::Points& target, Eigen::VectorXd* r);
  // Time-history mode: from the last call's solution, extrapolated along its change.
  void Extrapolate(double scale, Eigen::VectorXd* r);
  // Newton iterations from residual r (|r| = *r_norm); returns whether the last correction was
  // below step_tolerance.
  bool Iterate(double scale, double reference, Eigen::VectorXd* r, double* r_norm);
  // Backtracking along du from the current positions; leaves the positions at the accepted step
  // and returns its length t (halved once more if none was accepted).
  double LineSearch(double scale, const Eigen::VectorXd& r, double r_norm,
                    const Eigen::VectorXd& du, Eigen::VectorXd* r_new, double* r_new_norm);
  // Free-DOF residual r = f(x) + scale · load into r; returns |scale · load| on the free DOFs.
  double Residual(double scale, Eigen::VectorXd* r);
  // The total potential Π = elastic energy - scale · load · u.
  double Potential(double scale) const;
  // Factorises the tangent at the state's positions: the exact one when it is positive definite
  // on the free DOFs, else the rotated one (corotational), else the rest stiffness (always
  // positive definite: a quasi-Newton step). The linear model's K is constant: factorised once.
  bool FactoriseTangent();
  // positions += t du on the free DOFs.
  void MoveFreeDofs(const Eigen::VectorXd& du, double t);
  // The result once the load steps are done: the reactions, the workspace's history.
  StaticResult Finish();

  const FemModel& model_;
  const Shape sh_;
  const StaticLoads& loads_;
  TissueState* const state_;
  const ViscousStep* const viscous_;
  StaticWorkspace::Impl& ws_;
  std::vector<int32_t>& dof_;  // ws_.dof
  const bool single_iteration_;
  const size_t n_;        // num_nodes
  int32_t num_dofs_ = 0;  // free DOFs
  mesh::Points load_;     // [N], total load at full scale: external forces and gravity
  mesh::Points start_;    // [m], the positions the call started from
  mesh::Points forces_;   // [N], f at the positions of the last Residual
  StaticResult result_;
  bool linear_factorised_ = false;
};

StaticResult FemModel::StaticSolve::Run() {
  AdoptWorkspace();
  CheckLoadsAndNumberDofs();
  load_ = mesh::Points::Zero(3, model_.num_nodes());
  if (loads_.external_forces != nullptr) load_ = *loads_.external_forces;
  for (size_t i = 0; i < n_; ++i) {
    load_.col(static_cast<Eigen::Index>(i)) += model_.mass_[i] * loads_.gravity;
  }
  start_ = state_->positions;
  forces_.resize(3, model_.num_nodes());
  // A single iteration (NewtonIteration) is at full load, with the held DOFs put in place.
  const int load_steps = single_iteration_ ? 1 : loads_.load_steps;
  for (int step = 1; step <= load_steps; ++step) {
    if (!SolveLoadStep(static_cast<double>(step) / load_steps)) break;
  }
  return Finish();
}

void FemModel::StaticSolve::AdoptWorkspace() {
  if (ws_.owner == &model_) return;
  ws_.owner = &model_;
  ws_.tangent = model_.pattern_;
  ws_.lower_dof.clear();
  ws_.analysed = false;
  ws_.factorised = false;
  ws_.has_history = false;
}

void FemModel::StaticSolve::CheckLoadsAndNumberDofs() {
  const int32_t num_nodes = model_.num_nodes();
  if (loads_.external_forces != nullptr &&
      (loads_.external_forces->cols() != num_nodes || !loads_.external_forces->allFinite())) {
    Refuse("static external forces must be 3 x num_nodes and finite");
  }
  if (!loads_.gravity.allFinite()) Refuse("static gravity must be finite");
  if (!(loads_.load_steps > 0) || !(loads_.tolerance > 0.0) || !(loads_.step_tolerance >= 0.0) ||
      !(loads_.max_newton_iterations > 0)) {
    Refuse("load_steps, tolerance, step_tolerance and max_newton_iterations must be > 0");
  }
  if (loads_.reuse_factorisation && !(loads_.reuse_ratio > 0.0 && loads_.reuse_ratio < 1.0)) {
    Refuse("reuse_ratio must lie in (0, 1)");
  }
  dof_.assign(3 * n_, 0);
  for (const int32_t node : loads_.fixed_nodes) {
    if (node < 0 || node >= num_nodes) {
      Refuse("fixed node " + std::to_string(node) + " out of range");
    }
    for (size_t c = 0; c < 3; ++c) dof_[3 * static_cast<size_t>(node) + c] = -1;
  }
  if (!loads_.prescribed_nodes.empty() &&
      (loads_.prescribed_positions == nullptr ||
       loads_.prescribed_positions->cols() !=
           static_cast<Eigen::Index>(loads_.prescribed_nodes.size()) ||
       !loads_.prescribed_positions->allFinite())) {
    Refuse("prescribed positions must be 3 x prescribed_nodes and finite");
  }
  for (const int32_t node : loads_.prescribed_nodes) {
    if (node < 0 || node >= num_nodes) {
      Refuse("prescribed node " + std::to_string(node) + " out of range");
    }
    for (size_t c = 0; c < 3; ++c) dof_[3 * static_cast<size_t>(node) + c] = -1;
  }
  for (const ComponentConstraint& c : loads_.components) {
    if (c.node < 0 || c.node >= num_nodes || c.axis < 0 || c.axis > 2 || !std::isfinite(c.value)) {
      Refuse("component constraint on node " + std::to_string(c.node) + " axis " +
             std::to_string(c.axis) + " is out of range or not finite");
    }
    dof_[3 * static_cast<size_t>(c.node) + static_cast<size_t>(c.axis)] = -1;
  }
  num_dofs_ = 0;
  for (int32_t& d : dof_) {
    if (d == 0) d = num_dofs_++;
  }
  if (dof_ != ws_.lower_dof) {  // new held DOFs: a new reduced pattern and a new analysis
    ws_.k_free = ws_.tangent.ScalarLowerPattern(dof_, num_dofs_, &ws_.k_source);
    ws_.lower_dof = dof_;
    ws_.analysed = false;
    ws_.factorised = false;
  }
}

mesh::Points FemModel::StaticSolve::LoadStepTarget(double scale) const {
  // The Dirichlet values move in increments too.
  mesh::Points target = state_->positions;
  for (const int32_t node : loads_.fixed_nodes) target.col(node) = sh_.rest.col(node);
  for (size_t k = 0; k < loads_.prescribed_nodes.size(); ++k) {
    const int32_t node = loads_.prescribed_nodes[k];
    const Eigen::Index kk = static_cast<Eigen::Index>(k);
    target.col(node) =
        start_.col(node) + scale * (loads_.prescribed_positions->col(kk) - start_.col(node));
  }
  for (const ComponentConstraint& c : loads_.components) {
    const double from = start_(c.axis, c.node);
    target(c.axis, c.node) = from + scale * (c.value - from);
  }
  return target;
}

bool FemModel::StaticSolve::SolveLoadStep(double scale) {
  const mesh::Points target = LoadStepTarget(scale);
  Eigen::VectorXd r;
  Predict(scale, target, &r);
  Extrapolate(scale, &r);
  result_.residual_history.clear();
  const double load_norm = Residual(scale, &r);
  // A scale for "zero" when nothing is loaded (pure Dirichlet): the forces at the start.
  double reference = load_norm;
  if (!(reference > 0.0)) {
    reference = 0.0;
    for (Eigen::Index k = 0; k < forces_.size(); ++k) {
      reference += forces_.data()[k] * forces_.data()[k];
    }
    reference = std::max(std::sqrt(reference), 1e-300);
  }
  double r_norm = r.norm();
  const bool small_step = Iterate(scale, reference, &r, &r_norm);
  result_.final_residual = r_norm / reference;
  result_.converged = r_norm <= loads_.tolerance * reference || small_step || num_dofs_ == 0;
  return result_.converged;
}

void FemModel::StaticSolve::Predict(double scale, const mesh::Points& target, Eigen::VectorXd* r) {
  const mesh::Points increment = target - state_->positions;  // zero on free DOFs
  // The free DOFs follow the held ones through the tangent at the last equilibrium,
  // K_ff Δu_f = r_f - K_fc d_c (moving only the held nodes would crush the elements next to
  // them, and a hyperelastic tangent there may not be positive definite).
  if (single_iteration_ || num_dofs_ == 0 || !(increment.cwiseAbs().maxCoeff() > 0.0) ||
      !FactoriseTangent()) {
    state_->positions = target;
    return;
  }
  Residual(scale, r);
  mesh::Points moved(3, model_.num_nodes());
  ws_.tangent.Multiply(increment.data(), moved.data(), nullptr);
  for (size_t k = 0; k < 3 * n_; ++k) {
    if (dof_[k] >= 0) (*r)[dof_[k]] -= moved.data()[k];
  }
  Eigen::VectorXd du(num_dofs_);
  ws_.cholesky.Solve(r->data(), du.data());
  const mesh::Points before = state_->positions;
  state_->positions = target;
  MoveFreeDofs(du, 1.0);
  if (!std::isfinite(Residual(scale, r)) || !r->allFinite()) {  // overshot: no predictor
    state_->positions = before + increment;
  }
}

void FemModel::StaticSolve::Extrapolate(double scale, Eigen::VectorXd* r) {
  // A state that is the one the last call left starts from its positions extrapolated along that
  // call's change (the next step of a creep or relaxation is close to it), cutting the first
  // residual and so the iterations; not where that is not finite.
  if (!loads_.reuse_factorisation || loads_.load_steps != 1 || single_iteration_ ||
      !ws_.has_history || ws_.last_solution.cols() != model_.num_nodes() ||
      state_->positions != ws_.last_solution) {
    return;
  }
  const mesh::Points here = state_->positions;
  for (size_t k = 0; k < 3 * n_; ++k) {
    if (dof_[k] >= 0) state_->positions.data()[k] += ws_.last_change.data()[k];
  }
  if (!std::isfinite(Residual(scale, r)) || !r->allFinite() || !std::isfinite(Potential(scale))) {
    state_->positions = here;
  }
}

bool FemModel::StaticSolve::Iterate(double scale, double reference, Eigen::VectorXd* r,
                                    double* r_norm) {
  bool small_step = false;
  const int max_iterations = single_iteration_ ? 1 : loads_.max_newton_iterations;
  bool refactorise = false;
  for (int it = 0; num_dofs_ > 0 && it < max_iterations &&
                   (single_iteration_ || *r_norm > loads_.tolerance * reference) && !small_step;
       ++it) {
    // Modified Newton keeps the last factor until a step with it does not shrink the residual
    // by reuse_ratio.
    const bool reuse = loads_.reuse_factorisation && ws_.factorised && !refactorise;
    if (!reuse && !FactoriseTangent()) break;
    Eigen::VectorXd du(num_dofs_);
    ws_.cholesky.Solve(r->data(), du.data());
    Eigen::VectorXd r_new;
    double r_new_norm = 0.0;
    const double t = LineSearch(scale, *r, *r_norm, du, &r_new, &r_new_norm);
    refactorise = r_new_norm > loads_.reuse_ratio * *r_norm;
    *r = r_new;
    *r_norm = r_new_norm;
    double u_norm2 = 0.0;
    for (size_t k = 0; k < 3 * n_; ++k) {
      const double u = state_->positions.data()[k] - sh_.rest.data()[k];
      u_norm2 += u * u;
    }
    small_step = t * du.norm() <= loads_.step_tolerance * std::sqrt(u_norm2);
    ++result_.newton_iterations;
    result_.residual_history.push_back(*r_norm / reference);
  }
  return small_step;
}

double FemModel::StaticSolve::LineSearch(double scale, const Eigen::VectorXd& r, double r_norm,
                                         const Eigen::VectorXd& du, Eigen::VectorXd* r_new,
                                         double* r_new_norm) {
  // Backtracking on the potential (Armijo), accepting a full step that lowers the residual
  // (tested first: the potential is evaluated only when needed).
  double pi0 = 0.0;
  bool have_pi0 = false;
  const double slope = -r.dot(du);  // dΠ/dt along du at t = 0 (r = -∇Π)
  const mesh::Points before = state_->positions;
  double t = 1.0;
  for (int ls = 0; ls < 20; ++ls) {
    state_->positions = before;
    MoveFreeDofs(du, t);
    Residual(scale, r_new);
    *r_new_norm = r_new->norm();
    if (*r_new_norm < r_norm) break;
    if (!have_pi0) {
      const mesh::Points trial = state_->positions;
      state_->positions = before;
      pi0 = Potential(scale);
      have_pi0 = true;
      state_->positions = trial;
    }
    if (Potential(scale) <= pi0 + 1e-4 * t * slope) break;
    t *= 0.5;
  }
  return t;
}

double FemModel::StaticSolve::Residual(double scale, Eigen::VectorXd* r) {
  model_.ElasticForces(sh_, state_->positions, forces_.data(), nullptr, viscous_);
  r->setZero(num_dofs_);
  double load_norm2 = 0.0;
  for (size_t k = 0; k < 3 * n_; ++k) {
    if (dof_[k] < 0) continue;
    const double l = scale * load_.data()[k];
    (*r)[dof_[k]] = forces_.data()[k] + l;
    load_norm2 += l * l;
  }
  return std::sqrt(load_norm2);
}

double FemModel::StaticSolve::Potential(double scale) const {
  double value = model_.ElasticEnergy(sh_, state_->positions, viscous_);
  for (Eigen::Index k = 0; k < load_.size(); ++k) {
    value -= scale * load_.data()[k] * (state_->positions.data()[k] - sh_.rest.data()[k]);
  }
  return value;
}

bool FemModel::StaticSolve::FactoriseTangent() {
  if (model_.kind_ == FemKind::kLinear && linear_factorised_) return true;
  for (int attempt = 0; attempt < 3; ++attempt) {
    if (attempt == 1 && model_.kind_ != FemKind::kCorotational) continue;
    // 0: the exact tangent at x; 1: the rotated (warped) one, positive semi-definite; 2: the
    // exact tangent at rest.
    model_.AssembleElementTangents(sh_, attempt == 2 ? sh_.rest : state_->positions, attempt != 1,
                                   viscous_, &ws_.tangent);
    ws_.tangent.FillScalarLower(ws_.k_source, &ws_.k_free);
    if (!ws_.analysed) {
      ws_.cholesky.Analyse(ws_.k_free);
      ws_.analysed = true;
    }
    ++result_.factorisations;
    if (ws_.cholesky.Factorise(ws_.k_free)) {
      linear_factorised_ = true;
      ws_.factorised = true;
      return true;
    }
  }
  ws_.factorised = false;
  return false;
}

void FemModel::StaticSolve::MoveFreeDofs(const Eigen::VectorXd& du, double t) {
  for (size_t k = 0; k < 3 * n_; ++k) {
    if (dof_[k] >= 0) state_->positions.data()[k] += t * du[dof_[k]];
  }
}

StaticResult FemModel::StaticSolve::Finish() {
  state_->velocities.setZero();
  if (single_iteration_) {
    result_.converged = result_.final_residual <= loads_.tolerance;
    return std::move(result_);
  }
  ws_.has_history = result_.converged;
  if (result_.converged) {
    ws_.last_change = state_->positions - start_;
    ws_.last_solution = state_->positions;
  }
  // Reactions: what the supports must supply, -(f(x) + load) on the held DOFs. forces_ is f at
  // the final positions already: every path above ends on a residual evaluation there.
  result_.reactions = mesh::Points::Zero(3, model_.num_nodes());
  for (size_t k = 0; k < 3 * n_; ++k) {
    if (dof_[k] < 0) result_.reactions.data()[k] = -(forces_.data()[k] + load_.data()[k]);
  }
  return std::move(result_);
}

StaticResult FemModel::SolveStaticImpl(const StaticLoads& loads, TissueState* state,
                                       const ViscousStep* viscous, StaticWorkspace* workspace,
                                       bool single_iteration) const {
  StaticWorkspace local;
  if (workspace == nullptr) workspace = &local;
  return StaticSolve(*this, loads, state, viscous, workspace->impl_.get(), single_iteration).Run();
}

StaticResult FemModel::SolveStatic(const StaticLoads& loads, TissueState* state,
                                   StaticWorkspace* workspace) const {
  return SolveStaticImpl(loads, state, nullptr, workspace, false);
}

StaticResult FemModel::NewtonIteration(const StaticLoads& loads, TissueState* state,
                                       StaticWorkspace* workspace) const {
  return SolveStaticImpl(loads, state, nullptr, workspace, true);
}

StaticResult FemModel::SolveQuasiStatic(const StaticLoads& loads, double dt, TissueState* state,
                                        StaticWorkspace* workspace) const {
  if (!checks::FinitePositive(dt)) Refuse("quasi-static dt [s] must be > 0");
  if (prony_.empty()) return SolveStaticImpl(loads, state, nullptr, workspace, false);
  StaticWorkspace local;
  if (workspace == nullptr) workspace = &local;
  std::vector<double>& offset = workspace->impl_->offset;
  offset.resize(9 * static_cast<size_t>(num_tets()));
  const ViscousStep viscous = BeginViscousStep(*state, dt, offset.data());
  StaticResult result = SolveStaticImpl(loads, state, &viscous, workspace, false);
  if (result.converged) {
    EndViscousStep(dt, state);
    state->time += dt;
  }
  return result;
}

}  // namespace somasim::models::fem
