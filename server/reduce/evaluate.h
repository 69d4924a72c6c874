// `somasim-reduce --evaluate` (issue 12; docs/reduced.md): a reduced model against the full
// model it was made from, on load histories it was not built from (an EvaluationPlan). Each case
// runs on the full model quasi-statically with its QLV internal variables (SolveQuasiStatic)
// and on the reduced model (its quasi-static steps, creep scaling included), with the same
// loads at the same times; compared:
//   field error  sqrt(Σ_t |u(t) − û(t)|²) / sqrt(Σ_t |u(t)|²)  over every node and step,
//   node error   the same at the loaded node only,
//   and the loaded node's displacement at the end (full and reduced) [m].
// Offline (minutes on liver4055); allocates.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "idl/reduced_model.pb.h"
#include "server/models/fem/fem_model.h"
#include "server/models/reduced/kl_model.h"

namespace somasim::reduce {

// One step of a case (the curves behind a case's errors; `--per-step FILE` writes them).
struct StepRecord {
  double time_s = 0.0;
  double scale = 0.0;        // the force's scale at this step (CaseScale)
  double field_error = 0.0;  // |u − û| / |u| over every node at this step (0 when u = 0)
  // |u − û| over the nodes within kNearRadius of the loaded node, and over the others, each
  // relative to the whole |u| (near² + far² = field²).
  double near_error = 0.0;
  double far_error = 0.0;
  double basis_error = -1.0;  // |u − B Bᵀ u| / |u| at this step, -1 without modes
  Eigen::Vector3d node_full_m = Eigen::Vector3d::Zero();     // u at the loaded node [m]
  Eigen::Vector3d node_reduced_m = Eigen::Vector3d::Zero();  // û there [m]
};

// The radius [m] (about a tool's dent) that splits a step's error into near and far.
inline constexpr double kNearRadius = 0.02;

struct CaseResult {
  std::string name, group;
  double field_error = 0.0;
  double node_error = 0.0;
  double full_end_m = 0.0;     // |u| at the loaded node at the end [m]
  double reduced_end_m = 0.0;  // |û| there [m]
  int steps = 0;
  bool converged = true;  // every full step converged
  // Reduced steps whose Newton solve stopped short of its tolerance (TissueState's
  // solver_unconverged): their fields are the last iterates.
  int64_t reduced_unconverged = 0;
  // The basis's floor: the field error of the full solution's orthogonal projection onto the
  // modes (B Bᵀ u, orthonormal B), which no model on these modes can beat by much; -1 when no
  // modes were given.
  double basis_error = -1.0;
  double reduced_step_us = 0.0;      // the reduced model's mean step (wall time) [µs]
  std::vector<StepRecord> per_step;  // one per step
};

// The force scale of `c` at time t (piecewise linear; 1 without a history).
double CaseScale(const reduced::EvaluationCase& c, double t);

// Checks a plan against a model of `num_nodes` nodes; throws std::invalid_argument naming the
// case and field (a node out of range or held, a force not of 3 finite values, times not
// increasing, end_time or dt not > 0, too many steps).
void CheckPlan(const reduced::EvaluationPlan& plan, int32_t num_nodes,
               const std::vector<int32_t>& fixed);

// `reduced`: any model on the full model's mesh (seed 000's KlReducedModel, the
// NonlinearReducedModel); `modes` (3N × n, orthonormal), if given, for the basis's floor.
std::vector<CaseResult> Evaluate(const models::fem::FemModel& full,
                                 const std::vector<int32_t>& fixed,
                                 const models::TissueModel& reduced,
                                 const reduced::EvaluationPlan& plan,
                                 const Eigen::MatrixXd* modes = nullptr);

}  // namespace somasim::reduce
