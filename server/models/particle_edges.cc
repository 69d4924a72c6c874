#include "server/models/particle_edges.h"

#include <algorithm>
#include <stdexcept>
#include <string>

namespace somasim::models {

std::vector<std::array<int32_t, 2>> SortedEdges(const std::vector<std::array<int32_t, 2>>& edges,
                                                Eigen::Index num_nodes, const char* model,
                                                const char* noun) {
  std::vector<std::array<int32_t, 2>> ordered;
  ordered.reserve(edges.size());
  for (size_t e = 0; e < edges.size(); ++e) {
    const auto [a, b] = edges[e];
    if (a < 0 || b < 0 || a >= num_nodes || b >= num_nodes || a == b) {
      throw std::invalid_argument(std::string(model) + ": " + noun + " " + std::to_string(e) +
                                  " joins nodes " + std::to_string(a) + " and " +
                                  std::to_string(b) + ", not two distinct nodes of 0.." +
                                  std::to_string(num_nodes - 1));
    }
    ordered.push_back({std::min(a, b), std::max(a, b)});
  }
  std::sort(ordered.begin(), ordered.end());
  return ordered;
}

double EdgeRestLength(const mesh::Points& rest, int32_t i, int32_t j, const char* model,
                      const char* noun) {
  const double length = (rest.col(j) - rest.col(i)).norm();
  if (!(length > 0.0)) {
    throw std::invalid_argument(std::string(model) + ": nodes " + std::to_string(i) + " and " +
                                std::to_string(j) + " coincide (a zero-length " + noun + ")");
  }
  return length;
}

void LumpMasses(const std::vector<double>& node_size, double density, double node_mass,
                std::vector<double>* mass, std::vector<double>* inverse_mass) {
  const size_t n = node_size.size();
  mass->resize(n);
  inverse_mass->resize(n);
  for (size_t i = 0; i < n; ++i) {
    (*mass)[i] = node_mass > 0.0 ? node_mass : density * node_size[i];
    (*inverse_mass)[i] = (*mass)[i] > 0.0 ? 1.0 / (*mass)[i] : 0.0;
  }
}

void NodeEdgeLists(size_t num_nodes, const std::vector<int32_t>& edge_i,
                   const std::vector<int32_t>& edge_j, std::vector<int32_t>* start,
                   std::vector<int32_t>* edges) {
  const size_t m = edge_i.size();
  start->assign(num_nodes + 1, 0);
  for (size_t e = 0; e < m; ++e) {
    ++(*start)[static_cast<size_t>(edge_i[e]) + 1];
    ++(*start)[static_cast<size_t>(edge_j[e]) + 1];
  }
  for (size_t i = 0; i < num_nodes; ++i) (*start)[i + 1] += (*start)[i];
  edges->resize(2 * m);
  std::vector<int32_t> fill(start->begin(), start->end() - 1);
  for (size_t e = 0; e < m; ++e) {
    (*edges)[static_cast<size_t>(fill[static_cast<size_t>(edge_i[e])]++)] = static_cast<int32_t>(e);
    (*edges)[static_cast<size_t>(fill[static_cast<size_t>(edge_j[e])]++)] = static_cast<int32_t>(e);
  }
}

void AddEdgeStiffness(const Eigen::Vector3d& d, double rest_length, double k,
                      Eigen::Matrix3d* k_local) {
  const double length = d.norm();
  if (!(length > 0.0)) return;
  const Eigen::Vector3d u = d / length;
  const Eigen::Matrix3d uu = u * u.transpose();
  *k_local += k * (uu + (1.0 - rest_length / length) * (Eigen::Matrix3d::Identity() - uu));
}

}  // namespace somasim::models
