#include "common/mesh/quality.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>

#include "common/mesh/geometry.h"

namespace somasim::mesh {
namespace {

// Outward face normals (unnormalised, |n| = 2·area) of a positively oriented tet; face k is
// the face opposite corner k.
void FaceNormals(const Eigen::Vector3d* x, Eigen::Vector3d* n) {
  n[0] = (x[2] - x[1]).cross(x[3] - x[1]);
  n[1] = (x[3] - x[0]).cross(x[2] - x[0]);
  n[2] = (x[1] - x[0]).cross(x[3] - x[0]);
  n[3] = (x[2] - x[0]).cross(x[1] - x[0]);
}

}  // namespace

double TetNormalisedVolume(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                           const Eigen::Vector3d& c, const Eigen::Vector3d& d) {
  const double longest =
      std::sqrt(std::max({(b - a).squaredNorm(), (c - a).squaredNorm(), (d - a).squaredNorm(),
                          (c - b).squaredNorm(), (d - b).squaredNorm(), (d - c).squaredNorm()}));
  if (!(longest > 0)) return 0.0;
  return 6.0 * TetSignedVolume(a, b, c, d) / (longest * longest * longest);
}

TetQuality ComputeTetQuality(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                             const Eigen::Vector3d& c, const Eigen::Vector3d& d) {
  const Eigen::Vector3d x[4] = {a, b, c, d};
  TetQuality q;
  q.signed_volume = TetSignedVolume(a, b, c, d);

  Eigen::Vector3d n[4];
  FaceNormals(x, n);
  double area_sum = 0.0;
  for (const Eigen::Vector3d& ni : n) area_sum += 0.5 * ni.norm();

  double longest = 0.0;
  q.min_dihedral_deg = 180.0;
  q.max_dihedral_deg = 0.0;
  for (int i = 0; i < 4; ++i) {
    for (int j = i + 1; j < 4; ++j) {
      longest = std::max(longest, (x[i] - x[j]).norm());
      // The edge (i, j) is shared by the faces opposite the two other corners k and l; the
      // dihedral angle is π minus the angle between their outward normals.
      int k = 0;
      while (k == i || k == j) ++k;
      int l = k + 1;
      while (l == i || l == j) ++l;
      const double denom = n[k].norm() * n[l].norm();
      double angle = 0.0;
      if (denom > 0) {
        const double cosine = std::clamp(n[k].dot(n[l]) / denom, -1.0, 1.0);
        angle = 180.0 - std::acos(cosine) * 180.0 / std::numbers::pi;
      }
      q.min_dihedral_deg = std::min(q.min_dihedral_deg, angle);
      q.max_dihedral_deg = std::max(q.max_dihedral_deg, angle);
    }
  }
  // Inradius r = 3|V| / A; aspect ratio L_max / (2√6 r) is 1 for the regular tetrahedron.
  const double inradius = area_sum > 0 ? 3.0 * std::abs(q.signed_volume) / area_sum : 0.0;
  q.aspect_ratio = inradius > 0 ? longest / (2.0 * std::sqrt(6.0) * inradius)
                                : std::numeric_limits<double>::infinity();
  return q;
}

QualitySummary SummariseQuality(const TetMesh& mesh) {
  QualitySummary s;
  s.num_tets = mesh.tetrahedra.cols();
  if (s.num_tets == 0) return s;
  s.min_dihedral_deg = 180.0;
  s.min_volume = std::numeric_limits<double>::infinity();
  double aspect_sum = 0.0;
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    const Eigen::Vector3d a = mesh.vertices.col(mesh.tetrahedra(0, t));
    const Eigen::Vector3d b = mesh.vertices.col(mesh.tetrahedra(1, t));
    const Eigen::Vector3d c = mesh.vertices.col(mesh.tetrahedra(2, t));
    const Eigen::Vector3d d = mesh.vertices.col(mesh.tetrahedra(3, t));
    const TetQuality q = ComputeTetQuality(a, b, c, d);
    if (std::abs(TetNormalisedVolume(a, b, c, d)) < kDegenerateTetNormalisedVolume) {
      ++s.num_degenerate;
    } else if (q.signed_volume < 0) {
      ++s.num_inverted;
    }
    s.min_dihedral_deg = std::min(s.min_dihedral_deg, q.min_dihedral_deg);
    s.max_dihedral_deg = std::max(s.max_dihedral_deg, q.max_dihedral_deg);
    s.max_aspect_ratio = std::max(s.max_aspect_ratio, q.aspect_ratio);
    s.min_volume = std::min(s.min_volume, q.signed_volume);
    aspect_sum += q.aspect_ratio;
  }
  s.mean_aspect_ratio = aspect_sum / static_cast<double>(s.num_tets);
  return s;
}

}  // namespace somasim::mesh
