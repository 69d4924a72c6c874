// Volume reaction of a closed shell through the solid angle at its surface nodes: seed 004
// ("Моделирование объемных тел", SPEC §4.3). A pure, allocation-free kernel that the particle
// models (position-based, mass-spring) add to their internal forces.
//
// Solid angle (seed 004 after Mazonka 2012, its ref. [6]). At surface node i with 1-ring unit
// vectors s_1..s_n, s_j = (x_j − x_i)/|x_j − x_i|,
//   Ω_i = 2π − Σ_j arg z_j,
//   z_j = (s_{j−1}·s_j)(s_j·s_{j+1}) − s_{j−1}·s_{j+1} + i s_{j−1}·(s_j × s_{j+1})   (cyclic j).
// arg z_j is the turning angle of the spherical polygon s_1..s_n at s_j (π minus its interior
// angle there), so Ω_i is the polygon's area by Gauss–Bonnet. The seed writes arg Π_j z_j; the
// sum of per-factor atan2 values in (−π, π] is the same angle modulo 2π without the wrap of the
// product's argument, so Ω_i is continuous as long as no turning angle crosses ±π (the ring
// would have to fold back onto itself). The rest value Ω_i0 uses the same formula.
//
// Convention (the seed leaves it open): Ω_i is the INTERIOR solid angle, the one the body fills
// at node i: 2π on a flat patch, π/2 at a cube's corner, 2π(1 − cos θ) at the apex of a circular
// cone of half-angle θ, less than 2π at a convex node and more than 2π in a dent. It is obtained
// by ordering each ring clockwise seen from outside (the triangles are counter-clockwise seen
// from outside, mesh_types.h); the opposite order gives the exterior angle 4π − Ω_i.
//
// Reaction. d_i = Ω_i − Ω_i0 [sr]. Seed 004 gives the reaction along the normal of the plane of
// the neighbours as γ+ d² + σ+ d (d > 0) and γ− d² − σ− d (d < 0). Read literally the d < 0
// branch has the same sign as the d > 0 one for γ−, σ− >= 0, which would not restore the shape.
// Here the reaction is restoring on both sides, of magnitude γ± d² + σ± |d|, and derives from a
// potential so that it conserves momentum, angular momentum and energy:
//   E_i = σ± d²/2 + γ± |d|³/3   (± the sign of d),   E = Σ_i E_i,   f = −∂E/∂x,
// so the generalised force conjugate to Ω_i is −dE_i/dd = −(σ± d + γ± d|d|), whose magnitude is
// the seed's law σ±|d| + γ± d². It acts on node i and on its ring through the lever ∂Ω_i/∂x
// [1/m]: f = −E_i'(d) ∂Ω_i/∂x for every node x of the term (exact analytic gradient). Since Ω_i
// depends only on directions from x_i, the ring's forces sum to minus node i's (no net force)
// and Ω_i is rotation invariant (no net torque).
//
// Relation to the seed's direction. For a regular ring (neighbours evenly spread on a circle)
// ∂Ω_i/∂x_i lies, by symmetry, exactly along the normal of the neighbours' plane, pointing into
// the body (moving node i inwards opens the angle); on an irregular ring it is close to that
// normal (within 0.3° on an 80-vertex sphere mesh, tested). So a dent (d > 0) pushes node i
// outwards and a bulge (d < 0) pulls it back, as the seed intends; the equal and opposite forces on
// the ring are what makes the reaction a potential. The seed's force in newtons for node i's own
// term equals ours with its σ, γ multiplied by |∂Ω_i/∂x_i| (about 1 / edge length).
//
// Units: E [J], Ω [sr], so σ± [J/sr²] and γ± [J/sr³]; forces [N], stiffness [N/m].
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
