// somasim-reduce's engine (server/reduce/builder.h) on a small beam: creep curves against the
// analytic creep compliance of a linear viscoelastic solid, the built model against the full
// solves it was built from, the choice of K, bad plans refused by name.
#include "server/reduce/builder.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/mesh_gen/structured_meshes.h"
#include "server/models/fem/block_sparse.h"
#include "server/models/reduced/nonlinear_model.h"
#include "server/models/reduced/reduce_fem.h"
#include "server/reduce/evaluate.h"

namespace somasim::reduce {
namespace {

using Eigen::Vector3d;
using models::fem::FemKind;
using models::fem::FemModel;
using models::fem::FemParameters;

struct Beam {
  explicit Beam(FemKind kind, std::vector<models::fem::PronyTerm> prony = {}) {
    mesh = mesh_gen::BoxGridTets(7, 3, 3, Vector3d::Zero(), Vector3d(0.12, 0.03, 0.03));
    FemParameters p;
    p.kind = kind;
    p.youngs_modulus = 5000.0;
    p.poisson_ratio = 0.35;
    p.density = 1055.0;
    p.prony = std::move(prony);
    model = FemModel::FromTetMesh(mesh, p);
    for (int32_t i = 0; i < model->num_nodes(); ++i) {
      if (mesh.vertices(0, i) < 1e-9) plan.fixed.push_back(i);
    }
  }
  int32_t Node(double x, double y, double z) const {
    for (int32_t i = 0; i < model->num_nodes(); ++i) {
      if ((mesh.vertices.col(i) - Vector3d(x, y, z)).norm() < 1e-9) return i;
    }
    return -1;
  }
  mesh::TetMesh mesh;
  std::unique_ptr<FemModel> model;
  SamplingPlan plan;
};

// A linear material with one Prony term, G(t) = γ∞ + γ1 e^{-t/τ}, creeps under a held load as
// J(t) = 1/γ∞ − (1/γ∞ − 1) e^{−γ∞ t/τ} times its elastic displacement, everywhere: with
// γ1 = 0.5, τ = 1 s, c(t) = 2 − e^{−t/2}.
TEST(ReduceBuilder, CreepCurvesFollowTheLinearSolidsCreepCompliance) {
  Beam beam(FemKind::kLinear, {{0.5, 1.0}});
  beam.plan.points = {beam.Node(0.12, 0.03, 0.03)};
  beam.plan.directions = 1;
  beam.plan.forces = {0.05};
  beam.plan.creep_duration = 6.0;
  beam.plan.creep_interval = 0.05;
  const BuildReport r = BuildKlModel(*beam.model, beam.mesh, beam.plan);
  ASSERT_EQ(r.data.creep.size(), 1u);
  const std::vector<double>& c = r.data.creep[0].multiplier;
  ASSERT_EQ(c.size(), 121u);
  EXPECT_EQ(c[0], 1.0);
  double worst = 0.0, worst_late = 0.0;
  for (size_t k = 1; k < c.size(); ++k) {
    const double t = 0.05 * static_cast<double>(k);
    const double error = std::abs(c[k] - (2.0 - std::exp(-0.5 * t)));
    worst = std::max(worst, error);
    if (t >= 1.0) worst_late = std::max(worst_late, error);
    EXPECT_GE(c[k], c[k - 1] - 1e-12) << "creep never recovers under a held load";
  }
  std::printf("creep curve vs 2 - exp(-t/2): max error %.2e (after 1 s %.2e), c(6) = %.4f\n", worst,
              worst_late, c.back());
  // The recursive QLV update is exact for strain linear over a step; the load's jump at t = 0
  // is taken as a ramp over the first step, an error of order γ1 dt/τ that then decays.
  EXPECT_LT(worst, 0.02);
  EXPECT_LT(worst_late, 0.01);
}

// Linear: the snapshots at two magnitudes are proportional, so 3 points × 3 directions give
// 9 modes, every candidate tangent is the same K, and the model reproduces each full solve.
TEST(ReduceBuilder, TheBuiltModelReproducesTheFullSolvesItWasBuiltFrom) {
  Beam beam(FemKind::kLinear);
  beam.plan.points = {beam.Node(0.12, 0.03, 0.03), beam.Node(0.08, 0.0, 0.03),
                      beam.Node(0.06, 0.015, 0.0)};
  beam.plan.forces = {0.05, 0.1};
  beam.plan.pod.energy_fraction = 1.0;
  std::vector<std::string> stages;
  const BuildReport r =
      BuildKlModel(*beam.model, beam.mesh, beam.plan, [&](const BuildProgress& p) {
        if (stages.empty() || stages.back() != p.stage) {
          stages.push_back(p.stage);
        }
      });
  EXPECT_EQ(stages, (std::vector<std::string>{"snapshots", "modes", "stiffness"}));
  EXPECT_EQ(r.snapshots, 18u);
  EXPECT_EQ(r.unconverged, 0);
  EXPECT_EQ(r.data.modes.cols(), 9);
  ASSERT_EQ(r.candidates.size(), 3u);
  for (const double e : r.candidate_errors) EXPECT_LT(e, 1e-9);
  for (const models::reduced::StaticCase& c : r.cases) {
    const mesh::Points u = models::reduced::ReducedStaticDisplacement(
        r.data.modes, r.data.reduced_stiffness, c.forces);
    EXPECT_LT((u - c.displacement).norm(), 1e-9 * c.displacement.norm());
  }
  EXPECT_NO_THROW(models::reduced::KlReducedModel::Create(r.data));
}

// Hyperelastic (seed 000's liver material): K is chosen by its error, and the chosen error is
// the least of the candidates'.
TEST(ReduceBuilder, ChoosesTheTangentWithTheLeastError) {
  Beam beam(FemKind::kHyperelastic);
  beam.plan.points = {beam.Node(0.12, 0.03, 0.03), beam.Node(0.10, 0.0, 0.03)};
  beam.plan.forces = {0.002, 0.02};
  beam.plan.pod.max_modes = 4;
  const BuildReport r = BuildKlModel(*beam.model, beam.mesh, beam.plan);
  ASSERT_EQ(r.candidate_errors.size(), 3u);
  for (size_t k = 0; k < r.candidates.size(); ++k) {
    std::printf("%s: L2 error %.4f\n", r.candidates[k].c_str(), r.candidate_errors[k]);
    EXPECT_LE(r.candidate_errors[r.chosen], r.candidate_errors[k]);
  }
  EXPECT_GT(r.candidate_errors[r.chosen], 0.0);
  EXPECT_EQ(r.data.modes.cols(), 4);
}

// The nonlinear build on the small hyperelastic, viscoelastic beam: the region node's static
// samples and responses join the snapshots, the cubature converges on a fraction of the
// elements, every region node gets its static correction, the Petrov–Galerkin test basis is
// K0⁻¹ B, and the model reproduces a trained load (the free corner pushed along its inward
// normal and held: the full model's creep) within 1 % over the whole history (somasim-reduce
// --evaluate's measure) — with either projection (Galerkin at its 1 % cubature). The in-process
// counterpart of the kidney program test, small enough for the sanitizer build.
// The nonlinear builds' plan on the beam: the loaded corner (returned) as the KL plan's one point
// (its normal, one force, creep for `creep` s) and, with an edge node, the region nodes: normal
// and `tilts` tilts at `forces`; 12 modes.
int32_t NonlinearPlan(Beam* beam, double force, double creep, int tilts,
                      std::vector<double> forces) {
  const int32_t corner = beam->Node(0.12, 0.03, 0.03);
  SamplingPlan& plan = beam->plan;
  plan.points = {corner};
  plan.directions = 1;
  plan.forces = {force};
  plan.creep_duration = creep;
  plan.creep_interval = 0.25;
  plan.region_nodes = {corner, beam->Node(0.12, 0.0, 0.03)};
  plan.tilts = tilts;
  plan.nonlinear_forces = std::move(forces);
  plan.nonlinear_pod.max_modes = 12;
  plan.nonlinear_pod.energy_fraction = 1.0;
  return corner;
}

TEST(ReduceBuilder, TheNonlinearModelReproducesATrainedLoadThroughItsCreep) {
  for (const bool petrov : {true, false}) {
    SCOPED_TRACE(petrov ? "Petrov-Galerkin" : "Galerkin");
    Beam beam(FemKind::kHyperelastic, {{0.3, 0.5}});
    const int32_t corner = NonlinearPlan(&beam, 0.01, 2.0, 2, {0.005, 0.01, 0.02});
    beam.plan.petrov_galerkin = petrov;
    beam.plan.cubature.tolerance = petrov ? 0.001 : 0.01;  // as somasim-reduce sets them
    const BuildReport kl = BuildKlModel(*beam.model, beam.mesh, beam.plan);
    std::vector<std::string> stages;
    const NonlinearBuildReport r =
        BuildNonlinearModel(*beam.model, beam.mesh, beam.plan, kl, [&](const BuildProgress& p) {
          if (stages.empty() || stages.back() != p.stage) stages.push_back(p.stage);
        });
    EXPECT_EQ(r.unconverged, 0);
    EXPECT_EQ(r.region_solves, 2u * 3u * 3u);  // region nodes × (normal + 2 tilts) × forces
    EXPECT_EQ(r.data.modes.cols(), 12);
    EXPECT_TRUE(r.cubature.converged);
    EXPECT_GT(r.cubature.elements.size(), 0u);
    EXPECT_LT(r.cubature.elements.size(), static_cast<size_t>(beam.mesh.tetrahedra.cols()));
    std::printf("cubature: %zu of %ld elements\n", r.cubature.elements.size(),
                static_cast<long>(beam.mesh.tetrahedra.cols()));
    EXPECT_EQ(r.correction_nodes, 2);
    EXPECT_EQ(stages.back(), "correction");
    EXPECT_EQ(std::count(stages.begin(), stages.end(), "test basis"), petrov ? 1 : 0);
    if (petrov) {  // K0 Ψ = B on the free DOFs
      ASSERT_EQ(r.data.test_modes.rows(), r.data.modes.rows());
      ASSERT_EQ(r.data.test_modes.cols(), r.data.modes.cols());
      models::fem::BlockSparseMatrix k0;
      beam.model->AssembleTangent(beam.mesh.vertices, &k0);
      std::vector<uint8_t> held(static_cast<size_t>(beam.model->num_nodes()), 0);
      for (const int32_t i : beam.plan.fixed) held[static_cast<size_t>(i)] = 1;
      for (Eigen::Index j = 0; j < r.data.modes.cols(); ++j) {
        Eigen::VectorXd k_psi(r.data.modes.rows());
        k0.Multiply(r.data.test_modes.col(j).data(), k_psi.data(), nullptr);
        for (const int32_t i : beam.plan.fixed) k_psi.segment<3>(3 * i).setZero();
        EXPECT_LE((k_psi - r.data.modes.col(j)).norm(), 1e-6 * r.data.modes.col(j).norm())
            << "mode " << j;
        for (const int32_t i : beam.plan.fixed) {
          EXPECT_EQ(r.data.test_modes.col(j).segment<3>(3 * i).norm(), 0.0);
        }
      }
    } else {
      EXPECT_EQ(r.data.test_modes.size(), 0);
    }
    const auto model = models::reduced::NonlinearReducedModel::Create(r.data);
    ASSERT_NE(model, nullptr);
    EXPECT_EQ(model->petrov_galerkin(), petrov);
    // The corner pushed inward (its boundary normal, reversed) by 0.01 N for 2 s.
    const Eigen::Vector3d inward = -BoundaryNormals(beam.mesh).col(corner);
    reduced::EvaluationPlan plan;
    reduced::EvaluationCase* c = plan.add_cases();
    c->set_name("trained");
    c->set_node(corner);
    for (int k = 0; k < 3; ++k) c->add_force(0.01 * inward[k]);
    c->set_end_time(2.0);
    c->set_dt(0.25);
    const std::vector<CaseResult> results =
        Evaluate(*beam.model, beam.plan.fixed, *model, plan, &r.data.modes);
    ASSERT_EQ(results.size(), 1u);
    std::printf("trained load: field %.2f %%, node %.2f %%, floor %.2f %%\n",
                100 * results[0].field_error, 100 * results[0].node_error,
                100 * results[0].basis_error);
    EXPECT_TRUE(results[0].converged);
    EXPECT_GT(results[0].full_end_m, 0.0);
    // When written: 0.01 / 0.01 % in both projections (before the correction's part in the modes:
    // 0.36 / 0.33 % Petrov–Galerkin, 0.25 / 0.19 % Galerkin).
    EXPECT_LT(results[0].field_error, 0.01);
    EXPECT_LT(results[0].node_error, 0.01);
    ASSERT_EQ(results[0].per_step.size(), 8u);
    // Held: the full model creeps, and the reduced one with it.
    EXPECT_GT(results[0].per_step.back().node_full_m.norm(),
              1.02 * results[0].per_step.front().node_full_m.norm());
    EXPECT_GT(results[0].per_step.back().node_reduced_m.norm(),
              1.02 * results[0].per_step.front().node_reduced_m.norm());
  }
}

// The static correction's part in the modes (builder.h's correction_in_modes): under large
// forces on the near-incompressible liver material the reduced equilibrium drifts from the full
// one inside span(B). The builder's fit takes most of that offset off its own samples, and a
// held-out load at a region node (a new direction and magnitude) is closer to the full model
// with it than without.
TEST(ReduceBuilder, TheCorrectionsPartInTheModesBringsAHeldOutLoadCloser) {
  Beam beam(FemKind::kHyperelastic);
  const int32_t corner = NonlinearPlan(&beam, 0.02, 0.5, 4, {0.01, 0.03, 0.06});
  const BuildReport kl = BuildKlModel(*beam.model, beam.mesh, beam.plan);
  const NonlinearBuildReport r = BuildNonlinearModel(*beam.model, beam.mesh, beam.plan, kl);
  ASSERT_EQ(r.unconverged, 0);
  const models::reduced::NonlinearModelData& d = r.data;
  ASSERT_EQ(d.correction_coefficients.rows(), d.modes.cols());
  ASSERT_EQ(d.correction_coefficients.cols(), 4 * 3 * 2);  // 3 magnitudes × 2 nodes
  std::printf("in-span error on the samples: %.2f %% before the fit, %.2f %% after\n",
              100 * r.in_span_error_before, 100 * r.in_span_error_after);
  EXPECT_LT(r.in_span_error_after, 0.5 * r.in_span_error_before);
  models::reduced::NonlinearModelData stripped = d;
  stripped.correction_coefficients.resize(0, 0);
  const auto with = models::reduced::NonlinearReducedModel::Create(d);
  const auto without = models::reduced::NonlinearReducedModel::Create(stripped);
  // 0.045 N at the corner, 20° off its inward normal between two trained tilts, held 1 s.
  const Eigen::Vector3d inward = -BoundaryNormals(beam.mesh).col(corner);
  const Eigen::Vector3d side = inward.unitOrthogonal();
  const Eigen::Vector3d direction =
      std::cos(0.35) * inward +
      std::sin(0.35) * (std::cos(0.8) * side + std::sin(0.8) * inward.cross(side));
  reduced::EvaluationPlan plan;
  reduced::EvaluationCase* c = plan.add_cases();
  c->set_name("held out");
  c->set_node(corner);
  for (int k = 0; k < 3; ++k) c->add_force(0.045 * direction[k]);
  c->add_time(0.0);  // ramped over 1 s, held 0.5 s
  c->add_scale(0.0);
  c->add_time(1.0);
  c->add_scale(1.0);
  c->set_end_time(1.5);
  c->set_dt(0.25);
  const CaseResult a = Evaluate(*beam.model, beam.plan.fixed, *with, plan, &d.modes)[0];
  const CaseResult b = Evaluate(*beam.model, beam.plan.fixed, *without, plan, &d.modes)[0];
  std::printf("held-out load: field %.2f %% with, %.2f %% without (floor %.2f %%)\n",
              100 * a.field_error, 100 * b.field_error, 100 * a.basis_error);
  EXPECT_TRUE(a.converged);
  EXPECT_EQ(a.reduced_unconverged, 0);
  // When written: 0.17 % with, 0.66 % without.
  EXPECT_LT(a.field_error, 0.5 * b.field_error);
  // Without it (the plan's switch) the builder writes none.
  beam.plan.correction_in_modes = false;
  EXPECT_EQ(BuildNonlinearModel(*beam.model, beam.mesh, beam.plan, kl)
                .data.correction_coefficients.size(),
            0);
}

TEST(ReduceBuilder, RefusesBadPlansByName) {
  const Beam beam(FemKind::kLinear);
  const auto message = [&](const std::function<void(SamplingPlan*)>& change) {
    SamplingPlan plan = beam.plan;
    plan.points = {beam.Node(0.12, 0.03, 0.03)};
    change(&plan);
    try {
      BuildKlModel(*beam.model, beam.mesh, plan);
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("accepted");
  };
  EXPECT_NE(message([](SamplingPlan* p) { p->points.clear(); }).find("no sample point"),
            std::string::npos);
  EXPECT_NE(
      message([&](SamplingPlan* p) { p->points = {beam.Node(0.0, 0.0, 0.0)}; }).find("is held"),
      std::string::npos);
  EXPECT_NE(message([&](SamplingPlan* p) {
              p->points = {beam.Node(0.06, 0.015, 0.015)};
            }).find("not on the boundary"),
            std::string::npos);
  EXPECT_NE(message([](SamplingPlan* p) { p->points = {999}; }).find("point 999 out of range"),
            std::string::npos);
  EXPECT_NE(message([](SamplingPlan* p) { p->fixed.clear(); }).find("no support"),
            std::string::npos);
  EXPECT_NE(message([](SamplingPlan* p) {
              p->forces = {0.1, -1.0};
            }).find("force magnitude"),
            std::string::npos);
  EXPECT_NE(message([](SamplingPlan* p) { p->directions = 2; }).find("directions"),
            std::string::npos);
  EXPECT_NE(message([](SamplingPlan* p) { p->creep_interval = 0.0; }).find("creep_interval"),
            std::string::npos);
}

}  // namespace
}  // namespace somasim::reduce
