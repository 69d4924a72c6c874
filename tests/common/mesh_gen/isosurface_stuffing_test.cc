// Isosurface stuffing: valid, conforming, well-shaped meshes of implicit solids (Labelle &
// Shewchuk 2007 guarantee dihedral angles in [10.7°, 164.8°]).
#include "common/mesh_gen/isosurface_stuffing.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <stdexcept>

#include "common/mesh/geometry.h"
#include "common/mesh/quality.h"
#include "common/mesh/topology.h"
#include "common/mesh_gen/implicit.h"

namespace somasim::mesh_gen {
namespace {

using Eigen::Vector3d;

// Every property the built-in organs rely on, for one mesh.
void ExpectValidStuffedMesh(const ImplicitSolid& solid, const mesh::TetMesh& tets) {
  ASSERT_GT(tets.tetrahedra.cols(), 0);
  const mesh::QualitySummary quality = mesh::SummariseQuality(tets);
  EXPECT_EQ(quality.num_inverted, 0);
  EXPECT_EQ(quality.num_degenerate, 0);
  EXPECT_GE(quality.min_dihedral_deg, 10.7);
  EXPECT_LE(quality.max_dihedral_deg, 164.9);
  const mesh::SurfaceMesh boundary = mesh::ExtractBoundarySurface(tets);
  const mesh::SurfaceTopology topology = mesh::AnalyseSurfaceTopology(boundary);
  EXPECT_TRUE(topology.watertight);
  EXPECT_TRUE(topology.manifold);
  // Every node is used by a tetrahedron.
  std::vector<bool> used(static_cast<size_t>(tets.vertices.cols()), false);
  for (Eigen::Index t = 0; t < tets.tetrahedra.cols(); ++t) {
    for (int c = 0; c < 4; ++c) used[static_cast<size_t>(tets.tetrahedra(c, t))] = true;
  }
  EXPECT_EQ(std::count(used.begin(), used.end(), false), 0);
  // Boundary nodes lie on the surface, interior nodes inside.
  std::vector<bool> on_boundary(used.size(), false);
  for (Eigen::Index f = 0; f < boundary.triangles.cols(); ++f) {
    for (int c = 0; c < 3; ++c) on_boundary[static_cast<size_t>(boundary.triangles(c, f))] = true;
  }
  for (Eigen::Index v = 0; v < tets.vertices.cols(); ++v) {
    const double value = solid.Value(tets.vertices.col(v));
    if (on_boundary[static_cast<size_t>(v)]) {
      EXPECT_LT(std::abs(value), 1e-9) << "boundary node " << v;
    } else {
      EXPECT_LT(value, 0.0) << "interior node " << v;
    }
  }
}

TEST(IsosurfaceStuffing, SphereMeshIsValidWithGuaranteedAngles) {
  const Ellipsoid sphere(Vector3d(0.01, -0.02, 0.03), Vector3d::Constant(0.05));
  StuffingOptions options;
  options.spacing = 0.012;
  const mesh::TetMesh tets = StuffIsosurface(sphere, options);
  ExpectValidStuffedMesh(sphere, tets);
}

TEST(IsosurfaceStuffing, GuaranteeHoldsForManySpacingsAndOffsets) {
  // Coarse to fine lattices in many positions relative to flat and elongated ellipsoids: the
  // angle bound must hold in every configuration of cut points, not just on average.
  for (const Vector3d& semi_axes : {Vector3d(0.06, 0.03, 0.02), Vector3d(0.08, 0.02, 0.01)}) {
    const Ellipsoid ellipsoid(Vector3d(0.001, 0.002, -0.003), semi_axes);
    for (int shift = 0; shift < 24; ++shift) {
      StuffingOptions options;
      options.spacing = semi_axes.minCoeff() * (0.2 + 0.07 * shift);
      options.offset = Vector3d(std::fmod(0.37 * shift, 1.0), std::fmod(0.61 * shift, 1.0),
                                std::fmod(0.13 * shift + 0.05, 1.0));
      SCOPED_TRACE(testing::Message()
                   << "semi-axes " << semi_axes.transpose() << " shift " << shift);
      const mesh::TetMesh tets = StuffIsosurface(ellipsoid, options);
      if (tets.tetrahedra.cols() == 0) continue;  // lattice coarser than the solid
      ExpectValidStuffedMesh(ellipsoid, tets);
    }
  }
}

TEST(IsosurfaceStuffing, VolumeConvergesToTheSolidsVolume) {
  const double radius = 0.05;
  const Ellipsoid sphere(Vector3d::Zero(), Vector3d::Constant(radius));
  const double exact = 4.0 / 3.0 * std::numbers::pi * radius * radius * radius;
  double previous_error = 1.0;
  for (const double spacing : {0.02, 0.01, 0.005}) {
    StuffingOptions options;
    options.spacing = spacing;
    const double error = std::abs(mesh::TetMeshVolume(StuffIsosurface(sphere, options)) - exact);
    EXPECT_LT(error, previous_error) << spacing;
    previous_error = error;
  }
  EXPECT_LT(previous_error / exact, 0.01);
}

TEST(IsosurfaceStuffing, IsDeterministic) {
  const Ellipsoid ellipsoid(Vector3d::Zero(), Vector3d(0.05, 0.04, 0.03));
  StuffingOptions options;
  options.spacing = 0.013;
  const mesh::TetMesh first = StuffIsosurface(ellipsoid, options);
  const mesh::TetMesh second = StuffIsosurface(ellipsoid, options);
  EXPECT_EQ(first.vertices, second.vertices);
  EXPECT_EQ(first.tetrahedra, second.tetrahedra);
}

TEST(IsosurfaceStuffing, RefusesBadOptionsNamingThem) {
  const Ellipsoid sphere(Vector3d::Zero(), Vector3d::Constant(0.05));
  const auto message = [&](const StuffingOptions& options) -> std::string {
    try {
      StuffIsosurface(sphere, options);
    } catch (const std::invalid_argument& error) {
      return error.what();
    }
    return "accepted";
  };
  StuffingOptions options;
  options.spacing = std::nan("");
  EXPECT_NE(message(options).find("spacing"), std::string::npos);
  options.spacing = -1.0;
  EXPECT_NE(message(options).find("spacing"), std::string::npos);
  options.spacing = 1e-5;  // 10^12 lattice vertices
  EXPECT_NE(message(options).find("limit"), std::string::npos);
  options = StuffingOptions{};
  options.offset.x() = 1.0;
  EXPECT_NE(message(options).find("offset"), std::string::npos);
  options = StuffingOptions{};
  options.alpha_short = 0.5;
  EXPECT_NE(message(options).find("alpha_short"), std::string::npos);
}

}  // namespace
}  // namespace somasim::mesh_gen
