// The cut surface (server/cutting/cut_surface.h) against the cutter's own extraction and against
// mesh::ExtractBoundarySurface after real cuts: one CutSurface, built once from the volume's
// tetrahedra, gives for the cutter's alive flags after every blade step the same triangles in the
// same order with the same inner-face marks as TetCutter::ExtractSurface, and those are the
// boundary of the alive tetrahedra, marked inner exactly where a face is not on the original
// outer surface. Bad input is refused.
#include "server/cutting/cut_surface.h"

#include <gtest/gtest.h>

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <random>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "server/cutting/tet_cutter.h"
#include "tests/support/sanitizer.h"

namespace somasim::cutting {
namespace {

using Eigen::Vector3d;

std::array<int32_t, 3> Sorted(const mesh::Triangles& triangles, Eigen::Index i) {
  std::array<int32_t, 3> key = {triangles(0, i), triangles(1, i), triangles(2, i)};
  std::sort(key.begin(), key.end());
  return key;
}

// The reference: the boundary of the alive tetrahedra by mesh::ExtractBoundarySurface (faces in
// the order of tetrahedron and local face, the volume's numbering), and per face whether it is
// off the original outer surface.
void ReferenceSurface(const mesh::TetMesh& volume, const std::vector<uint8_t>& alive,
                      const std::set<std::array<int32_t, 3>>& outer, mesh::Triangles* triangles,
                      std::vector<uint8_t>* inner) {
  mesh::TetMesh kept;
  kept.vertices = volume.vertices;
  std::vector<Eigen::Index> columns;
  for (size_t t = 0; t < alive.size(); ++t) {
    if (alive[t] != 0) columns.push_back(static_cast<Eigen::Index>(t));
  }
  kept.tetrahedra.resize(4, static_cast<Eigen::Index>(columns.size()));
  for (size_t i = 0; i < columns.size(); ++i) {
    kept.tetrahedra.col(static_cast<Eigen::Index>(i)) = volume.tetrahedra.col(columns[i]);
  }
  *triangles = mesh::ExtractBoundarySurface(kept).triangles;
  inner->resize(static_cast<size_t>(triangles->cols()));
  for (Eigen::Index i = 0; i < triangles->cols(); ++i) {
    (*inner)[static_cast<size_t>(i)] = outer.count(Sorted(*triangles, i)) == 0 ? 1 : 0;
  }
}

std::set<std::array<int32_t, 3>> OuterFaces(const mesh::TetMesh& volume) {
  const mesh::SurfaceMesh boundary = mesh::ExtractBoundarySurface(volume);
  std::set<std::array<int32_t, 3>> outer;
  for (Eigen::Index i = 0; i < boundary.triangles.cols(); ++i) {
    outer.insert(Sorted(boundary.triangles, i));
  }
  return outer;
}

TEST(CutSurface, OfTheUncutVolumeIsItsBoundaryWithNoInnerFace) {
  const mesh::TetMesh volume = mesh_gen::GenerateBuiltinOrganVolume("liver288");
  const CutSurface surface(static_cast<int32_t>(volume.vertices.cols()), volume.tetrahedra);
  EXPECT_EQ(surface.num_tets(), volume.tetrahedra.cols());
  const std::vector<uint8_t> alive(static_cast<size_t>(volume.tetrahedra.cols()), 1);
  mesh::Triangles triangles;
  std::vector<uint8_t> inner;
  surface.Extract(alive, &triangles, &inner);
  EXPECT_EQ(triangles, mesh::ExtractBoundarySurface(volume).triangles);
  ASSERT_EQ(inner.size(), static_cast<size_t>(triangles.cols()));
  EXPECT_EQ(std::count(inner.begin(), inner.end(), 1), 0);
}

TEST(CutSurface, MatchesTheCuttersExtractionAndTheBoundaryOfTheAliveAfterRealCuts) {
  const std::vector<std::string> organs =
      testing::kUnderSanitizer ? std::vector<std::string>{"plate192"}
                               : std::vector<std::string>{"plate192", "liver288", "kidney424"};
  std::mt19937_64 rng(20261129);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const auto unit = [&] {
    return Vector3d(2.0 * u(rng) - 1.0, 2.0 * u(rng) - 1.0, 2.0 * u(rng) - 1.0).normalized();
  };
  for (const std::string& name : organs) {
    const mesh::TetMesh volume = mesh_gen::GenerateBuiltinOrganVolume(name);
    const auto num_nodes = static_cast<int32_t>(volume.vertices.cols());
    // One surface for every cut, as the topology's publisher holds it.
    const CutSurface surface(num_nodes, volume.tetrahedra);
    const std::set<std::array<int32_t, 3>> outer = OuterFaces(volume);
    int compared = 0, with_inner_faces = 0;
    for (int path = 0; path < 12; ++path) {
      mesh::Points x = volume.vertices;
      TetCutter cutter(volume.tetrahedra, x);
      // A blade of 1–4 cm from a random node of the organ, moving 6–12 steps of up to 5 mm,
      // turning as it goes.
      Vector3d p = volume.vertices.col(static_cast<Eigen::Index>(u(rng) * (num_nodes - 1)));
      Vector3d dir = unit();
      Vector3d heading = unit();
      const double length = 0.01 + 0.03 * u(rng);
      const int steps = 6 + static_cast<int>(u(rng) * 7);
      for (int k = 0; k < steps; ++k) {
        const Vector3d p1 = p + 0.005 * u(rng) * heading;
        const Vector3d dir1 = (dir + 0.2 * unit()).normalized();
        cutter.Step({p, p + length * dir, p1, p1 + length * dir1}, &x);
        p = p1;
        dir = dir1;
        heading = (heading + 0.3 * unit()).normalized();

        const std::string what =
            name + " path " + std::to_string(path) + " step " + std::to_string(k);
        mesh::Triangles from_cutter, from_surface, reference;
        std::vector<uint8_t> inner_cutter, inner_surface, inner_reference;
        cutter.ExtractSurface(&from_cutter, &inner_cutter);
        surface.Extract(cutter.alive_flags(), &from_surface, &inner_surface);
        ReferenceSurface(volume, cutter.alive_flags(), outer, &reference, &inner_reference);
        ASSERT_EQ(from_surface, from_cutter) << what;
        ASSERT_EQ(inner_surface, inner_cutter) << what;
        ASSERT_EQ(from_surface, reference) << what;
        ASSERT_EQ(inner_surface, inner_reference) << what;
        ++compared;
        with_inner_faces += std::count(inner_surface.begin(), inner_surface.end(), 1) > 0 ? 1 : 0;
      }
    }
    // The blades cut: a good share of the comparisons are of surfaces with inner faces (the
    // first steps of a path have opened nothing yet).
    EXPECT_GT(with_inner_faces, compared / 5) << name;
  }
}

TEST(CutSurface, RefusesAliveFlagsOfAnotherCountAndIndicesOutOfRange) {
  const mesh::TetMesh volume = mesh_gen::GenerateBuiltinOrganVolume("plate192");
  const CutSurface surface(static_cast<int32_t>(volume.vertices.cols()), volume.tetrahedra);
  mesh::Triangles triangles;
  std::vector<uint8_t> inner;
  const std::vector<uint8_t> three(3, 1);
  try {
    surface.Extract(three, &triangles, &inner);
    FAIL() << "three flags for 392 tetrahedra accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_STREQ(e.what(), "cut surface: 3 alive flags for 392 tetrahedra");
  }
  mesh::Tetrahedra bad = volume.tetrahedra;
  bad(2, 5) = 192;
  EXPECT_THROW(CutSurface(192, bad), std::invalid_argument);
  bad(2, 5) = -1;
  EXPECT_THROW(CutSurface(192, bad), std::invalid_argument);
  // An empty surface extracts nothing.
  const CutSurface empty;
  empty.Extract({}, &triangles, &inner);
  EXPECT_EQ(triangles.cols(), 0);
  EXPECT_TRUE(inner.empty());
}

}  // namespace
}  // namespace somasim::cutting
