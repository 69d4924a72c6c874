// Seed 001 §1.1's mesh intensity (Chen, Zhao & Zhu 2015, eq. 1–9): per background cell (the
// mesh's tetrahedra), the strain-energy density's gradient over the node density, normalised
// between the organ's extremes; the hybrid refines the region where it is high. Definitions:
// docs/models.md, "The hybrid in detail". Pure: no I/O.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/meshless/mls.h"

namespace somasim::models::meshless {

struct CellIntensity {
  std::vector<double> energy_density;  // DSE at the cell's centroid [J/m³], num_tets
  std::vector<double> gradient;        // GSED = |∇DSE| [J/m⁴], num_tets
  std::vector<double> node_density;    // DM [1/m³], num_tets
  std::vector<double> intensity;       // r_d [J/m], num_tets
  std::vector<double> normalised;   // (r_d − R_min) / (R_max − R_min) in [0, 1]; 0 if all equal
  double r_min = 0.0, r_max = 0.0;  // [J/m]
};

// The cells' shape-function gradients at their Gauss points, evaluated once (28 bytes per Gauss
// point and covering node): an intensity is then sparse products instead of MLS evaluations
// (the costs: docs/models.md).
class CellIntensityEvaluator {
 public:
  // `tets`: 4 × num_tets indices into the shape functions' nodes. Throws std::invalid_argument
  // for an index out of range or a flat cell.
  CellIntensityEvaluator(const MlsShapeFunctions& shape, const mesh::Tetrahedra& tets);
  // For nodal parameters û (3 × num_nodes [m]), with Lamé λ, μ [Pa]. Allocates (the result).
  // Throws std::invalid_argument for a size that does not match or a non-finite parameter.
  CellIntensity Compute(const mesh::Points& parameters, double lambda, double mu) const;

 private:
  int32_t num_nodes_ = 0;
  // Gauss point g = 4 t + k of cell t: its covering nodes and ∇φ at start_[g] .. start_[g + 1).
  std::vector<int64_t> start_;
  std::vector<int32_t> node_;
  std::vector<Eigen::Vector3d> gradient_;
  // Per cell: the rows of the linear fit's inverse that give ∇DSE from the four values (3 × 4),
  // and its volume [m³].
  std::vector<Eigen::Matrix<double, 3, 4>> slope_;
  std::vector<double> volume_;
};

// The same in one call (builds the evaluator: for a single use).
CellIntensity ComputeCellIntensity(const MlsShapeFunctions& shape, const mesh::Tetrahedra& tets,
                                   const mesh::Points& parameters, double lambda, double mu);

}  // namespace somasim::models::meshless
