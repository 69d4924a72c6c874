// Reading and writing by file name: format from the extension, I/O errors, TetGen's sibling
// files, surface-only formats given a volume.
#include "common/mesh_io/mesh_io.h"

#include <gtest/gtest.h>

#include <filesystem>

#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

MeshErrorKind KindOfRead(const std::string& path) {
  try {
    ReadMeshFile(path, {});
  } catch (const MeshError& e) {
    EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
    return e.kind();
  }
  ADD_FAILURE() << "no error reading " << path;
  return MeshErrorKind::kSyntax;
}

TEST(MeshIo, FormatComesFromTheExtension) {
  EXPECT_EQ(FormatFromPath("a/b/Liver.MSH"), FileFormat::kGmsh);
  EXPECT_EQ(FormatFromPath("x.vtu"), FileFormat::kVtu);
  EXPECT_EQ(FormatFromPath("x.vtk"), FileFormat::kVtkLegacy);
  EXPECT_EQ(FormatFromPath("x.obj"), FileFormat::kObj);
  EXPECT_EQ(FormatFromPath("x.stl"), FileFormat::kStl);
  EXPECT_EQ(FormatFromPath("x.1.ele"), FileFormat::kTetGen);
  EXPECT_FALSE(FormatFromPath("x.ply").has_value());
  EXPECT_FALSE(FormatFromPath("noext").has_value());
  EXPECT_TRUE(FormatHoldsTetrahedra(FileFormat::kVtu));
  EXPECT_FALSE(FormatHoldsTetrahedra(FileFormat::kStl));
}

TEST(MeshIo, MissingFileDirectoryAndUnknownExtensionAreRefused) {
  const std::string dir = testing::MakeTempDir("somasim-meshio");
  EXPECT_EQ(KindOfRead(dir + "/absent.vtu"), MeshErrorKind::kIo);
  std::filesystem::create_directory(dir + "/folder.msh");
  EXPECT_EQ(KindOfRead(dir + "/folder.msh"), MeshErrorKind::kIo);
  testing::WriteBytes(dir + "/mesh.ply", "ply\n");
  EXPECT_EQ(KindOfRead(dir + "/mesh.ply"), MeshErrorKind::kUnsupported);
  EXPECT_THROW(WriteMeshFile(dir + "/out.xyz", testing::RegularTet(), {}), MeshError);
  EXPECT_THROW(WriteMeshFile(dir + "/no/such/dir/out.vtu", testing::RegularTet(), {}), MeshError);
}

TEST(MeshIo, EmptyFileIsRefusedByEveryFormat) {
  const std::string dir = testing::MakeTempDir("somasim-empty");
  for (const char* ext : {".obj", ".stl", ".vtk", ".vtu", ".msh", ".node"}) {
    const std::string path = dir + "/empty" + ext;
    testing::WriteBytes(path, "");
    EXPECT_NE(KindOfRead(path), MeshErrorKind::kIo) << ext;
  }
}

TEST(MeshIo, TetGenIsReadFromAnyOfItsFiles) {
  const std::string dir = testing::MakeTempDir("somasim-tetgen");
  const MeshData box = testing::BoxTets(2, 1, 1);
  const WriteReport report = WriteMeshFile(dir + "/box.node", box, {});
  EXPECT_NE(report.files.find("box.ele"), std::string::npos);
  for (const char* name : {"/box.node", "/box.ele", "/box.face"}) {
    EXPECT_TRUE(testing::SameMesh(box, ReadMeshFile(dir + name, {}), 0.0)) << name;
  }
  std::filesystem::remove(dir + "/box.ele");
  EXPECT_EQ(KindOfRead(dir + "/box.ele"), MeshErrorKind::kIo);
  const MeshData surface_only = ReadMeshFile(dir + "/box.node", {});
  EXPECT_EQ(surface_only.tetrahedra.cols(), 0);
  EXPECT_EQ(surface_only.triangles.cols(), box.triangles.cols());
}

TEST(MeshIo, SurfaceFormatsGetTheBoundaryOfAVolume) {
  const std::string dir = testing::MakeTempDir("somasim-boundary");
  MeshData box = testing::BoxTets(2, 2, 2);
  box.triangles.resize(3, 0);
  const WriteReport report = WriteMeshFile(dir + "/box.obj", box, {});
  EXPECT_TRUE(report.wrote_boundary_surface);
  const MeshData back = ReadMeshFile(dir + "/box.obj", {});
  EXPECT_EQ(back.vertices.cols(), 26);  // the centre node is dropped
  EXPECT_EQ(back.triangles.cols(), 6 * 8);
  EXPECT_EQ(back.tetrahedra.cols(), 0);
}

TEST(MeshIo, ReadMeshBytesMatchesReadMeshFile) {
  const std::string dir = testing::MakeTempDir("somasim-bytes");
  const MeshData box = testing::BoxTets(1, 2, 1);
  WriteMeshFile(dir + "/box.msh", box, {});
  const std::string bytes = testing::Slurp(dir + "/box.msh");
  EXPECT_TRUE(testing::SameMesh(ReadMeshFile(dir + "/box.msh", {}),
                                ReadMeshBytes(FileFormat::kGmsh, bytes, "box.msh", {}), 0.0));
}

}  // namespace
}  // namespace somasim::mesh_io
