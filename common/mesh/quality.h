// Element quality measures of linear tetrahedra.
#pragma once

#include <Eigen/Core>

#include "common/mesh/mesh_types.h"

namespace somasim::mesh {

struct TetQuality {
  double signed_volume = 0.0;     // [m³]; <= 0 means inverted or degenerate
  double aspect_ratio = 0.0;      // longest edge / (2·√6·inradius); 1 for a regular tet, >= 1
  double min_dihedral_deg = 0.0;  // smallest of the six dihedral angles [deg], 0..180
  double max_dihedral_deg = 0.0;  // largest of the six dihedral angles [deg], 0..180
};

// Quality of one tetrahedron given its corner positions [m].
TetQuality ComputeTetQuality(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                             const Eigen::Vector3d& c, const Eigen::Vector3d& d);

// Normalised volume 6·V / L_max³ (0.7071 for a regular tet, 0 for a flat one). Scale-free, so a
// degeneracy threshold on it does not depend on the mesh's unit.
double TetNormalisedVolume(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                           const Eigen::Vector3d& c, const Eigen::Vector3d& d);

// Below this normalised volume a tetrahedron is degenerate (flat to rounding).
inline constexpr double kDegenerateTetNormalisedVolume = 1e-10;

struct QualitySummary {
  int64_t num_tets = 0;
  int64_t num_inverted = 0;    // signed volume < 0 (and not degenerate)
  int64_t num_degenerate = 0;  // |normalised volume| < kDegenerateTetNormalisedVolume
  double min_dihedral_deg = 0.0;
  double max_dihedral_deg = 0.0;
  double max_aspect_ratio = 0.0;
  double mean_aspect_ratio = 0.0;
  double min_volume = 0.0;  // [m³]
};

// Summary over all tetrahedra (fixed-order reduction). An empty mesh gives zeros.
QualitySummary SummariseQuality(const TetMesh& mesh);

}  // namespace somasim::mesh
