#include "server/models/generalised_surface.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "common/mesh/topology.h"

namespace somasim::models {

using Eigen::Vector3d;

double PointTriangleDistance(const Vector3d& p, const Vector3d& a, const Vector3d& b,
                             const Vector3d& c) {
  // Ericson, Real-Time Collision Detection §5.1.5: the Voronoi regions of corners, edges, face.
  const Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) return ap.norm();
  const Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) return bp.norm();
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
    const double v = d1 / (d1 - d3);
    return (p - (a + v * ab)).norm();
  }
  const Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) return cp.norm();
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
    const double w = d2 / (d2 - d6);
    return (p - (a + w * ac)).norm();
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    return (p - (b + w * (c - b))).norm();
  }
  const double denominator = va + vb + vc;
  if (!(denominator > 0.0)) {  // a degenerate triangle: the nearest of its edges' ends
    return std::min({ap.norm(), bp.norm(), cp.norm()});
  }
  const double v = vb / denominator, w = vc / denominator;
  return (p - (a + v * ab + w * ac)).norm();
}

OuterShell SelectOuterShell(const mesh::TetMesh& mesh, double fraction) {
  if (!(fraction > 0.0 && fraction <= 0.5)) {
    throw std::invalid_argument("generalised surface: shell fraction must be in (0, 0.5], got " +
                                std::to_string(fraction));
  }
  // Checks indices and coordinates, with the same messages as every particle model.
  (void)TetMeshEdges(mesh, "generalised surface");
  const mesh::SurfaceMesh boundary = mesh::ExtractBoundarySurface(mesh);
  const mesh::Points& x = mesh.vertices;
  const Eigen::Index num_faces = boundary.triangles.cols();
  // Bounding sphere of each face (centroid, radius) to skip faces that cannot be nearer.
  mesh::Points centre(3, num_faces);
  std::vector<double> radius(static_cast<size_t>(num_faces));
  std::vector<uint8_t> on_boundary(static_cast<size_t>(x.cols()), 0);
  for (Eigen::Index f = 0; f < num_faces; ++f) {
    const auto t = boundary.triangles.col(f);
    centre.col(f) = (x.col(t(0)) + x.col(t(1)) + x.col(t(2))) / 3.0;
    double r = 0.0;
    for (int k = 0; k < 3; ++k) {
      r = std::max(r, (x.col(t(k)) - centre.col(f)).norm());
      on_boundary[static_cast<size_t>(t(k))] = 1;
    }
    radius[static_cast<size_t>(f)] = r;
  }
  OuterShell shell;
  shell.depth.assign(static_cast<size_t>(x.cols()), 0.0);
  double deepest = 0.0;
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (on_boundary[static_cast<size_t>(i)] != 0) continue;
    const Vector3d p = x.col(i);
    double best = std::numeric_limits<double>::infinity();
    for (Eigen::Index f = 0; f < num_faces; ++f) {
      if ((p - centre.col(f)).norm() - radius[static_cast<size_t>(f)] >= best) continue;
      const auto t = boundary.triangles.col(f);
      best = std::min(best, PointTriangleDistance(p, x.col(t(0)), x.col(t(1)), x.col(t(2))));
    }
    shell.depth[static_cast<size_t>(i)] = best;
    deepest = std::max(deepest, best);
  }
  shell.thickness = 2.0 * deepest;
  const double limit = fraction * shell.thickness;
  shell.in_shell.assign(static_cast<size_t>(x.cols()), 0);
  for (size_t i = 0; i < shell.depth.size(); ++i) {
    if (shell.depth[i] <= limit) {
      shell.in_shell[i] = 1;
      ++shell.num_shell_nodes;
    }
  }
  return shell;
}

MeshEdges ShellEdges(const mesh::TetMesh& mesh, const OuterShell& shell) {
  if (shell.in_shell.size() != static_cast<size_t>(mesh.vertices.cols())) {
    throw std::invalid_argument("generalised surface: the shell has " +
                                std::to_string(shell.in_shell.size()) + " nodes but the mesh " +
                                std::to_string(mesh.vertices.cols()));
  }
  const MeshEdges all = TetMeshEdges(mesh, "generalised surface");
  MeshEdges kept;
  for (size_t e = 0; e < all.edges.size(); ++e) {
    const auto [i, j] = all.edges[e];
    if (shell.in_shell[static_cast<size_t>(i)] != 0 &&
        shell.in_shell[static_cast<size_t>(j)] != 0) {
      kept.edges.push_back(all.edges[e]);
      kept.edge_size.push_back(all.edge_size[e]);
    }
  }
  kept.node_size = all.node_size;
  for (size_t i = 0; i < kept.node_size.size(); ++i) {
    if (shell.in_shell[i] == 0) kept.node_size[i] = 0.0;
  }
  if (kept.edges.empty()) {
    throw std::invalid_argument("generalised surface: no tetrahedron edge lies in the shell");
  }
  return kept;
}

}  // namespace somasim::models
