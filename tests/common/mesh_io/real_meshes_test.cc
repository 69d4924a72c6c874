// SOFA's real mesh files (shared/data/meshes, see its README): every good one is read with the
// right counts and bounding box, every broken one is refused naming its fault, and every good
// one survives a round trip through every format that can hold it.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <iterator>
#include <set>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_io/mesh_io.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

struct GoodFile {
  std::string name;
  int64_t nodes, tetrahedra, triangles;
  Eigen::Vector3d bbox_min, bbox_max;  // as stored in the file (its own unit)
  std::vector<SkippedElements> skipped;
};

std::vector<GoodFile> GoodFiles() {
  return {
      {"liver.msh", 181, 596, 0, {-4.67928, 0.217888, -1.69285}, {1.80331, 5.15717, 2.72858}, {}},
      {"liver2.msh",
       507,
       1493,
       860,
       {-1.201153028242965, -0.5328919162107728, -0.8494964736010371},
       {0.9429998926873655, 0.633438647741628, 0.4591514020437499},
       {{"line", 71}}},
      {"msh4_cube.msh", 14, 24, 24, {0, 0, 0}, {1, 1, 1}, {{"point", 8}, {"line", 12}}},
      {"liver.obj", 181, 0, 274, {-4.67928, 0.217888, -1.69285}, {1.80331, 5.15717, 2.72858}, {}},
      {"liver-smooth.obj", 2194, 0, 4384, {-4.658, 0.264, -1.674}, {1.728, 5.172, 2.738}, {}},
      {"liver.vtk", 5008, 0, 10000, {25.7094, 60.8448, 43.5186}, {219.984, 214.55, 200.0}, {}},
      {"Armadillo_Tetra_4406.vtu",
       1446,
       4406,
       0,
       {-6.33702, -5.40248, -5.76189},
       {6.33169, 9.69253, 5.76059},
       {}},
      {"raptorTetra_8418.vtu",
       2996,
       8418,
       0,
       {-2.11393, -0.247808, -9.13365},
       {2.10897, 6.97908, 6.88252},
       {}},
  };
}

TEST(RealMeshes, GoodFilesReadWithTheirCountsAndBoundingBox) {
  for (const GoodFile& f : GoodFiles()) {
    SCOPED_TRACE(f.name);
    MeshData m;
    ASSERT_NO_THROW(m = ReadMeshFile(testing::SharedMesh(f.name), {}));
    EXPECT_EQ(m.vertices.cols(), f.nodes);
    EXPECT_EQ(m.tetrahedra.cols(), f.tetrahedra);
    EXPECT_EQ(m.triangles.cols(), f.triangles);
    EXPECT_EQ(m.num_flipped, 0);
    ASSERT_EQ(m.skipped.size(), f.skipped.size());
    for (size_t i = 0; i < f.skipped.size(); ++i) {
      EXPECT_EQ(m.skipped[i].type, f.skipped[i].type);
      EXPECT_EQ(m.skipped[i].count, f.skipped[i].count);
    }
    if (f.bbox_min != f.bbox_max) {
      const mesh::BoundingBox box = mesh::ComputeBoundingBox(m.vertices);
      const double tol = 2e-3 * (f.bbox_max - f.bbox_min).maxCoeff();
      for (int k = 0; k < 3; ++k) {
        EXPECT_NEAR(box.min[k], f.bbox_min[k], tol) << "axis " << k;
        EXPECT_NEAR(box.max[k], f.bbox_max[k], tol) << "axis " << k;
      }
    }
  }
}

TEST(RealMeshes, UnitOptionScalesToMetres) {
  ReadOptions cm;
  cm.unit = Unit::kCentimetre;
  const MeshData m = ReadMeshFile(testing::SharedMesh("liver.msh"), cm);
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(m.vertices);
  EXPECT_NEAR(box.min[0], -0.0467928, 1e-9);
  EXPECT_NEAR(box.max[1], 0.0515717, 1e-9);
  // About 6.5 cm wide: SOFA's toy-scale liver (the README's reading).
  EXPECT_NEAR((box.max - box.min)[0], 0.0648, 1e-3);
}

TEST(RealMeshes, VolumeMeshesAreValidSolids) {
  for (const char* name : {"liver.msh", "liver2.msh", "msh4_cube.msh", "Armadillo_Tetra_4406.vtu",
                           "raptorTetra_8418.vtu"}) {
    SCOPED_TRACE(name);
    const MeshData m = ReadMeshFile(testing::SharedMesh(name), {});
    const mesh::TetMesh volume{m.vertices, m.tetrahedra};
    const mesh::SurfaceMesh boundary = mesh::ExtractBoundarySurface(volume);
    const mesh::SurfaceTopology topo = mesh::AnalyseSurfaceTopology(boundary);
    EXPECT_EQ(topo.num_boundary_edges, 0);  // closed
    // The raptor's boundary pinches along 9 edges (four triangles meet there), a quirk of the
    // file; every other volume mesh has a closed two-manifold-edged boundary.
    EXPECT_EQ(topo.num_nonmanifold_edges, std::string(name) == "raptorTetra_8418.vtu" ? 9 : 0);
    // The boundary encloses exactly the tetrahedra's volume (divergence theorem).
    const double v = mesh::TetMeshVolume(volume);
    EXPECT_GT(v, 0);
    EXPECT_NEAR(mesh::SurfaceEnclosedVolume(boundary), v, 1e-9 * v);
  }
  const MeshData cube = ReadMeshFile(testing::SharedMesh("msh4_cube.msh"), {});
  EXPECT_NEAR(mesh::TetMeshVolume({cube.vertices, cube.tetrahedra}), 1.0, 1e-12);
}

// liver.obj is the surface of liver.msh (the README says so): the boundary of the volume mesh
// and the OBJ's triangles are the same triangles in space, but for one spot where the .msh has
// a boundary node of three triangles that the OBJ covers with a single triangle (276 vs 274).
TEST(RealMeshes, LiverObjIsTheBoundaryOfLiverMsh) {
  const MeshData volume = ReadMeshFile(testing::SharedMesh("liver.msh"), {});
  const MeshData obj = ReadMeshFile(testing::SharedMesh("liver.obj"), {});
  const mesh::SurfaceMesh boundary =
      mesh::ExtractBoundarySurface({volume.vertices, volume.tetrahedra});
  using Corner = std::array<double, 3>;
  using Tri = std::array<Corner, 3>;
  const auto triangle_set = [](const mesh::Points& p, const mesh::Triangles& t) {
    std::set<Tri> set;
    for (Eigen::Index i = 0; i < t.cols(); ++i) {
      Tri tri;
      for (int k = 0; k < 3; ++k) {
        // Rounded to 1e-4 file units: the OBJ prints fewer digits than the .msh.
        for (int d = 0; d < 3; ++d) {
          tri[static_cast<size_t>(k)][static_cast<size_t>(d)] =
              std::round(p(d, t(k, i)) * 1e4) / 1e4;
        }
      }
      std::sort(tri.begin(), tri.end());
      set.insert(tri);
    }
    return set;
  };
  const std::set<Tri> a = triangle_set(boundary.vertices, boundary.triangles);
  const std::set<Tri> b = triangle_set(obj.vertices, obj.triangles);
  EXPECT_EQ(a.size(), static_cast<size_t>(boundary.triangles.cols()));
  std::vector<Tri> only_in_obj, only_in_msh;
  std::set_difference(b.begin(), b.end(), a.begin(), a.end(), std::back_inserter(only_in_obj));
  std::set_difference(a.begin(), a.end(), b.begin(), b.end(), std::back_inserter(only_in_msh));
  ASSERT_EQ(only_in_obj.size(), 1u);
  ASSERT_EQ(only_in_msh.size(), 3u);
  // The three .msh triangles share one corner, and their other corners are the OBJ triangle's.
  std::set<Corner> outer;
  for (const Tri& t : only_in_msh) outer.insert(t.begin(), t.end());
  std::set<Corner> in_all;
  for (const Corner& c : only_in_msh[0]) {
    if (std::find(only_in_msh[1].begin(), only_in_msh[1].end(), c) != only_in_msh[1].end() &&
        std::find(only_in_msh[2].begin(), only_in_msh[2].end(), c) != only_in_msh[2].end()) {
      in_all.insert(c);
    }
  }
  ASSERT_EQ(in_all.size(), 1u);
  std::set<Corner> rim = outer;
  rim.erase(*in_all.begin());
  EXPECT_EQ(rim, std::set<Corner>(only_in_obj[0].begin(), only_in_obj[0].end()));
}

struct BrokenFile {
  std::string name;
  MeshErrorKind kind;
  std::string fault;  // a phrase the message must contain
};

TEST(RealMeshes, BrokenFilesAreRefusedNamingTheirFault) {
  const std::vector<BrokenFile> broken = {
      {"6_tetra_bad.msh", MeshErrorKind::kIndex, "element id 44 is duplicated"},
      // POINTS 5008 edited to 508, and the binary data rewritten as text escapes.
      {"liver_for_test_broken.vtk", MeshErrorKind::kCount, "POINTS declares 508 points"},
      // NumberOfPoints and NumberOfCells edited, offsets and connectivity cut short.
      {"Armadillo_Tetra_4406_for_test_broken.vtu", MeshErrorKind::kCount, "NumberOfPoints is 1445"},
  };
  for (const BrokenFile& f : broken) {
    SCOPED_TRACE(f.name);
    const std::string path = testing::SharedMesh(f.name);
    try {
      ReadMeshFile(path, {});
      ADD_FAILURE() << "accepted";
    } catch (const MeshError& e) {
      EXPECT_EQ(e.kind(), f.kind) << e.what();
      EXPECT_EQ(e.file(), path);
      EXPECT_TRUE(e.where().line > 0 || e.where().byte >= 0) << e.what();
      EXPECT_NE(std::string(e.what()).find(f.fault), std::string::npos) << e.what();
    }
  }
}

TEST(RealMeshes, GoodFilesRoundTripThroughEveryVolumeFormat) {
  const std::string dir = testing::MakeTempDir("somasim-real-roundtrip");
  for (const GoodFile& f : GoodFiles()) {
    const MeshData m = ReadMeshFile(testing::SharedMesh(f.name), {});
    for (const char* ext : {".vtk", ".vtu", ".msh", ".node"}) {
      for (Encoding e : {Encoding::kAscii, Encoding::kBinary}) {
        if (std::string(ext) == ".node" && e == Encoding::kBinary) continue;
        SCOPED_TRACE(f.name + " via " + ext + (e == Encoding::kAscii ? " ascii" : " binary"));
        WriteOptions o;
        o.encoding = e;
        const std::string path = dir + "/" + f.name + ext;
        ASSERT_NO_THROW(WriteMeshFile(path, m, o));
        MeshData back;
        ASSERT_NO_THROW(back = ReadMeshFile(path, {}));
        EXPECT_TRUE(testing::SameMesh(m, back, 0.0));
      }
    }
  }
}

}  // namespace
}  // namespace somasim::mesh_io
