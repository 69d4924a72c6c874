#include "common/mesh/geometry.h"

namespace somasim::mesh {

BoundingBox ComputeBoundingBox(const Points& points) {
  BoundingBox box;
  if (points.cols() == 0) return box;
  box.min = points.rowwise().minCoeff();
  box.max = points.rowwise().maxCoeff();
  box.empty = false;
  return box;
}

double TetSignedVolume(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                       const Eigen::Vector3d& d) {
  return (b - a).dot((c - a).cross(d - a)) / 6.0;
}

double TetSignedVolume(const Points& points, const Eigen::Ref<const Eigen::Vector4i>& tet) {
  return TetSignedVolume(points.col(tet[0]), points.col(tet[1]), points.col(tet[2]),
                         points.col(tet[3]));
}

double TetMeshVolume(const TetMesh& mesh) {
  double volume = 0.0;
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    volume += TetSignedVolume(mesh.vertices, mesh.tetrahedra.col(t));
  }
  return volume;
}

double SurfaceEnclosedVolume(const SurfaceMesh& surface) {
  // Divergence theorem: V = Σ_t (a · (b × c)) / 6 over outward-facing triangles.
  double volume = 0.0;
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    const Eigen::Vector3d a = surface.vertices.col(surface.triangles(0, t));
    const Eigen::Vector3d b = surface.vertices.col(surface.triangles(1, t));
    const Eigen::Vector3d c = surface.vertices.col(surface.triangles(2, t));
    volume += a.dot(b.cross(c));
  }
  return volume / 6.0;
}

double SurfaceArea(const SurfaceMesh& surface) {
  double area = 0.0;
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    const Eigen::Vector3d a = surface.vertices.col(surface.triangles(0, t));
    const Eigen::Vector3d b = surface.vertices.col(surface.triangles(1, t));
    const Eigen::Vector3d c = surface.vertices.col(surface.triangles(2, t));
    area += 0.5 * (b - a).cross(c - a).norm();
  }
  return area;
}

}  // namespace somasim::mesh
