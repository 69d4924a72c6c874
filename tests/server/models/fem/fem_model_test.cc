// Linear and corotational FEM (SPEC §4.4): forces are exact energy gradients, tangents are force
// Jacobians, the patch test holds, a refined cantilever bends as Euler–Bernoulli says, the
// corotational model is invariant under rigid rotation and equals the linear one for small
// deformation, Newton converges quadratically, implicit dynamics settles on the static solution,
// steps allocate nothing, bad input is refused.
#include "server/models/fem/fem_model.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh_gen/structured_meshes.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

FemParameters Material(FemKind kind, double poisson = 0.3) {
  FemParameters p;
  p.kind = kind;
  p.youngs_modulus = 5000.0;  // [Pa], seed 001's liver
  p.poisson_ratio = poisson;
  p.density = 1055.0;
  return p;
}

mesh::TetMesh SmallBox() {
  return mesh_gen::BoxGridTets(3, 3, 4, Vector3d::Zero(), Vector3d(0.02, 0.02, 0.03));
}

void Perturb(mesh::Points* x, double amplitude, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> offset(-amplitude, amplitude);
  for (Eigen::Index i = 0; i < x->size(); ++i) x->data()[i] += offset(rng);
}

// A deformed configuration: a large rotation, a stretch and random noise of the rest shape.
mesh::Points Deformed(const mesh::Points& rest, unsigned seed) {
  const Matrix3d q = Eigen::AngleAxisd(0.9, Vector3d(1.0, 2.0, 0.5).normalized()).matrix();
  const Matrix3d stretch = Vector3d(1.1, 0.95, 1.02).asDiagonal();
  mesh::Points x = q * stretch * rest;
  Perturb(&x, 5e-4, seed);
  return x;
}

class FemKinds : public ::testing::TestWithParam<FemKind> {};

TEST_P(FemKinds, ForcesAreMinusTheEnergyGradient) {
  const auto model = FemModel::FromTetMesh(SmallBox(), Material(GetParam()));
  auto state = model->MakeState();
  state->positions = GetParam() == FemKind::kLinear ? model->rest_positions()
                                                    : Deformed(model->rest_positions(), 3);
  Perturb(&state->positions, 1e-3, 4);
  mesh::Points forces;
  model->InternalForces(*state, &forces);
  const double h = 1e-7;
  for (Eigen::Index k = 0; k < forces.size(); k += 7) {
    const double x0 = state->positions.data()[k];
    state->positions.data()[k] = x0 + h;
    const double plus = model->Energy(*state, Vector3d::Zero()).elastic;
    state->positions.data()[k] = x0 - h;
    const double minus = model->Energy(*state, Vector3d::Zero()).elastic;
    state->positions.data()[k] = x0;
    const double gradient = (plus - minus) / (2.0 * h);
    EXPECT_NEAR(forces.data()[k], -gradient, 1e-6 * forces.cwiseAbs().maxCoeff()) << "dof " << k;
  }
}

TEST_P(FemKinds, ExactTangentIsTheForceJacobian) {
  const auto model = FemModel::FromTetMesh(SmallBox(), Material(GetParam()));
  auto state = model->MakeState();
  state->positions = GetParam() == FemKind::kLinear ? model->rest_positions()
                                                    : Deformed(model->rest_positions(), 5);
  Perturb(&state->positions, 1e-3, 6);
  const int32_t e = 7;
  const Eigen::Matrix<double, 12, 12> k = model->ElementTangent(state->positions, e, true);
  // -∂f/∂x of this one element alone (a one-element model), by central differences.
  mesh::TetMesh one;
  one.vertices.resize(3, 4);
  one.tetrahedra.resize(4, 1);
  for (int a = 0; a < 4; ++a) {
    one.vertices.col(a) = model->rest_positions().col(model->elements().tets(a, e));
    one.tetrahedra(a, 0) = a;
  }
  const auto single = FemModel::FromTetMesh(one, Material(GetParam()));
  auto s = single->MakeState();
  for (int a = 0; a < 4; ++a)
    s->positions.col(a) = state->positions.col(model->elements().tets(a, e));
  const Eigen::Matrix<double, 12, 12> k_single = single->ElementTangent(s->positions, 0, true);
  EXPECT_LT((k - k_single).norm(), 1e-12 * k.norm());
  const double h = 1e-8;
  mesh::Points fp, fm;
  for (int col = 0; col < 12; ++col) {
    const Eigen::Index dof = col;
    const double x0 = s->positions.data()[dof];
    s->positions.data()[dof] = x0 + h;
    single->InternalForces(*s, &fp);
    s->positions.data()[dof] = x0 - h;
    single->InternalForces(*s, &fm);
    s->positions.data()[dof] = x0;
    for (int row = 0; row < 12; ++row) {
      const double fd = -(fp.data()[row] - fm.data()[row]) / (2.0 * h);
      EXPECT_NEAR(k(row, col), fd, 1e-6 * k.cwiseAbs().maxCoeff()) << row << ", " << col;
    }
  }
}

// Every element of an affine field x = G X + c has the same F, so interior nodes are in
// equilibrium: prescribing the affine field on the boundary must reproduce it inside exactly.
TEST_P(FemKinds, PatchTestReproducesAHomogeneousStrain) {
  const mesh::TetMesh box = mesh_gen::BoxGridTets(4, 4, 4, Vector3d::Zero(), Vector3d::Ones());
  const auto model = FemModel::FromTetMesh(box, Material(GetParam()));
  Matrix3d g = Matrix3d::Identity();
  g += 0.03 * (Matrix3d() << 1.0, 0.4, -0.2, 0.1, -0.5, 0.3, 0.2, 0.1, 0.7).finished();
  if (GetParam() != FemKind::kLinear) {  // large rotation too: F = Q (I + small)
    g = Eigen::AngleAxisd(0.7, Vector3d(0.3, -1.0, 0.2).normalized()).matrix() * g;
  }
  const Vector3d c(0.1, -0.2, 0.05);
  std::vector<int32_t> boundary;
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    const Vector3d p = box.vertices.col(i);
    if ((p.array() < 1e-9).any() || (p.array() > 1.0 - 1e-9).any()) boundary.push_back(i);
  }
  mesh::Points targets(3, static_cast<Eigen::Index>(boundary.size()));
  for (size_t k = 0; k < boundary.size(); ++k) {
    targets.col(static_cast<Eigen::Index>(k)) = g * box.vertices.col(boundary[k]) + c;
  }
  auto state = model->MakeState();
  StaticLoads loads;
  loads.prescribed_nodes = boundary;
  loads.prescribed_positions = &targets;
  loads.load_steps = 2;
  loads.tolerance = 1e-12;
  const StaticResult result = model->SolveStatic(loads, state.get());
  ASSERT_TRUE(result.converged);
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    EXPECT_LT((state->positions.col(i) - (g * box.vertices.col(i) + c)).norm(), 1e-9)
        << "node " << i;
  }
}

INSTANTIATE_TEST_SUITE_P(Fem, FemKinds, ::testing::Values(FemKind::kLinear, FemKind::kCorotational),
                         [](const auto& kind) {
                           return std::string(kind.param == FemKind::kLinear ? "Linear"
                                                                             : "Corotational");
                         });

// A unit cube in uniaxial tension as component constraints: symmetry planes x = 0, y = 0, z = 0,
// and with `pull` the face x = 1 held at x = stretch; `pulled` gets that face's nodes.
std::vector<ComponentConstraint> UniaxialSupports(const mesh::TetMesh& cube, double stretch,
                                                  bool pull, std::vector<int32_t>* pulled) {
  std::vector<ComponentConstraint> held;
  for (int32_t i = 0; i < static_cast<int32_t>(cube.vertices.cols()); ++i) {
    for (int axis = 0; axis < 3; ++axis) {
      if (cube.vertices(axis, i) < 1e-9) held.push_back({i, axis, 0.0});
    }
    if (cube.vertices(0, i) > 1.0 - 1e-9) {
      if (pull) held.push_back({i, 0, stretch});
      pulled->push_back(i);
    }
  }
  return held;
}

// Uniaxial tension of a liver cube (seed 000's material, near its incompressible limit):
// symmetry planes x = 0, y = 0, z = 0, the face x = 1 pulled to stretch λ, the rest free. The
// analytic incompressible answer: Ī1 = λ² + 2/λ, Cauchy σ = 2 (λ² - 1/λ) W'(Ī1), nominal
// P = σ / λ, which the face's reaction must match.
TEST(FemHyperelastic, UniaxialStretchMatchesTheIncompressibleCurve) {
  const mesh::TetMesh cube = mesh_gen::BoxGridTets(3, 3, 3, Vector3d::Zero(), Vector3d::Ones());
  FemParameters p = Material(FemKind::kHyperelastic);
  p.hyperelastic = LiverNava2008(0.4999);  // κ0 ≈ 5000 μ0
  const auto model = FemModel::FromTetMesh(cube, p);
  const HyperelasticMaterial& m = p.hyperelastic;
  for (const double stretch : {1.05, 1.15, 1.3}) {
    std::vector<int32_t> pulled;
    const std::vector<ComponentConstraint> held = UniaxialSupports(cube, stretch, true, &pulled);
    StaticLoads loads;
    loads.components = held;
    loads.load_steps = 4;
    auto state = model->MakeState();
    const StaticResult result = model->SolveStatic(loads, state.get());
    ASSERT_TRUE(result.converged) << "stretch " << stretch;
    double force = 0.0;  // [N] on the unit face: the nominal stress [Pa]
    for (const int32_t i : pulled) force += result.reactions(0, i);
    const double i1_bar = stretch * stretch + 2.0 / stretch;
    double w1 = 0.0;
    for (int k = 1; k <= 5; ++k) {
      w1 += k * m.c[static_cast<size_t>(k - 1)] * std::pow(i1_bar - 3.0, k - 1);
    }
    const double nominal = 2.0 * (stretch * stretch - 1.0 / stretch) * w1 / stretch;
    EXPECT_NEAR(force, nominal, 0.01 * nominal) << "stretch " << stretch;
    // Nearly incompressible: the lateral faces contract by 1/√λ.
    const double lateral = state->positions.row(1).maxCoeff();
    EXPECT_NEAR(lateral, 1.0 / std::sqrt(stretch), 1e-3) << "stretch " << stretch;
  }
}

// Fung's QLV with seed 000's Prony series: after a step stretch held constant, the stress relaxes
// exactly as G(t) = γ∞ + Σ γ_k e^{-t/τ_k} times the instantaneous elastic stress.
TEST(FemViscoelastic, RelaxationAfterAStepStrainFollowsTheProny) {
  const mesh::TetMesh cube = mesh_gen::BoxGridTets(3, 3, 3, Vector3d::Zero(), Vector3d::Ones());
  FemParameters p = Material(FemKind::kHyperelastic);
  p.prony = LiverNava2008Prony();
  const auto model = FemModel::FromTetMesh(cube, p);
  std::vector<int32_t> pulled;
  const std::vector<ComponentConstraint> held = UniaxialSupports(cube, 1.1, true, &pulled);
  StaticLoads loads;
  loads.components = held;
  auto state = model->MakeState();
  const auto face_force = [&](const StaticResult& r) {
    double force = 0.0;
    for (const int32_t i : pulled) force += r.reactions(0, i);
    return force;
  };
  const StaticResult jump = model->SolveQuasiStatic(loads, 1e-6, state.get());  // the step
  ASSERT_TRUE(jump.converged);
  const double instantaneous = face_force(jump);
  ASSERT_GT(instantaneous, 0.0);
  double t = 0.0;
  for (int step = 0; step < 200; ++step) {
    const StaticResult hold = model->SolveQuasiStatic(loads, 0.1, state.get());
    ASSERT_TRUE(hold.converged) << step;
    t += 0.1;
    double g = 1.0;
    for (const PronyTerm& term : p.prony) g += term.gamma * (std::exp(-t / term.tau) - 1.0);
    if (step % 20 == 19) {
      EXPECT_NEAR(face_force(hold), g * instantaneous, 0.01 * g * instantaneous) << t;
    }
  }
}

// Under a step load the strain creeps with the creep compliance of the Prony series: for
// G(s) (Laplace) = γ∞/s + Σ γ_k/(s + 1/τ_k), J(s) = 1/(s² G(s)) has poles at 0 and at the roots
// r_1, r_2 of s G(s) (two retardation times), so J(t) = 1/γ∞ + Σ_j R_j e^{r_j t}. At small strain
// the elastic response is linear, so u(t) = J(t) u(0⁺).
TEST(FemViscoelastic, CreepUnderAStepLoadFollowsTheCreepCompliance) {
  const mesh::TetMesh cube = mesh_gen::BoxGridTets(3, 3, 3, Vector3d::Zero(), Vector3d::Ones());
  FemParameters p = Material(FemKind::kHyperelastic);
  p.prony = LiverNava2008Prony();
  const auto model = FemModel::FromTetMesh(cube, p);
  std::vector<int32_t> pulled;
  const std::vector<ComponentConstraint> held = UniaxialSupports(cube, 1.0, false, &pulled);
  mesh::Points forces = mesh::Points::Zero(3, model->num_nodes());
  for (const int32_t i : pulled) {  // 1 Pa nominal on the unit face, by tributary area
    double w = 1.0;
    for (int axis = 1; axis < 3; ++axis) {
      const double c = cube.vertices(axis, i);
      if (c < 1e-9 || c > 1.0 - 1e-9) w *= 0.5;
    }
    forces(0, i) = w / 4.0;  // 2 × 2 cells on the face
  }
  StaticLoads loads;
  loads.components = held;
  loads.external_forces = &forces;
  loads.tolerance = 1e-12;
  auto state = model->MakeState();
  ASSERT_TRUE(model->SolveQuasiStatic(loads, 1e-6, state.get()).converged);
  const double u0 = state->positions.row(0).maxCoeff() - 1.0;
  ASSERT_GT(u0, 0.0);
  // Roots of s G(s) (times Π (s + a_k)): γ∞ (s + a1)(s + a2) + γ1 s (s + a2) + γ2 s (s + a1).
  const double g1 = p.prony[0].gamma, g2 = p.prony[1].gamma, ginf = 1.0 - g1 - g2;
  const double a1 = 1.0 / p.prony[0].tau, a2 = 1.0 / p.prony[1].tau;
  const double qa = ginf + g1 + g2, qb = ginf * (a1 + a2) + g1 * a2 + g2 * a1, qc = ginf * a1 * a2;
  const double disc = std::sqrt(qb * qb - 4.0 * qa * qc);
  const double r1 = (-qb + disc) / (2.0 * qa), r2 = (-qb - disc) / (2.0 * qa);
  const auto creep =
      [&](double time) {  // J(t) = 1/γ∞ + Σ residues of (s+a1)(s+a2)/(s qa (s-r1)(s-r2))
        const double res1 = (r1 + a1) * (r1 + a2) / (qa * r1 * (r1 - r2));
        const double res2 = (r2 + a1) * (r2 + a2) / (qa * r2 * (r2 - r1));
        return a1 * a2 / (qa * r1 * r2) + res1 * std::exp(r1 * time) + res2 * std::exp(r2 * time);
      };
  EXPECT_NEAR(creep(0.0), 1.0, 1e-12);
  EXPECT_NEAR(creep(1e9), 1.0 / ginf, 1e-9);
  double t = 0.0;
  for (int step = 0; step < 200; ++step) {
    ASSERT_TRUE(model->SolveQuasiStatic(loads, 0.1, state.get()).converged) << step;
    t += 0.1;
    const double u = state->positions.row(0).maxCoeff() - 1.0;
    if (step % 20 == 19) {
      EXPECT_NEAR(u / u0, creep(t), 0.01 * creep(t)) << t;
    }
  }
}

// The same creep history with a workspace kept across steps and modified Newton (the factor of
// an earlier step reused while it contracts the residual): the same positions to the solver
// tolerance, with fewer factorisations (the benchmark's path).
TEST(FemViscoelastic, ReusedFactorisationGivesTheSameCreep) {
  const mesh::TetMesh cube = mesh_gen::BoxGridTets(3, 3, 4, Vector3d::Zero(), Vector3d::Ones());
  FemParameters p = Material(FemKind::kHyperelastic);
  p.prony = LiverNava2008Prony();
  const auto model = FemModel::FromTetMesh(cube, p);
  std::vector<int32_t> pulled;
  const std::vector<ComponentConstraint> held = UniaxialSupports(cube, 1.0, false, &pulled);
  mesh::Points forces = mesh::Points::Zero(3, model->num_nodes());
  for (const int32_t i : pulled) forces(0, i) = 50.0;  // [N]: ~0.1 strain
  StaticLoads loads;
  loads.components = held;
  loads.external_forces = &forces;
  loads.tolerance = 1e-10;
  StaticLoads reused = loads;
  reused.reuse_factorisation = true;
  reused.reuse_ratio = 0.2;
  auto plain = model->MakeState();
  auto fast = model->MakeState();
  StaticWorkspace workspace;
  int plain_iterations = 0, fast_iterations = 0;
  for (int step = 0; step < 30; ++step) {
    const StaticResult a = model->SolveQuasiStatic(loads, 0.05, plain.get());
    const StaticResult b = model->SolveQuasiStatic(reused, 0.05, fast.get(), &workspace);
    ASSERT_TRUE(a.converged) << step;
    ASSERT_TRUE(b.converged) << step;
    plain_iterations += a.newton_iterations;
    fast_iterations += b.newton_iterations;
    const double u = (plain->positions - cube.vertices).cwiseAbs().maxCoeff();
    ASSERT_GT(u, 1e-3);
    EXPECT_LT((plain->positions - fast->positions).cwiseAbs().maxCoeff(), 1e-8 * u) << step;
  }
  EXPECT_GT(fast_iterations, 0);
  EXPECT_GT(plain_iterations, 0);
}

// NewtonIteration is SolveStatic's iteration: repeated, it reaches SolveStatic's equilibrium;
// the workspace survives a change of the held DOFs (a new analysis); AssembleTangent is the sum
// of the element tangents.
TEST(FemHyperelastic, NewtonIterationsReachTheStaticSolution) {
  const mesh::TetMesh beam =
      mesh_gen::BoxGridTets(7, 3, 3, Vector3d::Zero(), Vector3d(0.12, 0.03, 0.03));
  FemParameters p = Material(FemKind::kHyperelastic);
  const auto model = FemModel::FromTetMesh(beam, p);
  std::vector<int32_t> fixed, other;
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    if (beam.vertices(0, i) < 1e-9) fixed.push_back(i);
    if (beam.vertices(0, i) > 0.12 - 1e-9) other.push_back(i);
  }
  StaticLoads loads;
  loads.fixed_nodes = fixed;
  loads.gravity = Vector3d(0.0, 0.0, -2.0);
  loads.tolerance = 1e-10;
  StaticWorkspace workspace;
  auto reference = model->MakeState();
  ASSERT_TRUE(model->SolveStatic(loads, reference.get(), &workspace).converged);
  auto state = model->MakeState();
  StaticResult last;
  for (int it = 0; it < 30 && !last.converged; ++it) {
    last = model->NewtonIteration(loads, state.get(), &workspace);
    EXPECT_EQ(last.newton_iterations, 1);
  }
  ASSERT_TRUE(last.converged);
  const double sag = (reference->positions - beam.vertices).cwiseAbs().maxCoeff();
  ASSERT_GT(sag, 1e-3);
  EXPECT_LT((state->positions - reference->positions).cwiseAbs().maxCoeff(), 1e-7 * sag);
  // Other held nodes with the same workspace: the same answer as a fresh solve.
  StaticLoads both = loads;
  std::vector<int32_t> ends = fixed;
  ends.insert(ends.end(), other.begin(), other.end());
  both.fixed_nodes = ends;
  auto with_workspace = model->MakeState();
  auto fresh = model->MakeState();
  ASSERT_TRUE(model->SolveStatic(both, with_workspace.get(), &workspace).converged);
  ASSERT_TRUE(model->SolveStatic(both, fresh.get()).converged);
  EXPECT_LT((with_workspace->positions - fresh->positions).cwiseAbs().maxCoeff(), 1e-12);
  // The assembled tangent against the element tangents, block by block.
  BlockSparseMatrix tangent;
  model->AssembleTangent(state->positions, &tangent);
  BlockSparseMatrix sum = model->pattern();
  sum.SetZero();
  for (int32_t e = 0; e < model->num_tets(); ++e) {
    const Eigen::Matrix<double, 12, 12> k = model->ElementTangent(state->positions, e, true);
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b)
        sum.block(sum.element_block(e, a, b)) += k.block<3, 3>(3 * a, 3 * b);
    }
  }
  double worst = 0.0, scale = 0.0;
  for (int32_t k = 0; k < sum.num_blocks(); ++k) {
    worst = std::max(worst, (tangent.block(k) - sum.block(k)).cwiseAbs().maxCoeff());
    scale = std::max(scale, sum.block(k).cwiseAbs().maxCoeff());
  }
  EXPECT_LE(worst, 1e-14 * scale);
}

// The hyperelastic element tangent (rank-one form for the reduced polynomial) is V (g dP(dF) +
// dF offset) ∇N_a with dP from StressDifferential, for every column dF = e_c ∇N_bᵀ, with and
// without a viscous context; and it is the Jacobian of the forces.
TEST(FemHyperelastic, ElementTangentEqualsTheStressDifferential) {
  const mesh::TetMesh box = SmallBox();
  const FemParameters p = Material(FemKind::kHyperelastic);
  const auto model = FemModel::FromTetMesh(box, p);
  mesh::Points x = box.vertices;
  Perturb(&x, 2e-3, 17);  // strains of ~10 %
  std::vector<double> offset(9 * static_cast<size_t>(model->num_tets()));
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> value(-300.0, 300.0);  // [Pa]
  for (double& o : offset) o = value(rng);
  ViscousStep viscous;
  viscous.g = 0.7;
  viscous.offset = offset.data();
  const ViscousStep* const contexts[] = {nullptr, &viscous};
  for (const ViscousStep* context : contexts) {
    for (int32_t e = 0; e < model->num_tets(); e += 5) {
      const Eigen::Matrix<double, 12, 12> k = model->ElementTangent(x, e, true, context);
      Matrix3d f = Matrix3d::Identity();
      for (int a = 0; a < 4; ++a) {
        const int32_t node = model->elements().tets(a, e);
        f += (x.col(node) - box.vertices.col(node)) *
             model->elements().gradients.col(4 * e + a).transpose();
      }
      const double v = model->elements().volumes[static_cast<size_t>(e)];
      const double g = context != nullptr ? context->g : 1.0;
      for (int b = 0; b < 4; ++b) {
        for (int c = 0; c < 3; ++c) {
          const Matrix3d df =
              Vector3d::Unit(c) * model->elements().gradients.col(4 * e + b).transpose();
          Matrix3d dp = g * StressDifferential(p.hyperelastic, f, df);
          if (context != nullptr) dp += df * Eigen::Map<const Matrix3d>(offset.data() + 9 * e);
          for (int a = 0; a < 4; ++a) {
            const Vector3d expected = v * dp * model->elements().gradients.col(4 * e + a);
            EXPECT_LT((k.block<3, 1>(3 * a, 3 * b + c) - expected).norm(), 1e-12 * k.norm())
                << "element " << e << " a " << a << " b " << b << " c " << c;
          }
        }
      }
    }
  }
  // The Jacobian of the forces, by central differences (one element's model).
  mesh::TetMesh one;
  one.vertices.resize(3, 4);
  one.tetrahedra.resize(4, 1);
  for (int a = 0; a < 4; ++a) {
    one.vertices.col(a) = box.vertices.col(model->elements().tets(a, 3));
    one.tetrahedra(a, 0) = a;
  }
  const auto single = FemModel::FromTetMesh(one, p);
  auto s = single->MakeState();
  for (int a = 0; a < 4; ++a) s->positions.col(a) = x.col(model->elements().tets(a, 3));
  const Eigen::Matrix<double, 12, 12> k = single->ElementTangent(s->positions, 0, true);
  const double h = 1e-8;
  mesh::Points fp, fm;
  for (int col = 0; col < 12; ++col) {
    const double x0 = s->positions.data()[col];
    s->positions.data()[col] = x0 + h;
    single->InternalForces(*s, &fp);
    s->positions.data()[col] = x0 - h;
    single->InternalForces(*s, &fm);
    s->positions.data()[col] = x0;
    for (int row = 0; row < 12; ++row) {
      EXPECT_NEAR(k(row, col), -(fp.data()[row] - fm.data()[row]) / (2.0 * h),
                  1e-6 * k.cwiseAbs().maxCoeff())
          << row << ", " << col;
    }
  }
}

// The batched, warm-started rotations of a step are the SVD's whatever the start: after a large
// rigid rotation of the state (the warm starts far off: the fallback), a step equals the same
// step from a fresh state (identity starts), with CG converged tightly so that its warm start
// does not matter either.
TEST(FemCorotational, WarmStartedStepRotationsMatchTheColdOnes) {
  FemParameters p = Material(FemKind::kCorotational);
  p.cg_tolerance = 1e-14;
  p.cg_max_iterations = 5000;
  const auto model = FemModel::FromTetMesh(SmallBox(), p);
  auto state = model->MakeState();
  StepInputs inputs;
  inputs.dt = 0.01;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  const int32_t fixed[] = {0, 1, 2};
  inputs.fixed_nodes = fixed;
  for (int i = 0; i < 3; ++i) ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  const Matrix3d q = Eigen::AngleAxisd(2.0, Vector3d(0.3, 1.0, -0.4).normalized()).matrix();
  state->positions = q * state->positions;
  state->velocities = q * state->velocities;
  auto twin = model->MakeState();
  twin->positions = state->positions;
  twin->velocities = state->velocities;
  for (int i = 0; i < 2; ++i) {
    ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
    ASSERT_EQ(model->Step(inputs, twin.get()), StepStatus::kOk);
  }
  const double motion = (state->positions - q * model->rest_positions()).cwiseAbs().maxCoeff();
  ASSERT_GT(motion, 1e-5);
  EXPECT_LT((state->positions - twin->positions).cwiseAbs().maxCoeff(), 1e-9 * motion);
}

// A rejected step rolls back completely, the rotations' warm starts included: the steps after
// it are bit-identical to those of a run that never tried it.
TEST(FemCorotational, RejectedStepLeavesNoTrace) {
  FemParameters p = Material(FemKind::kCorotational);
  p.speed_limit = 1.0;  // [m/s]
  const auto model = FemModel::FromTetMesh(SmallBox(), p);
  auto tried = model->MakeState();
  auto plain = model->MakeState();
  StepInputs inputs;
  inputs.dt = 0.01;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  const int32_t fixed[] = {0, 1, 2};
  inputs.fixed_nodes = fixed;
  for (int i = 0; i < 3; ++i) {
    ASSERT_EQ(model->Step(inputs, tried.get()), StepStatus::kOk);
    ASSERT_EQ(model->Step(inputs, plain.get()), StepStatus::kOk);
  }
  StepInputs violent = inputs;
  const mesh::Points push = mesh::Points::Constant(3, model->num_nodes(), 50.0);  // [N]
  violent.external_forces = &push;
  ASSERT_EQ(model->Step(violent, tried.get()), StepStatus::kRejectedTooFast);
  for (int i = 0; i < 3; ++i) {
    ASSERT_EQ(model->Step(inputs, tried.get()), StepStatus::kOk);
    ASSERT_EQ(model->Step(inputs, plain.get()), StepStatus::kOk);
  }
  EXPECT_EQ(tried->positions, plain->positions);
  EXPECT_EQ(tried->velocities, plain->velocities);
}

TEST(FemCorotational, IsInvariantUnderRigidRotation) {
  const auto model = FemModel::FromTetMesh(SmallBox(), Material(FemKind::kCorotational));
  auto state = model->MakeState();
  state->positions = model->rest_positions();
  Perturb(&state->positions, 1e-3, 9);
  mesh::Points f, f_rotated;
  model->InternalForces(*state, &f);
  const double energy = model->Energy(*state, Vector3d::Zero()).elastic;
  const Matrix3d q = Eigen::AngleAxisd(2.5, Vector3d(-0.2, 0.6, 1.0).normalized()).matrix();
  state->positions = q * state->positions;
  model->InternalForces(*state, &f_rotated);
  EXPECT_LT((f_rotated - q * f).norm(), 1e-9 * f.norm());
  EXPECT_NEAR(model->Energy(*state, Vector3d::Zero()).elastic, energy, 1e-9 * energy);
  // The linear model is not invariant: rotating the rest shape "strains" it.
  const auto linear = FemModel::FromTetMesh(SmallBox(), Material(FemKind::kLinear));
  auto rest = linear->MakeState();
  rest->positions = q * linear->rest_positions();
  EXPECT_GT(linear->Energy(*rest, Vector3d::Zero()).elastic, 1e-6);
}

TEST(FemCorotational, EqualsLinearForSmallDeformation) {
  const mesh::TetMesh beam =
      mesh_gen::BoxGridTets(9, 3, 3, Vector3d::Zero(), Vector3d(0.2, 0.025, 0.025));
  const auto linear = FemModel::FromTetMesh(beam, Material(FemKind::kLinear));
  const auto corot = FemModel::FromTetMesh(beam, Material(FemKind::kCorotational));
  std::vector<int32_t> fixed;
  for (int32_t i = 0; i < linear->num_nodes(); ++i) {
    if (beam.vertices(0, i) < 1e-9) fixed.push_back(i);
  }
  StaticLoads loads;
  loads.fixed_nodes = fixed;
  loads.gravity = Vector3d(0.0, 0.0, -1e-4);  // a tip sag of ~micrometres
  auto a = linear->MakeState();
  auto b = corot->MakeState();
  ASSERT_TRUE(linear->SolveStatic(loads, a.get()).converged);
  ASSERT_TRUE(corot->SolveStatic(loads, b.get()).converged);
  const mesh::Points ua = a->positions - beam.vertices;
  const mesh::Points ub = b->positions - beam.vertices;
  ASSERT_GT(ua.norm(), 0.0);
  EXPECT_LT((ua - ub).norm(), 1e-4 * ua.norm());
}

// Euler–Bernoulli: a cantilever of length L, section b × h, tip load P sags P L³ / (3 E I),
// I = b h³ / 12. Linear tetrahedra are stiff in bending and converge slowly: with this grid's six
// tetrahedra per cell the sag is 10.5 % short at 41 × 9 × 9 nodes, 4.6 % at 81 × 9 × 9, 3.0 % at
// 161 × 9 × 9, 1.3 % at 161 × 13 × 13 (ν = 0, so the clamp adds no Poisson constraint; L/h = 10,
// so shear adds ~0.6 % to the true sag). 27k nodes: the Release build runs it.
TEST(FemLinear, RefinedCantileverMatchesEulerBernoulli) {
  if (somasim::testing::kUnderSanitizer) GTEST_SKIP() << "heavy validation: Release build only";
  const double length = 1.0, side = 0.1, youngs = 1e6, load = 0.01;  // [m], [m], [Pa], [N]
  const mesh::TetMesh beam =
      mesh_gen::BoxGridTets(161, 13, 13, Vector3d::Zero(), Vector3d(length, side, side));
  FemParameters p = Material(FemKind::kLinear, 0.0);
  p.youngs_modulus = youngs;
  const auto model = FemModel::FromTetMesh(beam, p);
  std::vector<int32_t> fixed, tip;
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    if (beam.vertices(0, i) < 1e-9) fixed.push_back(i);
    if (beam.vertices(0, i) > length - 1e-9) tip.push_back(i);
  }
  // Uniform traction on the end face: each tip node carries its share of the face (corner ¼,
  // edge ½, inside 1 of a cell's share).
  mesh::Points forces = mesh::Points::Zero(3, model->num_nodes());
  double total_weight = 0.0;
  for (const int32_t i : tip) {
    double w = 1.0;
    for (int axis = 1; axis < 3; ++axis) {
      const double c = beam.vertices(axis, i);
      if (c < 1e-9 || c > side - 1e-9) w *= 0.5;
    }
    forces(2, i) = w;
    total_weight += w;
  }
  forces *= -load / total_weight;
  StaticLoads loads;
  loads.fixed_nodes = fixed;
  loads.external_forces = &forces;
  auto state = model->MakeState();
  ASSERT_TRUE(model->SolveStatic(loads, state.get()).converged);
  double sag = 0.0;
  for (const int32_t i : tip) sag += beam.vertices(2, i) - state->positions(2, i);
  sag /= static_cast<double>(tip.size());
  const double inertia = side * side * side * side / 12.0;
  const double expected = load * length * length * length / (3.0 * youngs * inertia);
  EXPECT_NEAR(sag, expected, 0.03 * expected);
}

// At rest the corotational model's local stiffness is the exact Jacobian of the node's force.
TEST(FemCorotational, LocalStiffnessIsTheForceJacobianAtRest) {
  const auto model = FemModel::FromTetMesh(SmallBox(), Material(FemKind::kCorotational));
  auto state = model->MakeState();
  const int32_t node = 13;
  const Matrix3d k = model->LocalStiffness(*state, node);
  const double h = 1e-8;
  mesh::Points fp, fm;
  for (int c = 0; c < 3; ++c) {
    state->positions(c, node) += h;
    model->InternalForces(*state, &fp);
    state->positions(c, node) -= 2.0 * h;
    model->InternalForces(*state, &fm);
    state->positions(c, node) += h;
    for (int r = 0; r < 3; ++r) {
      EXPECT_NEAR(k(r, c), -(fp(r, node) - fm(r, node)) / (2.0 * h), 1e-6 * k.norm());
    }
  }
  EXPECT_GT(k.determinant(), 0.0);
}

TEST(FemStatic, NewtonConvergesQuadratically) {
  const mesh::TetMesh beam =
      mesh_gen::BoxGridTets(9, 3, 3, Vector3d::Zero(), Vector3d(0.2, 0.025, 0.025));
  const auto model = FemModel::FromTetMesh(beam, Material(FemKind::kCorotational));
  std::vector<int32_t> fixed;
  for (int32_t i = 0; i < model->num_nodes(); ++i) {
    if (beam.vertices(0, i) < 1e-9) fixed.push_back(i);
  }
  StaticLoads loads;
  loads.fixed_nodes = fixed;
  loads.gravity = Vector3d(0.0, 0.0, -9.81);  // a large sag: rotations of tens of degrees
  loads.tolerance = 1e-13;
  auto state = model->MakeState();
  const StaticResult result = model->SolveStatic(loads, state.get());
  ASSERT_TRUE(result.converged);
  const std::vector<double>& r = result.residual_history;
  ASSERT_GE(r.size(), 3u);
  EXPECT_GT((model->rest_positions() - state->positions).cwiseAbs().maxCoeff(), 0.02);
  // Near the solution each residual is about the square of the previous one.
  for (size_t k = 1; k < r.size(); ++k) {
    if (r[k - 1] < 1e-2 && r[k] > 1e-11) {
      EXPECT_LT(r[k], 1e3 * r[k - 1] * r[k - 1]) << k;
    }
  }
}

TEST(FemDynamic, DampedStepsSettleOnTheStaticSolution) {
  const mesh::TetMesh beam =
      mesh_gen::BoxGridTets(9, 3, 3, Vector3d::Zero(), Vector3d(0.2, 0.025, 0.025));
  for (const FemKind kind : {FemKind::kLinear, FemKind::kCorotational}) {
    // E = 0.5 MPa: the first bending mode is at ω ≈ 14 rad/s; α = 30/s damps it in a second.
    FemParameters p = Material(kind);
    p.youngs_modulus = 5e5;
    p.rayleigh_mass = 30.0;
    p.cg_tolerance = 1e-12;
    const auto model = FemModel::FromTetMesh(beam, p);
    std::vector<int32_t> fixed;
    for (int32_t i = 0; i < model->num_nodes(); ++i) {
      if (beam.vertices(0, i) < 1e-9) fixed.push_back(i);
    }
    StaticLoads loads;
    loads.fixed_nodes = fixed;
    loads.gravity = Vector3d(0.0, 0.0, -9.81);  // ~1 cm sag
    loads.tolerance = 1e-12;
    auto statics = model->MakeState();
    ASSERT_TRUE(model->SolveStatic(loads, statics.get()).converged);
    auto dynamics = model->MakeState();
    StepInputs inputs;
    inputs.dt = 0.01;
    inputs.gravity = loads.gravity;
    inputs.fixed_nodes = fixed;
    for (int step = 0; step < 500; ++step) {
      ASSERT_EQ(model->Step(inputs, dynamics.get()), StepStatus::kOk);
    }
    const double sag = (statics->positions - beam.vertices).cwiseAbs().maxCoeff();
    EXPECT_LT((dynamics->positions - statics->positions).cwiseAbs().maxCoeff(), 1e-4 * sag);
  }
}

// The step's vector element pass (forces and warped blocks in AVX-512 registers, where the CPU
// has them) equals the portable one up to rounding, for every elastic kind and with QLV offsets:
// ten steps of a box pulled by a grasp and sagging under gravity end at the same positions.
TEST(FemDynamic, VectorElementPassEqualsThePortableOne) {
  for (const FemKind kind : {FemKind::kLinear, FemKind::kCorotational}) {
    for (const bool qlv : {false, true}) {
      FemParameters p = Material(kind);
      p.rayleigh_mass = 0.1;
      p.rayleigh_stiffness = 1e-3;
      p.cg_tolerance = 1e-13;
      if (qlv) p.prony = LiverNava2008Prony();
      const auto vector = FemModel::FromTetMesh(SmallBox(), p);
      const auto portable = FemModel::FromTetMesh(SmallBox(), p);
      portable->set_force_scalar_element_pass(true);
      auto a = vector->MakeState();
      auto b = portable->MakeState();
      StepInputs inputs;
      inputs.gravity = Vector3d(0.0, 0.0, -9.81);
      const int32_t fixed[] = {0, 1, 2, 3};
      inputs.fixed_nodes = fixed;
      const int32_t top = vector->num_nodes() - 1;  // the corner opposite the held ones
      const Attachment grasp[] = {
          {top, vector->rest_positions().col(top) + Vector3d(0.004, 0.002, 0.006), 20.0}};
      inputs.attachments = grasp;
      for (int step = 0; step < 10; ++step) {
        ASSERT_EQ(vector->Step(inputs, a.get()), StepStatus::kOk);
        ASSERT_EQ(portable->Step(inputs, b.get()), StepStatus::kOk);
      }
      const double moved = (b->positions - portable->rest_positions()).cwiseAbs().maxCoeff();
      ASSERT_GT(moved, 1e-4);  // [m]: the box did deform
      EXPECT_LT((a->positions - b->positions).cwiseAbs().maxCoeff(), 1e-9 * moved)
          << static_cast<int>(kind) << qlv;
    }
  }
}

// The corotational kind's vector pass computes F, R, the forces and the blocks of eight elements
// at a time, hands the lanes its rotation iteration leaves to PolarRotationFrom, and takes the
// last num_tets mod 8 elements one at a time. All three paths against the portable passes: a
// box of 36 elements (4 groups and 4 left over) turned by 3 rad, where the iteration cannot
// start from the identity (the warm start of the first step: every lane is left), stretched,
// and with one element turned inside out.
TEST(FemDynamic, CorotationalVectorPassEqualsThePortableOneWhenRotationsNeedTheFallback) {
  const mesh::TetMesh box =
      mesh_gen::BoxGridTets(4, 2, 3, Vector3d::Zero(), Vector3d(0.03, 0.01, 0.02));
  ASSERT_EQ(box.tetrahedra.cols() % 8, 4);
  for (const bool qlv : {false, true}) {
    for (const bool inverted : {false, true}) {
      FemParameters p = Material(FemKind::kCorotational);
      p.cg_tolerance = 1e-13;
      if (qlv) p.prony = LiverNava2008Prony();
      const auto vector = FemModel::FromTetMesh(box, p);
      const auto portable = FemModel::FromTetMesh(box, p);
      portable->set_force_scalar_element_pass(true);
      auto a = vector->MakeState();
      auto b = portable->MakeState();
      const Matrix3d turn = Eigen::AngleAxisd(3.0, Vector3d(0.3, 1.0, 0.2).normalized()).matrix();
      mesh::Points x = turn * Vector3d(1.08, 0.97, 1.03).asDiagonal() * vector->rest_positions();
      if (inverted) {
        // Node 0 through the opposite face of its first element (a corner of the box: the only
        // element it belongs to that it inverts is that one, and its neighbours squeeze).
        const auto& t = box.tetrahedra;
        const Vector3d centroid = (x.col(t(1, 0)) + x.col(t(2, 0)) + x.col(t(3, 0))) / 3.0;
        x.col(t(0, 0)) = centroid + 0.3 * (centroid - x.col(t(0, 0)));
      }
      a->positions = x;
      b->positions = x;
      StepInputs inputs;
      inputs.dt = 1e-3;
      const int32_t fixed[] = {1, 2};
      inputs.fixed_nodes = fixed;
      for (int step = 0; step < 3; ++step) {
        ASSERT_EQ(vector->Step(inputs, a.get()), StepStatus::kOk);
        ASSERT_EQ(portable->Step(inputs, b.get()), StepStatus::kOk);
      }
      const double moved = (b->positions - x).cwiseAbs().maxCoeff();
      ASSERT_GT(moved, 1e-5);  // [m]: the forces did move the box
      EXPECT_LT((a->positions - b->positions).cwiseAbs().maxCoeff(), 1e-9 * moved)
          << qlv << inverted;
    }
  }
}

TEST(FemDynamic, StepsAllocateNothing) {
  FemParameters p = Material(FemKind::kCorotational);
  p.prony = LiverNava2008Prony();  // with the QLV internal variables
  const auto model = FemModel::FromTetMesh(SmallBox(), p);
  auto state = model->MakeState();
  StepInputs inputs;
  inputs.gravity = Vector3d(0.0, 0.0, -9.81);
  const int32_t fixed[] = {0, 1, 2};
  inputs.fixed_nodes = fixed;
  const int32_t prescribed[] = {5};
  mesh::Points target = state->positions.col(5) + Vector3d(0.0, 0.0, 1e-4);
  inputs.prescribed_nodes = prescribed;
  inputs.prescribed_positions = &target;
  const Attachment grasp[] = {{10, Vector3d(0.01, 0.01, 0.04), 5.0}};
  inputs.attachments = grasp;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  somasim::testing::AllocationCounter counter;
  for (int i = 0; i < 5; ++i) ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_EQ(counter.count(), 0);
  EXPECT_LT((state->positions.col(5) - target).norm(), 1e-15);
  EXPECT_EQ(state->positions.col(0), model->rest_positions().col(0));
}

TEST(FemModel, RefusesBadParametersAndMeshes) {
  const mesh::TetMesh box = SmallBox();
  const auto refused = [&](const FemParameters& p, const mesh::TetMesh& m,
                           const std::string& what) {
    try {
      FemModel::FromTetMesh(m, p);
      ADD_FAILURE() << "accepted: " << what;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  };
  FemParameters p = Material(FemKind::kCorotational);
  p.youngs_modulus = -1.0;
  refused(p, box, "youngs_modulus");
  p = Material(FemKind::kCorotational);
  p.poisson_ratio = 0.5;
  refused(p, box, "poisson_ratio");
  p = Material(FemKind::kCorotational);
  p.density = std::nan("");
  refused(p, box, "density");
  p = Material(FemKind::kCorotational);
  p.rayleigh_mass = -1.0;
  refused(p, box, "rayleigh");
  p = Material(FemKind::kCorotational);
  mesh::TetMesh bad = box;
  bad.vertices(1, 3) = std::nan("");
  refused(p, bad, "node 3 has a non-finite coordinate");
  bad = box;
  bad.tetrahedra(2, 5) = 10000;
  refused(p, bad, "tetrahedron 5 uses node 10000");
  bad = box;
  std::swap(bad.tetrahedra(0, 4), bad.tetrahedra(1, 4));
  refused(p, bad, "tetrahedron 4 is inverted");
  bad = box;
  bad.tetrahedra(3, 2) = bad.tetrahedra(0, 2);
  refused(p, bad, "tetrahedron 2 repeats node");
  bad = box;
  bad.tetrahedra.resize(4, 0);
  refused(p, bad, "no tetrahedra");
}

TEST(FemStatic, RefusesBadLoads) {
  const auto model = FemModel::FromTetMesh(SmallBox(), Material(FemKind::kLinear));
  auto state = model->MakeState();
  StaticLoads loads;
  const int32_t out_of_range[] = {-1};
  loads.fixed_nodes = out_of_range;
  EXPECT_THROW(model->SolveStatic(loads, state.get()), std::invalid_argument);
  loads = StaticLoads();
  mesh::Points wrong = mesh::Points::Zero(3, 2);
  loads.external_forces = &wrong;
  EXPECT_THROW(model->SolveStatic(loads, state.get()), std::invalid_argument);
  loads = StaticLoads();
  loads.gravity = Vector3d(0.0, std::nan(""), 0.0);
  EXPECT_THROW(model->SolveStatic(loads, state.get()), std::invalid_argument);
  loads = StaticLoads();
  loads.reuse_factorisation = true;
  loads.reuse_ratio = 1.0;
  EXPECT_THROW(model->SolveStatic(loads, state.get()), std::invalid_argument);
}

}  // namespace
}  // namespace somasim::models::fem
