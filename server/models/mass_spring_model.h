// Mass-spring system (MSS), seed 002 §2.1 eq. 1–5 (SPEC §4.1): springs along the mesh edges
// (a tetrahedral mesh's edges, or a surface's triangle edges), damping along each spring, and
// symplectic Euler integration as in the seed. Pure kernel.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/tissue_model.h"

namespace somasim::models {

// The material, given physically and mapped to springs by a documented rule (docs/models.md):
// spring constant k_e = E · Σ_{elements ∋ e} size(element) / |e|² (Van Gelder 1998, "Approximate
// simulation of elastic membranes by triangulated spring meshes"; size = volume for
// tetrahedra, area × thickness for triangles), lumped masses ρ · size / corners, and damping
// D_e = 2 ζ √(k_e m_e) with the pair's reduced mass m_e = m_i m_j / (m_i + m_j). A spring network
// cannot represent Poisson's ratio (it fixes ν = 1/4 in 3-D), so none is asked for.
enum class MassSpringIntegrator {
  // Seed 002 eq. 4–5: v += dt f/m, x += dt v. Cheap; stable while dt < 2/ω_max.
  kSymplecticEuler,
  // Linearised backward Euler (Baraff & Witkin 1998): (M + dt C + dt² K) Δv = dt (f - dt K v),
  // solved by Jacobi-preconditioned conjugate gradients, matrix-free over the springs. Stable
  // for stiff tissue at 1 ms. K keeps only the non-negative transverse stiffness
  // k (1 - l0/l)₊ so the system stays positive definite.
  kImplicitEuler,
};

struct MassSpringParameters {
  double youngs_modulus = 0.0;  // E [Pa], > 0 (unless spring_stiffness is given)
  double density = 1000.0;      // ρ [kg/m³], > 0 (unless node_mass is given)
  double damping_ratio = 0.05;  // ζ [-], >= 0: fraction of each spring's critical damping
  double thickness = 0.005;     // [m], > 0: shell thickness of a surface mesh
  // Raw constants, when > 0, replace the physical rule: every spring gets spring_stiffness
  // [N/m] and every node node_mass [kg].
  double spring_stiffness = 0.0;
  double node_mass = 0.0;
  double speed_limit = 100.0;  // [m/s], > 0: a faster node marks a diverged step
  MassSpringIntegrator integrator = MassSpringIntegrator::kSymplecticEuler;
  double cg_tolerance = 1e-8;   // implicit: relative residual |r|/|b| at which CG stops, > 0
  int cg_max_iterations = 500;  // implicit: CG iterations per step at most, > 0
};

class MassSpringModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the bad parameter or mesh fault (no elements, NaN
  // coordinates, zero-length edge, index out of range).
  static std::unique_ptr<MassSpringModel> FromTetMesh(const mesh::TetMesh& mesh,
                                                      const MassSpringParameters& parameters);
  static std::unique_ptr<MassSpringModel> FromSurface(const mesh::SurfaceMesh& surface,
                                                      const MassSpringParameters& parameters);

  // Springs given explicitly (pairs of node indices into rest, 3 × num_nodes), with the raw
  // constants spring_stiffness and node_mass, which must both be > 0 here.
  static std::unique_ptr<MassSpringModel> FromEdges(
      const mesh::Points& rest, const std::vector<std::array<int32_t, 2>>& edges,
      const MassSpringParameters& parameters);

  int32_t num_nodes() const override { return static_cast<int32_t>(mass_.size()); }
  int32_t num_springs() const { return static_cast<int32_t>(spring_i_.size()); }
  std::unique_ptr<TissueState> MakeState() const override;
  Eigen::Matrix3d LocalStiffness(const TissueState& state, int32_t node) const override;
  void InternalForces(const TissueState& state, mesh::Points* forces) const override;
  EnergyReport Energy(const TissueState& state, const Eigen::Vector3d& gravity) const override;

  const std::vector<double>& masses() const { return mass_; }          // [kg], num_nodes
  const std::vector<double>& stiffness() const { return stiffness_; }  // [N/m], num_springs
  const mesh::Points& rest_positions() const { return rest_; }

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;

 private:
  friend class MassSpringImplicitStep;
  void AdvanceImplicit(const StepInputs& inputs, TissueState* state) const;
  // Adds gravity, external forces and attachments to state forces (after InternalForces).
  void AddExternalForces(const StepInputs& inputs, TissueState* state) const;
  MassSpringModel() = default;
  // Builds springs from unique edges of `elements` (each column one element of `corners` nodes)
  // with the element sizes given, then masses and damping.
  void Build(const mesh::Points& rest, const std::vector<std::array<int32_t, 2>>& edges,
             const std::vector<double>& edge_size_sum, const std::vector<double>& node_size,
             const MassSpringParameters& parameters);

  mesh::Points rest_;         // [m], 3 × num_nodes
  std::vector<double> mass_;  // [kg], num_nodes
  std::vector<double> inverse_mass_;
  std::vector<int32_t> spring_i_;  // num_springs, i < j
  std::vector<int32_t> spring_j_;
  std::vector<double> rest_length_;  // [m]
  std::vector<double> stiffness_;    // [N/m]
  std::vector<double> damping_;      // [N s/m]
  std::vector<int32_t>
      first_node_start_;  // num_nodes + 1: springs [start_i, start_i+1) have i first
  std::vector<int32_t> node_spring_start_;  // num_nodes + 1, CSR of springs per node
  std::vector<int32_t> node_springs_;
  MassSpringIntegrator integrator_ = MassSpringIntegrator::kSymplecticEuler;
  double cg_tolerance_ = 1e-8;
  int cg_max_iterations_ = 500;
};

}  // namespace somasim::models
