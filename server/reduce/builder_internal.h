// Internal to somasim-reduce's engine (builder.cc, builder_nonlinear.cc): the helpers both
// builds use. Not part of the builder's interface.
#pragma once

#include <Eigen/Core>
#include <string>
#include <utility>

namespace somasim::reduce::builder_internal {

// Throws std::invalid_argument("sampling plan: " + what) unless ok.
void Require(bool ok, const std::string& what);

// Two unit tangents orthogonal to n (unit) and to each other.
std::pair<Eigen::Vector3d, Eigen::Vector3d> Tangents(const Eigen::Vector3d& n);

}  // namespace somasim::reduce::builder_internal
