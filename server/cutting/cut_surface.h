// The cut surface of a tetrahedral mesh: the boundary of its alive tetrahedra, each triangle
// marked as an inner face (exposed by a removal) or a face of the original outer surface. Built
// once from the volume's tetrahedra (it holds their face neighbours), then extracted for any alive
// flags: the cutter's own after a blade step, or a copy the cutting thread handed to the
// topology's publisher. Pure topology, no I/O.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"

namespace somasim::cutting {

// Local faces of a tetrahedron: face f is opposite corner f, outward for a positively oriented
// tetrahedron (as common/mesh/topology.cc).
inline constexpr int kTetFaces[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};
// Its six edges, as pairs of corners.
inline constexpr int kTetEdges[6][2] = {{0, 1}, {0, 2}, {0, 3}, {1, 2}, {1, 3}, {2, 3}};

class CutSurface {
 public:
  CutSurface() = default;  // no tetrahedra
  // `tets` (4 × num_tets) positively oriented, indices in [0, num_nodes). Throws
  // std::invalid_argument for an index out of range. Allocates.
  CutSurface(int32_t num_nodes, const mesh::Tetrahedra& tets);

  // The boundary of the tetrahedra whose flag is 1 (num_tets flags): outward, the volume's
  // numbering, 3 × F, faces ordered by tetrahedron and local face (as
  // mesh::ExtractBoundarySurface), and per triangle 1 when it is an inner face, else 0. Throws
  // std::invalid_argument when the flags are not num_tets. Sizes its outputs (allocates);
  // changes nothing here, so any thread may call it on a shared CutSurface.
  void Extract(std::span<const uint8_t> alive, mesh::Triangles* triangles,
               std::vector<uint8_t>* inner) const;

  int32_t num_tets() const { return static_cast<int32_t>(tets_.cols()); }
  const mesh::Tetrahedra& tets() const { return tets_; }
  // The neighbour of tetrahedron t across its face f: -1 on the original outer surface, -2 where
  // more than two tetrahedra share the face (mesh::TetFaceNeighbours).
  int32_t neighbour(int f, Eigen::Index t) const { return neighbours_(f, t); }

 private:
  mesh::Tetrahedra tets_;                                 // 4 × num_tets
  Eigen::Matrix<int32_t, 4, Eigen::Dynamic> neighbours_;  // 4 × num_tets
};

}  // namespace somasim::cutting
