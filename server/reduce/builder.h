// somasim-reduce's engine (issue 12, SPEC §4.5; seed 000 §3–4): sample the full FEM model under
// point loads, take the Karhunen–Loève modes of the displacement snapshots, choose the reduced
// stiffness among candidate tangents, and record creep curves. Offline: allocates, takes
// minutes on liver4055 (reported), never on a real-time path.
//
// For each sample point p (a surface node of an interaction region), direction d (the inward
// surface normal, and with directions = 3 the two tangents) and magnitude F, the full model's
// elastic static equilibrium under F d at p is a snapshot and a static case. With QLV (the
// model's Prony series), each point's creep run — 1 N along its inward normal held for
// creep_duration, quasi-static steps of creep_interval — gives its creep curve
// c(t) = |u_p(t)| / |u_p^elastic| (c(0) = 1) and its final state as one more snapshot.
// Candidates for K: the tangent at rest (seed 000's "initial" K) and at the equilibrium of the
// first point's normal load at each magnitude; the one with the least relative L2 error over the
// static cases is kept (seed 000: 22 % with the initial K, 17 % with the selected one).
#pragma once

#include <Eigen/Core>
#include <functional>
#include <string>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/fem_model.h"
#include "server/models/reduced/ecsw.h"
#include "server/models/reduced/kl_model.h"
#include "server/models/reduced/nonlinear_model.h"
#include "server/models/reduced/pod.h"
#include "server/models/reduced/reduce_fem.h"

namespace somasim::reduce {

struct SamplingPlan {
  std::vector<int32_t> points;                // loaded nodes, on the boundary, not held
  std::vector<double> forces{0.1, 0.5, 1.0};  // magnitudes [N], each > 0
  int directions = 3;                         // 1 or 3 (see above)
  std::vector<int32_t> fixed;                 // the supports (held nodes), not empty
  double creep_duration = 20.0;               // [s], >= 0 (0: no creep curves)
  double creep_interval = 0.1;                // [s], > 0
  models::reduced::PodSettings pod;           // the energy criterion
  double creep_radius = 0.01;                 // [m] for the model (kl_model.h)
  int load_steps = 1;                         // Newton's first load increments, > 0
  // The nonlinear model's extras (BuildNonlinearModel): every boundary node of the interaction
  // regions, whose responses to small loads along its normal and two tangents (the tangent at
  // rest) join the snapshots, so that a touch anywhere in the regions is in the basis; and the
  // cubature's settings.
  std::vector<int32_t> region_nodes;
  models::reduced::PodSettings nonlinear_pod;  // its own energy criterion and number of modes
  // Its POD in the rest tangent's energy inner product (QᵀKQ) instead of the Euclidean one
  // (QᵀQ, the default: 3.6–7.7 % instead of 4.3–9.5 % on the liver's inside cases at 64 modes).
  bool energy_inner_product = false;
  // Its tolerance: 1 % suits a Galerkin model; a Petrov–Galerkin one needs 0.1 % (somasim-reduce
  // sets it when the scene does not): its equations Ψᵀ f are, at rest, displacements
  // (Ψᵀ K0 B = BᵀB), so a relative error in them is one in ξ, where a Galerkin model's errors sit
  // in the stiff directions K̂⁻¹ damps. (The 63-node beam: a trained load 1.95 % off at 1 %,
  // 0.36 % at 0.1 %; Galerkin 0.25 % at 1 %.) Its smooth test fields need fewer elements for the
  // same tolerance (39 at 0.1 % against Galerkin's 68).
  models::reduced::CubatureSettings cubature;
  // Static samples at every region node: the inward normal and `tilts` directions tilted from it
  // by tilt_deg, each at the magnitudes nonlinear_forces (ascending; empty: `forces` and the
  // largest of them over γ∞, the material's long-term share, where QLV creep under it ends).
  int tilts = 4;
  double tilt_deg = 35.0;
  std::vector<double> nonlinear_forces;
  // At most this many training states for the cubature (evenly chosen: its least squares has
  // n × states rows).
  size_t max_cubature_states = 200;
  // The nonlinear model's static correction at the region nodes (nonlinear_model.h): their
  // linear responses beyond the modes, for point forces there.
  bool static_correction = true;
  // ... and its part in the modes: the reduced equilibrium's offset from the full model's
  // in-span field under the region samples' forces, fitted per node and magnitude, affine in
  // the force's direction (nonlinear_model.h's correction_coefficients). Needs
  // static_correction.
  bool correction_in_modes = true;
  // The nonlinear model's projection (nonlinear_model.h): Galerkin (Ψ = B, the default: an
  // energy's stationary point, robust under any load) or Petrov–Galerkin with Ψ = K0⁻¹ B (the
  // L2-best field in the linear range; docs/reduced.md compares them on the liver).
  bool petrov_galerkin = false;
};

struct BuildProgress {
  std::string stage;  // "snapshots", "creep", "modes", "stiffness"
  size_t done = 0, total = 0;
};

struct BuildReport {
  models::reduced::KlModelData data;
  Eigen::VectorXd eigenvalues;  // of QᵀQ, descending [m²]
  double kept_fraction = 0.0;
  std::vector<std::string> candidates;   // K's candidates, described
  std::vector<double> candidate_errors;  // their relative L2 errors on the static cases
  size_t chosen = 0;                     // index into candidates
  size_t snapshots = 0;
  int unconverged = 0;                             // full solves that did not converge (left out)
  double seconds = 0.0;                            // wall time of the build
  std::vector<models::reduced::StaticCase> cases;  // the static cases (for evaluation)
  // Every converged full solution [m] (3 × N each): the static cases and the creep runs' states
  // (each run's state at 1 s, 5 s and its end): the nonlinear model's training set.
  std::vector<mesh::Points> training;
};

struct NonlinearBuildReport {
  models::reduced::NonlinearModelData data;
  Eigen::VectorXd eigenvalues;  // of the normalised snapshots' QᵀQ, descending
  double kept_fraction = 0.0;
  size_t snapshots = 0;      // columns of Q (training states and region responses)
  size_t region_solves = 0;  // static samples at the region nodes (converged)
  int unconverged = 0;       // region samples that did not converge (left out)
  models::reduced::Cubature cubature;
  Eigen::Index correction_nodes = 0;      // nodes with a static correction
  Eigen::VectorXd correction_scale_mean;  // its scale κ per magnitude, the nodes' mean
  // Its part in the modes, on the region samples: the in-span field error of the corrected
  // model (relative to |u|, over all samples) without it and with the fitted G_p.
  double in_span_error_before = 0.0, in_span_error_after = 0.0;
  double seconds = 0.0;  // wall time of this part of the build
};

// Throws std::invalid_argument naming what is wrong with the plan (a point out of range, held or
// not on the boundary, no support, bad magnitudes, directions, durations).
BuildReport BuildKlModel(const models::fem::FemModel& full, const mesh::TetMesh& mesh,
                         const SamplingPlan& plan,
                         const std::function<void(const BuildProgress&)>& progress = {});

// The nonlinear reduced model (nonlinear_model.h) from the same plan and the KL build's training
// states: modes by POD, in the energy inner product of the tangent at rest, of the training
// states, the region nodes' small-load (linear) responses and their static samples (tilts,
// nonlinear_forces), each normalised to unit length (a 0.1 N state counts as much as a 1 N
// one), with the plan's nonlinear_pod criterion; then the ECSW cubature trained on the states.
// Throws std::invalid_argument for a model that is not hyperelastic or a region node out of range.
NonlinearBuildReport BuildNonlinearModel(
    const models::fem::FemModel& full, const mesh::TetMesh& mesh, const SamplingPlan& plan,
    const BuildReport& kl, const std::function<void(const BuildProgress&)>& progress = {});

// The boundary nodes' outward unit normals (area-weighted over their boundary triangles), zero
// for interior nodes: 3 × num_nodes.
mesh::Points BoundaryNormals(const mesh::TetMesh& mesh);

}  // namespace somasim::reduce
