// From a full FEM model to seed 000's reduced model (SPEC §4.5): the projections of a chosen
// stiffness onto the modes, and the choice among candidate stiffnesses (seed 000 §3; the seed's
// figures: docs/reduced.md). Offline (allocates; CHOLMOD is not needed: the tangent is only
// multiplied).
#pragma once

#include <Eigen/Core>
#include <span>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "server/models/fem/fem_model.h"
#include "server/models/reduced/kl_model.h"

namespace somasim::models::reduced {

// The model's exact tangent K at positions x (3 × N; the rest positions for the initial
// tangent) times the modes (3N × n): K B, and Bᵀ K B symmetrised. Throws std::invalid_argument
// for sizes that do not match the model.
void ProjectStiffness(const fem::FemModel& model, const mesh::Points& x,
                      const Eigen::MatrixXd& modes, Eigen::MatrixXd* stiffness_modes,
                      Eigen::MatrixXd* reduced_stiffness);

// A KL model of `model` on `modes` with the tangent at x (masses and rest from the model).
KlModelData KlDataFromFem(const fem::FemModel& model, const mesh::Points& x,
                          const Eigen::MatrixXd& modes);

// The relative L2 error of a reduced displacement field against the full one over a set of
// cases: sqrt(Σ_c |u_c − û_c|²) / sqrt(Σ_c |u_c|²). Each case: 3 × N fields.
double RelativeL2Error(std::span<const mesh::Points> full, std::span<const mesh::Points> reduced);

struct StaticCase {
  mesh::Points forces;        // [N], 3 × N: the load
  mesh::Points displacement;  // [m], 3 × N: the full model's static displacement under it
};

// The reduced static displacement B (Bᵀ K B)⁻¹ Bᵀ f for one load (K B's projection given).
mesh::Points ReducedStaticDisplacement(const Eigen::MatrixXd& modes,
                                       const Eigen::MatrixXd& reduced_stiffness,
                                       const mesh::Points& forces);

// Seed 000's choice of K: among the tangents at `candidates` (each 3 × N positions), the one
// whose reduced static displacements are nearest (RelativeL2Error) to the full model's over
// `cases`. Returns the index of the chosen candidate; `errors` (if given) gets each candidate's
// error. Throws std::invalid_argument for no candidate or no case.
size_t ChooseStiffness(const fem::FemModel& model, std::span<const mesh::Points> candidates,
                       const Eigen::MatrixXd& modes, std::span<const StaticCase> cases,
                       std::vector<double>* errors = nullptr);

// The Petrov–Galerkin test basis Ψ = K0⁻¹ B (nonlinear_model.h) of `modes` (3N × n) on the
// model's rest tangent with `fixed` nodes held (their rows of Ψ are 0): each mode as a tiny load
// (0.1 µN at its largest node), central differences of ± the load (the material's quadratic term
// cancels: K0 Ψ = B to ~1e-6), divided by the load's scale. 2n static solves on one factor (a
// `workspace` kept across calls reuses it). Throws std::invalid_argument when a solve does not
// converge.
Eigen::MatrixXd PetrovGalerkinTestBasis(const fem::FemModel& model, const Eigen::MatrixXd& modes,
                                        std::span<const int32_t> fixed,
                                        fem::StaticWorkspace* workspace = nullptr);

}  // namespace somasim::models::reduced
