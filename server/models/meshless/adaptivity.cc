#include "server/models/meshless/adaptivity.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace somasim::models::meshless {

CellIntensity ComputeCellIntensity(const MlsShapeFunctions& shape, const mesh::Tetrahedra& tets,
                                   const mesh::Points& parameters, double lambda, double mu) {
  const int32_t n = shape.num_nodes();
  if (parameters.cols() != n) {
    throw std::invalid_argument("adaptivity: parameters must be 3 x num_nodes (" +
                                std::to_string(n) + ")");
  }
  if (!parameters.allFinite()) throw std::invalid_argument("adaptivity: parameters not finite");
  const auto num_tets = static_cast<size_t>(tets.cols());
  CellIntensity out;
  out.energy_density.assign(num_tets, 0.0);
  out.gradient.assign(num_tets, 0.0);
  out.node_density.assign(num_tets, 0.0);
  out.intensity.assign(num_tets, 0.0);
  out.normalised.assign(num_tets, 0.0);
  // The degree-2 rule: the four permutations of (a, a, a, b).
  constexpr double kA = 0.1381966011250105, kB = 0.5854101966249685;
  const mesh::Points& x = shape.nodes();
  MlsEvaluation eval;
  for (size_t t = 0; t < num_tets; ++t) {
    const auto c = static_cast<Eigen::Index>(t);
    for (int a = 0; a < 4; ++a) {
      if (tets(a, c) < 0 || tets(a, c) >= n) {
        throw std::invalid_argument("adaptivity: tetrahedron " + std::to_string(t) +
                                    " has a node index out of range");
      }
    }
    const auto corner = [&](int a) -> Eigen::Vector3d { return x.col(tets(a, c)); };
    const double volume =
        std::abs((corner(1) - corner(0)).cross(corner(2) - corner(0)).dot(corner(3) - corner(0))) /
        6.0;
    const Eigen::Vector3d centroid = 0.25 * (corner(0) + corner(1) + corner(2) + corner(3));
    Eigen::Matrix4d fit;  // rows: (1, x_g − x_c)
    Eigen::Vector4d density;
    for (int g = 0; g < 4; ++g) {
      Eigen::Vector3d p = Eigen::Vector3d::Zero();
      for (int a = 0; a < 4; ++a) p += (a == g ? kB : kA) * corner(a);
      shape.Evaluate(p, true, &eval);
      Eigen::Matrix3d grad = Eigen::Matrix3d::Zero();  // ∂u_i/∂x_j
      for (size_t j = 0; j < eval.nodes.size(); ++j) {
        grad += parameters.col(eval.nodes[j]) *
                eval.gradients.col(static_cast<Eigen::Index>(j)).transpose();
      }
      const Eigen::Matrix3d strain = 0.5 * (grad + grad.transpose());
      const Eigen::Matrix3d stress =
          lambda * strain.trace() * Eigen::Matrix3d::Identity() + 2.0 * mu * strain;
      density[g] = 0.5 * (stress.cwiseProduct(strain)).sum();  // eq. 1
      fit(g, 0) = 1.0;
      fit.block<1, 3>(g, 1) = (p - centroid).transpose();
    }
    const Eigen::Vector4d coefficients = fit.partialPivLu().solve(density);
    out.energy_density[t] = coefficients[0];
    out.gradient[t] = coefficients.tail<3>().norm();           // eq. 2–4
    out.node_density[t] = 4.0 / volume;                        // eq. 5
    out.intensity[t] = out.gradient[t] / out.node_density[t];  // eq. 6–7
  }
  if (num_tets > 0) {
    const auto [lo, hi] = std::minmax_element(out.intensity.begin(), out.intensity.end());
    out.r_min = *lo;  // eq. 8–9
    out.r_max = *hi;
    const double range = out.r_max - out.r_min;
    if (range > 0.0) {
      for (size_t t = 0; t < num_tets; ++t) {
        out.normalised[t] = (out.intensity[t] - out.r_min) / range;
      }
    }
  }
  return out;
}

}  // namespace somasim::models::meshless
