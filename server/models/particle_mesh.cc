#include "server/models/particle_mesh.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "common/mesh/geometry.h"

namespace somasim::models {
namespace {

[[noreturn]] void Refuse(const char* model, const std::string& what) {
  throw std::invalid_argument(std::string(model) + ": " + what);
}

template <int kCorners>
void CheckElements(const Eigen::Matrix<int32_t, kCorners, Eigen::Dynamic>& elements,
                   Eigen::Index num_nodes, const char* kind, const char* kinds, const char* model) {
  if (elements.cols() == 0) Refuse(model, std::string("the mesh has no ") + kinds);
  for (Eigen::Index e = 0; e < elements.cols(); ++e) {
    for (int c = 0; c < kCorners; ++c) {
      const int32_t node = elements(c, e);
      if (node < 0 || node >= num_nodes) {
        Refuse(model, std::string(kind) + " " + std::to_string(e) + " uses node " +
                          std::to_string(node) + ", outside 0.." + std::to_string(num_nodes - 1));
      }
    }
  }
}

template <int kCorners>
MeshEdges CollectEdges(const Eigen::Matrix<int32_t, kCorners, Eigen::Dynamic>& elements,
                       const std::vector<double>& element_size, Eigen::Index num_nodes) {
  struct Entry {
    std::array<int32_t, 2> edge;
    double size;
  };
  std::vector<Entry> entries;
  entries.reserve(static_cast<size_t>(elements.cols()) * kCorners * (kCorners - 1) / 2);
  MeshEdges result;
  result.node_size.assign(static_cast<size_t>(num_nodes), 0.0);
  for (Eigen::Index e = 0; e < elements.cols(); ++e) {
    const double size = element_size[static_cast<size_t>(e)];
    for (int a = 0; a < kCorners; ++a) {
      const int32_t na = elements(a, e);
      result.node_size[static_cast<size_t>(na)] += size / kCorners;
      for (int b = a + 1; b < kCorners; ++b) {
        const int32_t nb = elements(b, e);
        entries.push_back({{std::min(na, nb), std::max(na, nb)}, size});
      }
    }
  }
  std::sort(entries.begin(), entries.end(),
            [](const Entry& x, const Entry& y) { return x.edge < y.edge; });
  for (const Entry& entry : entries) {
    if (!result.edges.empty() && result.edges.back() == entry.edge) {
      result.edge_size.back() += entry.size;
    } else {
      result.edges.push_back(entry.edge);
      result.edge_size.push_back(entry.size);
    }
  }
  return result;
}

}  // namespace

void CheckFinitePoints(const mesh::Points& points, const char* model) {
  if (points.cols() == 0) Refuse(model, "the mesh has no nodes");
  for (Eigen::Index i = 0; i < points.cols(); ++i) {
    if (!points.col(i).allFinite()) {
      Refuse(model, "node " + std::to_string(i) + " has a non-finite coordinate");
    }
  }
}

MeshEdges TetMeshEdges(const mesh::TetMesh& mesh, const char* model) {
  CheckFinitePoints(mesh.vertices, model);
  CheckElements<4>(mesh.tetrahedra, mesh.vertices.cols(), "tetrahedron", "tetrahedra", model);
  std::vector<double> volume(static_cast<size_t>(mesh.tetrahedra.cols()));
  for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
    volume[static_cast<size_t>(t)] =
        std::abs(mesh::TetSignedVolume(mesh.vertices, mesh.tetrahedra.col(t)));
  }
  return CollectEdges<4>(mesh.tetrahedra, volume, mesh.vertices.cols());
}

MeshEdges SurfaceEdges(const mesh::SurfaceMesh& surface, double thickness, const char* model) {
  CheckFinitePoints(surface.vertices, model);
  CheckElements<3>(surface.triangles, surface.vertices.cols(), "triangle", "triangles", model);
  std::vector<double> shell_volume(static_cast<size_t>(surface.triangles.cols()));
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    const Eigen::Vector3d a = surface.vertices.col(surface.triangles(0, t));
    const Eigen::Vector3d b = surface.vertices.col(surface.triangles(1, t));
    const Eigen::Vector3d c = surface.vertices.col(surface.triangles(2, t));
    shell_volume[static_cast<size_t>(t)] = 0.5 * (b - a).cross(c - a).norm() * thickness;
  }
  return CollectEdges<3>(surface.triangles, shell_volume, surface.vertices.cols());
}

void ApplyFixedAndPrescribed(const StepInputs& inputs, TissueState* state) {
  const double dt = inputs.dt;
  for (const int32_t node : inputs.fixed_nodes) {
    state->positions.col(node) -= dt * state->velocities.col(node);
    state->velocities.col(node).setZero();
  }
  for (size_t k = 0; k < inputs.prescribed_nodes.size(); ++k) {
    const int32_t node = inputs.prescribed_nodes[k];
    const Eigen::Vector3d target = inputs.prescribed_positions->col(static_cast<Eigen::Index>(k));
    const Eigen::Vector3d before = state->positions.col(node) - dt * state->velocities.col(node);
    state->velocities.col(node) = (target - before) / dt;
    state->positions.col(node) = target;
  }
}

void AddKineticAndGravity(const std::vector<double>& masses, const TissueState& state,
                          const Eigen::Vector3d& gravity, EnergyReport* report) {
  for (Eigen::Index i = 0; i < state.positions.cols(); ++i) {
    const double m = masses[static_cast<size_t>(i)];
    report->kinetic += 0.5 * m * state.velocities.col(i).squaredNorm();
    report->gravity -= m * gravity.dot(state.positions.col(i));
    report->momentum += m * state.velocities.col(i);
  }
}

}  // namespace somasim::models
