// Vertex-preserving cutting of a tetrahedral mesh (SPEC §5.3; seed 003, Nakao et al., §3–4):
// the blade PQ sweeps a quad S_t between two poses; a tetrahedron is cut when S_t crosses one of
// its edges; the cut tetrahedra's vertices are relocated onto the sweep and the cut tetrahedra
// are removed. No vertex is ever added or deleted. Pure geometry and topology (no physics, no
// I/O); every buffer is sized at construction, so a blade step allocates nothing.
//
// One step (Step), in stages: 1. the cut set, the tetrahedra the sweep crosses and, of those,
// the severed ones; 2. the removed set, its boundary kept a manifold (or the whole step undone);
// 3. the relocation of the removed tetrahedra's vertices (seed 003 eq. 1 and 2), never inverting
// an element; 4. the removal: alive flags and counts, the topology version +1 when anything was
// removed. Each stage's rules are narrated where it is implemented (tet_cutter.cc,
// tet_cutter_pinch.cc, tet_cutter_relocation.cc) and explained in docs/cutting.md.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/cutting/cut_surface.h"
#include "server/models/cut_geometry.h"

namespace somasim::cutting {

struct CutSettings {
  double min_volume_fraction = 0.05;  // a relocation keeps alive tets above this share
};

struct CutStepResult {
  int32_t cut = 0;         // |C|: tetrahedra the sweep crossed
  int32_t removed = 0;     // |R|
  int32_t pending = 0;     // crossed but not yet severed: waiting for the blade to pass
  int32_t kept = 0;        // severed but kept so that no vertex is orphaned
  int32_t repaired = 0;    // removed besides (of `removed`) to keep the boundary a manifold
  int32_t unresolved = 0;  // pinches that neither removing nor putting back could open ...
  bool undone = false;     // ... so the step was undone: nothing removed, nothing moved
  int32_t relocated = 0;   // vertices moved
  int32_t shortened = 0;   // moves shortened (or dropped) by the inversion guard
};

class TetCutter {
 public:
  // `tets` positively oriented, indices in [0, num_nodes); `positions` the configuration the
  // blade cuts in (3 × num_nodes). Throws std::invalid_argument for bad indices or sizes.
  TetCutter(const mesh::Tetrahedra& tets, const mesh::Points& positions,
            const CutSettings& settings = CutSettings{});

  // A new incision: forgets the sweep history (the tip's path) of the previous one.
  void BeginIncision();
  // One blade step from the previous pose (sweep.p0, q0) to this one (p1, q1): see above.
  // `positions` (3 × num_nodes) are relocated in place. A sweep that is not finite or has no
  // area cuts nothing.
  CutStepResult Step(const models::SweptQuad& sweep, mesh::Points* positions);

  int32_t num_nodes() const { return num_nodes_; }
  int32_t num_tets() const { return static_cast<int32_t>(alive_.size()); }
  int32_t num_alive() const { return num_alive_; }
  bool alive(int32_t tet) const { return alive_[static_cast<size_t>(tet)] != 0; }
  const std::vector<uint8_t>& alive_flags() const { return alive_; }
  uint32_t topology_version() const { return topology_version_; }
  // This step's removed tetrahedra and relocated vertices (valid until the next Step).
  std::span<const int32_t> removed_tets() const { return {removed_.data(), removed_count_}; }
  std::span<const int32_t> moved_nodes() const { return {moved_.data(), moved_count_}; }

  // The boundary of the alive tetrahedra (outward, the volume's numbering; faces ordered by
  // tetrahedron and local face, as mesh::ExtractBoundarySurface) and, per triangle, 1 when it is
  // an inner face (exposed by a removal), else 0. For the topology's republication after a cut,
  // not for the step: it sizes its outputs.
  void ExtractSurface(mesh::Triangles* triangles, std::vector<uint8_t>* inner) const;
  // The same for other alive flags (num_tets of them, 1 = alive): a copy the cutting thread
  // handed over. Touches no scratch of the cutter, so another thread may call it while this
  // cutter is idle or on a different instance. Both are the cutter's CutSurface::Extract; a
  // reader that needs only this holds a CutSurface of its own instead of a TetCutter.
  void ExtractSurface(std::span<const uint8_t> alive, mesh::Triangles* triangles,
                      std::vector<uint8_t>* inner) const;

  // Whether node is on the original outer surface.
  bool on_surface(int32_t node) const { return on_surface_[static_cast<size_t>(node)] != 0; }

  static constexpr int kHistory = 256;  // sweep quads (and tip segments) remembered

 private:
  // Step's stages (tet_cutter.cc; the pinch repairs and the undo in tet_cutter_pinch.cc, the
  // relocation in tet_cutter_relocation.cc).
  void FindCrossed(const models::SweptQuad& sweep, const Eigen::Vector3d& lo,
                   const Eigen::Vector3d& hi, double tolerance, const mesh::Points& x);
  void KeepSevered(const models::SweptQuad& sweep, const Eigen::Vector3d& n, double tolerance,
                   double inside_tolerance, const mesh::Points& x);
  void RemoveSevered(CutStepResult* result);
  void RepairPinches();
  bool UndoIfPinched(size_t severed_removed, CutStepResult* result);
  size_t CompactRemoved(size_t severed_removed);
  void RelocateVertices(const models::SweptQuad& sweep, const Eigen::Vector3d& n,
                        size_t severed_count, mesh::Points* positions, CutStepResult* result);

  Eigen::Vector3d Relocate(int32_t node, const Eigen::Vector3d& v, const Eigen::Vector3d& n,
                           const models::SweptQuad& sweep, const mesh::Points& x) const;
  bool InsideSwept(const Eigen::Vector3d& x, double tolerance) const;
  // Whether the boundary segment of the swept region nearest to y is the tip's path (then a, b
  // are that segment) rather than the blade p1 q1.
  bool NearestIsTipPath(const Eigen::Vector3d& y, const models::SweptQuad& sweep,
                        Eigen::Vector3d* a, Eigen::Vector3d* b) const;
  Eigen::Vector3d SurfaceNormal(int32_t node, const mesh::Points& x) const;
  // Removes the tetrahedra of all but the largest group of alive ones around vertex v (w < 0)
  // or edge (v, w) — groups linked across faces holding v (and w) — unless that orphans a
  // vertex; whether it removed any.
  bool SplitPinch(int32_t v, int32_t w, bool dry_run);
  // Where the boundary triangles around v form two or more fans (its link an annulus: a tube
  // pinched at v), removes the shortest chain of tetrahedra around v joining the first fan to
  // another, unless that orphans a vertex; whether it removed any.
  bool SplitLink(int32_t v, bool dry_run);
  // Whether v's alive tetrahedra fall into groups or its boundary into fans.
  bool Pinched(int32_t v);
  // Puts back one tetrahedron holding v that this step removed, if that unpinches v.
  bool RestoreAround(int32_t v);
  // Marks t removed and lists it; false when this step's list is full.
  bool Remove(int32_t t);
  // Removes chosen_[0 .. count) unless that would leave a vertex in no alive tetrahedron;
  // whether it removed them.
  bool RemoveAllOrNone(int32_t count);
  // Node k (0..3) of tetrahedron t: the tetrahedra are surface_'s.
  int32_t tet_node(int k, Eigen::Index t) const { return surface_.tets()(k, t); }

  static constexpr int32_t kMaxFan = 256;
  std::array<int32_t, 3 * kMaxFan> link_{};
  std::array<int32_t, 3 * kMaxFan> link_parent_{};
  std::array<int32_t, kMaxFan> dist_{};
  std::array<int32_t, kMaxFan> parent_{};
  std::array<int32_t, kMaxFan> fan_{};
  std::array<int32_t, kMaxFan> chosen_{};  // what RemoveAllOrNone takes
  std::array<int32_t, kMaxFan> group_{};

  int32_t num_nodes_ = 0;
  CutSettings settings_;
  std::vector<uint8_t> alive_;
  int32_t num_alive_ = 0;
  std::vector<int32_t> node_alive_;        // alive tets per node
  std::vector<int32_t> node_tet_offsets_;  // node -> tets (all, alive or not)
  std::vector<int32_t> node_tet_entries_;
  CutSurface surface_;  // the tetrahedra, their face neighbours (-1 outside), the extraction
  std::vector<uint8_t> on_surface_;
  uint32_t topology_version_ = 0;

  // History of this incision: quads and tip segments, rings of kHistory.
  std::array<models::SweptQuad, kHistory> quads_{};
  int32_t num_quads_ = 0;  // total this incision (the ring holds the last kHistory)

  // Scratch, sized at construction.
  std::vector<int32_t> cut_;
  std::vector<int32_t> pending_;  // crossed, not yet severed
  size_t pending_count_ = 0;
  std::vector<uint32_t> pending_mark_;
  uint32_t pending_epoch_ = 0;
  std::vector<uint32_t> tet_stamp_;  // per tet: == tet_epoch_ when already listed
  uint32_t tet_epoch_ = 0;
  std::vector<int32_t> removed_;
  size_t removed_count_ = 0;
  std::vector<int32_t> moved_;
  size_t moved_count_ = 0;
  std::vector<uint32_t> stamp_;  // per node: == epoch_ when already in moved_
  std::vector<int32_t> losing_;  // per node: tets a pinch repair would take (0 between uses)
  uint32_t epoch_ = 0;
  std::vector<double> volume_before_;  // per tet, this step
};

}  // namespace somasim::cutting
