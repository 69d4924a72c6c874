// somasim-reduce as a program (server/reduce/somasim_reduce_main.cc) on the kidney's test
// reduction (tests/data/scenes/kidney_reduction.scene.txtpb): it writes a reduced model that
// loads against the organ's mesh, summarises it in JSON, and refuses what it cannot do with
// the documented exit codes and a message naming the cause.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "server/organs/reduced_file.h"
#include "server/reduce/builder.h"
#include "tests/support/mesh_fixtures.h"
#include "tests/support/run_program.h"
#include "tests/support/sanitizer.h"

namespace somasim::reduce {
namespace {

using organs::LoadedReducedModel;
using organs::LoadReducedModel;

std::string Scene(const std::string& name) {
  return "'" + std::string(SOMASIM_TEST_DATA_DIR) + "/scenes/" + name + "'";
}

// The JSON summary in the output (stdout, with the progress lines of stderr around it).
nlohmann::json Summary(const std::string& out) {
  const std::string text = "\n" + out;
  const size_t begin = text.find("\n{");
  const size_t end = text.rfind("\n}");
  if (begin == std::string::npos || end == std::string::npos || end < begin) return {};
  return nlohmann::json::parse(text.substr(begin + 1, end + 2 - begin - 1));
}

TEST(ReduceProgram, WritesAReducedModelThatLoadsOnTheOrgansMesh) {
  const std::string dir = testing::MakeTempDir("reduce");
  const std::string out = dir + "/kidney.somared";
  const testing::ToolRun r = testing::RunProgram(
      "somasim-reduce", Scene("kidney_reduction.scene.txtpb") + " --out " + out);
  ASSERT_EQ(r.status, 0) << r.out;
  const nlohmann::json j = Summary(r.out);
  EXPECT_EQ(j["organ"], "kidney");
  EXPECT_EQ(j["points"].size(), 4u);
  EXPECT_EQ(j["snapshots"], 4 * 3 * 2 + 4);  // static cases + each creep run's end
  EXPECT_EQ(j["unconverged"], 0);
  EXPECT_EQ(j["modes"], 12);
  EXPECT_EQ(j["creep_curves"], 4);
  EXPECT_EQ(j["stiffness_candidates"].size(), 3u);
  EXPECT_NE(r.out.find("snapshots 24/24"), std::string::npos) << r.out;
  const mesh_gen::BuiltinOrgan kidney = mesh_gen::GenerateBuiltinOrgan("kidney424");
  const LoadedReducedModel loaded = LoadReducedModel(out, &kidney.volume);
  EXPECT_EQ(loaded.model->num_modes(), 12);
  EXPECT_EQ(loaded.metadata.mesh(), "builtin:kidney424");
  EXPECT_NE(loaded.metadata.command().find("somasim-reduce"), std::string::npos);
  EXPECT_NE(loaded.metadata.stiffness().find("relative L2 errors"), std::string::npos);
  ASSERT_EQ(loaded.model->data().creep.size(), 4u);
  // The linear solid's creep: towards 1/γ∞ = 1/0.6.
  const std::vector<double>& c = loaded.model->data().creep[0].multiplier;
  EXPECT_EQ(c.front(), 1.0);
  EXPECT_GT(c.back(), 1.5);
  EXPECT_LT(c.back(), 1.0 / 0.6 + 1e-3);
  // A scene runs the organ on it (somasim-solve's dynamic analysis: the model's own steps).
  std::ofstream(dir + "/reduced.scene.txtpb")
      << "format_version: 1\n"
         "organ { id: \"kidney\" builtin: \"kidney424\" model { reduced_kl { file: "
         "\"kidney.somared\" } dt: 0.01 } }\n"
         "load { organ: \"kidney\" region { nodes { id: "
      << j["points"][0].get<int>()
      << " } } force { z: -0.3 } }\n"
         "analysis { dynamic { end_time: 0.5 } }\n";
  const testing::ToolRun solved = testing::RunProgram(
      "somasim-solve", "'" + dir + "/reduced.scene.txtpb' --out '" + dir + "/solved'");
  ASSERT_EQ(solved.status, 0) << solved.out;
  const nlohmann::json s = Summary(solved.out);
  EXPECT_EQ(s["organs"][0]["model"], "reduced_kl");
  EXPECT_EQ(s["organs"][0]["rejected_steps"], 0);
  EXPECT_GT(s["max_displacement_m"].get<double>(), 1e-4);
  EXPECT_LT(s["max_displacement_m"].get<double>(), 0.05);
  // On another organ's mesh it is refused, naming the field.
  std::ofstream(dir + "/wrong.scene.txtpb")
      << "format_version: 1\n"
         "organ { id: \"beam\" builtin: \"beam19k\"\n"
         "  model { reduced_kl { file: \"kidney.somared\" } } }\n"
         "analysis { dynamic { end_time: 0.1 } }\n";
  const testing::ToolRun wrong = testing::RunProgram(
      "somasim-solve", "'" + dir + "/wrong.scene.txtpb' --out '" + dir + "/wrong'");
  EXPECT_EQ(wrong.status, 3) << wrong.out;
  EXPECT_NE(wrong.out.find("wrong.scene.txtpb:3: organ[0].model.reduced_kl.file"),
            std::string::npos)
      << wrong.out;
  EXPECT_NE(wrong.out.find("made for a mesh of 430 nodes"), std::string::npos) << wrong.out;
  // The evaluation: a trained load (a sampled point along its inward normal, held) is
  // reproduced over its creep; a load far from the regions is not.
  const int32_t trained = j["points"][0].get<int>();
  const Eigen::Vector3d inward = -reduce::BoundaryNormals(kidney.volume).col(trained);
  int32_t far = -1;
  for (int32_t i = 0; i < kidney.volume.vertices.cols(); ++i) {
    if (kidney.volume.vertices(0, i) < -0.05 && kidney.volume.vertices(2, i) > 0.0) far = i;
  }
  ASSERT_GE(far, 0);
  std::ofstream(dir + "/plan.txtpb")
      << "organ: \"kidney\"\n"
         "cases { name: \"trained\" group: \"inside\" node: "
      << trained << " force: " << 0.3 * inward.x() << " force: " << 0.3 * inward.y()
      << " force: " << 0.3 * inward.z()
      << " end_time: 1.5 dt: 0.1 }\n"
         "cases { name: \"far\" group: \"outside\" node: "
      << far
      << " force: 0 force: 0.2 force: -0.2 time: 0 scale: 0 "
         "time: 0.5 scale: 1 end_time: 1 dt: 0.1 }\n";
  const std::string per_step = dir + "/per_step.csv";
  const testing::ToolRun evaluated = testing::RunProgram(
      "somasim-reduce", Scene("kidney_reduction.scene.txtpb") + " --evaluate " + out + " --plan " +
                            dir + "/plan.txtpb --per-step " + per_step);
  ASSERT_EQ(evaluated.status, 0) << evaluated.out;
  std::printf("%s", evaluated.out.c_str());
  const auto percent = [&](const std::string& row, int column) {
    size_t at = evaluated.out.find("| " + row + " |");
    for (int k = 0; k < column && at != std::string::npos; ++k)
      at = evaluated.out.find('|', at + 1);
    return at == std::string::npos ? -1.0 : std::atof(evaluated.out.c_str() + at + 1);
  };
  EXPECT_GE(percent("trained", 3), 0.0);
  EXPECT_LT(percent("trained", 3), 0.1);  // field error [%], printed to 0.1 %
  EXPECT_LT(percent("trained", 4), 0.1);  // loaded-node error [%]
  EXPECT_GT(percent("far", 3), 1.0);
  // --per-step: one row per case and step (15 + 10), each step's field error split into the
  // part near the loaded node and the rest (near² + far² = field², to the CSV's 9 digits), the
  // trained case within 0.2 % at every step; an existing file is refused before any work.
  {
    std::ifstream csv(per_step);
    std::string line;
    ASSERT_TRUE(std::getline(csv, line));
    EXPECT_EQ(line.rfind("case,time_s,scale,field_error,near_error,far_error,basis_error,", 0), 0u)
        << line;
    int rows = 0, far_rows = 0;
    while (std::getline(csv, line)) {
      ++rows;
      const size_t quote = line.find('"', 1);
      ASSERT_NE(quote, std::string::npos) << line;
      const std::string name = line.substr(1, quote - 1);
      std::vector<double> v;
      std::stringstream fields(line.substr(quote + 2));
      for (std::string f; std::getline(fields, f, ',');) v.push_back(std::stod(f));
      ASSERT_EQ(v.size(), 12u) << line;
      EXPECT_NEAR(v[3] * v[3] + v[4] * v[4], v[2] * v[2], 1e-6) << line;
      EXPECT_GE(v[5], 0.0) << line;  // the basis floor (modes given)
      if (name == "far") {
        ++far_rows;
        EXPECT_GT(std::abs(v[6]) + std::abs(v[7]) + std::abs(v[8]), 0.0) << line;
      } else {
        EXPECT_EQ(name, "trained");
        EXPECT_LT(v[2], 2e-3) << line;
      }
    }
    EXPECT_EQ(rows, 25);
    EXPECT_EQ(far_rows, 10);
    const testing::ToolRun exists = testing::RunProgram(
        "somasim-reduce", Scene("kidney_reduction.scene.txtpb") + " --evaluate " + out +
                              " --plan " + dir + "/plan.txtpb --per-step " + per_step);
    EXPECT_EQ(exists.status, 4);
    EXPECT_NE(exists.out.find("per_step.csv exists (never overwritten)"), std::string::npos)
        << exists.out;
  }
  // A plan naming a held node is refused by case.
  std::ofstream(dir + "/bad_plan.txtpb") << "cases { name: \"held\" node: " << 0
                                         << " force: 0 force: 0 force: 1 end_time: 1 dt: 0.1 }\n";
  const testing::ToolRun held =
      testing::RunProgram("somasim-reduce", Scene("kidney_reduction.scene.txtpb") + " --evaluate " +
                                                out + " --plan " + dir + "/bad_plan.txtpb");
  // Node 0 may or may not be held; either way a bad node is named.
  if (held.status != 0) {
    EXPECT_EQ(held.status, 3);
    EXPECT_NE(held.out.find("cases[0] (held)"), std::string::npos) << held.out;
  }
  std::ofstream(dir + "/bad_plan.txtpb")
      << "cases { name: \"nowhere\" node: 100000 force: 0 force: 0 force: 1 end_time: 1 "
         "dt: 0.1 }\n";
  const testing::ToolRun nowhere =
      testing::RunProgram("somasim-reduce", Scene("kidney_reduction.scene.txtpb") + " --evaluate " +
                                                out + " --plan " + dir + "/bad_plan.txtpb");
  EXPECT_EQ(nowhere.status, 3);
  EXPECT_NE(nowhere.out.find("cases[0] (nowhere): node 100000 out of range"), std::string::npos)
      << nowhere.out;
  // Never overwritten.
  const testing::ToolRun again = testing::RunProgram(
      "somasim-reduce", Scene("kidney_reduction.scene.txtpb") + " --out " + out);
  EXPECT_EQ(again.status, 4);
  EXPECT_NE(again.out.find("never overwritten"), std::string::npos) << again.out;
  std::filesystem::remove_all(dir);
}

// The nonlinear model (--nonlinear-out) on a hyperelastic kidney: written from the same build,
// loaded as the nonlinear kind, run by somasim-solve, and on held-out loads inside the regions
// (nodes no plan sampled statically, tilted, held and released) far nearer the full model than
// seed 000's model from the same build, the loaded node within 7 % (its static correction).
TEST(ReduceProgram, TheNonlinearModelBeatsTheSeedMethodOnHeldOutLoads) {
  // Four minutes under the sanitizers: the builder's nonlinear path has its small sanitizer run
  // in builder_test.cc (TheNonlinearModelReproducesATrainedLoadThroughItsCreep).
  if (testing::kUnderSanitizer) GTEST_SKIP() << "a heavy validation: run in the Release build";
  const std::string dir = testing::MakeTempDir("reduce-nl");
  const std::string scene = Scene("kidney_nonlinear_reduction.scene.txtpb");
  const testing::ToolRun r = testing::RunProgram(
      "somasim-reduce",
      scene + " --out " + dir + "/kl.somared --nonlinear-out " + dir + "/nl.somared");
  ASSERT_EQ(r.status, 0) << r.out;
  const nlohmann::json j = Summary(r.out);
  const nlohmann::json& nl = j["nonlinear"];
  EXPECT_EQ(nl["modes"], 32);
  EXPECT_EQ(nl["region_unconverged"], 0);
  EXPECT_EQ(nl["region_solves"], 16 * 3 * 3);  // region nodes × (normal + 2 tilts) × forces
  EXPECT_EQ(nl["correction_nodes"], 16);       // each region node's static correction
  EXPECT_TRUE(nl["cubature_converged"].get<bool>());
  const mesh_gen::BuiltinOrgan kidney = mesh_gen::GenerateBuiltinOrgan("kidney424");
  EXPECT_LT(nl["cubature_elements"].get<int>(), kidney.volume.tetrahedra.cols() / 3);
  const LoadedReducedModel loaded = LoadReducedModel(dir + "/nl.somared", &kidney.volume);
  ASSERT_NE(loaded.nonlinear, nullptr);
  EXPECT_EQ(loaded.metadata.kind(), "ecsw_nonlinear");
  EXPECT_EQ(loaded.nonlinear->data().prony.size(), 2u);
  // Held-out nodes: region nodes the plan did not sample, loaded 20° off their inward normal.
  std::vector<int32_t> held_out;
  for (const int32_t n : nl["region_nodes"].get<std::vector<int32_t>>()) {
    bool sampled = false;
    for (const auto& p : j["points"]) sampled = sampled || p.get<int32_t>() == n;
    if (!sampled) held_out.push_back(n);
  }
  ASSERT_GE(held_out.size(), 8u);
  const mesh::Points normals = reduce::BoundaryNormals(kidney.volume);
  std::ofstream plan(dir + "/plan.txtpb");
  plan << "organ: \"kidney\"\n";
  const char* histories[] = {"time: 0 scale: 1 end_time: 3",
                             "time: 0 scale: 0 time: 0.5 scale: 1 time: 1.5 scale: 1 time: 2 "
                             "scale: 0 end_time: 3"};
  for (int k = 0; k < 2; ++k) {
    const int32_t node = held_out[4 * static_cast<size_t>(k) + 1];
    const Eigen::Vector3d inward = -normals.col(node);
    const Eigen::Vector3d side = inward.cross(Eigen::Vector3d::UnitX()).normalized();
    const Eigen::Vector3d f = 0.25 * (std::cos(0.35) * inward + std::sin(0.35) * side);
    plan << "cases { name: \"case" << k << "\" group: \"inside\" node: " << node
         << " force: " << f.x() << " force: " << f.y() << " force: " << f.z() << " " << histories[k]
         << " dt: 0.25 }\n";
  }
  plan.close();
  const auto evaluate = [&](const std::string& model) {
    const testing::ToolRun e =
        testing::RunProgram("somasim-reduce", scene + " --evaluate " + dir + "/" + model +
                                                  " --plan " + dir + "/plan.txtpb");
    EXPECT_EQ(e.status, 0) << e.out;
    std::printf("%s", e.out.c_str());
    return e.out;
  };
  const std::string seed = evaluate("kl.somared"), ours = evaluate("nl.somared");
  EXPECT_NE(ours.find("ecsw_nonlinear, 32 modes"), std::string::npos) << ours;
  const auto percent = [](const std::string& out, const std::string& row, int column) {
    size_t at = out.find("| " + row + " |");
    for (int k = 0; k < column && at != std::string::npos; ++k) at = out.find('|', at + 1);
    return at == std::string::npos ? -1.0 : std::atof(out.c_str() + at + 1);
  };
  for (const std::string row : {"case0", "case1"}) {
    const double field = percent(ours, row, 3), node = percent(ours, row, 4);
    EXPECT_GE(field, 0.0) << row;
    // Measured 5.0 and 3.5 % with the static correction's part in the modes (8.9 and 7.4 %
    // without it; docs/reduced.md).
    EXPECT_LT(field, 10.0) << row;
    // The static correction puts back the loaded node's dent: measured 1.9 and 3.5 % (8.1 and
    // 9.3 % without the correction).
    EXPECT_LT(node, 7.0) << row;
    EXPECT_LT(2.0 * field, percent(seed, row, 3)) << row;
  }
  // The same build with the Petrov–Galerkin projection (`nonlinear_projection`): its file holds
  // the test basis, and on the same held-out loads it is as near the full model.
  {
    std::ifstream in(std::string(SOMASIM_TEST_DATA_DIR) +
                     "/scenes/kidney_nonlinear_reduction.scene.txtpb");
    std::ostringstream buffer;
    buffer << in.rdbuf();
    std::string text = buffer.str();
    const std::string anchor = "nonlinear_max_modes: 32";
    ASSERT_NE(text.find(anchor), std::string::npos);
    text.insert(text.find(anchor) + anchor.size(), "\n  nonlinear_projection: PETROV_GALERKIN");
    std::ofstream(dir + "/pg.scene.txtpb") << text;
  }
  const testing::ToolRun pg = testing::RunProgram(
      "somasim-reduce", "'" + dir + "/pg.scene.txtpb' --out " + dir + "/kl2.somared " +
                            "--nonlinear-out " + dir + "/pg.somared");
  ASSERT_EQ(pg.status, 0) << pg.out;
  EXPECT_EQ(Summary(pg.out)["nonlinear"]["projection"], "petrov_galerkin");
  EXPECT_EQ(j["nonlinear"]["projection"], "galerkin");
  const LoadedReducedModel petrov = LoadReducedModel(dir + "/pg.somared", &kidney.volume);
  ASSERT_NE(petrov.nonlinear, nullptr);
  EXPECT_TRUE(petrov.nonlinear->petrov_galerkin());
  EXPECT_FALSE(loaded.nonlinear->petrov_galerkin());
  EXPECT_NE(petrov.metadata.stiffness().find("Petrov"), std::string::npos);
  const std::string theirs = evaluate("pg.somared");
  for (const std::string row : {"case0", "case1"}) {
    const double field = percent(theirs, row, 3);
    EXPECT_GE(field, 0.0) << row;
    EXPECT_LT(field, 10.0) << row;  // measured 5.2 and 3.4 %
    EXPECT_LT(2.0 * field, percent(seed, row, 3)) << row;
  }
  // A session's organ on it (somasim-solve's dynamic analysis: the model's own steps).
  std::ofstream(dir + "/nl.scene.txtpb")
      << "format_version: 1\n"
         "organ { id: \"kidney\" builtin: \"kidney424\" model { reduced_kl { file: "
         "\"nl.somared\" } dt: 0.01 } }\n"
         "load { organ: \"kidney\" region { nodes { id: "
      << held_out[0]
      << " } } force { z: -0.2 } }\n"
         "analysis { dynamic { end_time: 0.3 } }\n";
  const testing::ToolRun solved = testing::RunProgram(
      "somasim-solve", "'" + dir + "/nl.scene.txtpb' --out '" + dir + "/solved'");
  ASSERT_EQ(solved.status, 0) << solved.out;
  const nlohmann::json s = Summary(solved.out);
  EXPECT_EQ(s["organs"][0]["rejected_steps"], 0);
  EXPECT_GT(s["max_displacement_m"].get<double>(), 1e-4);
  EXPECT_LT(s["max_displacement_m"].get<double>(), 0.05);
  // A linear organ has no nonlinear model.
  const testing::ToolRun linear = testing::RunProgram(
      "somasim-reduce", Scene("kidney_reduction.scene.txtpb") + " --out " + dir +
                            "/l.somared --nonlinear-out " + dir + "/l2.somared");
  EXPECT_EQ(linear.status, 3) << linear.out;
  EXPECT_NE(linear.out.find("is not fem_hyperelastic"), std::string::npos) << linear.out;
  EXPECT_FALSE(std::filesystem::exists(dir + "/l.somared"));
  std::filesystem::remove_all(dir);
}

TEST(ReduceProgram, RefusesScenesWithoutAUsablePlanByName) {
  const std::string dir = testing::MakeTempDir("reduce-bad");
  const testing::ToolRun none = testing::RunProgram(
      "somasim-reduce", Scene("liver_creep.scene.txtpb") + " --out " + dir + "/x.somared");
  EXPECT_EQ(none.status, 3);
  EXPECT_NE(none.out.find("has no reduction block"), std::string::npos) << none.out;
  const std::string bad = dir + "/bad.scene.txtpb";
  std::ofstream(bad) << "format_version: 1\n"
                        "organ { id: \"k\" builtin: \"kidney424\" model { mass_spring {} }\n"
                        "  material { density: 1000 youngs_modulus: 5000 } }\n"
                        "reduction {\n"
                        "  organ: \"k\"\n"
                        "  interaction { sphere { center { x: 0 y: 0 z: 0 } radius: 0.01 } }\n"
                        "}\n";
  const testing::ToolRun not_fem =
      testing::RunProgram("somasim-reduce", bad + " --out " + dir + "/x.somared");
  EXPECT_EQ(not_fem.status, 3);
  EXPECT_NE(not_fem.out.find("bad.scene.txtpb:5: reduction[0].organ"), std::string::npos)
      << not_fem.out;
  EXPECT_NE(not_fem.out.find("needs a FEM model"), std::string::npos) << not_fem.out;
  std::ofstream(bad)
      << "format_version: 1\n"
         "organ { id: \"k\" builtin: \"kidney424\" model { fem_linear {} }\n"
         "  material { density: 1000 youngs_modulus: 5000 poisson_ratio: 0.4 }\n"
         "  fixed { box { min { x: -1 y: -1 z: -1 } max { x: 1 y: 1 z: -0.01 } } } }\n"
         "reduction {\n"
         "  organ: \"k\"\n"
         "  interaction { sphere { center { x: 0 y: 0 z: 0 } radius: 0.001 } }\n"
         "  directions: 2\n"
         "}\n";
  const testing::ToolRun directions =
      testing::RunProgram("somasim-reduce", bad + " --out " + dir + "/x.somared");
  EXPECT_EQ(directions.status, 3);
  EXPECT_NE(directions.out.find(":8: reduction[0].directions"), std::string::npos)
      << directions.out;
  EXPECT_EQ(testing::RunProgram("somasim-reduce", bad).status, 2);
  EXPECT_FALSE(std::filesystem::exists(dir + "/x.somared"));
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace somasim::reduce
