#include "server/models/fem/tet_elements.h"

#include <Eigen/Dense>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "server/models/particle_mesh.h"

namespace somasim::models::fem {
namespace {

[[noreturn]] void Refuse(const char* model, const std::string& what) {
  throw std::invalid_argument(std::string(model) + ": " + what);
}

}  // namespace

TetElements BuildTetElements(const mesh::TetMesh& mesh, const char* model) {
  CheckFinitePoints(mesh.vertices, model);
  const Eigen::Index n = mesh.vertices.cols();
  const Eigen::Index m = mesh.tetrahedra.cols();
  if (m == 0) Refuse(model, "the mesh has no tetrahedra");
  TetElements out;
  out.tets = mesh.tetrahedra;
  out.gradients.resize(3, 4 * m);
  out.volumes.resize(static_cast<size_t>(m));
  out.node_volume.assign(static_cast<size_t>(n), 0.0);
  for (Eigen::Index e = 0; e < m; ++e) {
    for (int a = 0; a < 4; ++a) {
      const int32_t node = mesh.tetrahedra(a, e);
      if (node < 0 || node >= n) {
        Refuse(model, "tetrahedron " + std::to_string(e) + " uses node " + std::to_string(node) +
                          ", outside 0.." + std::to_string(n - 1));
      }
      for (int b = 0; b < a; ++b) {
        if (mesh.tetrahedra(b, e) == node) {
          Refuse(model,
                 "tetrahedron " + std::to_string(e) + " repeats node " + std::to_string(node));
        }
      }
    }
    const Eigen::Vector3d x0 = mesh.vertices.col(mesh.tetrahedra(0, e));
    Eigen::Matrix3d dm;  // [X1 - X0, X2 - X0, X3 - X0]
    double longest = 0.0;
    for (int a = 1; a < 4; ++a) {
      dm.col(a - 1) = mesh.vertices.col(mesh.tetrahedra(a, e)) - x0;
      for (int b = 0; b < a; ++b) {
        longest = std::max(longest, (mesh.vertices.col(mesh.tetrahedra(a, e)) -
                                     mesh.vertices.col(mesh.tetrahedra(b, e)))
                                        .norm());
      }
    }
    const double volume = dm.determinant() / 6.0;
    if (!(volume > 1e-12 * longest * longest * longest)) {
      Refuse(model, "tetrahedron " + std::to_string(e) +
                        (volume < 0.0 ? " is inverted (negative volume)" : " is flat (no volume)"));
    }
    // F = Ds Dm⁻¹ = Σ_a x_a ∇N_aᵀ: ∇N_a (a = 1..3) is row a-1 of Dm⁻¹, ∇N_0 = -Σ.
    const Eigen::Matrix3d inverse = dm.inverse();
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (int a = 1; a < 4; ++a) {
      out.gradients.col(4 * e + a) = inverse.row(a - 1).transpose();
      sum += inverse.row(a - 1).transpose();
    }
    out.gradients.col(4 * e) = -sum;
    out.volumes[static_cast<size_t>(e)] = volume;
    for (int a = 0; a < 4; ++a) {
      out.node_volume[static_cast<size_t>(mesh.tetrahedra(a, e))] += volume / 4.0;
    }
  }
  out.node_start.assign(static_cast<size_t>(n) + 1, 0);
  for (Eigen::Index e = 0; e < m; ++e) {
    for (int a = 0; a < 4; ++a) ++out.node_start[static_cast<size_t>(mesh.tetrahedra(a, e)) + 1];
  }
  for (Eigen::Index i = 0; i < n; ++i) {
    out.node_start[static_cast<size_t>(i) + 1] += out.node_start[static_cast<size_t>(i)];
  }
  out.element_of_node.resize(static_cast<size_t>(4 * m));
  std::vector<int32_t> fill(out.node_start.begin(), out.node_start.end() - 1);
  for (Eigen::Index e = 0; e < m; ++e) {
    for (int a = 0; a < 4; ++a) {
      const auto node = static_cast<size_t>(mesh.tetrahedra(a, e));
      out.element_of_node[static_cast<size_t>(fill[node]++)] = static_cast<int32_t>(4 * e + a);
    }
  }
  return out;
}

Eigen::Matrix3d PolarRotation(const Eigen::Matrix3d& f) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(f, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d u = svd.matrixU();
  const Eigen::Matrix3d& v = svd.matrixV();
  // Singular values are sorted decreasing: flipping the last column of U (the smallest singular
  // value's) makes R proper when det(U Vᵀ) = -1 (an inverted or reflected element).
  if ((u * v.transpose()).determinant() < 0.0) u.col(2) = -u.col(2);
  return u * v.transpose();
}

}  // namespace somasim::models::fem
