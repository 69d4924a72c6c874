// Seed 000's reduced model (server/models/reduced/kl_model.h, reduce_fem.h) against the full
// linear FEM it reduces: exact on the loads it was trained with, the energy-best approximation in
// its span on others, the condensed stiffness with a complete basis, creep scaling, grasps,
// gravity, no allocation in a step, bad data refused by name. The model reconstructs the field
// from single-precision modes: displacements agree to ~2e-8 of their size (tolerance 2e-7).
#include "server/models/reduced/kl_model.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh_gen/structured_meshes.h"
#include "server/models/fem/fem_model.h"
#include "server/models/reduced/pod.h"
#include "server/models/reduced/reduce_fem.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models::reduced {
namespace {

using Eigen::Vector3d;

// A 12 × 3 × 3 cm linear-elastic beam (7 × 3 × 3 nodes) held at x = 0.
struct Beam {
  Beam() {
    mesh = mesh_gen::BoxGridTets(7, 3, 3, Vector3d::Zero(), Vector3d(0.12, 0.03, 0.03));
    fem::FemParameters p;
    p.kind = fem::FemKind::kLinear;
    p.youngs_modulus = 5000.0;
    p.poisson_ratio = 0.35;
    p.density = 1055.0;
    model = fem::FemModel::FromTetMesh(mesh, p);
    for (int32_t i = 0; i < model->num_nodes(); ++i) {
      if (mesh.vertices(0, i) < 1e-9) fixed.push_back(i);
    }
  }
  int32_t Node(double x, double y, double z) const {
    for (int32_t i = 0; i < model->num_nodes(); ++i) {
      if ((mesh.vertices.col(i) - Vector3d(x, y, z)).norm() < 1e-9) return i;
    }
    return -1;
  }
  mesh::Points PointLoad(int32_t node, const Vector3d& f) const {
    mesh::Points forces = mesh::Points::Zero(3, model->num_nodes());
    forces.col(node) = f;
    return forces;
  }
  // The full model's static displacement under `forces`.
  mesh::Points Full(const mesh::Points& forces) const {
    fem::StaticLoads loads;
    loads.external_forces = &forces;
    loads.fixed_nodes = fixed;
    loads.tolerance = 1e-12;
    auto state = model->MakeState();
    EXPECT_TRUE(model->SolveStatic(loads, state.get()).converged);
    return state->positions - mesh.vertices;
  }
  mesh::TetMesh mesh;
  std::unique_ptr<fem::FemModel> model;
  std::vector<int32_t> fixed;
};

Eigen::VectorXd Flat(const mesh::Points& p) {
  return Eigen::Map<const Eigen::VectorXd>(p.data(), p.size());
}

// Trained on six point loads: the tip corner in x, y, z, a mid-span top node in z and y, the
// tip's centre in z.
struct Trained {
  explicit Trained(const Beam& beam) {
    const int32_t tip = beam.Node(0.12, 0.03, 0.03), mid = beam.Node(0.06, 0.03, 0.03),
                  centre = beam.Node(0.12, 0.015, 0.015);
    loads = {
        beam.PointLoad(tip, Vector3d(0.05, 0, 0)),  beam.PointLoad(tip, Vector3d(0, 0.05, 0)),
        beam.PointLoad(tip, Vector3d(0, 0, -0.05)), beam.PointLoad(mid, Vector3d(0, 0, -0.1)),
        beam.PointLoad(mid, Vector3d(0, 0.1, 0)),   beam.PointLoad(centre, Vector3d(0, 0, 0.08))};
    Eigen::MatrixXd q(3 * beam.model->num_nodes(), static_cast<Eigen::Index>(loads.size()));
    for (size_t c = 0; c < loads.size(); ++c) {
      full.push_back(beam.Full(loads[c]));
      q.col(static_cast<Eigen::Index>(c)) = Flat(full.back());
    }
    PodSettings settings;
    settings.energy_fraction = 1.0;
    pod = ModesOfSnapshots(q, settings);
    model = KlReducedModel::Create(KlDataFromFem(*beam.model, beam.mesh.vertices, pod.modes));
    tip_node = tip;
  }
  std::vector<mesh::Points> loads, full;
  PodModes pod;
  std::unique_ptr<KlReducedModel> model;
  int32_t tip_node = -1;
};

mesh::Points StepOnce(const KlReducedModel& model, const mesh::Points& forces, TissueState* state) {
  StepInputs inputs;
  inputs.dt = 0.01;
  inputs.external_forces = &forces;
  EXPECT_EQ(model.Step(inputs, state), StepStatus::kOk);
  return state->positions - model.data().rest;
}

TEST(KlReducedModel, ReproducesTheLoadsItWasTrainedOnExactly) {
  const Beam beam;
  const Trained trained(beam);
  ASSERT_EQ(trained.model->num_modes(), 6);
  EXPECT_FALSE(trained.model->SupportsCutting());
  for (size_t c = 0; c < trained.loads.size(); ++c) {
    auto state = trained.model->MakeState();
    const mesh::Points u = StepOnce(*trained.model, trained.loads[c], state.get());
    EXPECT_LT((u - trained.full[c]).norm(), 2e-7 * trained.full[c].norm()) << "load " << c;
  }
  // A linear combination of trained loads: the same combination of displacements.
  const mesh::Points mix = 0.3 * trained.loads[0] - 0.7 * trained.loads[3];
  auto state = trained.model->MakeState();
  const mesh::Points expected = 0.3 * trained.full[0] - 0.7 * trained.full[3];
  EXPECT_LT((StepOnce(*trained.model, mix, state.get()) - expected).norm(), 2e-7 * expected.norm());
}

// Galerkin projection: for a load it was not trained on, the reduced displacement is the best in
// the modes' span in the energy norm |w|_K = √(wᵀ K w): better than the L2 projection B Bᵀ u.
TEST(KlReducedModel, IsTheEnergyBestApproximationInItsSpanOnOtherLoads) {
  const Beam beam;
  const Trained trained(beam);
  const mesh::Points load = beam.PointLoad(beam.Node(0.08, 0.0, 0.03), Vector3d(0.02, 0.03, -0.06));
  const mesh::Points full = beam.Full(load);
  auto state = trained.model->MakeState();
  const mesh::Points shown = StepOnce(*trained.model, load, state.get());
  const Eigen::MatrixXd& b = trained.pod.modes;
  // B ξ in double precision (the positions are reconstructed from single-precision modes).
  const Eigen::VectorXd reduced = b * trained.model->Coordinates(*state);
  EXPECT_LT((Flat(shown) - reduced).norm(), 2e-7 * reduced.norm());
  const Eigen::VectorXd projected = b * (b.transpose() * Flat(full));
  fem::BlockSparseMatrix k;
  beam.model->AssembleTangent(beam.mesh.vertices, &k);
  const auto energy = [&](const Eigen::VectorXd& w) {
    Eigen::VectorXd kw(w.size());
    k.Multiply(w.data(), kw.data(), nullptr);
    return w.dot(kw);
  };
  const double reduced_error = energy(Flat(full) - reduced);
  const double projected_error = energy(Flat(full) - projected);
  std::printf("energy-norm error: reduced %.3e, L2 projection %.3e (of %.3e)\n", reduced_error,
              projected_error, energy(Flat(full)));
  EXPECT_GT(reduced_error, 0.0);
  EXPECT_LE(reduced_error, projected_error * (1.0 + 1e-9));
  // And the error is orthogonal to the span in the energy inner product: Bᵀ K (u − û) = 0.
  Eigen::VectorXd residual(reduced.size());
  const Eigen::VectorXd difference = Flat(full) - reduced;
  k.Multiply(difference.data(), residual.data(), nullptr);
  EXPECT_LT((b.transpose() * residual).norm(), 1e-9 * Flat(load).norm());
}

// With every free DOF as a mode, the reduced model is the full one: its local stiffness at a
// node is the full model's condensed stiffness ((K_ff⁻¹)_ii)⁻¹; a held node is as stiff as the
// cap allows.
TEST(KlReducedModel, LocalStiffnessIsTheCondensedStiffnessWithACompleteBasis) {
  const mesh::TetMesh cube =
      mesh_gen::BoxGridTets(3, 3, 3, Vector3d::Zero(), Vector3d::Ones() * 0.02);
  fem::FemParameters p;
  p.kind = fem::FemKind::kLinear;
  p.youngs_modulus = 5000.0;
  p.poisson_ratio = 0.35;
  const auto fem_model = fem::FemModel::FromTetMesh(cube, p);
  const int32_t nodes = fem_model->num_nodes();
  std::vector<int32_t> free_dofs;
  for (int32_t i = 0; i < nodes; ++i) {
    if (cube.vertices(2, i) > 1e-9) {
      for (int a = 0; a < 3; ++a) free_dofs.push_back(3 * i + a);
    }
  }
  const auto n = static_cast<Eigen::Index>(free_dofs.size());
  Eigen::MatrixXd modes = Eigen::MatrixXd::Zero(3 * nodes, n);
  for (Eigen::Index k = 0; k < n; ++k) modes(free_dofs[static_cast<size_t>(k)], k) = 1.0;
  KlModelData data = KlDataFromFem(*fem_model, cube.vertices, modes);
  data.max_local_stiffness = 1e12;
  const Eigen::MatrixXd compliance = data.reduced_stiffness.inverse();  // K_ff⁻¹
  const auto model = KlReducedModel::Create(data);
  const auto state = model->MakeState();
  for (Eigen::Index k = 0; k < n; k += 3) {
    const int32_t node = free_dofs[static_cast<size_t>(k)] / 3;
    const Eigen::Matrix3d expected = compliance.block(k, k, 3, 3).inverse();
    const Eigen::Matrix3d got = model->LocalStiffness(*state, node);
    EXPECT_LT((got - expected).norm(), 1e-8 * expected.norm()) << "node " << node;
  }
  EXPECT_LT((model->LocalStiffness(*state, 0) - 1e12 * Eigen::Matrix3d::Identity()).norm(), 1e-3);
}

// Seed 000's viscoelastic scaling: under a load held from t₀ the displacement is c(t − t₀)
// times the elastic one, c the loaded node's creep curve (or a curve node's within the radius);
// removing the load resets it.
TEST(KlReducedModel, CreepCurveScalesTheDisplacementOfAHeldLoad) {
  const Beam beam;
  const Trained trained(beam);
  const int32_t tip = trained.tip_node;
  KlModelData data = trained.model->data();
  data.creep = {{tip, 0.5, {1.0, 1.5, 2.0, 2.5}}};  // c(t) = 1 + t up to 1.5 s, then 2.5
  data.creep_radius = 0.011;
  const auto model = KlReducedModel::Create(data);
  auto state = model->MakeState();
  const mesh::Points& load = trained.loads[2];  // at the tip
  const mesh::Points& elastic = trained.full[2];
  mesh::Points u;
  for (int k = 0; k < 50; ++k) u = StepOnce(*model, load, state.get());
  EXPECT_NEAR(model->CreepMultiplier(*state), 1.5, 1e-9);
  EXPECT_LT((u - 1.5 * elastic).norm(), 2e-7 * elastic.norm());
  for (int k = 0; k < 250; ++k) u = StepOnce(*model, load, state.get());
  EXPECT_NEAR(model->CreepMultiplier(*state), 2.5, 1e-12);
  EXPECT_LT((u - 2.5 * elastic).norm(), 2e-7 * elastic.norm());
  const mesh::Points none = mesh::Points::Zero(3, beam.model->num_nodes());
  EXPECT_LT(StepOnce(*model, none, state.get()).norm(), 1e-15);
  EXPECT_EQ(model->CreepMultiplier(*state), 1.0);
  StepOnce(*model, load, state.get());
  EXPECT_NEAR(model->CreepMultiplier(*state), 1.01, 1e-9);  // the load came on a step ago
  // The node 2 cm from the tip (the grid's spacing: 2 cm along x, 1.5 cm along y and z) uses no
  // curve with a 1.1 cm radius, the tip's with a 2.1 cm one.
  const int32_t near = beam.Node(0.10, 0.03, 0.03);
  auto other = model->MakeState();
  for (int k = 0; k < 50; ++k)
    StepOnce(*model, beam.PointLoad(near, Vector3d(0, 0, -0.05)), other.get());
  EXPECT_EQ(model->CreepMultiplier(*other), 1.0);
  data.creep_radius = 0.021;
  const auto wider = KlReducedModel::Create(data);
  auto third = wider->MakeState();
  for (int k = 0; k < 50; ++k)
    StepOnce(*wider, beam.PointLoad(near, Vector3d(0, 0, -0.05)), third.get());
  EXPECT_NEAR(wider->CreepMultiplier(*third), 1.5, 1e-9);
}

TEST(KlReducedModel, GravityIsTheLoadOfTheNodesWeights) {
  const Beam beam;
  const Trained trained(beam);
  const KlReducedModel& model = *trained.model;
  const Vector3d g(0.0, 0.0, -9.81);
  mesh::Points weights(3, model.num_nodes());
  for (int32_t i = 0; i < model.num_nodes(); ++i) weights.col(i) = model.data().masses[i] * g;
  auto a = model.MakeState();
  auto b = model.MakeState();
  StepInputs with_gravity;
  with_gravity.dt = 0.01;
  with_gravity.gravity = g;
  ASSERT_EQ(model.Step(with_gravity, a.get()), StepStatus::kOk);
  StepOnce(model, weights, b.get());
  const double sag = (b->positions - model.data().rest).norm();
  EXPECT_GT(sag, 1e-4);
  EXPECT_LT((a->positions - b->positions).norm(), 1e-12 * sag);
  // Internal forces balance the load in the modes' span: Bᵀ (f_int + f_ext) = 0.
  mesh::Points internal;
  model.InternalForces(*b, &internal);
  EXPECT_LT((model.data().modes.transpose() * Flat(internal + weights)).norm(),
            1e-9 * weights.norm());
  EXPECT_GT(model.Energy(*b, Vector3d::Zero()).elastic, 0.0);
}

// A grasp is a spring to its target: stiff enough, it takes the node there when the modes can
// (the tip's three directions were trained). Prescribed nodes are stiff springs too.
TEST(KlReducedModel, GraspsAndPrescribedNodesPullTheirNodesToTheTargets) {
  const Beam beam;
  const Trained trained(beam);
  const KlReducedModel& model = *trained.model;
  const int32_t tip = trained.tip_node;
  const Vector3d target = model.data().rest.col(tip) + Vector3d(0.002, -0.003, -0.01);
  const Attachment grasp{tip, target, 1e7};
  StepInputs inputs;
  inputs.dt = 0.01;
  inputs.attachments = {&grasp, 1};
  auto state = model.MakeState();
  ASSERT_EQ(model.Step(inputs, state.get()), StepStatus::kOk);
  EXPECT_LT((state->positions.col(tip) - target).norm(), 1e-4 * 0.01);
  const std::vector<int32_t> prescribed{tip};
  mesh::Points at(3, 1);
  at.col(0) = target;
  StepInputs moved;
  moved.dt = 0.01;
  moved.prescribed_nodes = prescribed;
  moved.prescribed_positions = &at;
  auto other = model.MakeState();
  ASSERT_EQ(model.Step(moved, other.get()), StepStatus::kOk);
  EXPECT_LT((other->positions.col(tip) - target).norm(), 1e-2 * 0.01);
}

// A step that overflows (a finite but absurd time step: the velocities become infinite) is
// rejected; positions
// and velocities are rebuilt from the last accepted ξ, and the next step goes on as if the bad
// one had not been.
TEST(KlReducedModel, ARejectedStepRestoresTheLastAcceptedState) {
  const Beam beam;
  const Trained trained(beam);
  const KlReducedModel& model = *trained.model;
  auto state = model.MakeState();
  auto reference = model.MakeState();
  StepOnce(model, trained.loads[0], state.get());
  StepOnce(model, trained.loads[0], reference.get());
  StepOnce(model, trained.loads[1], state.get());
  StepOnce(model, trained.loads[1], reference.get());
  const mesh::Points x = state->positions, v = state->velocities;
  EXPECT_GT(v.norm(), 0.0);
  StepInputs inputs;
  inputs.dt = 1e-310;  // > 0 and finite, but the velocities overflow
  inputs.external_forces = &trained.loads[2];
  EXPECT_EQ(model.Step(inputs, state.get()), StepStatus::kRejectedNonFinite);
  EXPECT_EQ(state->positions, x);
  EXPECT_EQ(state->velocities, v);
  EXPECT_EQ(state->counters.rejected_steps, 1);
  StepOnce(model, trained.loads[2], state.get());
  StepOnce(model, trained.loads[2], reference.get());
  EXPECT_EQ(state->positions, reference->positions);
  EXPECT_EQ(state->velocities, reference->velocities);
}

TEST(KlReducedModel, StepsAllocateNothing) {
  const Beam beam;
  const Trained trained(beam);
  KlModelData data = trained.model->data();
  data.creep = {{trained.tip_node, 0.5, {1.0, 1.2, 1.3}}};
  const auto model = KlReducedModel::Create(data);
  auto state = model->MakeState();
  const Attachment grasp{beam.Node(0.08, 0.0, 0.03), Vector3d(0.08, 0.0, 0.035), 50.0};
  const std::vector<int32_t> prescribed{beam.Node(0.12, 0.0, 0.0)};
  mesh::Points at = model->data().rest.col(prescribed[0]);
  const std::vector<int32_t> fixed{beam.Node(0.10, 0.0, 0.0)};  // the modes move it
  StepInputs inputs;
  inputs.dt = 0.01;
  inputs.gravity = Vector3d(0, 0, -9.81);
  inputs.external_forces = &trained.loads[2];
  inputs.attachments = {&grasp, 1};
  inputs.prescribed_nodes = prescribed;
  inputs.prescribed_positions = &at;
  inputs.fixed_nodes = fixed;
  ASSERT_EQ(model->Step(inputs, state.get()), StepStatus::kOk);
  StepInputs plain;
  plain.dt = 0.01;
  plain.external_forces = &trained.loads[0];
  testing::AllocationCounter counter;
  for (int k = 0; k < 20; ++k) {
    model->Step(k % 2 == 0 ? inputs : plain, state.get());
    model->LocalStiffness(*state, trained.tip_node);
  }
  EXPECT_EQ(counter.count(), 0);
  EXPECT_EQ(state->counters.steps, 21);
}

TEST(KlReducedModel, RefusesBadDataAndBadStepsByName) {
  const Beam beam;
  const Trained trained(beam);
  const KlModelData good = trained.model->data();
  const auto message = [](KlModelData d) {
    try {
      KlReducedModel::Create(std::move(d));
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("accepted");
  };
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(message(good), "accepted");
  KlModelData d = good;
  d.masses.pop_back();
  EXPECT_NE(message(d).find("masses"), std::string::npos);
  d = good;
  d.masses[3] = 0.0;
  EXPECT_NE(message(d).find("mass"), std::string::npos);
  d = good;
  d.rest(1, 4) = nan;
  EXPECT_NE(message(d).find("rest positions"), std::string::npos);
  d = good;
  d.modes.conservativeResize(d.modes.rows() - 3, Eigen::NoChange);
  EXPECT_NE(message(d).find("modes must be 3N"), std::string::npos);
  d = good;
  d.modes(7, 2) = nan;
  EXPECT_NE(message(d).find("mode is not finite"), std::string::npos);
  d = good;
  d.stiffness_modes.conservativeResize(Eigen::NoChange, 5);
  EXPECT_NE(message(d).find("stiffness_modes"), std::string::npos);
  d = good;
  d.reduced_stiffness(0, 1) += 1.0;
  EXPECT_NE(message(d).find("not symmetric"), std::string::npos);
  d = good;
  d.reduced_stiffness(2, 2) = -d.reduced_stiffness(2, 2);
  EXPECT_NE(message(d).find("not positive definite"), std::string::npos);
  d = good;
  d.creep = {{9999, 0.5, {1.0}}};
  EXPECT_NE(message(d).find("node 9999 out of range"), std::string::npos);
  d = good;
  d.creep = {{3, 0.5, {1.0}}, {3, 0.5, {1.0}}};
  EXPECT_NE(message(d).find("another curve"), std::string::npos);
  d = good;
  d.creep = {{3, 0.5, {1.0, nan}}};
  EXPECT_NE(message(d).find("creep curve 0: a multiplier"), std::string::npos);
  d = good;
  d.creep = {{3, 0.5, {1.2, 1.3}}};
  EXPECT_NE(message(d).find("c(0) must be 1"), std::string::npos);
  d = good;
  d.creep = {{3, 0.0, {1.0}}};
  EXPECT_NE(message(d).find("interval"), std::string::npos);
  d = good;
  d.creep = {{3, 0.5, {}}};
  EXPECT_NE(message(d).find("no sample"), std::string::npos);
  // A step with a NaN force or a node out of range changes nothing.
  const KlReducedModel& model = *trained.model;
  auto state = model.MakeState();
  StepOnce(model, trained.loads[1], state.get());
  const mesh::Points before = state->positions;
  mesh::Points bad = trained.loads[1];
  bad(2, 5) = nan;
  StepInputs inputs;
  inputs.dt = 0.01;
  inputs.external_forces = &bad;
  EXPECT_EQ(model.Step(inputs, state.get()), StepStatus::kBadInput);
  const Attachment outside{model.num_nodes(), Vector3d::Zero(), 1.0};
  StepInputs grasp;
  grasp.dt = 0.01;
  grasp.attachments = {&outside, 1};
  EXPECT_EQ(model.Step(grasp, state.get()), StepStatus::kBadInput);
  EXPECT_EQ(state->positions, before);
  EXPECT_EQ(model.LocalStiffness(*state, -1), Eigen::Matrix3d::Zero());
}

}  // namespace
}  // namespace somasim::models::reduced
