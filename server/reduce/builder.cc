#include "server/reduce/builder.h"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <set>
#include <stdexcept>
#include <utility>

#include "common/checks/finite.h"
#include "common/mesh/topology.h"
#include "server/models/reduced/reduce_fem.h"

namespace somasim::reduce {
namespace {

using models::fem::FemModel;
using models::fem::StaticLoads;
using models::fem::StaticWorkspace;
using models::reduced::StaticCase;

void Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("sampling plan: " + what);
}

// Two unit tangents orthogonal to n (unit).
std::pair<Eigen::Vector3d, Eigen::Vector3d> Tangents(const Eigen::Vector3d& n) {
  const Eigen::Vector3d helper =
      std::abs(n.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Vector3d t1 = n.cross(helper).normalized();
  return {t1, n.cross(t1)};
}

}  // namespace

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

BuildReport BuildKlModel(const FemModel& full, const mesh::TetMesh& mesh, const SamplingPlan& plan,
                         const std::function<void(const BuildProgress&)>& progress) {
  const auto started = std::chrono::steady_clock::now();
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
  const mesh::Points normals = BoundaryNormals(mesh);
  for (const int32_t p : plan.points) {
    Require(p >= 0 && p < nodes, "point " + std::to_string(p) + " out of range");
    Require(held.count(p) == 0, "point " + std::to_string(p) + " is held");
    Require(normals.col(p).squaredNorm() > 0.5,
            "point " + std::to_string(p) + " is not on the boundary");
  }
  const auto report = [&](const char* stage, size_t done, size_t total) {
    if (progress) progress({stage, done, total});
  };

  BuildReport out;
  StaticWorkspace workspace;
  std::vector<Eigen::VectorXd> snapshots;
  const auto solve = [&](const mesh::Points& forces, mesh::Points* displacement) {
    StaticLoads loads;
    loads.external_forces = &forces;
    loads.fixed_nodes = plan.fixed;
    loads.load_steps = plan.load_steps;
    auto state = full.MakeState();
    const models::fem::StaticResult r = full.SolveStatic(loads, state.get(), &workspace);
    *displacement = state->positions - full.rest_positions();
    return r.converged;
  };
  // Elastic static snapshots.
  std::vector<std::pair<int32_t, Eigen::Vector3d>> loads;  // (point, unit direction)
  for (const int32_t p : plan.points) {
    const Eigen::Vector3d inward = -Eigen::Vector3d(normals.col(p));
    loads.emplace_back(p, inward);
    if (plan.directions == 3) {
      const auto [t1, t2] = Tangents(inward);
      loads.emplace_back(p, t1);
      loads.emplace_back(p, t2);
    }
  }
  const size_t total = loads.size() * plan.forces.size();
  std::vector<mesh::Points> level_states;  // the first point's normal load at each magnitude
  for (size_t l = 0; l < loads.size(); ++l) {
    for (size_t m = 0; m < plan.forces.size(); ++m) {
      StaticCase c;
      c.forces = mesh::Points::Zero(3, nodes);
      c.forces.col(loads[l].first) = plan.forces[m] * loads[l].second;
      if (!solve(c.forces, &c.displacement)) {
        ++out.unconverged;
      } else {
        snapshots.emplace_back(
            Eigen::Map<const Eigen::VectorXd>(c.displacement.data(), c.displacement.size()));
        if (l == 0) level_states.push_back(full.rest_positions() + c.displacement);
        out.training.push_back(c.displacement);
        out.cases.push_back(std::move(c));
      }
      report("snapshots", l * plan.forces.size() + m + 1, total);
    }
  }
  Require(!out.cases.empty(), "no full solve converged");
  // Creep curves (QLV): 1 N along each point's inward normal, held.
  const auto steps = static_cast<size_t>(std::llround(plan.creep_duration / plan.creep_interval));
  if (full.num_prony_terms() > 0 && steps > 0) {
    for (size_t k = 0; k < plan.points.size(); ++k) {
      const int32_t p = plan.points[k];
      const Eigen::Vector3d inward = -Eigen::Vector3d(normals.col(p));
      mesh::Points forces = mesh::Points::Zero(3, nodes);
      forces.col(p) = inward;
      mesh::Points elastic;
      if (!solve(forces, &elastic)) {
        ++out.unconverged;
        continue;
      }
      const double u0 = elastic.col(p).norm();
      models::reduced::CreepCurve curve;
      curve.node = p;
      curve.interval = plan.creep_interval;
      curve.multiplier.push_back(1.0);
      StaticLoads held_load;
      held_load.external_forces = &forces;
      held_load.fixed_nodes = plan.fixed;
      held_load.reuse_factorisation = true;
      auto state = full.MakeState();
      StaticWorkspace creep_workspace;
      bool ok = true;
      for (size_t s = 0; s < steps && ok; ++s) {
        ok = full.SolveQuasiStatic(held_load, plan.creep_interval, state.get(), &creep_workspace)
                 .converged;
        curve.multiplier.push_back((state->positions.col(p) - full.rest_positions().col(p)).norm() /
                                   u0);
        const double t = plan.creep_interval * static_cast<double>(s + 1);
        if (ok && (std::abs(t - 1.0) < 0.5 * plan.creep_interval ||
                   std::abs(t - 5.0) < 0.5 * plan.creep_interval)) {
          out.training.push_back(state->positions - full.rest_positions());
        }
      }
      if (!ok) {
        ++out.unconverged;
        continue;
      }
      const mesh::Points last = state->positions - full.rest_positions();
      snapshots.emplace_back(Eigen::Map<const Eigen::VectorXd>(last.data(), last.size()));
      out.training.push_back(last);
      out.data.creep.push_back(std::move(curve));
      report("creep", k + 1, plan.points.size());
    }
  }
  // Modes.
  report("modes", 0, 1);
  Eigen::MatrixXd q(3 * static_cast<Eigen::Index>(nodes),
                    static_cast<Eigen::Index>(snapshots.size()));
  for (size_t s = 0; s < snapshots.size(); ++s) q.col(static_cast<Eigen::Index>(s)) = snapshots[s];
  out.snapshots = snapshots.size();
  models::reduced::PodModes pod = models::reduced::ModesOfSnapshots(q, plan.pod);
  out.eigenvalues = pod.eigenvalues;
  out.kept_fraction = pod.kept_fraction;
  report("modes", 1, 1);
  // K among the candidates.
  std::vector<mesh::Points> candidates{full.rest_positions()};
  out.candidates.emplace_back("initial tangent (rest)");
  for (size_t m = 0; m < level_states.size(); ++m) {
    candidates.push_back(level_states[m]);
    char text[96];
    std::snprintf(text, sizeof text, "tangent at %.3g N on node %d", plan.forces[m],
                  plan.points.front());
    out.candidates.emplace_back(text);
  }
  report("stiffness", 0, candidates.size());
  out.chosen = models::reduced::ChooseStiffness(full, candidates, pod.modes, out.cases,
                                                &out.candidate_errors);
  report("stiffness", candidates.size(), candidates.size());
  models::reduced::KlModelData data =
      models::reduced::KlDataFromFem(full, candidates[out.chosen], pod.modes);
  data.creep = std::move(out.data.creep);
  data.creep_radius = plan.creep_radius;
  out.data = std::move(data);
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  return out;
}

NonlinearBuildReport BuildNonlinearModel(
    const FemModel& full, const mesh::TetMesh& mesh, const SamplingPlan& plan,
    const BuildReport& kl, const std::function<void(const BuildProgress&)>& progress) {
  const auto started = std::chrono::steady_clock::now();
  const int32_t nodes = full.num_nodes();
  Require(full.kind() == models::fem::FemKind::kHyperelastic,
          "the nonlinear reduced model needs a hyperelastic organ");
  Require(!kl.training.empty(), "no training state");
  const auto report = [&](const char* stage, size_t done, size_t total) {
    if (progress) progress({stage, done, total});
  };
  std::set<int32_t> held(plan.fixed.begin(), plan.fixed.end());
  const mesh::Points normals = BoundaryNormals(mesh);
  std::vector<Eigen::VectorXd> columns;
  const auto add = [&](const mesh::Points& u) {
    const double norm = u.norm();
    if (norm > 0.0)
      columns.emplace_back(Eigen::Map<const Eigen::VectorXd>(u.data(), u.size()) / norm);
  };
  for (const mesh::Points& u : kl.training) add(u);
  std::vector<mesh::Points> states = kl.training;  // the cubature's candidates
  NonlinearBuildReport out;
  // The region nodes' linear responses to unit forces along x, y, z (3N × 3 each).
  std::vector<int32_t> correction_nodes;
  std::vector<Eigen::MatrixXd> responses;
  // The region samples' loads and the full model's displacement of the loaded node, for the
  // correction's scale: per sample its node, magnitude index, force [N] and u_r [m].
  struct Dent {
    int32_t node = 0;
    size_t magnitude = 0;
    Eigen::Vector3d force, displacement;
    size_t state = 0;  // index into states: the full solution
  };
  std::vector<Dent> dents;
  // The magnitudes of the region samples.
  std::vector<double> magnitudes = plan.nonlinear_forces;
  if (magnitudes.empty()) {
    magnitudes = plan.forces;
    double gamma_sum = 0.0;
    for (const models::fem::PronyTerm& t : full.prony()) gamma_sum += t.gamma;
    const double largest = *std::max_element(plan.forces.begin(), plan.forces.end());
    if (gamma_sum > 0.0 && gamma_sum < 1.0) magnitudes.push_back(largest / (1.0 - gamma_sum));
  }
  std::sort(magnitudes.begin(), magnitudes.end());
  for (const double f : magnitudes) Require(checks::FinitePositive(f), "a magnitude is not > 0");
  Require(plan.tilts >= 0 && checks::FiniteNonNegative(plan.tilt_deg) && plan.tilt_deg < 90.0,
          "tilts must be >= 0 and tilt_deg in [0, 90)");
  // Every region node: its responses to 1 mN along the normal and two tangents (linear: the
  // tangent at rest, factorised once), then its static samples, each direction's magnitudes in
  // ascending order from the last one's solution (continuation).
  StaticWorkspace workspace;
  size_t done = 0;
  const double tilt = plan.tilt_deg * 3.14159265358979323846 / 180.0;
  for (const int32_t r : plan.region_nodes) {
    Require(r >= 0 && r < nodes, "region node " + std::to_string(r) + " out of range");
    ++done;
    if (held.count(r) != 0 || normals.col(r).squaredNorm() < 0.5) continue;
    const Eigen::Vector3d inward = -Eigen::Vector3d(normals.col(r));
    const auto [t1, t2] = Tangents(inward);
    mesh::Points forces = mesh::Points::Zero(3, nodes);
    StaticLoads loads;
    loads.external_forces = &forces;
    loads.fixed_nodes = plan.fixed;
    loads.reuse_factorisation = true;
    // The responses per newton along x, y, z (from those along the orthonormal d1, d2, d3:
    // Y e_a = Σ_j (d_j · e_a) Y d_j), kept for the static correction.
    Eigen::MatrixXd unit = Eigen::MatrixXd::Zero(3 * static_cast<Eigen::Index>(nodes), 3);
    bool linear_ok = true;
    for (const Eigen::Vector3d& d : {inward, t1, t2}) {
      forces.col(r) = 1e-3 * d;
      auto state = full.MakeState();
      if (full.SolveStatic(loads, state.get(), &workspace).converged) {
        const mesh::Points u = state->positions - full.rest_positions();
        add(u);
        const Eigen::Map<const Eigen::VectorXd> y(u.data(), u.size());
        for (int a = 0; a < 3; ++a) unit.col(a) += (d(a) / 1e-3) * y;
      } else {
        linear_ok = false;
      }
    }
    if (linear_ok) {
      correction_nodes.push_back(r);
      responses.push_back(std::move(unit));
    }
    std::vector<Eigen::Vector3d> directions{inward};
    for (int k = 0; k < plan.tilts; ++k) {
      const double azimuth = 2.0 * 3.14159265358979323846 * k / plan.tilts;
      directions.push_back(std::cos(tilt) * inward +
                           std::sin(tilt) * (std::cos(azimuth) * t1 + std::sin(azimuth) * t2));
    }
    StaticLoads samples = loads;
    samples.reuse_factorisation = false;
    samples.load_steps = plan.load_steps;
    StaticWorkspace sample_workspace;
    for (const Eigen::Vector3d& d : directions) {
      auto state = full.MakeState();
      for (size_t m = 0; m < magnitudes.size(); ++m) {
        const double f = magnitudes[m];
        forces.col(r) = f * d;
        if (!full.SolveStatic(samples, state.get(), &sample_workspace).converged) {
          ++out.unconverged;
          break;  // the larger magnitudes would start from an unconverged state
        }
        const mesh::Points u = state->positions - full.rest_positions();
        add(u);
        dents.push_back({r, m, f * d, u.col(r), states.size()});
        states.push_back(u);
        ++out.region_solves;
      }
    }
    report("region samples", done, plan.region_nodes.size());
  }
  report("modes", 0, 1);
  Eigen::MatrixXd q(3 * static_cast<Eigen::Index>(nodes),
                    static_cast<Eigen::Index>(columns.size()));
  for (size_t c = 0; c < columns.size(); ++c) q.col(static_cast<Eigen::Index>(c)) = columns[c];
  out.snapshots = columns.size();
  // POD in the Euclidean inner product (the default) or in the rest tangent's energy (pod.h).
  Eigen::MatrixXd weighted;
  if (plan.energy_inner_product) {
    models::fem::BlockSparseMatrix tangent;
    full.AssembleTangent(full.rest_positions(), &tangent);
    weighted.resize(q.rows(), q.cols());
    for (Eigen::Index c = 0; c < q.cols(); ++c) {
      tangent.Multiply(q.col(c).data(), weighted.col(c).data(), nullptr);
    }
  }
  models::reduced::PodModes pod = models::reduced::ModesOfSnapshots(
      q, plan.nonlinear_pod, plan.energy_inner_product ? &weighted : nullptr);
  out.eigenvalues = pod.eigenvalues;
  out.kept_fraction = pod.kept_fraction;
  report("modes", 1, 1);
  // The Petrov–Galerkin test basis Ψ = K0⁻¹ B (nonlinear_model.h, reduce_fem.h), on the rest
  // factor the region nodes' responses used.
  Eigen::MatrixXd test_modes;
  if (plan.petrov_galerkin) {
    report("test basis", 0, 1);
    try {
      test_modes =
          models::reduced::PetrovGalerkinTestBasis(full, pod.modes, plan.fixed, &workspace);
    } catch (const std::invalid_argument& e) {
      Require(false, e.what());
    }
    report("test basis", 1, 1);
  }
  report("cubature", 0, 1);
  // The cubature's training: at most max_cubature_states states, evenly spread over the list.
  std::vector<mesh::Points> training;
  const size_t take = std::min(states.size(), std::max<size_t>(plan.max_cubature_states, 1));
  for (size_t k = 0; k < take; ++k) training.push_back(states[k * states.size() / take]);
  out.cubature = models::reduced::TrainCubature(full, pod.modes, training, plan.cubature,
                                                plan.petrov_galerkin ? &test_modes : nullptr);
  report("cubature", 1, 1);
  models::reduced::NonlinearModelData& d = out.data;
  d.rest = full.rest_positions();
  d.masses = full.masses();
  d.modes = std::move(pod.modes);
  d.test_modes = std::move(test_modes);
  d.tets.resize(4, static_cast<Eigen::Index>(out.cubature.elements.size()));
  for (size_t k = 0; k < out.cubature.elements.size(); ++k) {
    d.tets.col(static_cast<Eigen::Index>(k)) = full.elements().tets.col(out.cubature.elements[k]);
  }
  d.weights = out.cubature.weights;
  d.elements = out.cubature.elements;
  d.material = full.material();
  d.prony = full.prony();
  // The static correction (nonlinear_model.h): R_p = K0⁻¹ E_p − B K̂0⁻¹ Ψᵀ E_p with K̂0 the
  // model's own reduced tangent at rest (its cubature's; Ψ = B for Galerkin).
  if (plan.static_correction && !correction_nodes.empty()) {
    report("correction", 0, 1);
    const auto model = models::reduced::NonlinearReducedModel::Create(d);
    const auto state = model->MakeState();
    Eigen::VectorXd force;
    Eigen::MatrixXd tangent;
    model->ReducedForces(*state, Eigen::VectorXd::Zero(d.modes.cols()), 0.0, &force, &tangent);
    const Eigen::FullPivLU<Eigen::MatrixXd> rest_lu(tangent);
    Require(rest_lu.isInvertible(), "the reduced tangent at rest is singular");
    const Eigen::MatrixXd& test = d.test_modes.size() > 0 ? d.test_modes : d.modes;
    const auto c = static_cast<Eigen::Index>(correction_nodes.size());
    d.correction_nodes = correction_nodes;
    d.corrections.resize(d.modes.rows(), 3 * c);
    for (Eigen::Index k = 0; k < c; ++k) {
      const Eigen::MatrixXd bt =
          test.middleRows(3 * static_cast<Eigen::Index>(correction_nodes[size_t(k)]), 3)
              .transpose();  // Ψᵀ E_p: n × 3
      d.corrections.middleCols<3>(3 * k) = responses[size_t(k)] - d.modes * rest_lu.solve(bt);
    }
    out.correction_nodes = c;
    // Its scale κ per node and magnitude: the reduced model's own elastic equilibrium under each
    // region sample's force (Newton from the last magnitude's, as the full solves ran) against
    // the full model's dent at the loaded node, d = u_full − u_reduced ≈ κ R_pp f, fitted over
    // the node's directions by least squares (κ = Σ d·q / Σ q·q, q = R_pp f; clamped to
    // [0, 1.5]).
    const auto magnitudes_count = static_cast<Eigen::Index>(magnitudes.size());
    Eigen::MatrixXd numerator = Eigen::MatrixXd::Zero(magnitudes_count, c);
    Eigen::MatrixXd denominator = Eigen::MatrixXd::Zero(magnitudes_count, c);
    std::vector<Eigen::Index> index_of(static_cast<size_t>(nodes), -1);
    for (Eigen::Index k = 0; k < c; ++k) index_of[size_t(correction_nodes[size_t(k)])] = k;
    const Eigen::Index n = d.modes.cols();
    Eigen::VectorXd xi = Eigen::VectorXd::Zero(n);
    // Each sample's reduced equilibrium (n; NaN where it did not converge), for the part in the
    // modes below.
    Eigen::MatrixXd equilibria(n, static_cast<Eigen::Index>(dents.size()));
    equilibria.setConstant(std::numeric_limits<double>::quiet_NaN());
    for (size_t s_index = 0; s_index < dents.size(); ++s_index) {
      const Dent& dent = dents[s_index];
      const Eigen::Index k = index_of[size_t(dent.node)];
      if (k < 0) continue;
      if (dent.magnitude == 0) xi.setZero();  // a new direction: from rest
      const Eigen::VectorXd load = test.middleRows(3 * dent.node, 3).transpose() * dent.force;
      bool solved = false;
      for (int iteration = 0; iteration < 40; ++iteration) {
        model->ReducedForces(*state, xi, 0.0, &force, &tangent);
        if (!force.allFinite()) break;
        const Eigen::VectorXd residual = force + load;
        if (residual.norm() <= 1e-9 * (load.norm() + force.norm())) {
          solved = true;
          break;
        }
        const Eigen::VectorXd step = tangent.partialPivLu().solve(residual);
        double alpha = 1.0;  // halve a step that inverts an element
        Eigen::VectorXd trial = xi + step;
        for (int h = 0; h < 20; ++h) {
          model->ReducedForces(*state, trial, 0.0, &force, nullptr);
          if (force.allFinite()) break;
          alpha *= 0.5;
          trial = xi + alpha * step;
        }
        xi = trial;
      }
      if (solved) equilibria.col(static_cast<Eigen::Index>(s_index)) = xi;
    }
    const auto features = models::reduced::CorrectionFeatures;
    // κ from the dents the reduced equilibria leave (with the part in the modes, once fitted).
    const auto fit_scales = [&] {
      numerator.setZero();
      denominator.setZero();
      const Eigen::Index count = magnitudes_count;
      const bool in_modes = d.correction_coefficients.size() > 0;
      for (size_t s_index = 0; s_index < dents.size(); ++s_index) {
        const Dent& dent = dents[s_index];
        const Eigen::Index k = index_of[size_t(dent.node)];
        const auto column = static_cast<Eigen::Index>(s_index);
        if (k < 0 || !equilibria.col(column).allFinite()) continue;
        Eigen::VectorXd coordinates = equilibria.col(column);
        if (in_modes) {
          coordinates += d.correction_coefficients.middleCols<4>(
                             4 * (k * count + Eigen::Index(dent.magnitude))) *
                         features(dent.force);
        }
        const Eigen::Vector3d reduced = d.modes.middleRows(3 * dent.node, 3) * coordinates;
        const Eigen::Vector3d linear =
            d.corrections.block<3, 3>(3 * Eigen::Index(dent.node), 3 * k) * dent.force;
        numerator(Eigen::Index(dent.magnitude), k) += (dent.displacement - reduced).dot(linear);
        denominator(Eigen::Index(dent.magnitude), k) += linear.squaredNorm();
      }
      d.correction_scales = Eigen::MatrixXd::Ones(magnitudes_count, c);
      for (Eigen::Index m = 0; m < magnitudes_count; ++m) {
        for (Eigen::Index k = 0; k < c; ++k) {
          if (denominator(m, k) > 0.0) {
            d.correction_scales(m, k) = std::clamp(numerator(m, k) / denominator(m, k), 0.0, 1.5);
          }
        }
      }
    };
    d.correction_magnitudes = magnitudes;
    fit_scales();
    if (plan.correction_in_modes) {
      // The part in the modes: per sample the offset t = (BᵀB)⁻¹ Bᵀ (u_full − κ R_p f) − ξ that
      // B ξ + κ R_p f leaves in span(B), fitted per node and magnitude as G φ(f), φ = (f, |f|),
      // over the node's directions by least squares (G = T Φᵀ (Φ Φᵀ)⁺). Affine in the direction:
      // the offset along the normal (|f|) and its change with the tilt (f); where the directions
      // span only a plane, as with two tilts, G sees the plane's part only.
      // κ is then fitted again to the dents the fitted part leaves, and the part again to that κ
      // (once: the second pass moves κ by a few per cent).
      const Eigen::LDLT<Eigen::MatrixXd> gram(d.modes.transpose() * d.modes);
      const auto fit_coefficients = [&] {
        std::vector<Eigen::MatrixXd> tf(static_cast<size_t>(magnitudes_count * c),
                                        Eigen::MatrixXd::Zero(n, 4));
        std::vector<Eigen::Matrix4d> ff(tf.size(), Eigen::Matrix4d::Zero());
        std::vector<Eigen::VectorXd> offsets(dents.size());
        double field_norm = 0.0, before = 0.0, after = 0.0;
        for (size_t s_index = 0; s_index < dents.size(); ++s_index) {
          const Dent& dent = dents[s_index];
          const Eigen::Index k = index_of[size_t(dent.node)];
          const auto column = static_cast<Eigen::Index>(s_index);
          if (k < 0 || !equilibria.col(column).allFinite()) continue;
          const mesh::Points& u = states[dent.state];
          const Eigen::Map<const Eigen::VectorXd> flat(u.data(), u.size());
          const double kappa = d.correction_scales(Eigen::Index(dent.magnitude), k);
          const Eigen::VectorXd rest_of =
              flat - kappa * (d.corrections.middleCols<3>(3 * k) * dent.force);
          offsets[s_index] = gram.solve(d.modes.transpose() * rest_of) - equilibria.col(column);
          const size_t block = size_t(k * magnitudes_count) + dent.magnitude;
          const Eigen::Vector4d phi = features(dent.force);
          tf[block] += offsets[s_index] * phi.transpose();
          ff[block] += phi * phi.transpose();
          field_norm += flat.squaredNorm();
        }
        d.correction_coefficients = Eigen::MatrixXd::Zero(n, 4 * magnitudes_count * c);
        for (size_t block = 0; block < tf.size(); ++block) {
          const Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> eigen(ff[block]);
          const Eigen::Vector4d& values = eigen.eigenvalues();  // ascending, >= 0
          if (!(values(3) > 0.0)) continue;                     // no sample
          Eigen::Vector4d inverse = Eigen::Vector4d::Zero();
          for (int a = 0; a < 4; ++a) {
            if (values(a) > 1e-9 * values(3)) inverse(a) = 1.0 / values(a);
          }
          d.correction_coefficients.middleCols<4>(4 * static_cast<Eigen::Index>(block)) =
              tf[block] *
              (eigen.eigenvectors() * inverse.asDiagonal() * eigen.eigenvectors().transpose());
        }
        for (size_t s_index = 0; s_index < dents.size(); ++s_index) {
          if (offsets[s_index].size() == 0) continue;
          const Dent& dent = dents[s_index];
          const Eigen::Index k = index_of[size_t(dent.node)];
          const Eigen::Index block = k * magnitudes_count + Eigen::Index(dent.magnitude);
          before += (d.modes * offsets[s_index]).squaredNorm();
          after +=
              (d.modes * (offsets[s_index] - d.correction_coefficients.middleCols<4>(4 * block) *
                                                 features(dent.force)))
                  .squaredNorm();
        }
        if (field_norm > 0.0) {
          out.in_span_error_before = std::sqrt(before / field_norm);
          out.in_span_error_after = std::sqrt(after / field_norm);
        }
      };
      fit_coefficients();
      fit_scales();
      fit_coefficients();
    }
    out.correction_scale_mean = d.correction_scales.rowwise().mean();
    report("correction", 1, 1);
  }
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  return out;
}

}  // namespace somasim::reduce
