// Seed 001 §1.1 (Chen, Zhao & Zhu 2015, eq. 1–9): where the EFG field needs resolution. Per
// background cell (the mesh's tetrahedra), from the strain-energy density's gradient over the
// node density. Pure: no I/O.
//
//   DSE = ½ σ : ε                          (eq. 1: strain-energy density [J/m³])
//   GSED = |∇DSE| = |(∂DSE/∂x, ∂DSE/∂y, ∂DSE/∂z)|   (eq. 2–4 [J/m⁴])
//   DM = N_k / V_k                         (eq. 5: nodes of cell k over its volume [1/m³])
//   r_d = GSED / DM                        (eq. 6–7: the cell's mesh intensity [J/m])
//   R_max = max r_d, R_min = min r_d       (eq. 8–9)
// The seed does not print eq. 1–9's bodies (only their names survive in the text); these are
// the standard strain-gradient indicator it describes ("基于应变梯度的方法不需要求解二阶导数").
// Here ε is the small strain of the MLS field at the cell's four degree-2 Gauss points (σ = λ tr ε
// I
// + 2 μ ε), ∇DSE the gradient of the linear function through the four values (exact for four
// points), N_k = 4 (a tetrahedron's nodes). A cell whose normalised intensity
// (r_d − R_min) / (R_max − R_min) is high is refined (its nodes join the surgical region); one
// whose intensity is low is coarsened (its nodes may leave it).
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

// The cells' shape-function gradients at their Gauss points, evaluated once (35 ms on liver288,
// 0.6 s on liver4055; memory 28 bytes per Gauss point and covering node: ~4 MB on liver288,
// ~40 MB on liver4055): an intensity is then sparse products, 1.7 ms on liver288 and 33 ms on
// liver4055 (instead of ~25 ms and ~0.4 s of MLS evaluations).
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
