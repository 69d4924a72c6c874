// Volume reaction of a closed shell through the solid angle at its surface nodes: seed 004
// ("Моделирование объемных тел", SPEC §4.3). A pure, allocation-free kernel that the particle
// models (position-based, mass-spring) add to their internal forces. At each surface node the
// restoring reaction to the change d = Ω − Ω0 of its interior solid angle (Mazonka's formula)
// derives from the potential E = σ± d²/2 + γ± |d|³/3, with the exact analytic gradient over the
// node and its ring; docs/models.md derives it and says where the seed is read. Units: E [J],
// Ω [sr], σ± [J/sr²], γ± [J/sr³].
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "common/mesh/mesh_types.h"

namespace somasim::models {

struct SolidAngleVolumeParameters {
  double gamma_plus = 0.0;   // γ+ [J/sr³], finite, >= 0: cubic term of E for d > 0 (dents)
  double sigma_plus = 0.0;   // σ+ [J/sr²], finite, >= 0: quadratic term of E for d > 0
  double gamma_minus = 0.0;  // γ− [J/sr³], finite, >= 0: cubic term of E for d < 0 (bulges)
  double sigma_minus = 0.0;  // σ− [J/sr²], finite, >= 0: quadratic term of E for d < 0
};

class SolidAngleVolumeTerm {
 public:
  // One term per vertex of a closed, consistently oriented (counter-clockwise seen from
  // outside), manifold triangle surface; the rest shape is surface.vertices.
  // Throws std::invalid_argument, prefixed "solid-angle volume: ", naming the fault: a parameter
  // negative or not finite; no triangles; a non-finite vertex; a triangle index out of range or
  // repeated; an edge with a single triangle (open surface); an edge used twice in the same
  // direction (non-manifold edge or inconsistent orientation); a vertex whose triangles form
  // several fans (non-manifold vertex); a degenerate ring at rest (a neighbour at the node's
  // position, or two consecutive neighbours in line with the node, i.e. a zero-angle triangle
  // corner); a rest solid angle outside (0, 4π) (a folded ring).
  static SolidAngleVolumeTerm Build(const mesh::SurfaceMesh& surface,
                                    const SolidAngleVolumeParameters& parameters);
  // The same on a subset of a larger model's nodes: `triangles` (3 × num_triangles) index into
  // `rest` (3 × num_points), e.g. the boundary of a tetrahedral mesh. Points that no triangle
  // uses get no term and no force.
  static SolidAngleVolumeTerm Build(const mesh::Points& rest, const mesh::Triangles& triangles,
                                    const SolidAngleVolumeParameters& parameters);

  int32_t num_points() const { return num_points_; }  // columns expected in x and forces
  int32_t num_terms() const { return static_cast<int32_t>(nodes_.size()); }
  const SolidAngleVolumeParameters& parameters() const { return parameters_; }
  // True when `node` is a vertex of the surface (has a term).
  bool HasTerm(int32_t node) const;
  // Ring of `node` (requires HasTerm), clockwise seen from outside: the order Ω_i uses.
  std::vector<int32_t> Ring(int32_t node) const;
  // Ω_i0 at rest [sr] (requires HasTerm).
  double RestSolidAngle(int32_t node) const;

  // The interior solid angle Ω_i [sr] at `node` for positions x (3 × num_points [m]).
  // Throws std::out_of_range if `node` has no term.
  double SolidAngle(const mesh::Points& x, int32_t node) const;
  // E = Σ_i E_i [J]. Allocation-free.
  double Energy(const mesh::Points& x) const;
  // forces (3 × num_points [N]) += −∂E/∂x. Allocation-free; x and forces must have
  // num_points columns (asserted).
  void AddForces(const mesh::Points& x, mesh::Points* forces) const;
  // −∂f_node/∂x_node [N/m], 3 × 3, of the total reaction on `node` (its own term and its
  // neighbours' terms), by central differences of the analytic force with a step of 1e-6 × the
  // node's mean ring edge, symmetrised (the exact matrix, a diagonal block of E's Hessian, is
  // symmetric); relative accuracy about 1e-8. Near rest it is Σ σ± g gᵀ over those terms
  // (g = ∂Ω/∂x_node), positive semi-definite; away from rest the E'·∂²Ω part can make it
  // indefinite. Zero for a point without a term. Allocation-free.
  Eigen::Matrix3d LocalStiffness(const mesh::Points& x, int32_t node) const;

 private:
  SolidAngleVolumeTerm() = default;

  int32_t num_points_ = 0;
  SolidAngleVolumeParameters parameters_;
  std::vector<int32_t> nodes_;         // node of each term, num_terms
  std::vector<int32_t> ring_offsets_;  // num_terms + 1; term t's ring is ring_[off[t], off[t+1])
  std::vector<int32_t> ring_;          // rings, clockwise seen from outside
  std::vector<double> rest_angle_;     // Ω_i0 [sr], num_terms
  std::vector<int32_t> term_of_node_;  // num_points; −1 when a point has no term
};

}  // namespace somasim::models
