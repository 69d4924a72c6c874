// Read → write → read through every format and encoding preserves a mesh: the same index
// arrays (topology bit-for-bit) and coordinates to the precision the format stores.
#include <gtest/gtest.h>

#include <limits>
#include <string>
#include <vector>

#include "common/mesh/topology.h"
#include "common/mesh_io/mesh_io.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

struct Target {
  std::string name;       // test label
  std::string extension;  // chooses the format
  WriteOptions options;
  bool float32 = false;  // coordinates stored as float32
  bool surface_only = false;
  bool renumbers = false;  // STL: nodes come back in order of first appearance
};

std::vector<Target> AllTargets() {
  std::vector<Target> t;
  const auto add = [&](std::string name, std::string ext, WriteOptions o, bool f32, bool surf,
                       bool renum) {
    t.push_back({std::move(name), std::move(ext), o, f32, surf, renum});
  };
  WriteOptions ascii, binary;
  binary.encoding = Encoding::kBinary;
  add("obj", ".obj", ascii, false, true, false);
  add("stl_ascii", ".stl", ascii, false, true, true);
  add("stl_binary", ".stl", binary, true, true, true);
  add("vtk_ascii", ".vtk", ascii, false, false, false);
  add("vtk_binary", ".vtk", binary, false, false, false);
  add("vtu_ascii", ".vtu", ascii, false, false, false);
  add("vtu_appended_raw", ".vtu", binary, false, false, false);
  WriteOptions b64 = binary;
  b64.vtu_base64 = true;
  add("vtu_base64", ".vtu", b64, false, false, false);
  WriteOptions big = binary;
  big.big_endian = true;
  add("vtu_appended_big_endian", ".vtu", big, false, false, false);
  for (GmshVersion v : {GmshVersion::kV1, GmshVersion::kV22, GmshVersion::kV41}) {
    for (Encoding e : {Encoding::kAscii, Encoding::kBinary}) {
      if (v == GmshVersion::kV1 && e == Encoding::kBinary) continue;
      WriteOptions o;
      o.gmsh_version = v;
      o.encoding = e;
      const std::string vname = v == GmshVersion::kV1 ? "1" : v == GmshVersion::kV22 ? "22" : "41";
      add("msh" + vname + (e == Encoding::kAscii ? "_ascii" : "_binary"), ".msh", o, false, false,
          false);
    }
  }
  add("tetgen", ".node", ascii, false, false, false);
  return t;
}

// What a surface-only format gives back for a mesh: the boundary (volume) or the triangles,
// without unreferenced nodes.
MeshData SurfaceView(const MeshData& m) {
  MeshData s;
  mesh::SurfaceMesh surface = m.tetrahedra.cols() > 0
                                  ? mesh::ExtractBoundarySurface({m.vertices, m.tetrahedra})
                                  : mesh::SurfaceMesh{m.vertices, m.triangles};
  surface = mesh::CompactSurface(surface, nullptr);
  s.vertices = surface.vertices;
  s.triangles = surface.triangles;
  s.tetrahedra.resize(4, 0);
  return s;
}

void CheckRoundTrip(const MeshData& original, const std::string& label) {
  const std::string dir = testing::MakeTempDir("somasim-roundtrip");
  for (const Target& target : AllTargets()) {
    SCOPED_TRACE(label + " via " + target.name);
    const std::string path = dir + "/" + target.name + target.extension;
    ASSERT_NO_THROW(WriteMeshFile(path, original, target.options));
    MeshData back;
    ASSERT_NO_THROW(back = ReadMeshFile(path, {}));
    const MeshData expected = target.surface_only ? SurfaceView(original) : original;
    // float32 keeps ~7 digits: the largest coordinate here is 1 m.
    const double tol = target.float32 ? 1e-7 : 0.0;
    if (target.renumbers) {
      EXPECT_TRUE(testing::SameMeshUpToVertexOrder(expected, back, tol));
    } else {
      EXPECT_TRUE(testing::SameMesh(expected, back, tol));
    }
    // And once more: what we wrote and read back writes and reads identically again.
    const std::string again = dir + "/again_" + target.name + target.extension;
    ASSERT_NO_THROW(WriteMeshFile(again, back, target.options));
    EXPECT_TRUE(testing::SameMesh(back, ReadMeshFile(again, {}), 0.0));
  }
}

TEST(RoundTrip, VolumeMeshWithBoundaryTrianglesSurvivesEveryFormat) {
  mesh_io::MeshData box = testing::BoxTets(3, 2, 2, 0.3, 0.2, 0.1);
  box.vertices.colwise() += Eigen::Vector3d(-0.123456789012345, 0.1, 1.0 / 3.0);
  CheckRoundTrip(box, "BoxTets");
}

TEST(RoundTrip, ClosedSurfaceSurvivesEveryFormat) {
  CheckRoundTrip(testing::BoxSurface(2, 3, 1), "BoxSurface");
}

TEST(RoundTrip, OpenPatchSurvivesEveryFormat) {
  CheckRoundTrip(testing::SquarePatch(4), "SquarePatch");
}

TEST(RoundTrip, OutputUnitScalesCoordinates) {
  const std::string dir = testing::MakeTempDir("somasim-units");
  const MeshData box = testing::BoxTets(1, 1, 1, 0.02, 0.03, 0.04);
  WriteOptions mm;
  mm.unit = Unit::kMillimetre;
  WriteMeshFile(dir + "/box.vtu", box, mm);
  ReadOptions read_mm;
  read_mm.unit = Unit::kMillimetre;
  EXPECT_TRUE(testing::SameMesh(box, ReadMeshFile(dir + "/box.vtu", read_mm), 1e-15));
  const MeshData raw = ReadMeshFile(dir + "/box.vtu", {});  // numbers as written: millimetres
  EXPECT_NEAR(raw.vertices.row(2).maxCoeff(), 40.0, 1e-12);
}

}  // namespace
}  // namespace somasim::mesh_io
