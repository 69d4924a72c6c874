#include "server/cutting/cut_surface.h"

#include <stdexcept>
#include <string>

#include "common/mesh/topology.h"

namespace somasim::cutting {

CutSurface::CutSurface(int32_t num_nodes, const mesh::Tetrahedra& tets) : tets_(tets) {
  for (Eigen::Index t = 0; t < tets_.cols(); ++t) {
    for (int k = 0; k < 4; ++k) {
      if (tets_(k, t) < 0 || tets_(k, t) >= num_nodes) {
        throw std::invalid_argument("cut surface: tetrahedron " + std::to_string(t) + " has node " +
                                    std::to_string(tets_(k, t)) + ", outside 0.." +
                                    std::to_string(num_nodes - 1));
      }
    }
  }
  neighbours_ = mesh::TetFaceNeighbours(num_nodes, tets_);
}

void CutSurface::Extract(std::span<const uint8_t> alive, mesh::Triangles* triangles,
                         std::vector<uint8_t>* inner) const {
  if (alive.size() != static_cast<size_t>(tets_.cols())) {
    throw std::invalid_argument("cut surface: " + std::to_string(alive.size()) +
                                " alive flags for " + std::to_string(tets_.cols()) + " tetrahedra");
  }
  std::vector<int32_t> faces;  // 4 t + f
  for (Eigen::Index t = 0; t < tets_.cols(); ++t) {
    if (alive[static_cast<size_t>(t)] == 0) continue;
    for (int f = 0; f < 4; ++f) {
      const int32_t nb = neighbours_(f, t);
      if (nb >= 0 && alive[static_cast<size_t>(nb)] != 0) continue;
      faces.push_back(static_cast<int32_t>(4 * t + f));
    }
  }
  triangles->resize(3, static_cast<Eigen::Index>(faces.size()));
  inner->resize(faces.size());
  for (size_t i = 0; i < faces.size(); ++i) {
    const int32_t t = faces[i] / 4;
    const int f = faces[i] % 4;
    for (int k = 0; k < 3; ++k)
      (*triangles)(k, static_cast<Eigen::Index>(i)) = tets_(kTetFaces[f][k], t);
    (*inner)[i] = neighbours_(f, t) >= 0 ? 1 : 0;
  }
}

}  // namespace somasim::cutting
