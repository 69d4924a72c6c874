// The nonlinear reduced model (server/models/reduced/nonlinear_model.h) and its ECSW cubature
// (ecsw.h): with a complete basis and every element at weight 1 it is the full hyperelastic QLV
// model's quasi-static solution step by step; its forces are the gradient of its energy and its
// tangent their derivative (finite differences); a trained cubature reproduces the reduced
// forces of all elements to its tolerance on held-out states with far fewer elements; NNLS finds
// a known sparse solution; steps allocate nothing; bad data is refused by name; a load too
// large to balance stops the step unconverged, no element inverted.
#include "server/models/reduced/nonlinear_model.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <limits>
#include <numeric>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh_gen/structured_meshes.h"
#include "server/models/fem/fem_model.h"
#include "server/models/reduced/ecsw.h"
#include "server/models/reduced/pod.h"
#include "server/models/reduced/reduce_fem.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models::reduced {
namespace {

using Eigen::Vector3d;

// A 6 × 2 × 2 cm beam of seed 000's liver material with its Prony series (5 × 2 × 2 nodes
// unless given), held at x = 0.
struct Beam {
  explicit Beam(int nx = 5, int ny = 2, int nz = 2) {
    mesh = mesh_gen::BoxGridTets(nx, ny, nz, Vector3d::Zero(), Vector3d(0.06, 0.02, 0.02));
    fem::FemParameters p;
    p.kind = fem::FemKind::kHyperelastic;
    p.hyperelastic = fem::LiverNava2008();
    p.prony = fem::LiverNava2008Prony();
    p.density = 1055.0;
    model = fem::FemModel::FromTetMesh(mesh, p);
    for (int32_t i = 0; i < model->num_nodes(); ++i) {
      if (mesh.vertices(0, i) < 1e-9) {
        fixed.push_back(i);
      } else {
        free.push_back(i);
      }
    }
  }
  int32_t Node(double x, double y, double z) const {
    for (int32_t i = 0; i < model->num_nodes(); ++i) {
      if ((mesh.vertices.col(i) - Vector3d(x, y, z)).norm() < 1e-9) return i;
    }
    return -1;
  }
  // Unit vectors of every free DOF: the complete basis.
  Eigen::MatrixXd CompleteBasis() const {
    Eigen::MatrixXd b = Eigen::MatrixXd::Zero(3 * model->num_nodes(), 3 * free.size());
    for (size_t k = 0; k < free.size(); ++k) {
      for (int a = 0; a < 3; ++a) b(3 * free[k] + a, static_cast<Eigen::Index>(3 * k + a)) = 1.0;
    }
    return b;
  }
  // A basis of `count` POD-like directions: random combinations of the free DOFs.
  Eigen::MatrixXd RandomModes(Eigen::Index count, unsigned seed) const {
    std::mt19937 rng(seed);
    std::normal_distribution<double> normal;
    Eigen::MatrixXd modes = Eigen::MatrixXd::Zero(3 * model->num_nodes(), count);
    for (const int32_t i : free) {
      for (int a = 0; a < 3; ++a) {
        for (Eigen::Index j = 0; j < count; ++j) modes(3 * i + a, j) = 1e-2 * normal(rng);
      }
    }
    return modes;
  }
  // K0⁻¹ B (3N × n), the Petrov–Galerkin test basis (reduce_fem.h; builder_test.cc checks that
  // K0 Ψ = B).
  Eigen::MatrixXd TestBasis(const Eigen::MatrixXd& modes) const {
    return PetrovGalerkinTestBasis(*model, modes, fixed);
  }
  // K0⁻¹ E_p (3N × 3 [m/N]): the static responses to tiny forces along x, y, z at `node`.
  Eigen::MatrixXd UnitResponses(int32_t node) const {
    const int32_t n = model->num_nodes();
    mesh::Points forces = mesh::Points::Zero(3, n);
    fem::StaticLoads loads;
    loads.external_forces = &forces;
    loads.fixed_nodes = fixed;
    loads.tolerance = 1e-12;
    constexpr double kTiny = 1e-7;  // [N]
    Eigen::MatrixXd unit(3 * n, 3);
    for (int a = 0; a < 3; ++a) {
      forces.setZero();
      forces(a, node) = kTiny;
      auto full = model->MakeState();
      EXPECT_TRUE(model->SolveStatic(loads, full.get()).converged);
      const mesh::Points u = full->positions - mesh.vertices;
      unit.col(a) = Eigen::Map<const Eigen::VectorXd>(u.data(), u.size()) / kTiny;
    }
    return unit;
  }
  NonlinearModelData Data(const Eigen::MatrixXd& modes) const {
    NonlinearModelData d;
    d.rest = mesh.vertices;
    d.masses = model->masses();
    d.modes = modes;
    d.tets = mesh.tetrahedra;
    d.weights.assign(static_cast<size_t>(model->num_tets()), 1.0);
    d.material = model->material();
    d.prony = model->prony();
    d.newton_tolerance = 1e-11;
    return d;
  }
  mesh::TetMesh mesh;
  std::unique_ptr<fem::FemModel> model;
  std::vector<int32_t> fixed, free;
};

TEST(NonlinearReducedModel, WithACompleteBasisIsTheFullViscoelasticQuasiStaticSolution) {
  const Beam beam;
  auto reduced = NonlinearReducedModel::Create(beam.Data(beam.CompleteBasis()));
  const int32_t tip = beam.Node(0.06, 0.02, 0.02);
  ASSERT_GE(tip, 0);
  mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
  fem::StaticLoads loads;
  loads.external_forces = &forces;
  loads.fixed_nodes = beam.fixed;
  loads.tolerance = 1e-11;
  auto full_state = beam.model->MakeState();
  auto state = reduced->MakeState();
  StepInputs inputs;
  inputs.dt = 0.25;
  inputs.external_forces = &forces;
  // Press 0.5 s, hold 1 s, release: large strain (the tip moves ~1 cm) and relaxation both ways.
  for (int s = 1; s <= 12; ++s) {
    const double t = 0.25 * s;
    const double scale = t <= 0.5 ? t / 0.5 : (t <= 1.5 ? 1.0 : 0.0);
    forces.col(tip) = scale * Vector3d(0.0, 0.02, -0.06);
    ASSERT_TRUE(beam.model->SolveQuasiStatic(loads, 0.25, full_state.get()).converged);
    ASSERT_EQ(reduced->Step(inputs, state.get()), StepStatus::kOk) << "step " << s;
    const mesh::Points u = full_state->positions - beam.mesh.vertices;
    const mesh::Points v = state->positions - beam.mesh.vertices;
    EXPECT_LE((u - v).norm(), 1e-6 * u.norm() + 1e-12) << "step " << s;
    if (s == 3) {
      EXPECT_GT(u.col(tip).norm(), 5e-3);  // nonlinear range
    }
  }
}

// Galerkin: the forces are −∂E/∂ξ and the tangent (symmetric) their derivative. Petrov–Galerkin
// (random test modes): the tangent D̃ᵀ (∂P/∂F) D is their derivative, not symmetric. With and
// without a Prony history (finite differences).
TEST(NonlinearReducedModel, ForcesAreTheEnergyGradientAndTheTangentTheirDerivative) {
  for (const bool petrov : {false, true}) {
    SCOPED_TRACE(petrov ? "Petrov-Galerkin" : "Galerkin");
    const Beam beam;
    const Eigen::MatrixXd modes = beam.RandomModes(6, 7);
    NonlinearModelData data = beam.Data(modes);
    if (petrov) data.test_modes = beam.RandomModes(6, 11);
    for (size_t e = 0; e < data.weights.size(); ++e)
      data.weights[e] = 0.5 + 0.1 * static_cast<double>(e % 7);
    auto model = NonlinearReducedModel::Create(data);
    auto state = model->MakeState();
    // Load history so that the Prony variables are not zero.
    mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
    forces.col(beam.Node(0.06, 0.0, 0.02)) = Vector3d(0.01, 0.0, -0.04);
    StepInputs inputs;
    inputs.dt = 0.1;
    inputs.external_forces = &forces;
    for (int s = 0; s < 3; ++s) ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    EXPECT_EQ(state->counters.solver_unconverged, 0);
    const Eigen::VectorXd xi = model->Coordinates(*state) * 1.3;
    ASSERT_GT(xi.norm(), 0.0);
    for (const double dt : {0.0, 0.1}) {
      Eigen::VectorXd force;
      Eigen::MatrixXd tangent;
      model->ReducedForces(*state, xi, dt, &force, &tangent);
      const double h = 1e-6;
      for (Eigen::Index j = 0; j < xi.size(); ++j) {
        Eigen::VectorXd plus = xi, minus = xi, fp, fm;
        plus(j) += h;
        minus(j) -= h;
        model->ReducedForces(*state, plus, dt, &fp, nullptr);
        model->ReducedForces(*state, minus, dt, &fm, nullptr);
        const Eigen::VectorXd fd = -(fp - fm) / (2 * h);
        EXPECT_LE((fd - tangent.col(j)).norm(), 1e-6 * tangent.norm())
            << "dt " << dt << " col " << j;
      }
      if (dt == 0.0 && !petrov) {  // f = −∂E/∂ξ (the elastic energy)
        for (Eigen::Index j = 0; j < xi.size(); ++j) {
          const auto energy = [&](double d) {
            Eigen::VectorXd x = xi;
            x(j) += d;
            return model->ElasticEnergyAt(x);
          };
          const double fd = -(energy(h) - energy(-h)) / (2 * h);
          EXPECT_NEAR(fd, force(j), 1e-6 * force.norm()) << "component " << j;
        }
      }
    }
    // Galerkin's tangent is symmetric (hyperelastic, symmetric Prony offsets); Petrov–Galerkin's
    // is not.
    Eigen::VectorXd force;
    Eigen::MatrixXd tangent;
    model->ReducedForces(*state, xi, 0.1, &force, &tangent);
    if (petrov) {
      EXPECT_GT((tangent - tangent.transpose()).norm(), 1e-3 * tangent.norm());
    } else {
      EXPECT_LE((tangent - tangent.transpose()).norm(), 1e-9 * tangent.norm());
    }
  }
}

// Petrov–Galerkin with Ψ = K0⁻¹ B (nonlinear_model.h): in the linear range its field is, step
// by step through a press, the creep under a held force and the recovery after release, the L2
// projection of the full viscoelastic model's field onto the modes — the best the modes hold —
// where the Galerkin model's is not; and with its static correction (R_p = K0⁻¹ E_p −
// B K̂0⁻¹ Ψ_pᵀ) it is the full field itself.
TEST(NonlinearReducedModel, PetrovGalerkinIsTheL2ProjectionOfTheFullSolutionInTheLinearRange) {
  const Beam beam;
  const Eigen::MatrixXd modes = beam.RandomModes(6, 5);
  const int32_t tip = beam.Node(0.06, 0.02, 0.02);
  ASSERT_GE(tip, 0);
  const int32_t n = beam.model->num_nodes();
  NonlinearModelData data = beam.Data(modes);
  data.test_modes = beam.TestBasis(modes);
  const auto petrov = NonlinearReducedModel::Create(data);
  const auto galerkin = NonlinearReducedModel::Create(beam.Data(modes));
  EXPECT_TRUE(petrov->petrov_galerkin());
  EXPECT_FALSE(galerkin->petrov_galerkin());
  EXPECT_THROW(PetrovGalerkinTestBasis(*beam.model, modes.topRows(9), beam.fixed),
               std::invalid_argument);  // modes not 3N × n
  // The static correction at the tip for the Petrov–Galerkin model.
  mesh::Points forces = mesh::Points::Zero(3, n);
  fem::StaticLoads loads;
  loads.external_forces = &forces;
  loads.fixed_nodes = beam.fixed;
  loads.tolerance = 1e-12;
  const Eigen::MatrixXd unit = beam.UnitResponses(tip);
  Eigen::VectorXd force;
  Eigen::MatrixXd tangent;
  petrov->ReducedForces(*petrov->MakeState(), Eigen::VectorXd::Zero(6), 0.0, &force, &tangent);
  // At rest K̂ = Ψᵀ K0 B = BᵀB.
  EXPECT_LE((tangent - modes.transpose() * modes).norm(), 1e-6 * tangent.norm());
  NonlinearModelData corrected_data = data;
  corrected_data.correction_nodes = {tip};
  corrected_data.corrections =
      unit - modes * tangent.partialPivLu().solve(
                         data.test_modes.middleRows(3 * tip, 3).transpose().eval());
  const auto corrected = NonlinearReducedModel::Create(corrected_data);
  auto full_state = beam.model->MakeState();
  auto p_state = petrov->MakeState();
  auto g_state = galerkin->MakeState();
  auto c_state = corrected->MakeState();
  StepInputs inputs;
  inputs.dt = 0.25;
  inputs.external_forces = &forces;
  loads.tolerance = 1e-11;
  const Eigen::LDLT<Eigen::MatrixXd> gram(modes.transpose() * modes);
  double worst_petrov = 0.0, worst_galerkin = 0.0, worst_corrected = 0.0, largest = 0.0;
  for (int s = 1; s <= 16; ++s) {  // press 0.5 s, hold to 2 s (creep), release (recovery)
    const double t = 0.25 * s;
    const double scale = t <= 0.5 ? t / 0.5 : (t <= 2.0 ? 1.0 : 0.0);
    forces.setZero();
    // [N]: ~0.45 µm, the linear range. The distance from the projection grows ∝ F (the
    // material's nonlinearity: 1.1e-2 of the projection at 100× this force).
    forces.col(tip) = scale * Vector3d(0.0, 2e-7, -6e-7);
    ASSERT_TRUE(beam.model->SolveQuasiStatic(loads, 0.25, full_state.get()).converged);
    ASSERT_EQ(petrov->Step(inputs, p_state.get()), StepStatus::kOk) << "step " << s;
    ASSERT_EQ(galerkin->Step(inputs, g_state.get()), StepStatus::kOk) << "step " << s;
    ASSERT_EQ(corrected->Step(inputs, c_state.get()), StepStatus::kOk) << "step " << s;
    const mesh::Points u = full_state->positions - beam.mesh.vertices;
    const Eigen::Map<const Eigen::VectorXd> uv(u.data(), u.size());
    const Eigen::VectorXd projection = modes * gram.solve(modes.transpose() * uv);
    const auto field = [&](const TissueState& state) {
      const mesh::Points v = state.positions - beam.mesh.vertices;
      return Eigen::VectorXd(Eigen::Map<const Eigen::VectorXd>(v.data(), v.size()));
    };
    largest = std::max(largest, projection.norm());
    worst_petrov = std::max(worst_petrov, (field(*p_state) - projection).norm());
    worst_galerkin = std::max(worst_galerkin, (field(*g_state) - projection).norm());
    worst_corrected = std::max(worst_corrected, (field(*c_state) - uv).norm());
  }
  std::printf(
      "6 random modes, tip force pressed, held, released: distance from the L2 projection "
      "%.2e (Petrov-Galerkin), %.2e (Galerkin); corrected Petrov-Galerkin from the full field "
      "%.2e (of the largest projection)\n",
      worst_petrov / largest, worst_galerkin / largest, worst_corrected / largest);
  EXPECT_LT(worst_petrov, 1e-3 * largest);  // the material's nonlinearity, ∝ F
  EXPECT_GT(worst_galerkin, 0.05 * largest);
  EXPECT_LT(worst_corrected, 1e-3 * largest);
}

// With a complete basis every regular test basis gives the same (the full) solution: loads,
// gravity, grasps and LocalStiffness are tested consistently (here Ψ = B M, M random).
TEST(NonlinearReducedModel, WithACompleteBasisAnyTestBasisGivesTheSameSolution) {
  const Beam beam;
  const Eigen::MatrixXd basis = beam.CompleteBasis();
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> uniform(-0.3, 0.3);
  Eigen::MatrixXd mix = Eigen::MatrixXd::Identity(basis.cols(), basis.cols());
  for (Eigen::Index i = 0; i < mix.size(); ++i) mix.data()[i] += uniform(rng) / 8.0;
  NonlinearModelData data = beam.Data(basis);
  data.max_newton_iterations = 100;  // large strain from rest: a few dozen damped iterations
  const auto galerkin = NonlinearReducedModel::Create(data);
  data.test_modes = basis * mix;
  const auto petrov = NonlinearReducedModel::Create(data);
  auto p = petrov->MakeState();
  auto g = galerkin->MakeState();
  const int32_t tip = beam.Node(0.06, 0.02, 0.02);
  Attachment grasp;
  grasp.node = beam.Node(0.06, 0.0, 0.0);
  grasp.target = beam.mesh.vertices.col(grasp.node) + Vector3d(0.0, 0.002, 0.001);
  grasp.stiffness = 50.0;
  mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
  forces.col(tip) = Vector3d(0.0, 0.01, -0.03);
  StepInputs inputs;
  inputs.dt = 0.25;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  inputs.external_forces = &forces;
  inputs.attachments = std::span<const Attachment>(&grasp, 1);
  for (int s = 0; s < 4; ++s) {
    if (s == 3) inputs.attachments = {};  // released: the tissue recovers
    ASSERT_EQ(petrov->Step(inputs, p.get()), StepStatus::kOk) << "step " << s;
    ASSERT_EQ(galerkin->Step(inputs, g.get()), StepStatus::kOk) << "step " << s;
    const mesh::Points u = g->positions - beam.mesh.vertices;
    EXPECT_LE((p->positions - g->positions).norm(), 1e-6 * u.norm()) << "step " << s;
  }
  EXPECT_EQ(p->counters.solver_unconverged, 0);
  const Eigen::Matrix3d kp = petrov->LocalStiffness(*p, tip);
  const Eigen::Matrix3d kg = galerkin->LocalStiffness(*g, tip);
  EXPECT_LE((kp - kg).norm(), 1e-6 * kg.norm());
  EXPECT_LE((kp - kp.transpose()).norm(), 1e-9 * kp.norm());
}

TEST(Ecsw, NnlsFindsAKnownSparseNonNegativeSolution) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> uniform(-1.0, 1.0);
  Eigen::MatrixXd g(60, 200);
  for (Eigen::Index i = 0; i < g.rows(); ++i) {
    for (Eigen::Index j = 0; j < g.cols(); ++j) g(i, j) = uniform(rng);
  }
  Eigen::VectorXd truth = Eigen::VectorXd::Zero(200);
  truth(5) = 2.0;
  truth(17) = 0.5;
  truth(90) = 1.5;
  truth(150) = 3.0;
  const Eigen::VectorXd b = g * truth;
  const NnlsResult r = SparseNnls(g, b, 1e-10, 100);
  EXPECT_TRUE(r.converged);
  EXPECT_LE(r.relative_residual, 1e-10);
  ASSERT_EQ(r.columns, (std::vector<int32_t>{5, 17, 90, 150}));
  for (size_t k = 0; k < 4; ++k) EXPECT_NEAR(r.weights[k], truth(r.columns[k]), 1e-8);
  // A target outside the cone of positive columns: the best non-negative fit, every weight > 0,
  // not converged.
  const Eigen::MatrixXd positive = g.cwiseAbs();
  const NnlsResult cone = SparseNnls(positive, -(positive * truth), 1e-10, 100);
  EXPECT_FALSE(cone.converged);
  for (const double w : cone.weights) EXPECT_GT(w, 0.0);
  EXPECT_THROW(SparseNnls(g, Eigen::VectorXd::Zero(59), 1e-3, 10), std::invalid_argument);
  Eigen::MatrixXd bad = g;
  bad(3, 3) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(SparseNnls(bad, b, 1e-3, 10), std::invalid_argument);
  EXPECT_THROW(SparseNnls(g, b, 0.0, 10), std::invalid_argument);
  EXPECT_THROW(SparseNnls(g, b, 1e-3, 0), std::invalid_argument);
}

// Training snapshots: static equilibria of the beam under point loads at the tip nodes.
struct Trained {
  explicit Trained(const Beam& beam) {
    auto st = beam.model->MakeState();
    fem::StaticLoads loads;
    mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
    loads.external_forces = &forces;
    loads.fixed_nodes = beam.fixed;
    loads.load_steps = 2;
    for (const double y : {0.0, 0.02}) {
      for (const double z : {0.0, 0.02}) {
        for (const Vector3d& f : {Vector3d(0, 0, -0.08), Vector3d(0, 0.06, 0), Vector3d(0.1, 0, 0),
                                  Vector3d(0, 0, -0.02)}) {
          forces.setZero();
          forces.col(beam.Node(0.06, y, z)) = f;
          auto s = beam.model->MakeState();
          EXPECT_TRUE(beam.model->SolveStatic(loads, s.get()).converged);
          snapshots.push_back(s->positions - beam.mesh.vertices);
        }
      }
    }
    Eigen::MatrixXd q(3 * beam.model->num_nodes(), static_cast<Eigen::Index>(snapshots.size()));
    for (size_t k = 0; k < snapshots.size(); ++k) {
      q.col(static_cast<Eigen::Index>(k)) =
          Eigen::Map<const Eigen::VectorXd>(snapshots[k].data(), snapshots[k].size());
    }
    PodSettings pod;
    pod.energy_fraction = 1.0;
    pod.max_modes = 10;
    modes = ModesOfSnapshots(q, pod).modes;
  }
  std::vector<mesh::Points> snapshots;
  Eigen::MatrixXd modes;
};

// `all` with its elements and weights replaced by the cubature's.
NonlinearModelData Sampled(const NonlinearModelData& all, const mesh::TetMesh& mesh,
                           const Cubature& cubature) {
  NonlinearModelData d = all;
  d.tets.resize(4, static_cast<Eigen::Index>(cubature.elements.size()));
  for (size_t k = 0; k < cubature.elements.size(); ++k) {
    d.tets.col(static_cast<Eigen::Index>(k)) = mesh.tetrahedra.col(cubature.elements[k]);
  }
  d.weights = cubature.weights;
  d.elements = cubature.elements;
  return d;
}

// The relative differences of two models' reduced forces and tangents (the worst of each) at
// held-out states: mixes of two training projections, scaled.
std::pair<double, double> HeldOutForceDifferences(const NonlinearReducedModel& a,
                                                  const NonlinearReducedModel& b,
                                                  const Trained& trained) {
  const auto sa = a.MakeState();
  const auto sb = b.MakeState();
  double force = 0.0, tangent = 0.0;
  for (const double mix : {0.3, 0.7}) {
    const mesh::Points u = mix * trained.snapshots[1] + (1.0 - mix) * 0.8 * trained.snapshots[6];
    const Eigen::VectorXd xi =
        trained.modes.transpose() * Eigen::Map<const Eigen::VectorXd>(u.data(), u.size());
    Eigen::VectorXd f1, f2;
    Eigen::MatrixXd k1, k2;
    a.ReducedForces(*sa, xi, 0.0, &f1, &k1);
    b.ReducedForces(*sb, xi, 0.0, &f2, &k2);
    force = std::max(force, (f1 - f2).norm() / f1.norm());
    tangent = std::max(tangent, (k1 - k2).norm() / k1.norm());
  }
  return {force, tangent};
}

// The displacement after 4 quasi-static steps of 0.25 s under `force` [N] at the beam's corner
// (0.06, 0, 0.02), and the steps that did not converge.
mesh::Points HeldOutDisplacement(const NonlinearReducedModel& model, const Beam& beam,
                                 const Vector3d& force, int64_t* unconverged) {
  mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
  forces.col(beam.Node(0.06, 0.0, 0.02)) = force;
  StepInputs inputs;
  inputs.dt = 0.25;
  inputs.external_forces = &forces;
  auto state = model.MakeState();
  for (int s = 0; s < 4; ++s) EXPECT_EQ(model.Step(inputs, state.get()), StepStatus::kOk);
  *unconverged = state->counters.solver_unconverged;
  return state->positions - beam.mesh.vertices;
}

TEST(Ecsw, TrainedCubatureReproducesTheReducedForcesOfAllElementsWithFewOfThem) {
  const Beam beam(9, 3, 3);  // 192 elements
  const Trained trained(beam);
  CubatureSettings settings;
  settings.tolerance = 1e-2;
  const Cubature cubature = TrainCubature(*beam.model, trained.modes, trained.snapshots, settings);
  EXPECT_TRUE(cubature.converged);
  EXPECT_LE(cubature.relative_residual, 1e-2);
  EXPECT_EQ(cubature.snapshots, 16);
  EXPECT_LT(cubature.elements.size(), static_cast<size_t>(beam.model->num_tets()) / 3);
  // Reduced models with all elements and with the cubature, at held-out states (a mix of the
  // training projections, scaled), with a Prony history.
  NonlinearModelData all = beam.Data(trained.modes);
  auto full_reduced = NonlinearReducedModel::Create(all);
  auto ecsw = NonlinearReducedModel::Create(Sampled(all, beam.mesh, cubature));
  const auto [force_difference, tangent_difference] =
      HeldOutForceDifferences(*full_reduced, *ecsw, trained);
  EXPECT_LE(force_difference, 2e-2);
  EXPECT_LE(tangent_difference, 5e-2);
  // Quasi-static solutions of the two under a held-out load agree closely.
  int64_t unconverged = 0;
  const Vector3d load(0.01, 0.03, -0.05);
  const mesh::Points u1 = HeldOutDisplacement(*full_reduced, beam, load, &unconverged);
  const mesh::Points u2 = HeldOutDisplacement(*ecsw, beam, load, &unconverged);
  EXPECT_LE((u1 - u2).norm(), 2e-2 * u1.norm());
  // A linear model's cubature is refused.
  fem::FemParameters linear;
  linear.kind = fem::FemKind::kLinear;
  linear.youngs_modulus = 5000.0;
  auto other = fem::FemModel::FromTetMesh(beam.mesh, linear);
  EXPECT_THROW(TrainCubature(*other, trained.modes, trained.snapshots, settings),
               std::invalid_argument);
}

// A Petrov–Galerkin model's cubature is trained on its own equations Ψᵀ f: it reproduces the
// all-element Ψᵀ f and tangent at held-out states, and the quasi-static solution, with a
// fraction of the elements; trained on Bᵀ f instead it would fit the wrong sums.
TEST(Ecsw, TrainedOnPetrovGalerkinForcesReproducesThemWithFewElements) {
  const Beam beam(9, 3, 3);  // 192 elements
  const Trained trained(beam);
  const Eigen::MatrixXd psi = beam.TestBasis(trained.modes);
  CubatureSettings settings;
  settings.tolerance = 1e-3;
  const Cubature cubature =
      TrainCubature(*beam.model, trained.modes, trained.snapshots, settings, &psi);
  const Cubature galerkin_cubature =
      TrainCubature(*beam.model, trained.modes, trained.snapshots, settings);
  EXPECT_TRUE(cubature.converged);
  EXPECT_LE(cubature.relative_residual, 1e-3);
  EXPECT_LT(cubature.elements.size(), static_cast<size_t>(beam.model->num_tets()) / 2);
  std::printf("cubature at 0.1 %%: %zu elements (Petrov-Galerkin), %zu (Galerkin) of %d\n",
              cubature.elements.size(), galerkin_cubature.elements.size(), beam.model->num_tets());
  NonlinearModelData all = beam.Data(trained.modes);
  all.test_modes = psi;
  auto full_reduced = NonlinearReducedModel::Create(all);
  auto ecsw = NonlinearReducedModel::Create(Sampled(all, beam.mesh, cubature));
  auto wrong = NonlinearReducedModel::Create(Sampled(all, beam.mesh, galerkin_cubature));
  const auto [force_difference, tangent_difference] =
      HeldOutForceDifferences(*full_reduced, *ecsw, trained);
  EXPECT_LE(force_difference, 5e-3);
  EXPECT_LE(tangent_difference, 2e-2);
  // A moderate load (the tip ~5 mm): at 0.1 N the beam's Petrov–Galerkin tangent turns
  // singular (nonlinear_model.h) and neither model converges.
  const Vector3d load(0.0003, 0.0009, -0.0015);
  int64_t unconverged_all = 0, unconverged_ecsw = 0, unconverged_wrong = 0;
  const mesh::Points u1 = HeldOutDisplacement(*full_reduced, beam, load, &unconverged_all);
  const mesh::Points u2 = HeldOutDisplacement(*ecsw, beam, load, &unconverged_ecsw);
  const mesh::Points u3 = HeldOutDisplacement(*wrong, beam, load, &unconverged_wrong);
  EXPECT_EQ(unconverged_all, 0);
  EXPECT_EQ(unconverged_ecsw, 0);
  std::printf("held-out load: %.2e (trained on its equations), %.2e (on Galerkin's)\n",
              (u1 - u2).norm() / u1.norm(), (u1 - u3).norm() / u1.norm());
  EXPECT_LE((u1 - u2).norm(), 1.5e-2 * u1.norm());      // 0.74 % when written
  EXPECT_GT((u1 - u3).norm(), 4.0 * (u1 - u2).norm());  // 9.8 % when written
  // Test modes of another shape are refused.
  const Eigen::MatrixXd narrow = psi.leftCols(2);
  EXPECT_THROW(TrainCubature(*beam.model, trained.modes, trained.snapshots, settings, &narrow),
               std::invalid_argument);
}

TEST(NonlinearReducedModel, GraspsPullTheirNodesAndLocalStiffnessIsTheCondensedTangent) {
  const Beam beam;
  auto model = NonlinearReducedModel::Create(beam.Data(beam.CompleteBasis()));
  auto state = model->MakeState();
  const int32_t tip = beam.Node(0.06, 0.02, 0.02);
  Attachment grasp;
  grasp.node = tip;
  grasp.target = beam.mesh.vertices.col(tip) + Vector3d(0.0, 0.0, 0.004);
  grasp.stiffness = 50.0;
  StepInputs inputs;
  inputs.dt = 0.01;
  inputs.attachments = std::span<const Attachment>(&grasp, 1);
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  const double lift = state->positions(2, tip) - beam.mesh.vertices(2, tip);
  EXPECT_GT(lift, 1e-4);
  EXPECT_LT(lift, 0.004);
  // With the complete basis the condensed stiffness is the full tangent's Schur complement:
  // check K_local f = displacement of a small extra force (linear response at the state).
  inputs.attachments = {};
  inputs.dt = 1e-7;  // QLV's instantaneous response (g = 1), which LocalStiffness gives
  auto rest = model->MakeState();
  const Eigen::Matrix3d k = model->LocalStiffness(*rest, tip);
  EXPECT_LE((k - k.transpose()).norm(), 1e-9 * k.norm());
  mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
  forces.col(tip) = Vector3d(0.0, 1e-5, -2e-5);
  inputs.external_forces = &forces;
  ASSERT_EQ(model->Step(inputs, rest.get()), StepStatus::kOk);
  const Vector3d du = rest->positions.col(tip) - beam.mesh.vertices.col(tip);
  EXPECT_LE((k * du - forces.col(tip)).norm(), 1e-3 * forces.col(tip).norm());
}

TEST(NonlinearReducedModel, StepsAllocateNothing) {
  const Beam beam;
  const Trained trained(beam);
  for (const bool petrov : {false, true}) {
    SCOPED_TRACE(petrov ? "Petrov-Galerkin" : "Galerkin");
    NonlinearModelData data = beam.Data(trained.modes);
    if (petrov) data.test_modes = beam.TestBasis(trained.modes);
    data.newton_tolerance = 1e-8;
    const int32_t tip = beam.Node(0.06, 0.02, 0.02);
    data.correction_nodes = {tip};  // the static correction's path too (values immaterial here)
    data.corrections = 1e-3 * Eigen::MatrixXd::Ones(data.modes.rows(), 3);
    data.correction_magnitudes = {0.01, 0.05};
    data.correction_scales = Eigen::MatrixXd::Ones(2, 1);
    data.correction_coefficients = 1e-3 * Eigen::MatrixXd::Ones(data.modes.cols(), 8);
    auto model = NonlinearReducedModel::Create(data);
    auto state = model->MakeState();
    mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
    Attachment grasp;
    grasp.node = beam.Node(0.06, 0.0, 0.0);
    grasp.target = beam.mesh.vertices.col(grasp.node) + Vector3d(0.0, 0.002, 0.0);
    grasp.stiffness = 30.0;
    StepInputs inputs;
    inputs.dt = 1e-3;
    inputs.gravity = Vector3d(0, 0, -9.81);
    inputs.external_forces = &forces;
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);  // warm-up
    testing::AllocationCounter counter;
    for (int s = 0; s < 20; ++s) {
      forces.col(tip) = Vector3d(0.0, 0.0, -0.003 * s);
      inputs.attachments =
          s % 2 == 0 ? std::span<const Attachment>(&grasp, 1) : std::span<const Attachment>();
      ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
      (void)model->LocalStiffness(*state, tip);
    }
    EXPECT_EQ(counter.count(), 0);
    EXPECT_EQ(model->petrov_galerkin(), petrov);
  }
}

TEST(NonlinearReducedModel, ALoadTooLargeToBalanceStopsUnconvergedWithoutInvertingAnElement) {
  const Beam beam;
  auto model = NonlinearReducedModel::Create(beam.Data(beam.CompleteBasis()));
  auto state = model->MakeState();
  mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
  const int32_t tip = beam.Node(0.06, 0.02, 0.02);
  forces.col(tip) = Vector3d(0.0, 0.0, -0.02);
  StepInputs inputs;
  inputs.dt = 0.25;
  inputs.external_forces = &forces;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_EQ(state->counters.solver_unconverged, 0);
  forces.col(tip) = Vector3d(0.0, 0.0, -1e4);  // would crush the tip's elements
  EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_EQ(state->counters.solver_unconverged, 1);
  EXPECT_TRUE(state->positions.allFinite());
  EXPECT_TRUE(std::isfinite(model->ElasticEnergyAt(model->Coordinates(*state))));
  // Back to a load it can carry: converged again.
  forces.col(tip) = Vector3d(0.0, 0.0, -0.02);
  EXPECT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_EQ(state->counters.solver_unconverged, 1);
}

// After a release the tissue recovers with no load at all: the residual's relative tolerance
// cannot be met but in rounding, so Newton is measured against the largest load carried — each
// recovering step converges in a few iterations (before: every one ran to its limit, counted
// unconverged), in both projections.
TEST(NonlinearReducedModel, AReleasedTissueRecoversInConvergedSteps) {
  const Beam beam;
  const Eigen::MatrixXd modes = beam.RandomModes(6, 5);
  for (const bool petrov : {false, true}) {
    SCOPED_TRACE(petrov ? "Petrov-Galerkin" : "Galerkin");
    NonlinearModelData data = beam.Data(modes);
    data.newton_tolerance = 1e-8;
    if (petrov) data.test_modes = beam.TestBasis(modes);
    const auto model = NonlinearReducedModel::Create(data);
    auto state = model->MakeState();
    mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
    const int32_t tip = beam.Node(0.06, 0.02, 0.02);
    StepInputs inputs;
    inputs.dt = 0.25;
    inputs.external_forces = &forces;
    forces.col(tip) = Vector3d(0.0, 2e-5, -6e-5);  // [N]
    for (int s = 0; s < 4; ++s) ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    EXPECT_EQ(state->counters.solver_unconverged, 0);
    forces.setZero();  // released: the tissue creeps back
    const Eigen::VectorXd pressed = model->Coordinates(*state);
    const int64_t before = state->counters.solver_iterations;
    for (int s = 0; s < 8; ++s) ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    EXPECT_EQ(state->counters.solver_unconverged, 0);
    EXPECT_LE(state->counters.solver_iterations - before, 8 * 10);
    std::printf("%s: %ld Newton iterations over 8 recovering steps\n",
                petrov ? "Petrov-Galerkin" : "Galerkin",
                static_cast<long>(state->counters.solver_iterations - before));
    // Recovering, not yet back: the Prony variables still hold part of the press.
    const double left = model->Coordinates(*state).norm();
    EXPECT_GT(left, 1e-3 * pressed.norm());
    EXPECT_LT(left, 0.5 * pressed.norm());
  }
}

// The static correction (nonlinear_model.h): with R_p = K0⁻¹ E_p − B K̂0⁻¹ Bᵀ E_p at the tip, a
// small (linear-range) force there — pressed, held while the tissue creeps, released while it
// recovers — gives the full viscoelastic model's field on a 6-mode basis that alone misses most
// of it; a force at another node is not corrected.
TEST(NonlinearReducedModel, TheStaticCorrectionGivesTheFullResponseToAPointForce) {
  const Beam beam;
  const Eigen::MatrixXd modes = beam.RandomModes(6, 5);
  const int32_t tip = beam.Node(0.06, 0.02, 0.02);
  ASSERT_GE(tip, 0);
  const int32_t n = beam.model->num_nodes();
  // K0⁻¹ E_p by the full model's static solves under a tiny force (linear range), K̂0 from the
  // uncorrected model.
  mesh::Points forces = mesh::Points::Zero(3, n);
  fem::StaticLoads loads;
  loads.external_forces = &forces;
  loads.fixed_nodes = beam.fixed;
  loads.tolerance = 1e-12;
  const Eigen::MatrixXd unit = beam.UnitResponses(tip);
  const auto plain = NonlinearReducedModel::Create(beam.Data(modes));
  Eigen::VectorXd force;
  Eigen::MatrixXd tangent;
  plain->ReducedForces(*plain->MakeState(), Eigen::VectorXd::Zero(6), 0.0, &force, &tangent);
  NonlinearModelData data = beam.Data(modes);
  data.correction_nodes = {tip};
  data.corrections = unit - modes * tangent.ldlt().solve(modes.middleRows(3 * tip, 3).transpose());
  const auto corrected = NonlinearReducedModel::Create(data);
  auto full_state = beam.model->MakeState();
  auto plain_state = plain->MakeState();
  auto state = corrected->MakeState();
  StepInputs inputs;
  inputs.dt = 0.25;
  inputs.external_forces = &forces;
  loads.tolerance = 1e-11;
  double worst = 0.0, worst_plain = 0.0, largest = 0.0;
  for (int s = 1; s <= 16; ++s) {  // press 0.5 s, hold to 2 s (creep), release (recovery)
    const double t = 0.25 * s;
    const double scale = t <= 0.5 ? t / 0.5 : (t <= 2.0 ? 1.0 : 0.0);
    forces.setZero();
    forces.col(tip) = scale * Vector3d(0.0, 2e-5, -6e-5);  // [N]: ~45 µm, linear range
    ASSERT_TRUE(beam.model->SolveQuasiStatic(loads, 0.25, full_state.get()).converged);
    ASSERT_EQ(corrected->Step(inputs, state.get()), StepStatus::kOk) << "step " << s;
    ASSERT_EQ(plain->Step(inputs, plain_state.get()), StepStatus::kOk) << "step " << s;
    const mesh::Points u = full_state->positions - beam.mesh.vertices;
    largest = std::max(largest, u.norm());
    worst = std::max(worst, (state->positions - full_state->positions).norm());
    worst_plain = std::max(worst_plain, (plain_state->positions - full_state->positions).norm());
  }
  std::printf(
      "6 modes, tip force 0.063 mN pressed, held, released: worst field error %.2e of the "
      "largest field uncorrected, %.2e corrected\n",
      worst_plain / largest, worst / largest);
  EXPECT_GT(worst_plain, 0.3 * largest);  // the modes alone miss most of it
  EXPECT_LT(worst, 1e-3 * largest);  // the full one (1.4e-4: the material's nonlinearity, ∝ F)
  // The scale κ(|e|): held at its last value beyond the last magnitude (here 0.5 from 1 µN on),
  // so the correction halves.
  NonlinearModelData scaled_data = data;
  scaled_data.correction_magnitudes = {1e-6};
  scaled_data.correction_scales = Eigen::MatrixXd::Constant(1, 1, 0.5);
  const auto scaled = NonlinearReducedModel::Create(scaled_data);
  auto one = corrected->MakeState();
  auto half = scaled->MakeState();
  auto none = plain->MakeState();
  forces.setZero();
  forces.col(tip) = Vector3d(0.0, 2e-5, -6e-5);
  ASSERT_EQ(corrected->Step(inputs, one.get()), StepStatus::kOk);
  ASSERT_EQ(scaled->Step(inputs, half.get()), StepStatus::kOk);
  ASSERT_EQ(plain->Step(inputs, none.get()), StepStatus::kOk);
  const double full_correction = (one->positions - none->positions).norm();
  EXPECT_GT(full_correction, 0.0);
  EXPECT_NEAR((half->positions - none->positions).norm(), 0.5 * full_correction,
              1e-9 * full_correction);
  // A force at another node is not corrected: the two models agree there.
  const int32_t other = beam.Node(0.06, 0.0, 0.0);
  auto a = corrected->MakeState();
  auto b = plain->MakeState();
  forces.setZero();
  forces.col(other) = Vector3d(0.0, 0.0, -6e-4);
  ASSERT_EQ(corrected->Step(inputs, a.get()), StepStatus::kOk);
  ASSERT_EQ(plain->Step(inputs, b.get()), StepStatus::kOk);
  EXPECT_LT((a->positions - b->positions).norm(), 1e-12);
}

// The correction's part in the modes: node p's field gains B G_p(|e|) (e, |e|), G_p piecewise
// linear in |e| through (0, 0) and the blocks given at the magnitudes, held beyond the last; ξ (the
// reduced equilibrium) is untouched, and so is a force at a node without a correction.
TEST(NonlinearReducedModel, TheCorrectionsPartInTheModesAddsBGTimesTheForceAndItsMagnitude) {
  const Beam beam;
  const Eigen::MatrixXd modes = beam.RandomModes(6, 7);
  const int32_t tip = beam.Node(0.06, 0.02, 0.02), other = beam.Node(0.06, 0.0, 0.0);
  NonlinearModelData data = beam.Data(modes);
  data.prony.clear();  // elastic: the effective force is the force
  data.correction_nodes = {other, tip};
  data.corrections = 1e-3 * Eigen::MatrixXd::Ones(modes.rows(), 6);
  data.correction_magnitudes = {1e-4, 3e-4};
  data.correction_scales = Eigen::MatrixXd::Constant(2, 2, 0.8);
  const auto plain = NonlinearReducedModel::Create(data);
  // Blocks (n × 4 each, node-major): the tip's at 0.1 mN and 0.3 mN; the other node's zero.
  const Eigen::MatrixXd g1 = 20.0 * Eigen::MatrixXd::Random(6, 4);
  const Eigen::MatrixXd g2 = 50.0 * Eigen::MatrixXd::Random(6, 4);
  data.correction_coefficients = Eigen::MatrixXd::Zero(6, 16);
  data.correction_coefficients.middleCols<4>(8) = g1;
  data.correction_coefficients.middleCols<4>(12) = g2;
  const auto corrected = NonlinearReducedModel::Create(data);
  mesh::Points forces = mesh::Points::Zero(3, beam.model->num_nodes());
  StepInputs inputs;
  inputs.dt = 0.25;
  inputs.external_forces = &forces;
  const Vector3d direction = Vector3d(0.0, 0.6, -0.8);
  for (const double magnitude : {0.5e-4, 1e-4, 2e-4, 3e-4, 6e-4}) {
    SCOPED_TRACE(magnitude);
    forces.setZero();
    forces.col(tip) = magnitude * direction;
    auto a = plain->MakeState();
    auto b = corrected->MakeState();
    ASSERT_EQ(plain->Step(inputs, a.get()), StepStatus::kOk);
    ASSERT_EQ(corrected->Step(inputs, b.get()), StepStatus::kOk);
    Eigen::MatrixXd g;  // G(|e|) by hand
    if (magnitude <= 1e-4) {
      g = (magnitude / 1e-4) * g1;
    } else if (magnitude <= 3e-4) {
      const double w = (magnitude - 1e-4) / 2e-4;
      g = (1.0 - w) * g1 + w * g2;
    } else {
      g = g2;
    }
    const Eigen::Vector3d e = forces.col(tip);
    const Eigen::VectorXd expected = modes * (g * Eigen::Vector4d(e(0), e(1), e(2), e.norm()));
    const mesh::Points shift = b->positions - a->positions;
    EXPECT_LT((Eigen::Map<const Eigen::VectorXd>(shift.data(), shift.size()) - expected).norm(),
              1e-9 * expected.norm());
    EXPECT_GT(expected.norm(), 0.0);
    EXPECT_LT((corrected->Coordinates(*b) - plain->Coordinates(*a)).norm(), 1e-12);
  }
  forces.setZero();
  forces.col(other) = Vector3d(0.0, 0.0, -2e-4);  // its blocks are zero
  auto a = plain->MakeState();
  auto b = corrected->MakeState();
  ASSERT_EQ(plain->Step(inputs, a.get()), StepStatus::kOk);
  ASSERT_EQ(corrected->Step(inputs, b.get()), StepStatus::kOk);
  EXPECT_LT((b->positions - a->positions).norm(), 1e-15);
}

TEST(NonlinearReducedModel, RefusesBadDataByName) {
  const Beam beam;
  const NonlinearModelData good = beam.Data(beam.CompleteBasis());
  const auto refused = [&](const std::function<void(NonlinearModelData*)>& edit,
                           const std::string& what) {
    NonlinearModelData d = good;
    edit(&d);
    try {
      NonlinearReducedModel::Create(d);
      ADD_FAILURE() << "accepted: " << what;
    } catch (const std::invalid_argument& error) {
      EXPECT_NE(std::string(error.what()).find(what), std::string::npos) << error.what();
    }
  };
  refused([](NonlinearModelData* d) { d->weights.pop_back(); }, "weights");
  refused([](NonlinearModelData* d) { d->weights[2] = std::nan(""); }, "weight");
  refused([](NonlinearModelData* d) { d->weights[0] = 0.0; }, "weight");
  refused([](NonlinearModelData* d) { d->tets(1, 3) = 999; }, "corner 999 out of range");
  refused([](NonlinearModelData* d) { std::swap(d->tets(0, 1), d->tets(1, 1)); },
          "sampled elements");
  refused([](NonlinearModelData* d) { d->modes(4, 0) = std::nan(""); }, "mode");
  refused([](NonlinearModelData* d) { d->masses.resize(3); }, "masses");
  refused([](NonlinearModelData* d) { d->material.c[0] = -1.0; }, "material");
  refused([](NonlinearModelData* d) { d->prony = {{0.7, 1.0}, {0.6, 2.0}}; }, "gammas");
  refused([](NonlinearModelData* d) { d->elements = {1, 2}; }, "elements");
  refused([](NonlinearModelData* d) { d->newton_tolerance = 0.0; }, "newton_tolerance");
  refused([](NonlinearModelData* d) { d->test_modes = d->modes.leftCols(2); },
          "test_modes must be empty or 3N × n");
  refused(
      [](NonlinearModelData* d) {
        d->test_modes = d->modes;
        d->test_modes(7, 1) = std::nan("");
      },
      "a test mode is not finite");
  refused(
      [](NonlinearModelData* d) {
        d->correction_nodes = {3};
        d->corrections = Eigen::MatrixXd::Zero(d->modes.rows(), 2);
      },
      "corrections must be 3N × 3c");
  refused(
      [](NonlinearModelData* d) {
        d->correction_nodes = {3, 3};
        d->corrections = Eigen::MatrixXd::Zero(d->modes.rows(), 6);
      },
      "listed twice");
  refused(
      [](NonlinearModelData* d) {
        d->correction_nodes = {-2};
        d->corrections = Eigen::MatrixXd::Zero(d->modes.rows(), 3);
      },
      "correction node -2 out of range");
  refused(
      [](NonlinearModelData* d) {
        d->correction_nodes = {3};
        d->corrections = Eigen::MatrixXd::Zero(d->modes.rows(), 3);
        d->corrections(5, 1) = std::nan("");
      },
      "a correction is not finite");
  const auto with_correction = [](NonlinearModelData* d) {
    d->correction_nodes = {3};
    d->corrections = Eigen::MatrixXd::Zero(d->modes.rows(), 3);
    d->correction_magnitudes = {0.1, 0.5};
    d->correction_scales = Eigen::MatrixXd::Ones(2, 1);
  };
  refused(
      [&](NonlinearModelData* d) {
        with_correction(d);
        d->correction_coefficients = Eigen::MatrixXd::Zero(d->modes.cols(), 6);
      },
      "correction_coefficients must be n × 4Mc");
  refused(
      [&](NonlinearModelData* d) {
        with_correction(d);
        d->correction_magnitudes.clear();
        d->correction_scales.resize(0, 0);
        d->correction_coefficients = Eigen::MatrixXd::Zero(d->modes.cols(), 8);
      },
      "needs the magnitudes");
  refused(
      [&](NonlinearModelData* d) {
        with_correction(d);
        d->correction_coefficients = Eigen::MatrixXd::Zero(d->modes.cols(), 8);
        d->correction_coefficients(2, 4) = std::nan("");
      },
      "a correction coefficient is not finite");
}

}  // namespace
}  // namespace somasim::models::reduced
