// The somasim-solve executable: the JSON keys of SPEC §6, the files it writes, its exit codes,
// and that it solves every built-in organ and every volume mesh of shared/data/meshes.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_io/mesh_io.h"
#include "tests/support/mesh_fixtures.h"
#include "tests/support/run_program.h"
#include "tests/support/sanitizer.h"

namespace somasim::solve {
namespace {

testing::ToolRun RunSolveTool(const std::string& args) {
  return testing::RunProgram("somasim-solve", args);
}

// The JSON object the tool prints (after any progress on stderr, which RunProgram appends).
nlohmann::json JsonOf(const testing::ToolRun& run) {
  const size_t start = run.out.find('{');
  if (start == std::string::npos) return {};
  return nlohmann::json::parse(run.out.substr(start), nullptr, false);
}

void ExpectSolved(const testing::ToolRun& run, const std::string& what) {
  ASSERT_EQ(run.status, 0) << what << "\n" << run.out;
  const nlohmann::json j = JsonOf(run);
  for (const char* key : {"max_displacement_m", "newton_iterations", "final_residual",
                          "wall_time_s", "converged", "organs"}) {
    EXPECT_TRUE(j.contains(key)) << what << ": no " << key;
  }
  EXPECT_TRUE(j.value("converged", false)) << what;
  const double u = j.value("max_displacement_m", -1.0);
  EXPECT_GT(u, 0.0) << what;
  EXPECT_TRUE(std::isfinite(u)) << what;
}

TEST(SomasimSolve, BuiltinSceneWritesVtuAndPrintsTheSpecKeys) {
  const std::string dir = testing::MakeTempDir("solve_tool");
  const testing::ToolRun run = RunSolveTool("builtin:liver288 --out " + dir + "/out");
  ExpectSolved(run, "liver288");
  const nlohmann::json j = JsonOf(run);
  EXPECT_GT(j.value("newton_iterations", 0), 0);
  EXPECT_LT(j.value("final_residual", 1.0), 1e-8);
  EXPECT_EQ(j["organs"][0]["nodes"], 288);
  EXPECT_TRUE(std::filesystem::exists(dir + "/out/liver288_0.vtu"));
  EXPECT_TRUE(std::filesystem::exists(dir + "/out/liver288_history.csv"));
}

// One test per organ and per shared mesh, so that ctest -j runs them side by side.
std::vector<std::string> BuiltinOrganNameList() {
  std::vector<std::string> names;
  for (const mesh_gen::BuiltinOrganSpec& spec : mesh_gen::BuiltinOrganSpecs()) {
    names.emplace_back(spec.name);
  }
  return names;
}

class SolvesBuiltinOrgan : public ::testing::TestWithParam<std::string> {};

TEST_P(SolvesBuiltinOrgan, WithItsDefaultScene) {
  const mesh_gen::BuiltinOrganSpec* spec = mesh_gen::FindBuiltinOrgan(GetParam());
  ASSERT_NE(spec, nullptr);
  // The large organs take seconds each: Release only (the sanitizer build checks the rest).
  if (testing::kUnderSanitizer && spec->num_nodes > 1000) GTEST_SKIP() << "large organ";
  const std::string dir = testing::MakeTempDir("solve_builtin_" + GetParam());
  ExpectSolved(RunSolveTool("builtin:" + GetParam() + " --out " + dir), GetParam());
}

INSTANTIATE_TEST_SUITE_P(SomasimSolve, SolvesBuiltinOrgan,
                         ::testing::ValuesIn(BuiltinOrganNameList()),
                         [](const ::testing::TestParamInfo<std::string>& organ) {
                           return organ.param;
                         });

// None is in metres (shared/data/meshes/README.md): liver.msh's OBJ twin says centimetres; the
// Armadillo and the raptor, in arbitrary units, are taken as millimetres. Those two have
// slivers (dihedral angles down to 0.6°) and pieces joined at single edges, which swing almost
// freely under their weight: a static solve needs hundreds of Newton iterations
// (docs/solve.md), so here they run 50 ms of dynamics; the well-formed meshes a static solve.
struct SharedMeshCase {
  const char* file;
  const char* unit;
  const char* analysis;
};

class SolvesSharedVolumeMesh : public ::testing::TestWithParam<SharedMeshCase> {};

TEST_P(SolvesSharedVolumeMesh, RestingUnderItsWeight) {
  const SharedMeshCase& c = GetParam();
  mesh_io::ReadOptions read;
  read.unit = *mesh_io::ParseUnit(c.unit);
  const mesh_io::MeshData data = mesh_io::ReadMeshFile(testing::SharedMesh(c.file), read);
  ASSERT_GT(data.tetrahedra.cols(), 0) << c.file;
  // As the built-in organs' default scene: resting on the lowest 10 % of its height, under
  // gravity, E = max(5 kPa, 20 ρ g L).
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(data.vertices);
  const double held = box.min.z() + 0.1 * (box.max.z() - box.min.z());
  const double e = std::max(5e3, 20.0 * 1000.0 * 9.81 * (box.max - box.min).maxCoeff());
  const std::string dir = testing::MakeTempDir("solve_shared");
  const std::string scene = dir + "/s.scene.txtpb";
  testing::WriteBytes(scene, "format_version: 1\nname: \"" + std::string(c.file) +
                                 "\"\norgan {\n  id: \"o\"\n  file: \"" +
                                 testing::SharedMesh(c.file) + "\"\n  unit: \"" + c.unit +
                                 "\"\n  model { fem_corotational {} dt: 0.005 }\n"
                                 "  material { density: 1000 youngs_modulus: " +
                                 std::to_string(e) +
                                 " poisson_ratio: 0.45 rayleigh_mass: 10 }\n"
                                 "  fixed { box { min { x: -10 y: -10 z: -10 } max { x: 10 "
                                 "y: 10 z: " +
                                 std::to_string(held) + " } } }\n}\ngravity { z: -9.81 }\n" +
                                 "analysis { " + c.analysis + " }\n");
  const testing::ToolRun run = RunSolveTool(scene + " --out " + dir + "/out");
  ExpectSolved(run, c.file);
  const nlohmann::json j = JsonOf(run);
  EXPECT_EQ(j["organs"][0]["nodes"], data.vertices.cols()) << c.file;
  EXPECT_TRUE(std::filesystem::exists(dir + "/out/o_0.vtu")) << c.file;
}

INSTANTIATE_TEST_SUITE_P(SomasimSolve, SolvesSharedVolumeMesh,
                         ::testing::Values(SharedMeshCase{"liver.msh", "cm", "static_solve {}"},
                                           SharedMeshCase{"liver2.msh", "cm", "static_solve {}"},
                                           SharedMeshCase{"msh4_cube.msh", "cm", "static_solve {}"},
                                           SharedMeshCase{"Armadillo_Tetra_4406.vtu", "mm",
                                                          "dynamic { end_time: 0.05 }"},
                                           SharedMeshCase{"raptorTetra_8418.vtu", "mm",
                                                          "dynamic { end_time: 0.05 }"}),
                         [](const ::testing::TestParamInfo<SharedMeshCase>& mesh) {
                           std::string name = mesh.param.file;
                           std::replace_if(
                               name.begin(), name.end(), [](char ch) { return !std::isalnum(ch); },
                               '_');
                           return name;
                         });

TEST(SomasimSolve, ExitCodesNameTheFault) {
  const std::string dir = testing::MakeTempDir("solve_tool_faults");
  // A bad scene: 3, with file, line and field.
  testing::WriteBytes(dir + "/bad.scene.txtpb",
                      "format_version: 1\norgan {\n  id: \"o\"\n  builtin: \"liver288\"\n"
                      "  model { fem_linear {} }\n  material { density: -1 }\n}\n");
  testing::ToolRun run = RunSolveTool(dir + "/bad.scene.txtpb --out " + dir);
  EXPECT_EQ(run.status, 3) << run.out;
  EXPECT_TRUE(testing::Contains(run.out, "bad.scene.txtpb:6: organ[0].material.density"))
      << run.out;
  // A broken mesh file: 3, naming the file.
  testing::WriteBytes(dir + "/broken.scene.txtpb",
                      "format_version: 1\norgan {\n  id: \"o\"\n  file: \"" +
                          testing::SharedMesh("Armadillo_Tetra_4406_for_test_broken.vtu") +
                          "\"\n  model { fem_linear {} }\n"
                          "  material { density: 1 youngs_modulus: 1 poisson_ratio: 0.3 }\n}\n"
                          "analysis { static_solve {} }\n");
  run = RunSolveTool(dir + "/broken.scene.txtpb --out " + dir);
  EXPECT_EQ(run.status, 3) << run.out;
  EXPECT_TRUE(testing::Contains(run.out, "Armadillo_Tetra_4406_for_test_broken.vtu")) << run.out;
  // No such scene: 4. Unknown organ: 3. Bad command line: 2.
  run = RunSolveTool(dir + "/missing.scene.txtpb --out " + dir);
  EXPECT_EQ(run.status, 4) << run.out;
  EXPECT_TRUE(testing::Contains(run.out, "missing.scene.txtpb")) << run.out;
  run = RunSolveTool("builtin:heart9 --out " + dir);
  EXPECT_EQ(run.status, 3) << run.out;
  EXPECT_TRUE(testing::Contains(run.out, "heart9")) << run.out;
  EXPECT_EQ(RunSolveTool("builtin:liver288").status, 2);
  EXPECT_EQ(RunSolveTool("").status, 2);
}

}  // namespace
}  // namespace somasim::solve
