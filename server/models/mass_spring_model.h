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
#include "server/models/mass_spring_slice_layout.h"
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
  // solved by conjugate gradients preconditioned with a multicolour symmetric block
  // Gauss–Seidel sweep (8 independent nodes per AVX-512 register; mass_spring_implicit_cg.cc),
  // matrix-free over the springs, started from Δv extrapolated from the last two steps. Stable
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
  // Implicit: relative residual |r|/|b| at which CG stops, > 0. The step's own linearisation and
  // time-discretisation error is O(dt²); at 1e-6 an organ's trajectory stays within micrometres
  // of an exact solve over hundreds of 1 ms steps (docs/benchmarks.md).
  double cg_tolerance = 1e-6;
  int cg_max_iterations = 500;  // implicit: CG iterations per step at most, > 0
  // Seed 001's generalised spring (eq. 10, SPEC §4.1): when > 0, every node with mass is tied to
  // its rest position by a zero-rest-length spring, f_i = k_s (x0_i - x_i) [N/m], >= 0. It is
  // damped at damping_ratio, -2 ζ √(k_s m_i) v_i (the seed's eq. 10 has no damping; without it
  // the shell would ring on its anchors for ever).
  double anchor_stiffness = 0.0;
  // FromGeneralisedSurface: the outer fraction of the organ's thickness that carries mass and
  // springs (seed 001: one fifth), in (0, 0.5].
  double shell_fraction = 0.2;
};

class MassSpringState;

class MassSpringModel final : public TissueModel {
 public:
  // Throws std::invalid_argument naming the bad parameter or mesh fault (no elements, NaN
  // coordinates, zero-length edge, index out of range).
  static std::unique_ptr<MassSpringModel> FromTetMesh(const mesh::TetMesh& mesh,
                                                      const MassSpringParameters& parameters);
  static std::unique_ptr<MassSpringModel> FromSurface(const mesh::SurfaceMesh& surface,
                                                      const MassSpringParameters& parameters);

  // Seed 001's generalised surface mesh (generalised_surface.h) of a tetrahedral organ, for the
  // region away from the tools: springs on the tetrahedra's edges within the outer
  // shell_fraction of the thickness, mass only there (the core's nodes are massless and stay at
  // rest), and every shell node anchored to its rest position (anchor_stiffness, > 0 here).
  static std::unique_ptr<MassSpringModel> FromGeneralisedSurface(
      const mesh::TetMesh& mesh, const MassSpringParameters& parameters);

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
  bool SupportsCutting() const override { return true; }
  // Removes the springs crossing the sweep (their stiffness and damping become 0 in the state).
  int32_t Cut(const SweptQuad& sweep, TissueState* state) const override;

  const std::vector<double>& masses() const { return mass_; }          // [kg], num_nodes
  const std::vector<double>& stiffness() const { return stiffness_; }  // [N/m], num_springs
  const mesh::Points& rest_positions() const { return rest_; }
  // Nodes tied to their rest position and k_s [N/m] (seed 001 eq. 10); empty without anchors.
  const std::vector<int32_t>& anchored_nodes() const { return anchor_nodes_; }
  double anchor_stiffness() const { return anchor_stiffness_; }

 protected:
  void Advance(const StepInputs& inputs, TissueState* state) const override;
  // The explicit step keeps the state it starts from as the last-good one (SwapWithLastGood) and
  // writes the new one in its pass over the nodes...
  bool SavesGoodStateItself() const override {
    return integrator_ == MassSpringIntegrator::kSymplecticEuler;
  }
  // ... and checks the state it writes.
  bool ChecksStateItself() const override {
    return integrator_ == MassSpringIntegrator::kSymplecticEuler;
  }

 private:
  // The implicit step (mass_spring_implicit*.cc): the linear system at the state the step starts
  // from (its kernels, MassSpringImplicitStep, read the spring arrays), then its CG solve into
  // state->implicit_dv, which returns whether CG converged and sets the iterations it took.
  friend class MassSpringImplicitStep;
  void AdvanceImplicit(const StepInputs& inputs, TissueState* state) const;
  void BuildImplicitSystem(const StepInputs& inputs, bool avx512, MassSpringState* state) const;
  bool SolveImplicitSystem(const StepInputs& inputs, bool avx512, MassSpringState* state,
                           int* iterations) const;
  // Implicit-step data and scratch (mass_spring_implicit_layout.cc): called at the end of Build
  // and by MakeState when the integrator is implicit.
  void BuildImplicitData();
  void SizeImplicitScratch(MassSpringState* state) const;
  // Adds gravity, external forces and attachments to state forces (after InternalForces).
  void AddExternalForces(const StepInputs& inputs, TissueState* state) const;
  // forces (3 × num_nodes, flat) += k_s (x0 - x) - d_i v on every anchored node.
  void AddAnchorForces(const TissueState& state, double* forces) const;
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
  std::vector<double> rest_length_;         // [m]
  std::vector<double> stiffness_;           // [N/m]
  std::vector<double> damping_;             // [N s/m]
  std::vector<int32_t> node_spring_start_;  // num_nodes + 1, CSR of springs per node
  std::vector<int32_t> node_springs_;
  std::vector<int32_t> anchor_nodes_;   // nodes with a zero-rest-length spring to rest
  std::vector<double> anchor_damping_;  // d_i = 2 ζ √(k_s m_i) [N s/m], one per anchored node
  double anchor_stiffness_ = 0.0;       // k_s [N/m]
  // The springs in the explicit slice pass's layout (mass_spring_slice_layout.h).
  MassSpringSliceLayout layout_;
  // --- implicit-step data (mass_spring_implicit_layout.cc) ---
  // Multicolour layout of the Gauss-Seidel preconditioner: nodes grouped by colour (no spring
  // joins two nodes of one colour), each colour padded to whole groups of 8 lanes. A lane is a
  // node's index in the solver's vectors (3 blocks x, y, z of implicit_padded_ doubles each).
  size_t implicit_padded_ = 0;                  // P, a multiple of 8
  std::vector<int32_t> implicit_node_;          // P: the node in each lane, -1 on padding
  std::vector<int32_t> implicit_lane_;          // num_nodes: each node's lane
  std::vector<int32_t> implicit_colour_start_;  // colours + 1: first group of each colour
  // Per group (of 8 lanes): rows of 8 slots, one spring per lane and row, first the springs to
  // lower colours (implicit_lower_rows_), then those to higher ones; groups + 1.
  std::vector<int32_t> implicit_row_start_;
  std::vector<int32_t> implicit_lower_rows_;  // groups
  std::vector<int32_t> implicit_neighbour_;   // rows × 8: the other node's lane (own on padding)
  std::vector<int32_t> implicit_spring_;      // rows × 8: the spring, num_springs on padding
  std::vector<double> implicit_sign_;         // rows × 8: +1 if the lane is the spring's i, -1 j
  std::vector<double> implicit_mass_;         // P: mass [kg] (0 on padding)
  std::vector<double> implicit_real_;         // P: 1 on a node's lane, 0 on padding
  std::vector<uint8_t> implicit_massless_group_;  // groups: 1 if a lane's node has no mass
  // --- end of implicit-step data ---
  MassSpringIntegrator integrator_ = MassSpringIntegrator::kSymplecticEuler;
  double cg_tolerance_ = 1e-8;
  int cg_max_iterations_ = 500;
};

}  // namespace somasim::models
