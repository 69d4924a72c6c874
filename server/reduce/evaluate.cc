#include "server/reduce/evaluate.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <set>
#include <stdexcept>

namespace somasim::reduce {

double CaseScale(const reduced::EvaluationCase& c, double t) {
  if (c.time_size() == 0) return 1.0;
  if (t <= c.time(0)) return c.scale(0);
  for (int k = 1; k < c.time_size(); ++k) {
    if (t <= c.time(k)) {
      const double w = (t - c.time(k - 1)) / (c.time(k) - c.time(k - 1));
      return (1.0 - w) * c.scale(k - 1) + w * c.scale(k);
    }
  }
  return c.scale(c.time_size() - 1);
}

void CheckPlan(const reduced::EvaluationPlan& plan, int32_t num_nodes,
               const std::vector<int32_t>& fixed) {
  const std::set<int32_t> held(fixed.begin(), fixed.end());
  if (plan.cases_size() == 0) throw std::invalid_argument("evaluation plan: no case");
  for (int k = 0; k < plan.cases_size(); ++k) {
    const reduced::EvaluationCase& c = plan.cases(k);
    const std::string where =
        "evaluation plan: cases[" + std::to_string(k) + "] (" + c.name() + ")";
    const auto fail = [&](const std::string& what) {
      throw std::invalid_argument(where + ": " + what);
    };
    if (c.node() < 0 || c.node() >= num_nodes) {
      fail("node " + std::to_string(c.node()) + " out of range");
    }
    if (held.count(c.node()) != 0) fail("node " + std::to_string(c.node()) + " is held");
    if (c.force_size() != 3) fail("force needs 3 values");
    for (const double f : c.force()) {
      if (!std::isfinite(f)) fail("force is not finite");
    }
    if (c.time_size() != c.scale_size()) fail("time and scale differ in length");
    for (int i = 0; i < c.time_size(); ++i) {
      if (!std::isfinite(c.time(i)) || !std::isfinite(c.scale(i))) fail("history not finite");
      if (i > 0 && !(c.time(i) > c.time(i - 1))) fail("time must increase");
    }
    if (!(c.end_time() > 0.0) || !std::isfinite(c.end_time())) fail("end_time must be > 0");
    if (!(c.dt() > 0.0) || !std::isfinite(c.dt())) fail("dt must be > 0");
    if (c.end_time() / c.dt() > 100000.0) fail("more than 100000 steps");
  }
}

std::vector<CaseResult> Evaluate(const models::fem::FemModel& full,
                                 const std::vector<int32_t>& fixed,
                                 const models::TissueModel& reduced,
                                 const reduced::EvaluationPlan& plan,
                                 const Eigen::MatrixXd* modes) {
  CheckPlan(plan, full.num_nodes(), fixed);
  if (reduced.num_nodes() != full.num_nodes()) {
    throw std::invalid_argument("evaluate: the reduced model is not on the full model's mesh");
  }
  std::vector<CaseResult> results;
  const mesh::Points& rest = full.rest_positions();
  for (const reduced::EvaluationCase& c : plan.cases()) {
    CaseResult r;
    r.name = c.name();
    r.group = c.group();
    const Eigen::Vector3d force(c.force(0), c.force(1), c.force(2));
    mesh::Points forces = mesh::Points::Zero(3, full.num_nodes());
    models::fem::StaticLoads loads;
    loads.external_forces = &forces;
    loads.fixed_nodes = fixed;
    loads.reuse_factorisation = true;
    models::fem::StaticWorkspace workspace;
    auto full_state = full.MakeState();
    auto reduced_state = reduced.MakeState();
    models::StepInputs inputs;
    inputs.dt = c.dt();
    inputs.external_forces = &forces;
    inputs.fixed_nodes = fixed;
    double error = 0.0, norm = 0.0, node_error = 0.0, node_norm = 0.0, floor = 0.0;
    double step_seconds = 0.0;
    const auto steps = static_cast<int>(std::llround(c.end_time() / c.dt()));
    // The nodes near the loaded one (kNearRadius), for the near / far split of each step.
    std::vector<uint8_t> near(static_cast<size_t>(full.num_nodes()), 0);
    for (Eigen::Index i = 0; i < rest.cols(); ++i) {
      near[static_cast<size_t>(i)] = (rest.col(i) - rest.col(c.node())).norm() <= kNearRadius;
    }
    r.per_step.reserve(static_cast<size_t>(std::max(steps, 0)));
    for (int s = 1; s <= steps; ++s) {
      const double t = c.dt() * s;
      forces.col(c.node()) = CaseScale(c, t) * force;
      r.converged = full.SolveQuasiStatic(loads, c.dt(), full_state.get(), &workspace).converged &&
                    r.converged;
      const auto before = std::chrono::steady_clock::now();
      if (reduced.Step(inputs, reduced_state.get()) != models::StepStatus::kOk) {
        r.converged = false;
      }
      step_seconds +=
          std::chrono::duration<double>(std::chrono::steady_clock::now() - before).count();
      const mesh::Points u = full_state->positions - rest;
      const mesh::Points v = reduced_state->positions - rest;
      StepRecord record;
      record.time_s = t;
      record.scale = CaseScale(c, t);
      const double step_error = (u - v).squaredNorm(), step_norm = u.squaredNorm();
      double near_error = 0.0;
      for (Eigen::Index i = 0; i < u.cols(); ++i) {
        if (near[static_cast<size_t>(i)] != 0) near_error += (u.col(i) - v.col(i)).squaredNorm();
      }
      const auto relative = [step_norm](double squared) {
        return step_norm > 0.0 ? std::sqrt(squared / step_norm) : 0.0;
      };
      record.field_error = relative(step_error);
      record.near_error = relative(near_error);
      record.far_error = relative(std::max(step_error - near_error, 0.0));
      error += step_error;
      if (modes != nullptr) {
        const Eigen::Map<const Eigen::VectorXd> flat(u.data(), u.size());
        const double step_floor = (flat - *modes * (modes->transpose() * flat)).squaredNorm();
        floor += step_floor;
        record.basis_error = relative(step_floor);
      }
      record.node_full_m = u.col(c.node());
      record.node_reduced_m = v.col(c.node());
      r.per_step.push_back(record);
      norm += step_norm;
      node_error += (u.col(c.node()) - v.col(c.node())).squaredNorm();
      node_norm += u.col(c.node()).squaredNorm();
      r.full_end_m = u.col(c.node()).norm();
      r.reduced_end_m = v.col(c.node()).norm();
    }
    r.steps = steps;
    r.reduced_unconverged = reduced_state->counters.solver_unconverged;
    r.reduced_step_us = steps > 0 ? 1e6 * step_seconds / steps : 0.0;
    r.field_error = norm > 0.0 ? std::sqrt(error / norm) : 0.0;
    r.node_error = node_norm > 0.0 ? std::sqrt(node_error / node_norm) : 0.0;
    if (modes != nullptr) r.basis_error = norm > 0.0 ? std::sqrt(floor / norm) : 0.0;
    results.push_back(r);
  }
  return results;
}

}  // namespace somasim::reduce
