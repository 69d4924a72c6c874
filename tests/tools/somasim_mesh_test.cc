// somasim-mesh: what `info`, `convert`, `tetrahedralize`, `list` and `generate` print and
// return, in-process and through the real executable (exit codes, JSON keys of SPEC §6).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <sstream>

#include "common/mesh/quality.h"
#include "common/mesh/topology.h"
#include "common/mesh_io/mesh_io.h"
#include "common/tools/mesh_commands.h"
#include "tests/support/mesh_fixtures.h"
#include "tests/support/run_program.h"

namespace somasim::tools {
namespace {

using testing::ToolRun;

// Runs build/bin/somasim-mesh with arguments (quoted by the caller).
ToolRun RunTool(const std::string& args) { return testing::RunProgram("somasim-mesh", args); }

TEST(SomasimMeshInfo, JsonHasTheSpecKeysInMetres) {
  const ToolRun run = RunTool("info --json --unit cm " + testing::SharedMesh("liver.msh"));
  ASSERT_EQ(run.status, 0) << run.out;
  const nlohmann::json j = nlohmann::json::parse(run.out);
  for (const char* key : {"nodes", "tetrahedra", "triangles", "bbox_min", "bbox_max", "volume_m3",
                          "min_dihedral_deg", "watertight"}) {
    EXPECT_TRUE(j.contains(key)) << key;
  }
  EXPECT_EQ(j["nodes"], 181);
  EXPECT_EQ(j["tetrahedra"], 596);
  EXPECT_NEAR(j["bbox_min"][0].get<double>(), -0.0467928, 1e-9);
  EXPECT_NEAR(j["bbox_max"][1].get<double>(), 0.0515717, 1e-9);
  EXPECT_TRUE(j["watertight"].get<bool>());
  EXPECT_GT(j["volume_m3"].get<double>(), 0.0);
  EXPECT_GT(j["min_dihedral_deg"].get<double>(), 0.0);
  EXPECT_EQ(j["unit"], "cm");
}

TEST(SomasimMeshInfo, TextNamesCountsAndUnit) {
  const ToolRun run = RunTool("info " + testing::SharedMesh("liver.msh") + " --unit cm");
  ASSERT_EQ(run.status, 0) << run.out;
  EXPECT_NE(run.out.find("nodes 181"), std::string::npos) << run.out;
  EXPECT_NE(run.out.find("read as cm"), std::string::npos) << run.out;
}

TEST(SomasimMeshInfo, BrokenFileExitsThreeNamingFileAndFault) {
  const ToolRun run = RunTool("info " + testing::SharedMesh("6_tetra_bad.msh"));
  EXPECT_EQ(run.status, kExitBadInput) << run.out;
  EXPECT_NE(run.out.find("6_tetra_bad.msh:"), std::string::npos) << run.out;
  EXPECT_NE(run.out.find("duplicated"), std::string::npos) << run.out;
}

TEST(SomasimMeshInfo, MissingFileExitsFour) {
  EXPECT_EQ(RunTool("info /nonexistent/mesh.vtu").status, kExitIo);
}

TEST(SomasimMesh, BadCommandLinesExitTwo) {
  EXPECT_EQ(RunTool("").status, kExitUsage);
  EXPECT_EQ(RunTool("frobnicate x").status, kExitUsage);
  EXPECT_EQ(RunTool("info").status, kExitUsage);
  EXPECT_EQ(RunTool("info x.vtu --unit furlong").status, kExitUsage);
  EXPECT_EQ(RunTool("convert a.vtu b.msh --msh-version 3").status, kExitUsage);
  EXPECT_EQ(RunTool("--help").status, 0);
}

TEST(SomasimMeshConvert, ConvertsBetweenFormatsKeepingTheMesh) {
  const std::string dir = testing::MakeTempDir("somasim-convert");
  const ToolRun run = RunTool("convert --unit cm " + testing::SharedMesh("liver.msh") + " " + dir +
                              "/liver.vtu --binary");
  ASSERT_EQ(run.status, 0) << run.out;
  mesh_io::ReadOptions cm;
  cm.unit = mesh_io::Unit::kCentimetre;
  const mesh_io::MeshData original = mesh_io::ReadMeshFile(testing::SharedMesh("liver.msh"), cm);
  EXPECT_TRUE(testing::SameMesh(original, mesh_io::ReadMeshFile(dir + "/liver.vtu", {}), 0.0));
  // A surface format gets the boundary and says so.
  const ToolRun obj = RunTool("convert " + dir + "/liver.vtu " + dir + "/liver.obj");
  ASSERT_EQ(obj.status, 0) << obj.out;
  EXPECT_NE(obj.out.find("boundary surface"), std::string::npos) << obj.out;
}

TEST(SomasimMeshConvert, InvertedInputNeedsFixOrientation) {
  const std::string dir = testing::MakeTempDir("somasim-fix");
  mesh_io::MeshData box = testing::BoxTets(1, 1, 1);
  std::swap(box.tetrahedra(0, 2), box.tetrahedra(1, 2));
  // Write it unchecked through a format whose writer does not validate: ASCII VTU.
  mesh_io::WriteMeshFile(dir + "/bad.vtu", box, {});
  const ToolRun refused = RunTool("convert " + dir + "/bad.vtu " + dir + "/out.msh");
  EXPECT_EQ(refused.status, kExitBadInput) << refused.out;
  EXPECT_NE(refused.out.find("inverted"), std::string::npos) << refused.out;
  const ToolRun fixed =
      RunTool("convert --fix-orientation " + dir + "/bad.vtu " + dir + "/out.msh");
  EXPECT_EQ(fixed.status, 0) << fixed.out;
  EXPECT_EQ(mesh_io::ReadMeshFile(dir + "/out.msh", {}).tetrahedra.cols(), 6);
}

TEST(SomasimMeshTetrahedralize, FillsSofaLiverSurfaceWithPositiveTets) {
  const std::string dir = testing::MakeTempDir("somasim-tetra");
  InfoOptions info;
  std::ostringstream out, err;
  TetrahedralizeOptions options;
  options.input = testing::SharedMesh("liver.obj");
  options.read.unit = mesh_io::Unit::kCentimetre;
  options.output = dir + "/liver.vtu";
  ASSERT_EQ(RunTetrahedralize(options, out, err), kExitOk) << err.str();
  const mesh_io::MeshData volume = mesh_io::ReadMeshFile(options.output, {});
  EXPECT_GT(volume.tetrahedra.cols(), 100);
  // The volume fills the surface: same enclosed volume, same bounding box.
  mesh_io::ReadOptions cm;
  cm.unit = mesh_io::Unit::kCentimetre;
  const mesh_io::MeshData surface = mesh_io::ReadMeshFile(options.input, cm);
  info.file = options.output;
  info.json = true;
  std::ostringstream json;
  ASSERT_EQ(RunInfo(info, json, err), kExitOk);
  const nlohmann::json j = nlohmann::json::parse(json.str());
  EXPECT_TRUE(j["watertight"].get<bool>());
  EXPECT_GT(j["min_dihedral_deg"].get<double>(), 0.0);
  for (size_t k = 0; k < 3; ++k) {
    EXPECT_NEAR(j["bbox_min"][k].get<double>(),
                surface.vertices.row(static_cast<Eigen::Index>(k)).minCoeff(), 1e-12);
    EXPECT_NEAR(j["bbox_max"][k].get<double>(),
                surface.vertices.row(static_cast<Eigen::Index>(k)).maxCoeff(), 1e-12);
  }
}

TEST(SomasimMeshTetrahedralize, MaxVolumeBoundsEveryTetrahedron) {
  const std::string dir = testing::MakeTempDir("somasim-maxvol");
  TetrahedralizeOptions options;
  options.input = testing::SharedMesh("liver.obj");
  options.read.unit = mesh_io::Unit::kCentimetre;
  options.output = dir + "/liver.msh";
  options.max_volume_m3 = 2e-8;  // the liver holds 3.66e-5 m^3: at least ~1800 tetrahedra
  std::ostringstream out, err;
  ASSERT_EQ(RunTetrahedralize(options, out, err), kExitOk) << err.str();
  const mesh_io::MeshData volume = mesh_io::ReadMeshFile(options.output, {});
  EXPECT_GT(volume.tetrahedra.cols(), 1800);
  double largest = 0;
  for (Eigen::Index t = 0; t < volume.tetrahedra.cols(); ++t) {
    const Eigen::Vector3d a = volume.vertices.col(volume.tetrahedra(0, t));
    const Eigen::Vector3d b = volume.vertices.col(volume.tetrahedra(1, t));
    const Eigen::Vector3d c = volume.vertices.col(volume.tetrahedra(2, t));
    const Eigen::Vector3d d = volume.vertices.col(volume.tetrahedra(3, t));
    largest = std::max(largest, (b - a).dot((c - a).cross(d - a)) / 6);
  }
  // TetGen treats -a as a refinement target, not a hard cap: a few tets end slightly above it.
  EXPECT_LE(largest, 2e-8 * 1.1);
  EXPECT_NE(out.str().find("a2e-08"), std::string::npos) << out.str();
}

TEST(SomasimMeshTetrahedralize, BadBoundsAreUsageErrors) {
  TetrahedralizeOptions options;
  options.input = testing::SharedMesh("liver.obj");
  options.output = testing::MakeTempDir("somasim-bounds") + "/out.vtu";
  options.tetgen = "/nonexistent/tetgen";  // must not get that far
  std::ostringstream out, err;
  for (double ratio : {1.0, 0.5, -2.0, std::nan(""), std::numeric_limits<double>::infinity()}) {
    options.radius_edge_ratio = ratio;
    EXPECT_EQ(RunTetrahedralize(options, out, err), kExitUsage) << ratio;
  }
  options.radius_edge_ratio = 1.414;
  for (double volume : {-1e-9, std::nan(""), std::numeric_limits<double>::infinity()}) {
    options.max_volume_m3 = volume;
    EXPECT_EQ(RunTetrahedralize(options, out, err), kExitUsage) << volume;
  }
  EXPECT_EQ(RunTool("tetrahedralize x.obj y.vtu --quality abc").status, kExitUsage);
}

TEST(SomasimMeshTetrahedralize, OpenSurfaceIsRefusedBeforeRunningTetgen) {
  const std::string dir = testing::MakeTempDir("somasim-open");
  mesh_io::WriteMeshFile(dir + "/patch.obj", testing::SquarePatch(3), {});
  TetrahedralizeOptions options;
  options.input = dir + "/patch.obj";
  options.output = dir + "/out.vtu";
  options.tetgen = "/nonexistent/tetgen";  // must not get that far
  std::ostringstream out, err;
  EXPECT_EQ(RunTetrahedralize(options, out, err), kExitTetrahedralize);
  EXPECT_NE(err.str().find("not closed"), std::string::npos) << err.str();
}

TEST(SomasimMeshTetrahedralize, MissingTetgenProgramIsReported) {
  const std::string dir = testing::MakeTempDir("somasim-notetgen");
  mesh_io::WriteMeshFile(dir + "/box.stl", testing::BoxSurface(1, 1, 1), {});
  TetrahedralizeOptions options;
  options.input = dir + "/box.stl";
  options.output = dir + "/out.vtu";
  options.tetgen = "/nonexistent/tetgen";
  std::ostringstream out, err;
  EXPECT_EQ(RunTetrahedralize(options, out, err), kExitTetrahedralize);
  EXPECT_NE(err.str().find("/nonexistent/tetgen"), std::string::npos) << err.str();
  options.output = dir + "/out.obj";  // cannot hold tetrahedra
  EXPECT_EQ(RunTetrahedralize(options, out, err), kExitUsage);
}

}  // namespace
}  // namespace somasim::tools

namespace somasim::tools {
namespace {

TEST(SomasimMeshList, PrintsEveryOrganWithItsCounts) {
  const ToolRun run = RunTool("list");
  ASSERT_EQ(run.status, 0) << run.out;
  for (const char* line :
       {"liver4055 (liver)", "4055 nodes / 19403 tetrahedra", "liver288", "kidney424", "plate192",
        "192 nodes / 392 tetrahedra", "tissue45", "45 vertices / 66 triangles", "spleen600",
        "600 vertices / 1196", "kidney2000", "gallbladder5400 (gallbladder)", "beam19k"}) {
    EXPECT_NE(run.out.find(line), std::string::npos) << line << "\n" << run.out;
  }
  const ToolRun json = RunTool("list --json");
  ASSERT_EQ(json.status, 0) << json.out;
  const nlohmann::json j = nlohmann::json::parse(json.out);
  ASSERT_EQ(j.size(), 9u);
  EXPECT_EQ(j[0]["name"], "liver4055");
  EXPECT_EQ(j[0]["alias"], "liver");
  EXPECT_EQ(j[0]["target_tetrahedra"], 9126);
  EXPECT_EQ(j[5]["triangles"], 1196);
}

TEST(SomasimMeshInfo, BuiltinOrganIsReportedLikeAFile) {
  const ToolRun run = RunTool("info builtin:liver288 --json");
  ASSERT_EQ(run.status, 0) << run.out;
  const nlohmann::json j = nlohmann::json::parse(run.out);
  EXPECT_EQ(j["nodes"], 288);
  EXPECT_EQ(j["tetrahedra"], 1019);
  EXPECT_TRUE(j["watertight"].get<bool>());
  EXPECT_GE(j["min_dihedral_deg"].get<double>(), 10.0);
  EXPECT_NE(j["format"].get<std::string>().find("built-in"), std::string::npos);
}

TEST(SomasimMeshInfo, UnknownBuiltinExitsFourListingTheNames) {
  const ToolRun run = RunTool("info builtin:heart");
  EXPECT_EQ(run.status, kExitIo) << run.out;
  EXPECT_NE(run.out.find("heart"), std::string::npos) << run.out;
  EXPECT_NE(run.out.find("kidney424"), std::string::npos) << run.out;
  // Built-in organs are in metres: another unit is refused, not silently applied.
  EXPECT_EQ(RunTool("info builtin:plate192 --unit mm").status, kExitBadInput);
}

TEST(SomasimMeshGenerate, WritesEveryFormatThatReadsBackTheSameMesh) {
  const std::string dir = testing::MakeTempDir("somasim-generate");
  const mesh_io::MeshData organ = LoadMesh("builtin:kidney424", {});
  for (const char* name : {"k.vtu", "k.vtk", "k.msh", "k.node"}) {
    const ToolRun run = RunTool("generate kidney424 " + dir + "/" + name);
    ASSERT_EQ(run.status, 0) << name << ": " << run.out;
    EXPECT_TRUE(testing::SameMesh(organ, mesh_io::ReadMeshFile(dir + "/" + name, {}), 0.0)) << name;
  }
  // Surface formats and --surface get the boundary; surface organs write their triangles.
  ASSERT_EQ(RunTool("generate kidney424 " + dir + "/k.obj").status, 0);
  const mesh_io::MeshData obj = mesh_io::ReadMeshFile(dir + "/k.obj", {});
  EXPECT_EQ(obj.triangles.cols(),
            mesh::ExtractBoundarySurface({organ.vertices, organ.tetrahedra}).triangles.cols());
  ASSERT_EQ(RunTool("generate kidney424 --surface " + dir + "/ks.vtu").status, 0);
  const mesh_io::MeshData surface = mesh_io::ReadMeshFile(dir + "/ks.vtu", {});
  EXPECT_EQ(surface.tetrahedra.cols(), 0);
  EXPECT_EQ(surface.triangles.cols(), obj.triangles.cols());
  ASSERT_EQ(RunTool("generate tissue45 " + dir + "/t.stl --out-unit mm").status, 0);
  mesh_io::ReadOptions mm;
  mm.unit = mesh_io::Unit::kMillimetre;
  EXPECT_EQ(mesh_io::ReadMeshFile(dir + "/t.stl", mm).triangles.cols(), 66);
}

TEST(SomasimMeshGenerate, BadNamesAndOutputsExitTwo) {
  const std::string dir = testing::MakeTempDir("somasim-generate-bad");
  const ToolRun unknown = RunTool("generate heart " + dir + "/h.vtu");
  EXPECT_EQ(unknown.status, kExitUsage) << unknown.out;
  EXPECT_NE(unknown.out.find("liver4055 (liver)"), std::string::npos) << unknown.out;
  EXPECT_EQ(RunTool("generate liver " + dir + "/h.xyz").status, kExitUsage);
  EXPECT_EQ(RunTool("generate tissue45 --volume " + dir + "/t.vtu").status, kExitUsage);
  EXPECT_EQ(RunTool("generate spleen600 --volume --surface " + dir + "/t.vtu").status, kExitUsage);
  EXPECT_EQ(RunTool("generate liver").status, kExitUsage);
  EXPECT_EQ(RunTool("generate liver /nonexistent/dir/l.vtu").status, kExitIo);
}

TEST(SomasimMeshGenerate, SurfaceOrganAsAVolumeHasGoodAngles) {
  const std::string dir = testing::MakeTempDir("somasim-generate-volume");
  ASSERT_EQ(RunTool("generate spleen600 --volume " + dir + "/s.vtu").status, 0);
  const mesh_io::MeshData volume = mesh_io::ReadMeshFile(dir + "/s.vtu", {});
  EXPECT_GT(volume.tetrahedra.cols(), 0);
  EXPECT_GE(mesh::SummariseQuality({volume.vertices, volume.tetrahedra}).min_dihedral_deg, 10.7);
}

TEST(SomasimMeshTetrahedralize, SurfaceOrganIsTetrahedralisedOnRequest) {
  const std::string dir = testing::MakeTempDir("somasim-tet-builtin");
  const ToolRun run = RunTool("tetrahedralize builtin:spleen600 " + dir + "/spleen.vtu");
  ASSERT_EQ(run.status, 0) << run.out;
  const mesh_io::MeshData volume = mesh_io::ReadMeshFile(dir + "/spleen.vtu", {});
  EXPECT_GT(volume.tetrahedra.cols(), 1196);
  const mesh::SurfaceMesh boundary = mesh::CompactSurface(
      mesh::ExtractBoundarySurface({volume.vertices, volume.tetrahedra}), nullptr);
  EXPECT_TRUE(mesh::AnalyseSurfaceTopology(boundary).watertight);
}

}  // namespace
}  // namespace somasim::tools

namespace somasim::tools {
namespace {

TEST(SomasimMeshRender, DrawsABuiltinOrganAndRefusesBadOptions) {
  const std::string dir = testing::MakeTempDir("somasim-render-cli");
  const ToolRun run = RunTool("render builtin:plate192 " + dir +
                              "/plate.png --size 64x48 --view=0.3,0.6,-1 --up 0,1,0 --no-edges");
  ASSERT_EQ(run.status, 0) << run.out;
  const std::string png = testing::Slurp(dir + "/plate.png");
  ASSERT_GT(png.size(), 24u);
  EXPECT_EQ(png.substr(1, 3), "PNG");
  for (const char* bad : {"--size 64x", "--size 0x10", "--size 9000x10", "--view=1,2",
                          "--view=0,0,0", "--up 0,0,0", "--up 1,nan,0"}) {
    const ToolRun refused =
        RunTool("render builtin:plate192 " + dir + "/bad.png " + std::string(bad));
    EXPECT_EQ(refused.status, kExitUsage) << bad << ": " << refused.out;
  }
  EXPECT_EQ(RunTool("render builtin:heart " + dir + "/h.png").status, kExitIo);
}

// TetGen's scratch folder is removed however the command ends: TetGen failing, or writing
// output that cannot be read (a stand-in program for each).
TEST(SomasimMeshTetrahedralize, LeavesNoScratchFolderWhenTetgenFailsOrWritesGarbage) {
  const std::string dir = testing::MakeTempDir("somasim-tetgen-scratch");
  const std::string scratch_parent = dir + "/tmp";
  std::filesystem::create_directories(scratch_parent);
  mesh_io::WriteMeshFile(dir + "/box.stl", testing::BoxSurface(1, 1, 1), {});
  const std::string garbage = dir + "/garbage-tetgen.sh", failing = dir + "/failing-tetgen.sh";
  // Called as `tetgen SWITCHES DIR/surface.smesh`: writes a truncated DIR/surface.1.node.
  std::ofstream(garbage) << "#!/bin/sh\nprintf '8 3 0 0\\n0 0 0' > \"${2%.smesh}.1.node\"\n";
  std::ofstream(failing) << "#!/bin/sh\necho 'tetgen: cannot mesh' >&2\nexit 1\n";
  std::filesystem::permissions(garbage, std::filesystem::perms::owner_all);
  std::filesystem::permissions(failing, std::filesystem::perms::owner_all);
  const char* old_tmpdir = std::getenv("TMPDIR");
  const std::string saved = old_tmpdir != nullptr ? old_tmpdir : "";
  setenv("TMPDIR", scratch_parent.c_str(), 1);
  TetrahedralizeOptions options;
  options.input = dir + "/box.stl";
  options.output = dir + "/out.vtu";
  std::ostringstream out, err;
  options.tetgen = garbage;
  const int garbage_status = RunTetrahedralize(options, out, err);
  options.tetgen = failing;
  const int failing_status = RunTetrahedralize(options, out, err);
  if (old_tmpdir != nullptr) {
    setenv("TMPDIR", saved.c_str(), 1);
  } else {
    unsetenv("TMPDIR");
  }
  EXPECT_NE(garbage_status, kExitOk) << err.str();
  EXPECT_EQ(failing_status, kExitTetrahedralize) << err.str();
  EXPECT_NE(err.str().find("surface.1.node"), std::string::npos) << err.str();
  EXPECT_NE(err.str().find("tetgen: cannot mesh"), std::string::npos) << err.str();
  EXPECT_TRUE(std::filesystem::is_empty(scratch_parent))
      << std::filesystem::directory_iterator(scratch_parent)->path();
}

}  // namespace
}  // namespace somasim::tools
