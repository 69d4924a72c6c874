#include "tests/server/contact/contact_test_meshes.h"

#include <cmath>
#include <numbers>

#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/structured_meshes.h"

namespace somasim::testing {

OrganWithSurface VolumeOrgan(const char* name) {
  OrganWithSurface out;
  out.volume = mesh_gen::GenerateBuiltinOrganVolume(name);
  out.surface = mesh::ExtractBoundarySurface(out.volume).triangles;
  return out;
}

OrganWithSurface BoxOrgan(int n, const Eigen::Vector3d& lo, const Eigen::Vector3d& hi) {
  OrganWithSurface out;
  out.volume = mesh_gen::BoxGridTets(n, n, n, lo, hi);
  out.surface = mesh::ExtractBoundarySurface(out.volume).triangles;
  return out;
}

mesh::SurfaceMesh FlatPatch(int n, double half) {
  mesh::SurfaceMesh patch;
  patch.vertices.resize(3, (n + 1) * (n + 1));
  for (int j = 0; j <= n; ++j) {
    for (int i = 0; i <= n; ++i) {
      patch.vertices.col(j * (n + 1) + i) =
          Eigen::Vector3d(-half + 2.0 * half * i / n, -half + 2.0 * half * j / n, 0.0);
    }
  }
  patch.triangles.resize(3, 2 * n * n);
  int t = 0;
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const int a = j * (n + 1) + i, b = a + 1, c = a + n + 1, d = c + 1;
      patch.triangles.col(t++) = Eigen::Vector3i(a, b, d).cast<int32_t>();
      patch.triangles.col(t++) = Eigen::Vector3i(a, d, c).cast<int32_t>();
    }
  }
  return patch;
}

double WindingNumber(const mesh::Points& positions, const mesh::Triangles& triangles,
                     const Eigen::Vector3d& x) {
  double total = 0.0;
  for (Eigen::Index t = 0; t < triangles.cols(); ++t) {
    const Eigen::Vector3d a = positions.col(triangles(0, t)) - x;
    const Eigen::Vector3d b = positions.col(triangles(1, t)) - x;
    const Eigen::Vector3d c = positions.col(triangles(2, t)) - x;
    const double la = a.norm(), lb = b.norm(), lc = c.norm();
    const double numerator = a.dot(b.cross(c));
    const double denominator = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
    total += 2.0 * std::atan2(numerator, denominator);
  }
  return total / (4.0 * std::numbers::pi);
}

}  // namespace somasim::testing
