#include "server/models/meshless/adaptivity.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace somasim::models::meshless {

CellIntensityEvaluator::CellIntensityEvaluator(const MlsShapeFunctions& shape,
                                               const mesh::Tetrahedra& tets)
    : num_nodes_(shape.num_nodes()) {
  const auto num_tets = static_cast<size_t>(tets.cols());
  // The degree-2 rule: the four permutations of (a, a, a, b).
  constexpr double kA = 0.1381966011250105, kB = 0.5854101966249685;
  const mesh::Points& x = shape.nodes();
  start_.reserve(4 * num_tets + 1);
  start_.push_back(0);
  slope_.resize(num_tets);
  volume_.resize(num_tets);
  MlsEvaluation eval;
  for (size_t t = 0; t < num_tets; ++t) {
    const auto c = static_cast<Eigen::Index>(t);
    for (int a = 0; a < 4; ++a) {
      if (tets(a, c) < 0 || tets(a, c) >= num_nodes_) {
        throw std::invalid_argument("adaptivity: tetrahedron " + std::to_string(t) +
                                    " has a node index out of range");
      }
    }
    const auto corner = [&](int a) -> Eigen::Vector3d { return x.col(tets(a, c)); };
    volume_[t] =
        std::abs((corner(1) - corner(0)).cross(corner(2) - corner(0)).dot(corner(3) - corner(0))) /
        6.0;
    if (!(volume_[t] > 0.0)) {
      throw std::invalid_argument("adaptivity: tetrahedron " + std::to_string(t) + " is flat");
    }
    const Eigen::Vector3d centroid = 0.25 * (corner(0) + corner(1) + corner(2) + corner(3));
    Eigen::Matrix4d fit;  // rows: (1, x_g − x_c)
    for (int g = 0; g < 4; ++g) {
      Eigen::Vector3d p = Eigen::Vector3d::Zero();
      for (int a = 0; a < 4; ++a) p += (a == g ? kB : kA) * corner(a);
      shape.Evaluate(p, true, &eval);
      for (size_t j = 0; j < eval.nodes.size(); ++j) {
        node_.push_back(eval.nodes[j]);
        gradient_.emplace_back(eval.gradients.col(static_cast<Eigen::Index>(j)));
      }
      start_.push_back(static_cast<int64_t>(node_.size()));
      fit(g, 0) = 1.0;
      fit.block<1, 3>(g, 1) = (p - centroid).transpose();
    }
    slope_[t] = fit.inverse().bottomRows<3>();  // ∇DSE = slope · (DSE_g)
  }
}

CellIntensity CellIntensityEvaluator::Compute(const mesh::Points& parameters, double lambda,
                                              double mu) const {
  if (parameters.cols() != num_nodes_) {
    throw std::invalid_argument("adaptivity: parameters must be 3 x num_nodes (" +
                                std::to_string(num_nodes_) + ")");
  }
  if (!parameters.allFinite()) throw std::invalid_argument("adaptivity: parameters not finite");
  const size_t num_tets = volume_.size();
  CellIntensity out;
  out.energy_density.assign(num_tets, 0.0);
  out.gradient.assign(num_tets, 0.0);
  out.node_density.assign(num_tets, 0.0);
  out.intensity.assign(num_tets, 0.0);
  out.normalised.assign(num_tets, 0.0);
  for (size_t t = 0; t < num_tets; ++t) {
    Eigen::Vector4d density;
    for (size_t k = 0; k < 4; ++k) {
      const size_t g = 4 * t + k;
      Eigen::Matrix3d grad = Eigen::Matrix3d::Zero();  // ∂u_i/∂x_j
      for (auto a = static_cast<size_t>(start_[g]); a < static_cast<size_t>(start_[g + 1]); ++a) {
        grad += parameters.col(node_[a]) * gradient_[a].transpose();
      }
      const Eigen::Matrix3d strain = 0.5 * (grad + grad.transpose());
      const Eigen::Matrix3d stress =
          lambda * strain.trace() * Eigen::Matrix3d::Identity() + 2.0 * mu * strain;
      density[static_cast<Eigen::Index>(k)] = 0.5 * stress.cwiseProduct(strain).sum();  // eq. 1
    }
    out.energy_density[t] = density.mean();          // the linear fit's value at the centroid
    out.gradient[t] = (slope_[t] * density).norm();  // eq. 2–4
    out.node_density[t] = 4.0 / volume_[t];          // eq. 5
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

CellIntensity ComputeCellIntensity(const MlsShapeFunctions& shape, const mesh::Tetrahedra& tets,
                                   const mesh::Points& parameters, double lambda, double mu) {
  if (parameters.cols() != shape.num_nodes()) {
    throw std::invalid_argument("adaptivity: parameters must be 3 x num_nodes (" +
                                std::to_string(shape.num_nodes()) + ")");
  }
  return CellIntensityEvaluator(shape, tets).Compute(parameters, lambda, mu);
}

}  // namespace somasim::models::meshless
