// somasim::solve in-process: scenes built on meshes (files in any unit and node order, built-in
// organs), the three analyses against analytic answers (homogeneous strain, pressure and weight
// balanced by the reactions, creep that grows under a constant load), the outputs, and every
// fault a mesh reveals named by field and line.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numeric>
#include <sstream>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_io/mesh_io.h"
#include "server/organs/organ_builder.h"
#include "server/solve/solve_runner.h"
#include "tests/server/solve/solve_fixtures.h"
#include "tests/support/mesh_fixtures.h"
#include "tests/support/sanitizer.h"

namespace somasim::solve {
namespace {

using organs::BuildOrgan;
using organs::BuiltOrgan;
using organs::HistoryScale;
using organs::UnheldParts;

constexpr double kLength = 0.1, kWidth = 0.02;  // [m] the test bar

// The test bar (4 × 2 × 2 hexahedra, 6 tetrahedra each) with its nodes renumbered by `order`
// (new index k holds old node order[k]), written to dir/name in `unit`.
void WriteBar(const std::string& path, const std::vector<int32_t>& order, mesh_io::Unit unit) {
  const mesh_io::MeshData box = testing::BoxTets(4, 2, 2, kLength, kWidth, kWidth);
  mesh_io::MeshData out;
  out.vertices = box.vertices;
  std::vector<int32_t> old_to_new(order.size());
  for (size_t k = 0; k < order.size(); ++k) {
    out.vertices.col(static_cast<Eigen::Index>(k)) = box.vertices.col(order[k]);
    old_to_new[static_cast<size_t>(order[k])] = static_cast<int32_t>(k);
  }
  out.tetrahedra =
      box.tetrahedra.unaryExpr([&](int32_t i) { return old_to_new[static_cast<size_t>(i)]; });
  mesh_io::WriteOptions write;
  write.unit = unit;
  mesh_io::WriteMeshFile(path, out, write);
}

std::vector<int32_t> Identity(int64_t n) {
  std::vector<int32_t> order(static_cast<size_t>(n));
  std::iota(order.begin(), order.end(), 0);
  return order;
}

int64_t BarNodes() { return testing::BoxTets(4, 2, 2).vertices.cols(); }

std::string Scene(const std::string& body) { return "format_version: 1\nname: \"t\"\n" + body; }

SolveSummary Solve(const std::string& dir, const std::string& text) {
  return testing::SolveText(dir, text);
}
using testing::ReadVtu;
using testing::VtuArrays;

// Uniaxial stretch with ν = 0: a homogeneous strain δ/L that linear elements reproduce exactly,
// so every node moves by δ x / L and the supports pull with E A δ / L.
const char* kBarStretch = R"(
organ {
  id: "bar"
  file: "bar.vtu"
  unit: "UNIT"
  model { fem_linear {} }
  material { density: 1000 youngs_modulus: 10000 poisson_ratio: 0 }
  fixed { box { min { x: -1 y: -1 z: -1 } max { x: 0.001 y: 1 z: 1 } } }
}
load {
  organ: "bar"
  region { box { min { x: 0.099 y: -1 z: -1 } max { x: 1 y: 1 z: 1 } } }
  displacement { x: 0.001 }
}
analysis { static_solve {} }
)";

void ExpectHomogeneousStretch(const std::string& dir, const SolveSummary& s) {
  ASSERT_EQ(s.organs.size(), 1u);
  const OrganSummary& o = s.organs[0];
  EXPECT_TRUE(s.converged);
  EXPECT_NEAR(s.max_displacement_m, 0.001, 1e-12);
  ASSERT_EQ(o.outputs.size(), 1u);
  EXPECT_EQ(o.outputs[0].file, dir + "/out/bar_0.vtu");
  const VtuArrays vtu = ReadVtu(o.outputs[0].file, "displacement");
  ASSERT_EQ(vtu.values.size(), 3 * static_cast<size_t>(BarNodes()));
  ASSERT_EQ(vtu.points.size(), vtu.values.size());
  for (size_t i = 0; i < vtu.values.size() / 3; ++i) {  // in the file's node order, metres
    EXPECT_NEAR(vtu.values[3 * i], 0.001 * vtu.points[3 * i] / kLength, 1e-12) << i;
    EXPECT_NEAR(vtu.values[3 * i + 1], 0.0, 1e-12) << i;
    EXPECT_NEAR(vtu.values[3 * i + 2], 0.0, 1e-12) << i;
  }
  const double pull = 1e4 * kWidth * kWidth * 0.001 / kLength;  // E A δ / L [N]
  ASSERT_EQ(o.reactions.size(), 2u);
  EXPECT_EQ(o.reactions[0].region, "organ[0].fixed[0]");
  EXPECT_NEAR(o.reactions[0].force.x(), -pull, 1e-9 * pull);
  EXPECT_EQ(o.reactions[1].region, "load[0]");
  EXPECT_NEAR(o.reactions[1].force.x(), pull, 1e-9 * pull);
  EXPECT_NEAR(o.reactions[1].force.tail<2>().norm(), 0.0, 1e-9 * pull);
}

TEST(SolveStatic, StretchedBarIsHomogeneousWithReactionsEA) {
  const std::string dir = testing::MakeTempDir("solve_bar");
  WriteBar(dir + "/bar.vtu", Identity(BarNodes()), mesh_io::Unit::kMetre);
  ExpectHomogeneousStretch(dir, Solve(dir, Scene(testing::Replace(kBarStretch, "UNIT", "m"))));
}

TEST(SolveStatic, ResultsFollowTheInputNodeOrderAndUnit) {
  std::vector<int32_t> order = Identity(BarNodes());
  std::reverse(order.begin(), order.end());
  std::rotate(order.begin(), order.begin() + 7, order.end());
  const std::string dir = testing::MakeTempDir("solve_bar_order");
  WriteBar(dir + "/bar.vtu", order, mesh_io::Unit::kCentimetre);
  const SolveSummary s = Solve(dir, Scene(testing::Replace(kBarStretch, "UNIT", "cm")));
  EXPECT_EQ(s.organs.at(0).unit, "cm");
  ExpectHomogeneousStretch(dir, s);  // the VTU holds metres: the reader saw them as such
}

TEST(SolveStatic, PressureOnTheEndFaceIsCarriedByTheSupports) {
  const std::string dir = testing::MakeTempDir("solve_pressure");
  WriteBar(dir + "/bar.vtu", Identity(BarNodes()), mesh_io::Unit::kMetre);
  const SolveSummary s = Solve(dir, Scene(R"(
organ {
  id: "bar"
  file: "bar.vtu"
  model { fem_corotational {} }
  material { density: 1000 youngs_modulus: 10000 poisson_ratio: 0.3 }
  fixed { box { min { x: -1 y: -1 z: -1 } max { x: 0.001 y: 1 z: 1 } } }
}
load {
  organ: "bar"
  region { box { min { x: 0.099 y: -1 z: -1 } max { x: 1 y: 1 z: 1 } } }
  pressure: 50
}
analysis { static_solve { load_steps: 2 } }
)"));
  const OrganSummary& o = s.organs.at(0);
  EXPECT_TRUE(s.converged);
  ASSERT_EQ(o.reactions.size(), 1u);
  // 50 Pa over the 2 cm × 2 cm end face pushes the bar 0.02 N towards -x; the support answers.
  EXPECT_NEAR(o.reactions[0].force.x(), 50.0 * kWidth * kWidth, 1e-9);
  EXPECT_NEAR(o.reactions[0].force.tail<2>().norm(), 0.0, 1e-9);
  // Compression of about p L / E = 0.5 mm (ν lets the end face bulge a little).
  EXPECT_NEAR(o.max_displacement_m, 50.0 * kLength / 1e4, 0.2 * 50.0 * kLength / 1e4);
}

TEST(SolveStatic, DefaultSceneOfABuiltinOrganHangsItsWeightOnTheSupport) {
  const scene::Scene s = scene::DefaultScene("kidney424");
  const std::string dir = testing::MakeTempDir("solve_default");
  SolveOptions options;
  options.out_dir = dir;
  const SolveSummary summary = RunSolve(s, scene::SceneLines("builtin:kidney424"), options);
  EXPECT_TRUE(summary.converged);
  EXPECT_GT(summary.newton_iterations, 0);
  EXPECT_LT(summary.final_residual, 1e-8);
  const OrganSummary& o = summary.organs.at(0);
  const mesh::TetMesh kidney = mesh_gen::GenerateBuiltinOrganVolume("kidney424");
  EXPECT_EQ(o.nodes, kidney.vertices.cols());
  const double weight = 1000.0 * 9.81 * mesh::TetMeshVolume(kidney);  // [N]
  ASSERT_EQ(o.reactions.size(), 1u);
  EXPECT_NEAR(o.reactions[0].force.z(), weight, 1e-6 * weight);
  EXPECT_NEAR(o.reactions[0].force.head<2>().norm(), 0.0, 1e-6 * weight);
  EXPECT_GT(o.max_displacement_m, 0.0);
  EXPECT_TRUE(std::filesystem::exists(dir + "/kidney424_0.vtu"));
}

// The EFG model (efg) in a static analysis: one linear solve per output time. The bar's stretch
// with ν = 0 is a linear field, which MLS reproduces: only the quadrature (the patch test's
// error, efg_model_test) and the penalty supports stand between it and δ x / L.
TEST(SolveStaticEfg, StretchedBarIsNearlyHomogeneousAndTheSupportsBalance) {
  const std::string dir = testing::MakeTempDir("solve_efg_bar");
  WriteBar(dir + "/bar.vtu", Identity(BarNodes()), mesh_io::Unit::kMetre);
  const SolveSummary s = Solve(
      dir,
      Scene(testing::Replace(testing::Replace(kBarStretch, "UNIT", "m"), "fem_linear", "efg")));
  ASSERT_EQ(s.organs.size(), 1u);
  const OrganSummary& o = s.organs[0];
  EXPECT_EQ(o.model, "efg");
  EXPECT_TRUE(s.converged);
  EXPECT_EQ(o.newton_iterations, 1);
  EXPECT_LT(o.final_residual, 1e-9);
  EXPECT_NEAR(s.max_displacement_m, 0.001, 1e-5);
  const VtuArrays vtu = ReadVtu(o.outputs.at(0).file, "displacement");
  ASSERT_EQ(vtu.values.size(), 3 * static_cast<size_t>(BarNodes()));
  for (size_t i = 0; i < vtu.values.size() / 3; ++i) {
    EXPECT_NEAR(vtu.values[3 * i], 0.001 * vtu.points[3 * i] / kLength, 2e-5) << i;
    EXPECT_NEAR(vtu.values[3 * i + 1], 0.0, 2e-5) << i;
    EXPECT_NEAR(vtu.values[3 * i + 2], 0.0, 2e-5) << i;
  }
  const double pull = 1e4 * kWidth * kWidth * 0.001 / kLength;  // E A δ / L [N]
  ASSERT_EQ(o.reactions.size(), 2u);
  EXPECT_NEAR(o.reactions[0].force.x(), -pull, 0.02 * pull);
  EXPECT_NEAR(o.reactions[1].force.x(), pull, 0.02 * pull);
  // Nothing else loads the bar: the supports balance each other exactly.
  EXPECT_LT((o.reactions[0].force + o.reactions[1].force).norm(), 1e-9 * pull);
}

// Seed 001's liver (tests/data/scenes/liver288_efg.scene.txtpb's organ): its weight is carried by
// the underside, all of it (Σ m_I g, the lumped masses); and the model is linear, so a force
// ramped by its history gives half the displacement at half the ramp, with the supports pulling
// back the force.
TEST(SolveStaticEfg, Liver288CarriesItsWeightAndRespondsLinearlyToARampedForce) {
  // Heavy validation (15–30 s under the sanitizers): Release build only. The stretched bar and
  // SolveDynamic run the same path under the sanitizers.
  if (somasim::testing::kUnderSanitizer) GTEST_SKIP() << "heavy validation: Release build only";
  const std::string dir = testing::MakeTempDir("solve_efg_liver");
  const std::string organ = R"(
organ {
  id: "liver"
  builtin: "liver288"
  model { efg {} }
  material { density: 1055 youngs_modulus: 5000 poisson_ratio: 0.35 }
  fixed { box { min { x: -1 y: -1 z: -1 } max { x: 1 y: 1 z: -0.033 } } }
}
analysis { static_solve {} }
)";
  const SolveSummary weight = Solve(dir, Scene(organ + "gravity { z: -9.81 }\n"));
  const scene::Scene parsed = scene::ParseScene(Scene(organ), "liver");
  const BuiltOrgan built = BuildOrgan(parsed, 0, scene::SceneLines("liver"), dir);
  ASSERT_NE(built.efg, nullptr);
  EXPECT_EQ(built.fem, nullptr);
  double mass = 0.0;
  for (const double m : built.efg->masses()) mass += m;
  EXPECT_NEAR(mass, 1055.0 * mesh::TetMeshVolume(built.volume), 1e-9 * mass);
  const OrganSummary& w = weight.organs.at(0);
  EXPECT_TRUE(weight.converged);
  ASSERT_EQ(w.reactions.size(), 1u);
  EXPECT_NEAR(w.reactions[0].force.z(), 9.81 * mass, 1e-9 * 9.81 * mass);
  EXPECT_NEAR(w.reactions[0].force.head<2>().norm(), 0.0, 1e-9 * 9.81 * mass);
  EXPECT_GT(w.max_displacement_m, 0.0);

  const SolveSummary ramp =
      Solve(dir, Scene(organ + "load { organ: \"liver\" region { sphere { center { x: 0 y: 0 z: "
                               "0.06 } radius: 0.012 } } force { z: -1 }\n"
                               "  history { t: 0 scale: 0 } history { t: 1 scale: 1 } }\n"
                               "output { time: 0.5 time: 1 }\n"));
  const OrganSummary& r = ramp.organs.at(0);
  EXPECT_TRUE(ramp.converged);
  EXPECT_EQ(r.newton_iterations, 2);  // one solve per output time
  ASSERT_EQ(r.outputs.size(), 2u);
  EXPECT_GT(r.outputs[1].max_displacement_m, 1e-4);
  EXPECT_NEAR(r.outputs[0].max_displacement_m, 0.5 * r.outputs[1].max_displacement_m,
              1e-9 * r.outputs[1].max_displacement_m);
  const VtuArrays half = ReadVtu(r.outputs[0].file, "displacement");
  const VtuArrays full = ReadVtu(r.outputs[1].file, "displacement");
  ASSERT_EQ(half.values.size(), full.values.size());
  for (size_t i = 0; i < full.values.size(); ++i) {
    EXPECT_NEAR(half.values[i], 0.5 * full.values[i], 1e-12) << i;
  }
  ASSERT_EQ(r.reactions.size(), 1u);
  EXPECT_NEAR(r.reactions[0].force.z(), 1.0, 1e-9);
  EXPECT_NEAR(r.reactions[0].force.head<2>().norm(), 0.0, 1e-9);
}

// The EFG hybrid (efg_hybrid) in a static analysis, through EfgHybridModel::SolveStatic: its
// statics are exact by construction (the surgical region's condensed system plus the far
// region's particular response: efg_hybrid_model.h), so on seed 001's liver under the EFG test's
// loads — its weight; a force ramped by its history, output at half and full ramp — and a
// pressure on its top (nodal forces, as the EFG gets it) it gives the EFG's equilibrium: the
// largest displacement to 1e-6 relative, and so the field and the supports' reactions.
TEST(SolveStaticEfgHybrid, Liver288GivesTheEfgEquilibriumUnderItsWeightARampedForceAndAPressure) {
  // Heavy validation (15–30 s under the sanitizers): Release build only. The stretched bar and
  // SolveDynamic run the same path under the sanitizers.
  if (somasim::testing::kUnderSanitizer) GTEST_SKIP() << "heavy validation: Release build only";
  const auto organ = [](const std::string& model) {
    return "organ {\n  id: \"liver\"\n  builtin: \"liver288\"\n  model { " + model +
           " }\n  material { density: 1055 youngs_modulus: 5000 poisson_ratio: 0.35 }\n"
           "  fixed { box { min { x: -1 y: -1 z: -1 } max { x: 1 y: 1 z: -0.033 } } }\n}\n"
           "analysis { static_solve {} }\n";
  };
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"weight", "gravity { z: -9.81 }\n"},
      {"ramped force",
       "load { organ: \"liver\" region { sphere { center { x: 0 y: 0 z: 0.06 } radius: 0.012 } } "
       "force { z: -1 }\n  history { t: 0 scale: 0 } history { t: 1 scale: 1 } }\n"
       "output { time: 0.5 time: 1 }\n"},
      {"pressure",
       "load { organ: \"liver\"\n"
       "  region { box { min { x: -1 y: -1 z: 0.03 } max { x: 1 y: 1 z: 1 } } } pressure: 100 }\n"},
  };
  for (const auto& [name, loads] : cases) {
    SCOPED_TRACE(name);
    const SolveSummary efg =
        Solve(testing::MakeTempDir("solve_efg_hybrid_efg"), Scene(organ("efg {}") + loads));
    const SolveSummary hybrid = Solve(testing::MakeTempDir("solve_efg_hybrid"),
                                      Scene(organ("efg_hybrid { region_radius: 0.05 }") + loads));
    const OrganSummary& e = efg.organs.at(0);
    const OrganSummary& h = hybrid.organs.at(0);
    EXPECT_EQ(h.model, "efg_hybrid");
    EXPECT_TRUE(efg.converged);
    EXPECT_TRUE(hybrid.converged);
    EXPECT_EQ(h.newton_iterations, e.newton_iterations);  // one solve per output time
    std::printf(
        "liver288 static, %s: max displacement efg %.12e m, efg_hybrid %.12e m (relative "
        "difference %.2e); final residual efg %.2e, efg_hybrid %.2e\n",
        name.c_str(), efg.max_displacement_m, hybrid.max_displacement_m,
        std::abs(hybrid.max_displacement_m - efg.max_displacement_m) / efg.max_displacement_m,
        e.final_residual, h.final_residual);
    ASSERT_GT(efg.max_displacement_m, 1e-5);
    EXPECT_NEAR(hybrid.max_displacement_m, efg.max_displacement_m, 1e-6 * efg.max_displacement_m);
    ASSERT_EQ(h.outputs.size(), e.outputs.size());
    for (size_t k = 0; k < e.outputs.size(); ++k) {
      EXPECT_NEAR(h.outputs[k].max_displacement_m, e.outputs[k].max_displacement_m,
                  1e-6 * e.outputs[k].max_displacement_m)
          << k;
      const VtuArrays ue = ReadVtu(e.outputs[k].file, "displacement");
      const VtuArrays uh = ReadVtu(h.outputs[k].file, "displacement");
      ASSERT_EQ(uh.values.size(), ue.values.size());
      for (size_t i = 0; i < ue.values.size(); ++i) {
        EXPECT_NEAR(uh.values[i], ue.values[i], 1e-6 * e.outputs[k].max_displacement_m) << i;
      }
    }
    ASSERT_EQ(h.reactions.size(), 1u);
    ASSERT_EQ(e.reactions.size(), 1u);
    EXPECT_LT((h.reactions[0].force - e.reactions[0].force).norm(),
              1e-6 * e.reactions[0].force.norm());
  }
}

// A bar pulled by a constant force: with G(t) = 0.5 + 0.5 e^{-t/τ} (τ = 1 s) the creep is that
// of a standard linear solid, u(t) = u_e (2 - e^{-t/(2τ)}), u_e the response with the
// instantaneous modulus (an elastic static solve).
const char* kBarCreep = R"(
organ {
  id: "bar"
  file: "bar.vtu"
  model { fem_corotational {} }
  material { density: 1000 youngs_modulus: 10000 poisson_ratio: 0.3 PRONY }
  fixed { box { min { x: -1 y: -1 z: -1 } max { x: 0.001 y: 1 z: 1 } } }
}
load {
  organ: "bar"
  region { box { min { x: 0.099 y: -1 z: -1 } max { x: 1 y: 1 z: 1 } } }
  force { x: 0.01 }
}
)";

TEST(SolveQuasiStatic, CreepFollowsTheStandardLinearSolidAndOutputsLandOnTheirTimes) {
  const std::string dir = testing::MakeTempDir("solve_creep");
  WriteBar(dir + "/bar.vtu", Identity(BarNodes()), mesh_io::Unit::kMetre);
  const double elastic =
      Solve(dir, Scene(testing::Replace(kBarCreep, "PRONY", "") + "analysis { static_solve {} }"))
          .max_displacement_m;
  const SolveSummary s =
      Solve(dir, Scene(testing::Replace(kBarCreep, "PRONY", "prony { gamma: 0.5 tau: 1 }") +
                       "analysis { quasi_static { end_time: 5 dt: 0.125 } }\n"
                       "output { time: 0.5 time: 5 }\n"));
  const OrganSummary& o = s.organs.at(0);
  EXPECT_TRUE(s.converged);
  EXPECT_EQ(o.steps, 40);
  ASSERT_EQ(o.outputs.size(), 2u);
  EXPECT_EQ(o.outputs[0].time, 0.5);
  EXPECT_TRUE(std::filesystem::exists(dir + "/out/bar_1.vtu"));
  std::ifstream csv(o.history_file);
  std::string line;
  std::vector<double> u;
  std::getline(csv, line);
  EXPECT_EQ(line, "t_s,max_displacement_m,load[0]_mean_displacement_m");
  while (std::getline(csv, line)) u.push_back(std::stod(line.substr(line.find(',') + 1)));
  ASSERT_EQ(u.size(), 41u);  // t = 0 and 40 steps
  for (size_t k = 2; k < u.size(); ++k) EXPECT_GE(u[k], u[k - 1]) << k;
  // The load jumps at t = 0 while each step assumes a linear strain history: the first steps lag
  // the exact step response; by t = 5 s (2.5 retardation times) the lag is below 1 %.
  EXPECT_NEAR(u.back() / elastic, 2.0 - std::exp(-2.5), 0.01 * (2.0 - std::exp(-2.5)));
  EXPECT_NEAR(o.outputs[1].max_displacement_m, u.back(), 1e-9 * u.back());  // CSV: 10 digits
  EXPECT_NEAR(o.reactions.at(0).force.x(), -0.01, 1e-9);
}

TEST(SolveDynamic, ParticleModelOnASurfaceRuns) {
  const scene::Scene s = scene::DefaultScene("tissue45");
  const SolveSummary summary = RunSolve(s, scene::SceneLines("builtin:tissue45"), {});
  EXPECT_EQ(summary.analysis, "dynamic");
  EXPECT_TRUE(summary.converged);
  const OrganSummary& o = summary.organs.at(0);
  EXPECT_EQ(o.model, "mass_spring");
  EXPECT_EQ(o.steps, 1000);
  EXPECT_EQ(o.rejected_steps, 0);
  EXPECT_GT(o.max_displacement_m, 0.0);
  EXPECT_TRUE(o.outputs.at(0).file.empty());  // no out_dir: nothing written
}

TEST(SolveDynamic, FemSettlesTowardsTheStaticSolution) {
  scene::Scene s = scene::DefaultScene("plate192");
  const SolveSummary statics = RunSolve(s, scene::SceneLines("p"), {});
  s.mutable_organ(0)->mutable_material()->set_rayleigh_mass(30.0);  // [1/s], overdamped
  s.mutable_organ(0)->mutable_model()->set_dt(0.01);
  s.mutable_analysis()->mutable_dynamic()->set_end_time(3.0);
  const SolveSummary dynamics = RunSolve(s, scene::SceneLines("p"), {});
  EXPECT_TRUE(dynamics.converged);
  EXPECT_NEAR(dynamics.max_displacement_m, statics.max_displacement_m,
              0.02 * statics.max_displacement_m);
}

// The EFG model in a dynamic analysis (its own Step, implicit Euler) settles, overdamped, on the
// static solution.
TEST(SolveDynamic, EfgSettlesTowardsTheStaticSolution) {
  scene::Scene s = scene::DefaultScene("plate192");
  scene::Organ& organ = *s.mutable_organ(0);
  organ.mutable_model()->clear_kind();
  organ.mutable_model()->mutable_efg()->set_rayleigh_mass(30.0);  // [1/s], overdamped
  const SolveSummary statics = RunSolve(s, scene::SceneLines("p"), {});
  EXPECT_EQ(statics.organs.at(0).model, "efg");
  organ.mutable_model()->set_dt(0.01);
  s.mutable_analysis()->mutable_dynamic()->set_end_time(3.0);
  const SolveSummary dynamics = RunSolve(s, scene::SceneLines("p"), {});
  EXPECT_TRUE(dynamics.converged);
  EXPECT_EQ(dynamics.organs.at(0).steps, 300);
  EXPECT_GT(statics.max_displacement_m, 0.0);
  EXPECT_NEAR(dynamics.max_displacement_m, statics.max_displacement_m,
              0.02 * statics.max_displacement_m);
}

// The EFG hybrid in a dynamic analysis (its own Step: implicit Euler on the surgical region, the
// far region following quasi-statically) settles, overdamped, on the static solution.
TEST(SolveDynamic, EfgHybridSettlesTowardsTheStaticSolution) {
  scene::Scene s = scene::DefaultScene("plate192");
  scene::Organ& organ = *s.mutable_organ(0);
  organ.mutable_model()->clear_kind();
  scene::EfgHybrid& hybrid = *organ.mutable_model()->mutable_efg_hybrid();
  hybrid.mutable_efg()->set_rayleigh_mass(30.0);  // [1/s], overdamped
  hybrid.set_region_radius(0.05);
  const SolveSummary statics = RunSolve(s, scene::SceneLines("p"), {});
  EXPECT_EQ(statics.organs.at(0).model, "efg_hybrid");
  EXPECT_TRUE(statics.converged);
  organ.mutable_model()->set_dt(0.01);
  s.mutable_analysis()->mutable_dynamic()->set_end_time(3.0);
  const SolveSummary dynamics = RunSolve(s, scene::SceneLines("p"), {});
  EXPECT_TRUE(dynamics.converged);
  EXPECT_EQ(dynamics.organs.at(0).steps, 300);
  EXPECT_EQ(dynamics.organs.at(0).rejected_steps, 0);
  EXPECT_GT(statics.max_displacement_m, 0.0);
  EXPECT_NEAR(dynamics.max_displacement_m, statics.max_displacement_m,
              0.02 * statics.max_displacement_m);
}

// Faults only the mesh reveals: each names the field and the line of the scene.
struct Fault {
  const char* scene;
  const char* field;
  int line;
  const char* words;
};

TEST(SolveFaults, NamedByFieldAndLine) {
  const std::string dir = testing::MakeTempDir("solve_faults");
  WriteBar(dir + "/bar.vtu", Identity(BarNodes()), mesh_io::Unit::kMetre);
  mesh_io::WriteMeshFile(dir + "/skin.obj", testing::BoxSurface(2, 2, 2), {});
  const std::string organ =
      "organ {\n  id: \"bar\"\n  file: \"bar.vtu\"\n  model { fem_linear {} }\n"
      "  material { density: 1000 youngs_modulus: 10000 poisson_ratio: 0.3 }\n}\n";  // lines 3–8
  const std::vector<Fault> faults = {
      {"load {\n organ: \"bar\"\n region { nodes { id: 0 id: 9999 } }\n force { x: 1 }\n}\n"
       "analysis { static_solve {} }\n",
       "load[0].region.nodes.id[1]", 11, "out of range"},
      {"load {\n organ: \"bar\"\n region { sphere { center { x: 5 } radius: 0.01 } }\n"
       " force { x: 1 }\n}\nanalysis { static_solve {} }\n",
       "load[0].region", 11, "selects no node"},
      {"load {\n organ: \"bar\"\n region { nodes { id: 0 } }\n displacement { x: 1 }\n}\n"
       "load {\n organ: \"bar\"\n region { nodes { id: 0 } }\n displacement { x: 1 }\n}\n"
       "analysis { static_solve {} }\n",
       "load[1].region", 16, "already held"},
      {"load {\n organ: \"bar\"\n region { nodes { id: 0 } }\n pressure: 1\n}\n"
       "analysis { static_solve {} }\n",
       "load[0].region", 11, "no whole boundary triangle"},
      {"analysis { quasi_static { end_time: 1 dt: 0.1 } }\noutput { time: 2 }\n", "output.time[0]",
       10, "after the analysis"},
      {"", "analysis", 1, "needs an analysis"},  // not written: the scene's line
  };
  for (const Fault& f : faults) {
    try {
      Solve(dir, Scene(organ + f.scene));
      ADD_FAILURE() << "accepted: " << f.scene;
    } catch (const scene::SceneError& e) {
      EXPECT_EQ(e.field(), f.field) << e.what();
      EXPECT_EQ(e.line(), f.line) << e.what();
      EXPECT_TRUE(testing::Contains(e.what(), f.words)) << e.what();
    }
  }
  const std::vector<std::pair<std::string, std::string>> organs = {
      {"organ {\n id: \"s\"\n file: \"skin.obj\"\n model { fem_corotational {} }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
       "analysis { static_solve {} }\n",
       "holds no tetrahedra"},
      {"organ {\n id: \"s\"\n builtin: \"tissue45\"\n model { fem_corotational {} }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
       "analysis { static_solve {} }\n",
       "open surface"},
      {"organ {\n id: \"s\"\n file: \"skin.obj\"\n model { efg {} }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
       "analysis { static_solve {} }\n",
       "FEM, EFG and reduced models need a volume mesh"},
      {"organ {\n id: \"s\"\n builtin: \"tissue45\"\n model { efg {} }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
       "analysis { dynamic { end_time: 1 } }\n",
       "open surface"},
      {"organ {\n id: \"s\"\n builtin: \"plate192\"\n model { efg {} }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n"
       " fixed { nodes { id: [0, 1, 2, 3] } }\n}\n"
       "analysis { quasi_static { end_time: 1 dt: 0.1 } }\n",
       "efg is elastic"},
      {"organ {\n id: \"s\"\n file: \"skin.obj\"\n model { efg_hybrid {} }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
       "analysis { static_solve {} }\n",
       "FEM, EFG and reduced models need a volume mesh"},
      {"organ {\n id: \"s\"\n builtin: \"tissue45\"\n model { efg_hybrid {} }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
       "analysis { dynamic { end_time: 1 } }\n",
       "open surface"},
      {"organ {\n id: \"s\"\n builtin: \"plate192\"\n model { efg_hybrid {} }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n"
       " fixed { nodes { id: [0, 1, 2, 3] } }\n}\n"
       "analysis { quasi_static { end_time: 1 dt: 0.1 } }\n",
       "efg_hybrid is elastic"},
      {"organ {\n id: \"s\"\n file: \"bar.vtu\"\n model { efg { support_neighbours: 50 } }\n"
       " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
       "analysis { dynamic { end_time: 1 } }\n",
       "support_neighbours must lie in 1..64 and be < the number of nodes"},  // 45 nodes
      {"organ {\n id: \"s\"\n builtin: \"plate192\"\n model { molecular {} }\n"
       " material { density: 1 youngs_modulus: 1 }\n}\nanalysis { dynamic { end_time: 1 } }\n",
       "surface mesh"},
      {"organ {\n id: \"s\"\n builtin: \"spleen600\"\n model { mass_spring {} }\n"
       " material { density: 1 youngs_modulus: 1 }\n}\nanalysis { static_solve {} }\n",
       "needs a FEM model"},
  };
  for (const auto& [text, words] : organs) {
    try {
      Solve(dir, Scene(text));
      ADD_FAILURE() << "accepted: " << text;
    } catch (const scene::SceneError& e) {
      EXPECT_GT(e.line(), 0) << e.what();
      EXPECT_TRUE(testing::Contains(e.what(), words)) << e.what();
    }
  }
  // A missing mesh file is the mesh reader's I/O fault, naming the file.
  try {
    Solve(dir,
          Scene(testing::Replace(organ, "bar.vtu", "gone.vtu") + "analysis { static_solve {} }\n"));
    ADD_FAILURE() << "a missing file was accepted";
  } catch (const mesh_io::MeshError& e) {
    EXPECT_EQ(e.kind(), mesh_io::MeshErrorKind::kIo);
    EXPECT_TRUE(testing::Contains(e.what(), "gone.vtu")) << e.what();
  }
}

// Two tetrahedra sharing only the edge 0–1: holding the first leaves the second free to turn
// about that edge (a singular stiffness), which a static analysis refuses by name.
BuiltOrgan Hinge() {
  BuiltOrgan o;
  o.volume.vertices.resize(3, 6);
  o.volume.vertices << 0, 1, 0, 0, 0, 1,  //
      0, 0, 1, 0, -1, 0,                  //
      0, 0, 0, 1, 0, -1;
  o.volume.tetrahedra.resize(4, 2);
  o.volume.tetrahedra << 0, 0, 1, 1, 2, 4, 3, 5;
  return o;
}

TEST(SolveUnheldParts, FindsAPieceOnAHingeAndAnOrganNothingHolds) {
  const BuiltOrgan hinge = Hinge();
  EXPECT_TRUE(testing::Contains(UnheldParts(hinge, {0, 1, 2, 3}), "along an edge"));
  EXPECT_EQ(UnheldParts(hinge, {0, 1, 2, 3, 4}), "");  // a third node holds the second piece
  EXPECT_EQ(UnheldParts(hinge, {0, 3, 4, 5}), "");     // the second holds the first
  EXPECT_TRUE(testing::Contains(UnheldParts(hinge, {0, 1, 4}), "along an edge"));
  // One piece held along a line only, or not at all.
  BuiltOrgan one = Hinge();
  one.volume.tetrahedra.conservativeResize(4, 1);
  EXPECT_TRUE(testing::Contains(UnheldParts(one, {}), "nothing holds the organ"));
  EXPECT_TRUE(testing::Contains(UnheldParts(one, {0, 1}), "nothing holds the organ"));
  EXPECT_EQ(UnheldParts(one, {0, 1, 2}), "");
}

TEST(SolveUnheldParts, StaticSolveOfAFreeOrganIsRefused) {
  try {
    Solve(testing::MakeTempDir("solve_free"),
          Scene("organ {\n id: \"free\"\n builtin: \"plate192\"\n model { fem_linear {} }\n"
                " material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
                "gravity { z: -9.81 }\nanalysis { static_solve {} }\n"));
    ADD_FAILURE() << "a free organ was solved";
  } catch (const scene::SceneError& e) {
    EXPECT_EQ(e.field(), "organ[0]");
    EXPECT_EQ(e.line(), 3);
    EXPECT_TRUE(testing::Contains(e.what(), "nothing holds")) << e.what();
  }
}

TEST(SolveHistory, ScaleIsPiecewiseLinearAndHeldOutside) {
  scene::Load load;
  EXPECT_EQ(HistoryScale(load, 3.0), 1.0);
  auto* a = load.add_history();
  a->set_t(1.0);
  a->set_scale(2.0);
  auto* b = load.add_history();
  b->set_t(3.0);
  b->set_scale(-2.0);
  EXPECT_EQ(HistoryScale(load, 0.0), 2.0);
  EXPECT_EQ(HistoryScale(load, 2.0), 0.0);
  EXPECT_EQ(HistoryScale(load, 2.5), -1.0);
  EXPECT_EQ(HistoryScale(load, 9.0), -2.0);
}

}  // namespace
}  // namespace somasim::solve
