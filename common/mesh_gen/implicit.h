// Implicit solids: the shapes of the built-in organs, before they are meshed.
//
// A solid is the region where Value(p) < 0. Value is continuous, > 0 outside and 0 on the
// surface; near the surface it approximates the signed distance [m] (within a factor of about
// two), so a Newton step p - Value·∇Value/|∇Value|² lands close to the surface. Pure functions,
// no I/O.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <vector>

#include "common/mesh/geometry.h"

namespace somasim::mesh_gen {

class ImplicitSolid {
 public:
  virtual ~ImplicitSolid() = default;
  // Signed value at p [m]: < 0 inside, > 0 outside.
  virtual double Value(const Eigen::Vector3d& p) const = 0;
  // A box that contains the whole solid: Value > 0 everywhere outside it.
  virtual mesh::BoundingBox Bounds() const = 0;
};

// Central-difference gradient of Value at p with step h [m] (h > 0).
Eigen::Vector3d ImplicitGradient(const ImplicitSolid& solid, const Eigen::Vector3d& p,
                                 double h = 1e-5);

// Moves p onto the surface by damped Newton steps along the gradient, at most max_iterations,
// stopping when |Value| < tolerance [m]. Returns the projected point (p itself if the gradient
// vanishes).
Eigen::Vector3d ProjectToSurface(const ImplicitSolid& solid, const Eigen::Vector3d& p,
                                 double tolerance = 1e-9, int max_iterations = 50);

// The point where Value changes sign on the segment [a, b], found by bisection refined with
// regula falsi (Illinois). Requires Value(a) and Value(b) of opposite signs (asserted);
// deterministic; |result - root| < tolerance [m].
Eigen::Vector3d FindSegmentRoot(const ImplicitSolid& solid, const Eigen::Vector3d& a,
                                const Eigen::Vector3d& b, double tolerance = 1e-12);

// An axis-aligned ellipsoid with centre c and semi-axes r [m] (all > 0). Value is the exact
// distance for a sphere and a distance-like scaling otherwise: (|(p-c)/r| - 1)·min(r).
class Ellipsoid final : public ImplicitSolid {
 public:
  Ellipsoid(const Eigen::Vector3d& centre, const Eigen::Vector3d& semi_axes);
  double Value(const Eigen::Vector3d& p) const override;
  mesh::BoundingBox Bounds() const override;

 private:
  Eigen::Vector3d centre_;
  Eigen::Vector3d semi_axes_;
};

}  // namespace somasim::mesh_gen
