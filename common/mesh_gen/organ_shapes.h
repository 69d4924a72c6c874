// The shapes of the built-in organs, as implicit solids: a few ellipsoids and round cones joined
// by smooth unions, bent and dented where the organ is. Each shape sits with its centre near the
// origin, in metres, its long axis along x. docs/builtin_organs.md shows them.
//
// Sizes follow adult anatomy and the seeds' models: liver ~21 cm wide and ~1.5 L (seed 000's CT
// liver, Nava et al. 2008); kidney ~11.5 cm long, bean-shaped with a hilum; spleen ~12 cm long,
// a flattened crescent; gallbladder ~9 cm long, pear-shaped (seed 002's organs).
#pragma once

#include <Eigen/Core>
#include <memory>

#include "common/mesh_gen/implicit.h"

namespace somasim::mesh_gen {

// Polynomial smooth minimum (union) and maximum (intersection) of two distance-like values with
// blend radius k [m] > 0 (Quilez's quadratic smin): equal to min/max when |a - b| >= k.
double SmoothMin(double a, double b, double k);
double SmoothMax(double a, double b, double k);

// Distance-like value of an ellipsoid with centre c, semi-axes r (> 0) and orientation R
// (columns = the ellipsoid's axes in world coordinates): (|R^T (p - c) / r| - 1) · min(r).
double EllipsoidValue(const Eigen::Vector3d& p, const Eigen::Vector3d& centre,
                      const Eigen::Vector3d& semi_axes,
                      const Eigen::Matrix3d& rotation = Eigen::Matrix3d::Identity());

// Exact signed distance to a round cone: the convex hull of a sphere of radius ra at a and one of
// radius rb at b (Quilez). Used for the gallbladder's fundus-to-neck taper.
double RoundConeValue(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                      double ra, double rb);

enum class OrganShape { kLiver, kKidney, kSpleen, kGallbladder };

// The solid of an organ. Value is distance-like (a Lipschitz bound of about 2).
std::unique_ptr<ImplicitSolid> MakeOrganShape(OrganShape shape);

// A point inside the organ from which its surface is star-shaped (every ray from it leaves the
// solid once), and the organ's long axis (unit); used to lay out closed surface meshes.
struct OrganFrame {
  Eigen::Vector3d centre;
  Eigen::Vector3d long_axis;
};
OrganFrame OrganShapeFrame(OrganShape shape);

}  // namespace somasim::mesh_gen
