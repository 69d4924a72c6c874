// somasim-reduce's engine, seed 000's model (builder.h): the boundary normals, the elastic
// snapshots and creep curves of the full model, the modes and the choice of K.
#include "server/reduce/builder.h"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <set>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/checks/finite.h"
#include "common/mesh/topology.h"
#include "server/models/reduced/reduce_fem.h"
#include "server/reduce/builder_internal.h"

namespace somasim::reduce {

using builder_internal::Require;
using builder_internal::Tangents;
using models::fem::FemModel;
using models::fem::StaticLoads;
using models::fem::StaticWorkspace;
using models::reduced::StaticCase;

void builder_internal::Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("sampling plan: " + what);
}

std::pair<Eigen::Vector3d, Eigen::Vector3d> builder_internal::Tangents(const Eigen::Vector3d& n) {
  const Eigen::Vector3d helper =
      std::abs(n.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Vector3d t1 = n.cross(helper).normalized();
  return {t1, n.cross(t1)};
}

mesh::Points BoundaryNormals(const mesh::TetMesh& mesh) {
  const mesh::SurfaceMesh surface = mesh::ExtractBoundarySurface(mesh);
  mesh::Points normals = mesh::Points::Zero(3, mesh.vertices.cols());
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    const auto v = surface.triangles.col(t);
    const Eigen::Vector3d a = mesh.vertices.col(v(0));
    const Eigen::Vector3d n = (Eigen::Vector3d(mesh.vertices.col(v(1))) - a)
                                  .cross(Eigen::Vector3d(mesh.vertices.col(v(2))) - a);
    for (int k = 0; k < 3; ++k) normals.col(v(k)) += n;
  }
  for (Eigen::Index i = 0; i < normals.cols(); ++i) {
    const double norm = normals.col(i).norm();
    if (norm > 0.0) normals.col(i) /= norm;
  }
  return normals;
}

namespace {

// BuildKlModel's plan checks (the points on the boundary, not held); returns the boundary
// normals.
mesh::Points CheckKlPlan(const FemModel& full, const mesh::TetMesh& mesh,
                         const SamplingPlan& plan) {
  const int32_t nodes = full.num_nodes();
  Require(mesh.vertices.cols() == nodes, "the mesh is not the model's");
  Require(!plan.points.empty(), "no sample point");
  Require(!plan.fixed.empty(), "no support (fixed nodes): the organ would float");
  Require(!plan.forces.empty(), "no force magnitude");
  for (const double f : plan.forces) {
    Require(checks::FinitePositive(f), "a force magnitude is not > 0");
  }
  Require(plan.directions == 1 || plan.directions == 3, "directions must be 1 or 3");
  Require(checks::FiniteNonNegative(plan.creep_duration), "creep_duration must be >= 0");
  Require(checks::FinitePositive(plan.creep_interval), "creep_interval must be > 0");
  Require(plan.load_steps > 0, "load_steps must be > 0");
  std::set<int32_t> held;
  for (const int32_t n : plan.fixed) {
    Require(n >= 0 && n < nodes, "fixed node " + std::to_string(n) + " out of range");
    held.insert(n);
  }
  mesh::Points normals = BoundaryNormals(mesh);
  for (const int32_t p : plan.points) {
    Require(p >= 0 && p < nodes, "point " + std::to_string(p) + " out of range");
    Require(held.count(p) == 0, "point " + std::to_string(p) + " is held");
    Require(normals.col(p).squaredNorm() > 0.5,
            "point " + std::to_string(p) + " is not on the boundary");
  }
  return normals;
}

// BuildKlModel's stages and what they pass on: the snapshots, K's candidate states, the report.
class KlBuild {
 public:
  KlBuild(const FemModel& full, const SamplingPlan& plan, mesh::Points normals,
          const std::function<void(const BuildProgress&)>& progress)
      : full_(full), plan_(plan), normals_(std::move(normals)), progress_(progress) {}

  // Elastic static snapshots: each point, direction and magnitude is a static case; the first
  // point's normal load's equilibria are K's candidates.
  void Snapshots() {
    const int32_t nodes = full_.num_nodes();
    std::vector<std::pair<int32_t, Eigen::Vector3d>> loads;  // (point, unit direction)
    for (const int32_t p : plan_.points) {
      const Eigen::Vector3d inward = -Eigen::Vector3d(normals_.col(p));
      loads.emplace_back(p, inward);
      if (plan_.directions == 3) {
        const auto [t1, t2] = Tangents(inward);
        loads.emplace_back(p, t1);
        loads.emplace_back(p, t2);
      }
    }
    const size_t total = loads.size() * plan_.forces.size();
    for (size_t l = 0; l < loads.size(); ++l) {
      for (size_t m = 0; m < plan_.forces.size(); ++m) {
        StaticCase c;
        c.forces = mesh::Points::Zero(3, nodes);
        c.forces.col(loads[l].first) = plan_.forces[m] * loads[l].second;
        if (!Solve(c.forces, &c.displacement)) {
          ++out.unconverged;
        } else {
          snapshots_.emplace_back(
              Eigen::Map<const Eigen::VectorXd>(c.displacement.data(), c.displacement.size()));
          if (l == 0) level_states_.push_back(full_.rest_positions() + c.displacement);
          out.training.push_back(c.displacement);
          out.cases.push_back(std::move(c));
        }
        Report("snapshots", l * plan_.forces.size() + m + 1, total);
      }
    }
    Require(!out.cases.empty(), "no full solve converged");
  }

  // Creep curves (QLV): 1 N along each point's inward normal, held; the runs' states at 1 s,
  // 5 s and their end join the training set, their end the snapshots.
  void CreepCurves() {
    const auto steps =
        static_cast<size_t>(std::llround(plan_.creep_duration / plan_.creep_interval));
    if (full_.num_prony_terms() == 0 || steps == 0) return;
    const mesh::Points& rest = full_.rest_positions();
    for (size_t k = 0; k < plan_.points.size(); ++k) {
      const int32_t p = plan_.points[k];
      const Eigen::Vector3d inward = -Eigen::Vector3d(normals_.col(p));
      mesh::Points forces = mesh::Points::Zero(3, full_.num_nodes());
      forces.col(p) = inward;
      mesh::Points elastic;
      if (!Solve(forces, &elastic)) {
        ++out.unconverged;
        continue;
      }
      const double u0 = elastic.col(p).norm();
      models::reduced::CreepCurve curve;
      curve.node = p;
      curve.interval = plan_.creep_interval;
      curve.multiplier.push_back(1.0);
      StaticLoads held_load;
      held_load.external_forces = &forces;
      held_load.fixed_nodes = plan_.fixed;
      held_load.reuse_factorisation = true;
      auto state = full_.MakeState();
      StaticWorkspace creep_workspace;
      bool ok = true;
      for (size_t s = 0; s < steps && ok; ++s) {
        ok = full_.SolveQuasiStatic(held_load, plan_.creep_interval, state.get(), &creep_workspace)
                 .converged;
        curve.multiplier.push_back((state->positions.col(p) - rest.col(p)).norm() / u0);
        const double t = plan_.creep_interval * static_cast<double>(s + 1);
        if (ok && (std::abs(t - 1.0) < 0.5 * plan_.creep_interval ||
                   std::abs(t - 5.0) < 0.5 * plan_.creep_interval)) {
          out.training.push_back(state->positions - rest);
        }
      }
      if (!ok) {
        ++out.unconverged;
        continue;
      }
      const mesh::Points last = state->positions - rest;
      snapshots_.emplace_back(Eigen::Map<const Eigen::VectorXd>(last.data(), last.size()));
      out.training.push_back(last);
      out.data.creep.push_back(std::move(curve));
      Report("creep", k + 1, plan_.points.size());
    }
  }

  // The modes of the snapshots, then K among the candidates (the least relative L2 error over
  // the static cases), and the model's data.
  void ModesAndStiffness() {
    Report("modes", 0, 1);
    Eigen::MatrixXd q(3 * static_cast<Eigen::Index>(full_.num_nodes()),
                      static_cast<Eigen::Index>(snapshots_.size()));
    for (size_t s = 0; s < snapshots_.size(); ++s) {
      q.col(static_cast<Eigen::Index>(s)) = snapshots_[s];
    }
    out.snapshots = snapshots_.size();
    models::reduced::PodModes pod = models::reduced::ModesOfSnapshots(q, plan_.pod);
    out.eigenvalues = pod.eigenvalues;
    out.kept_fraction = pod.kept_fraction;
    Report("modes", 1, 1);
    std::vector<mesh::Points> candidates{full_.rest_positions()};
    out.candidates.emplace_back("initial tangent (rest)");
    for (size_t m = 0; m < level_states_.size(); ++m) {
      candidates.push_back(level_states_[m]);
      char text[96];
      std::snprintf(text, sizeof text, "tangent at %.3g N on node %d", plan_.forces[m],
                    plan_.points.front());
      out.candidates.emplace_back(text);
    }
    Report("stiffness", 0, candidates.size());
    out.chosen = models::reduced::ChooseStiffness(full_, candidates, pod.modes, out.cases,
                                                  &out.candidate_errors);
    Report("stiffness", candidates.size(), candidates.size());
    models::reduced::KlModelData data =
        models::reduced::KlDataFromFem(full_, candidates[out.chosen], pod.modes);
    data.creep = std::move(out.data.creep);
    data.creep_radius = plan_.creep_radius;
    out.data = std::move(data);
  }

  BuildReport out;

 private:
  // The full model's elastic static equilibrium under `forces`: its displacement; false when
  // Newton did not converge.
  bool Solve(const mesh::Points& forces, mesh::Points* displacement) {
    StaticLoads loads;
    loads.external_forces = &forces;
    loads.fixed_nodes = plan_.fixed;
    loads.load_steps = plan_.load_steps;
    auto state = full_.MakeState();
    const models::fem::StaticResult r = full_.SolveStatic(loads, state.get(), &workspace_);
    *displacement = state->positions - full_.rest_positions();
    return r.converged;
  }
  void Report(const char* stage, size_t done, size_t total) const {
    if (progress_) progress_({stage, done, total});
  }

  const FemModel& full_;
  const SamplingPlan& plan_;
  const mesh::Points normals_;  // 3 × N, zero inside
  const std::function<void(const BuildProgress&)>& progress_;
  StaticWorkspace workspace_;
  std::vector<Eigen::VectorXd> snapshots_;
  std::vector<mesh::Points> level_states_;  // the first point's normal load at each magnitude
};

}  // namespace

BuildReport BuildKlModel(const FemModel& full, const mesh::TetMesh& mesh, const SamplingPlan& plan,
                         const std::function<void(const BuildProgress&)>& progress) {
  const auto started = std::chrono::steady_clock::now();
  KlBuild build(full, plan, CheckKlPlan(full, mesh, plan), progress);
  build.Snapshots();
  build.CreepCurves();
  build.ModesAndStiffness();
  build.out.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  return std::move(build.out);
}

}  // namespace somasim::reduce
