#include "common/mesh_io/tetgen_io.h"

#include <gtest/gtest.h>

#include <cctype>
#include <cmath>
#include <cstdint>
#include <functional>
#include <optional>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_io/mesh_error.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::mesh_io {
namespace {

using ::somasim::testing::BoxSurface;
using ::somasim::testing::BoxTets;
using ::somasim::testing::ErrorFrom;
using ::somasim::testing::RegularTet;
using ::somasim::testing::SameMesh;
using ::somasim::testing::Slurp;
using ::somasim::testing::TestData;

// Contents of a .node and optional .ele/.face, named m.node/m.ele/m.face in errors.
struct Files {
  std::string node;
  std::optional<std::string> ele;
  std::optional<std::string> face;
};

MeshData Read(const Files& f, const ReadOptions& options = {}) {
  TetGenInput input;
  input.node = f.node;
  input.node_name = "m.node";
  input.ele_name = "m.ele";
  input.face_name = "m.face";
  if (f.ele) input.ele = *f.ele;
  if (f.face) input.face = *f.face;
  return ReadTetGen(input, options);
}

Files FromWritten(const TetGenFiles& w) {
  Files f{w.node, std::nullopt, std::nullopt};
  if (!w.ele.empty()) f.ele = w.ele;
  if (!w.face.empty()) f.face = w.face;
  return f;
}

// The sample written by `tetgen -pq1.414a0.2 cube.poly` (see tests/data/tetgen/README.md).
Files Sample(const std::string& base) {
  return {Slurp(TestData("tetgen/" + base + ".node")), Slurp(TestData("tetgen/" + base + ".ele")),
          Slurp(TestData("tetgen/" + base + ".face"))};
}

MeshError ErrorOf(const Files& f, const ReadOptions& options = {}) {
  return ErrorFrom([&] { Read(f, options); },
                   f.node + "\n--\n" + f.ele.value_or("") + "\n--\n" + f.face.value_or(""));
}

// Rows of numbers of a TetGen file's data lines (header excluded), comments dropped.
std::vector<std::vector<int64_t>> DataRows(const std::string& text) {
  std::vector<std::vector<int64_t>> rows;
  std::istringstream in(text);
  std::string line;
  bool header = true;
  while (std::getline(in, line)) {
    line = line.substr(0, line.find('#'));
    std::istringstream fields(line);
    std::vector<int64_t> row;
    for (int64_t v; fields >> v;) row.push_back(v);
    if (row.empty()) continue;
    if (!header) rows.push_back(row);
    header = false;
  }
  return rows;
}

const char* kTetNode = "4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n";
const char* kTetEle = "1 4 0\n1 1 2 3 4\n";

TEST(TetGenWriter, WritesZeroBasedFilesWithoutAttributesOrMarkers) {
  MeshData tet = RegularTet(1.0);
  tet.vertices << 0, 1, 0, 0,  //
      0, 0, 1, 0,              //
      0, 0, 0, 1;
  tet.tetrahedra.col(0) << 0, 1, 2, 3;
  const TetGenFiles files = WriteTetGen(tet);
  EXPECT_EQ(files.node, "4  3  0  0\n0 0 0 0\n1 1 0 0\n2 0 1 0\n3 0 0 1\n");
  EXPECT_EQ(files.ele, "1  4  0\n0 0 1 2 3\n");
  EXPECT_EQ(files.face, "");  // no triangles: no .face
  const TetGenFiles surface = WriteTetGen(BoxSurface(1, 1, 1));
  EXPECT_EQ(surface.ele, "");
  EXPECT_EQ(surface.face.substr(0, 5), "12  0");
}

TEST(TetGenRoundTrip, IsBitExact) {
  MeshData awkward = BoxTets(3, 2, 2, 0.3, 0.7, 1.0 / 3.0);
  for (double& x : awkward.vertices.col(5)) x = std::nextafter(x, 2.0);
  for (const MeshData& mesh : {BoxTets(3, 2, 2), awkward, BoxSurface(3, 2, 2), RegularTet(0.01)}) {
    const MeshData read = Read(FromWritten(WriteTetGen(mesh)));
    EXPECT_TRUE(SameMesh(mesh, read, 0.0));
    EXPECT_EQ(read.format, "TetGen");
    EXPECT_EQ(read.num_flipped, 0);
    EXPECT_TRUE(read.skipped.empty());
  }
}

TEST(TetGenReader, ReadsRealTetGenOutputWithoutInvertedTetrahedra) {
  const Files files = Sample("cube");
  // No fix_orientation: TetGen's orientation is somasim's.
  const MeshData mesh = Read(files);
  EXPECT_EQ(mesh.vertices.cols(), 20);
  ASSERT_EQ(mesh.tetrahedra.cols(), 22);
  ASSERT_EQ(mesh.triangles.cols(), 36);
  EXPECT_EQ(mesh.num_flipped, 0);
  EXPECT_TRUE(mesh.skipped.empty());
  EXPECT_EQ(mesh.format, "TetGen (36 boundary faces turned to face outwards)");
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    EXPECT_GT(mesh::TetSignedVolume(mesh.vertices, mesh.tetrahedra.col(t)), 0) << t;
  }
  EXPECT_DOUBLE_EQ(mesh::TetMeshVolume({mesh.vertices, mesh.tetrahedra}), 1.0);

  // Tetrahedra exactly as TetGen wrote them (1-based in the file).
  const auto ele = DataRows(*files.ele);
  for (Eigen::Index t = 0; t < 22; ++t) {
    for (int k = 0; k < 4; ++k) {
      EXPECT_EQ(mesh.tetrahedra(k, t), ele[static_cast<size_t>(t)][static_cast<size_t>(k) + 1] - 1);
    }
  }
  // TetGen's faces of a -p mesh point into the volume; each is read as the same face, in the
  // same place, turned outwards (second and third corners swapped).
  const auto face = DataRows(*files.face);
  for (Eigen::Index t = 0; t < 36; ++t) {
    const auto& row = face[static_cast<size_t>(t)];
    EXPECT_EQ(mesh.triangles.col(t),
              Eigen::Vector3i(static_cast<int>(row[1] - 1), static_cast<int>(row[3] - 1),
                              static_cast<int>(row[2] - 1)));
  }
  const mesh::SurfaceMesh surface{mesh.vertices, mesh.triangles};
  EXPECT_TRUE(mesh::AnalyseSurfaceTopology(surface).watertight);
  EXPECT_DOUBLE_EQ(mesh::SurfaceEnclosedVolume(surface), 1.0);
}

TEST(TetGenReader, ReadsZeroBasedOutputWithAdjacentTetrahedraInFaces) {
  // tetgen -pq1.414a0.2znn: the same mesh numbered from 0, faces followed by 2 tetrahedra.
  EXPECT_TRUE(SameMesh(Read(Sample("cube")), Read(Sample("cube_znn")), 0.0));
}

TEST(TetGenReader, ReadsQuadraticOutputAsLinear) {
  // tetgen -pq1.414a0.2o2: 10-node tetrahedra and 6-node faces; the corners come first.
  const MeshData linear = Read(Sample("cube"));
  const MeshData mesh = Read(Sample("cube_o2"));
  EXPECT_EQ(mesh.vertices.cols(), 79);  // mid-edge nodes stay, unreferenced
  EXPECT_EQ(mesh.tetrahedra, linear.tetrahedra);
  EXPECT_EQ(mesh.triangles, linear.triangles);
  EXPECT_EQ(mesh.vertices.leftCols(20), linear.vertices);
  EXPECT_TRUE(mesh.skipped.empty());
  EXPECT_EQ(mesh.format,
            "TetGen (10-node tetrahedra read as their 4 corners; 6-node faces read as their 3 "
            "corners; 36 boundary faces turned to face outwards)");
}

TEST(TetGenReader, OnlyBoundaryFacesAreTurned) {
  // Two tetrahedra sharing the face (1 2 3): that interior face keeps the order it is written
  // in, either way, and so does a face of no tetrahedron.
  const Files f{"5 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 0 0 -1\n",
                "2 4 0\n1 1 2 3 4\n2 1 3 2 5\n", "3 0\n1 1 3 2\n2 1 2 3\n3 2 4 5\n"};
  const MeshData mesh = Read(f);
  EXPECT_EQ(mesh.triangles.col(0), Eigen::Vector3i(0, 2, 1));
  EXPECT_EQ(mesh.triangles.col(1), Eigen::Vector3i(0, 1, 2));
  EXPECT_EQ(mesh.triangles.col(2), Eigen::Vector3i(1, 3, 4));
  EXPECT_EQ(mesh.format, "TetGen");

  const Files g{kTetNode, kTetEle, "2 0\n1 1 2 4\n2 1 4 2\n"};
  const MeshData one = Read(g);
  // (1 2 4) faces away from node 3, i.e. out of the tetrahedron: kept; (1 4 2) is turned.
  EXPECT_EQ(one.triangles.col(0), Eigen::Vector3i(0, 1, 3));
  EXPECT_EQ(one.triangles.col(1), Eigen::Vector3i(0, 1, 3));
  EXPECT_EQ(one.format, "TetGen (1 boundary face turned to face outwards)");
}

TEST(TetGenReader, ReadsCommentsBlankLinesCrlfMarkersAndAttributes) {
  const Files f{
      "# points\r\n\r\n4 3 2 1 # four of them\r\n1 0 0 0 0.5 7 1\r\n# between\r\n"
      "2 1 0 0 0.5 7 1\r\n3 0 1 0 0.5 7 0\r\n  4   0 0 1 0.5 7 1  \r\n# end",
      "1 4 1\n\n1 1 2 3 4 -3.5\n", "1 1\n1 1 3 2 5\n"};
  const MeshData mesh = Read(f);
  EXPECT_EQ(mesh.vertices.cols(), 4);
  EXPECT_EQ(mesh.tetrahedra.cols(), 1);
  EXPECT_EQ(mesh.triangles.cols(), 1);
  // Optional header fields take TetGen's defaults.
  EXPECT_EQ(Read({"4\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n", "1\n1 1 2 3 4\n", "1\n1 1 3 2\n"})
                .tetrahedra.cols(),
            1);
  // A .node alone is a point cloud.
  EXPECT_EQ(Read({kTetNode, std::nullopt, std::nullopt}).vertices.cols(), 4);
}

TEST(TetGenReader, ScalesToMetres) {
  const MeshData mesh = Read({kTetNode, kTetEle, std::nullopt}, {Unit::kMillimetre, false});
  EXPECT_DOUBLE_EQ(mesh.vertices(0, 1), 0.001);
}

// TetGen files have counts but no end marker: a cut inside the last number of the last line
// leaves a shorter number (a different value) that cannot be detected. Every other cut is
// refused; those must at least not crash and keep the counts.
TEST(TetGenReader, EveryDetectableTruncationIsRefused) {
  const Files full = FromWritten(WriteTetGen(BoxTets(1, 1, 1)));
  const auto check = [&](const std::string& text, const std::function<Files(std::string)>& make) {
    std::string trimmed = text;
    while (!trimmed.empty() && std::isspace(static_cast<unsigned char>(trimmed.back()))) {
      trimmed.pop_back();
    }
    const size_t last_token = trimmed.find_last_of(" \n") + 1;
    for (size_t n = 0; n < text.size(); ++n) {
      const Files cut = make(text.substr(0, n));
      if (n <= last_token) {
        EXPECT_THROW(Read(cut), MeshError) << "prefix " << n << " of\n" << text;
      } else {
        try {
          const MeshData m = Read(cut);
          EXPECT_EQ(m.vertices.cols(), 8);
        } catch (const MeshError&) {
        }
      }
    }
  };
  check(full.node, [&](const std::string& s) { return Files{s, full.ele, full.face}; });
  check(*full.ele, [&](std::string s) { return Files{full.node, s, full.face}; });
  check(*full.face, [&](std::string s) { return Files{full.node, full.ele, s}; });
}

TEST(TetGenReader, RandomByteDamageOnlyRaisesMeshError) {
  const Files full = FromWritten(WriteTetGen(BoxTets(2, 1, 1)));
  std::mt19937 rng(11);
  for (int trial = 0; trial < 3000; ++trial) {
    Files damaged = full;
    std::string& target = trial % 3 == 0   ? damaged.node
                          : trial % 3 == 1 ? *damaged.ele
                                           : *damaged.face;
    target = testing::DamageBytes(target, 1 + trial % 4, &rng);
    try {
      Read(damaged);
    } catch (const MeshError&) {
    }
  }
}

TEST(TetGenReader, RefusesNonFiniteCoordinates) {
  for (const char* bad : {"nan", "inf", "-1e400"}) {
    const MeshError e =
        ErrorOf({std::string("4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 ") + bad + " 0\n4 0 0 1\n", kTetEle,
                 std::nullopt});
    EXPECT_EQ(e.kind(), MeshErrorKind::kValue) << bad;
    EXPECT_EQ(e.file(), "m.node");
    EXPECT_EQ(e.where().line, 4);
  }
}

TEST(TetGenReader, RefusesNodeReferencesOutOfRange) {
  MeshError e = ErrorOf({kTetNode, "1 4 0\n1 1 2 3 5\n", std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.file(), "m.ele");
  EXPECT_EQ(e.where().line, 2);
  EXPECT_NE(e.fault().find("refers to node 5, but the .node file numbers its points 1..4"),
            std::string::npos)
      << e.what();
  // Node 0 does not exist when the points are numbered from 1.
  e = ErrorOf({kTetNode, kTetEle, "1 0\n1 0 1 2\n"});
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.file(), "m.face");
}

TEST(TetGenReader, RefusesCountsThatDisagreeWithTheData) {
  MeshError e = ErrorOf({"5 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n", kTetEle, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_NE(e.fault().find("says 5 points but the file ends after 4"), std::string::npos)
      << e.what();
  e = ErrorOf({"3 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n", kTetEle, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_EQ(e.where().line, 5);
  e = ErrorOf({kTetNode, "2 4 0\n1 1 2 3 4\n", std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_EQ(e.file(), "m.ele");
  e = ErrorOf({kTetNode, kTetEle, "1 0\n1 1 2 3\n2 1 2 4\n"});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  EXPECT_EQ(e.file(), "m.face");
}

TEST(TetGenReader, AbsurdCountsFailFast) {
  MeshError e = ErrorOf({"1000000000000 3 0 0\n1 0 0 0\n", std::nullopt, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  e = ErrorOf({kTetNode, "1000000000000 4 0\n1 1 2 3 4\n", std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  e = ErrorOf({kTetNode, kTetEle, "1000000000000 0\n"});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  e = ErrorOf({"4 3 1000000000000 0\n1 0 0 0\n", std::nullopt, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
  e = ErrorOf({"-4 3 0 0\n", std::nullopt, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
}

TEST(TetGenReader, RefusesDuplicatedAndNonConsecutiveIndices) {
  MeshError e = ErrorOf({"4 3 0 0\n1 0 0 0\n2 1 0 0\n2 0 1 0\n4 0 0 1\n", kTetEle, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.where().line, 4);
  EXPECT_NE(e.fault().find("point index 2 is duplicated (first on line 3)"), std::string::npos)
      << e.what();
  e = ErrorOf({"4 3 0 0\n1 0 0 0\n2 1 0 0\n4 0 1 0\n5 0 0 1\n", kTetEle, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_NE(e.fault().find("point index 4 is out of sequence: expected 3"), std::string::npos)
      << e.what();
  e = ErrorOf({"4 3 0 0\n2 0 0 0\n3 1 0 0\n4 0 1 0\n5 0 0 1\n", std::nullopt, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.where().line, 2);
  // Elements are numbered like the points.
  e = ErrorOf({kTetNode, "1 4 0\n0 1 2 3 4\n", std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_EQ(e.file(), "m.ele");
  e = ErrorOf({kTetNode, kTetEle, "2 0\n1 1 2 4\n1 1 4 3\n"});
  EXPECT_EQ(e.kind(), MeshErrorKind::kIndex);
  EXPECT_NE(e.fault().find("face index 1 is duplicated"), std::string::npos) << e.what();
}

TEST(TetGenReader, RefusesTwoDimensionalFiles) {
  const MeshError e = ErrorOf({"3 2 0 0\n1 0 0\n2 1 0\n3 0 1\n", std::nullopt, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kUnsupported);
  EXPECT_EQ(e.where().line, 1);
}

TEST(TetGenReader, RefusesWrongLineSizes) {
  const char* bad_nodes[] = {
      "4 3 0 0\n1 0 0 0\n2 1 0\n3 0 1 0\n4 0 0 1\n",            // a coordinate missing
      "4 3 0 0\n1 0 0 0\n2 1 0 0 9\n3 0 1 0\n4 0 0 1\n",        // an extra value
      "4 3 0 1\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n",          // markers announced, not given
      "4 3 0 2\n1 0 0 0 1\n2 1 0 0 1\n3 0 1 0 1\n4 0 0 1 1\n",  // marker flag not 0|1
      "4 3 0 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n",        // header too long
      "4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 one\n",        // not a number
      "",                                                       // empty
      "\x7f\x45\x4c\x46\x02\x01\x01\x00 garbage",
  };
  for (const char* node : bad_nodes) {
    const MeshError e = ErrorOf({node, std::nullopt, std::nullopt});
    EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax) << node;
    EXPECT_EQ(e.file(), "m.node");
  }
  for (const char* ele : {"1 4 0\n1 1 2 3\n", "1 8 0\n1 1 2 3 4 1 2 3 4\n", "1 4 1\n1 1 2 3 4\n",
                          "1 4 0\n1 1 2 3 4.0\n"}) {
    const MeshError e = ErrorOf({kTetNode, ele, std::nullopt});
    EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax) << ele;
    EXPECT_EQ(e.file(), "m.ele");
  }
  for (const char* face :
       {"1 0\n1 1 2\n", "1 1\n1 1 2 3\n", "2 0\n1 1 2 3\n2 1 2 4 1 -1\n", "1 3\n1 1 2 3 1\n"}) {
    const MeshError e = ErrorOf({kTetNode, kTetEle, face});
    EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax) << face;
    EXPECT_EQ(e.file(), "m.face");
  }
}

TEST(TetGenReader, InvertedTetrahedronRefusedOrFixed) {
  const Files f{kTetNode, "2 4 0\n1 1 2 3 4\n2 1 3 2 4\n", std::nullopt};
  const MeshError e = ErrorOf(f);
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
  EXPECT_EQ(e.file(), "m.ele");
  EXPECT_EQ(e.where().line, 3);
  EXPECT_NE(e.fault().find("inverted"), std::string::npos) << e.what();
  const MeshData fixed = Read(f, {Unit::kMetre, true});
  EXPECT_EQ(fixed.num_flipped, 1);
  EXPECT_GT(mesh::TetSignedVolume(fixed.vertices, fixed.tetrahedra.col(1)), 0);
}

TEST(TetGenReader, RefusesDegenerateElements) {
  MeshError e = ErrorOf({"4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 1 1 0\n", kTetEle, std::nullopt});
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
  EXPECT_EQ(e.file(), "m.ele");
  e = ErrorOf({kTetNode, kTetEle, "1 0\n1 1 2 2\n"});
  EXPECT_EQ(e.kind(), MeshErrorKind::kElement);
  EXPECT_EQ(e.file(), "m.face");
  EXPECT_EQ(e.where().line, 2);
}

}  // namespace
}  // namespace somasim::mesh_io
