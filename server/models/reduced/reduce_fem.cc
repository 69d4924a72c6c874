#include "server/models/reduced/reduce_fem.h"

#include <Eigen/Cholesky>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "common/checks/finite.h"

namespace somasim::models::reduced {

void ProjectStiffness(const fem::FemModel& model, const mesh::Points& x,
                      const Eigen::MatrixXd& modes, Eigen::MatrixXd* stiffness_modes,
                      Eigen::MatrixXd* reduced_stiffness) {
  const Eigen::Index dofs = 3 * static_cast<Eigen::Index>(model.num_nodes());
  if (x.rows() != 3 || x.cols() != model.num_nodes() || !x.allFinite()) {
    throw std::invalid_argument("ProjectStiffness: positions must be 3 × N and finite");
  }
  if (modes.rows() != dofs || modes.cols() < 1) {
    throw std::invalid_argument("ProjectStiffness: modes must be 3N × n, got " +
                                std::to_string(modes.rows()) + " × " +
                                std::to_string(modes.cols()));
  }
  fem::BlockSparseMatrix tangent = model.pattern();
  model.AssembleTangent(x, &tangent);
  stiffness_modes->resize(dofs, modes.cols());
  for (Eigen::Index k = 0; k < modes.cols(); ++k) {
    tangent.Multiply(modes.col(k).data(), stiffness_modes->col(k).data(), nullptr);
  }
  const Eigen::MatrixXd projected = modes.transpose() * *stiffness_modes;
  *reduced_stiffness = 0.5 * (projected + projected.transpose());
}

KlModelData KlDataFromFem(const fem::FemModel& model, const mesh::Points& x,
                          const Eigen::MatrixXd& modes) {
  KlModelData data;
  data.rest = model.rest_positions();
  data.masses = model.masses();
  data.modes = modes;
  ProjectStiffness(model, x, modes, &data.stiffness_modes, &data.reduced_stiffness);
  return data;
}

double RelativeL2Error(std::span<const mesh::Points> full, std::span<const mesh::Points> reduced) {
  if (full.size() != reduced.size() || full.empty()) {
    throw std::invalid_argument("RelativeL2Error: as many reduced fields as full ones, >= 1");
  }
  double error = 0.0, norm = 0.0;
  for (size_t c = 0; c < full.size(); ++c) {
    if (full[c].cols() != reduced[c].cols() || full[c].rows() != reduced[c].rows()) {
      throw std::invalid_argument("RelativeL2Error: case " + std::to_string(c) +
                                  " has fields of different shapes");
    }
    error += (full[c] - reduced[c]).squaredNorm();
    norm += full[c].squaredNorm();
  }
  return norm > 0.0 ? std::sqrt(error / norm) : std::sqrt(error);
}

mesh::Points ReducedStaticDisplacement(const Eigen::MatrixXd& modes,
                                       const Eigen::MatrixXd& reduced_stiffness,
                                       const mesh::Points& forces) {
  const Eigen::Map<const Eigen::VectorXd> f(forces.data(), forces.size());
  const Eigen::VectorXd xi = reduced_stiffness.llt().solve(modes.transpose() * f);
  mesh::Points u(3, forces.cols());
  Eigen::Map<Eigen::VectorXd>(u.data(), u.size()) = modes * xi;
  return u;
}

size_t ChooseStiffness(const fem::FemModel& model, std::span<const mesh::Points> candidates,
                       const Eigen::MatrixXd& modes, std::span<const StaticCase> cases,
                       std::vector<double>* errors) {
  if (candidates.empty() || cases.empty()) {
    throw std::invalid_argument("ChooseStiffness: needs candidates and cases");
  }
  size_t best = 0;
  double best_error = std::numeric_limits<double>::infinity();
  if (errors != nullptr) errors->clear();
  for (size_t c = 0; c < candidates.size(); ++c) {
    Eigen::MatrixXd kb, reduced;
    ProjectStiffness(model, candidates[c], modes, &kb, &reduced);
    std::vector<mesh::Points> full, approx;
    for (const StaticCase& s : cases) {
      full.push_back(s.displacement);
      approx.push_back(ReducedStaticDisplacement(modes, reduced, s.forces));
    }
    const double error = RelativeL2Error(full, approx);
    if (errors != nullptr) errors->push_back(error);
    if (error < best_error) {
      best_error = error;
      best = c;
    }
  }
  return best;
}

Eigen::MatrixXd PetrovGalerkinTestBasis(const fem::FemModel& model, const Eigen::MatrixXd& modes,
                                        std::span<const int32_t> fixed,
                                        fem::StaticWorkspace* workspace) {
  if (modes.rows() != 3 * static_cast<Eigen::Index>(model.num_nodes())) {
    throw std::invalid_argument("test basis: the modes are not 3N × n for the model");
  }
  fem::StaticWorkspace own;
  if (workspace == nullptr) workspace = &own;
  Eigen::MatrixXd psi = Eigen::MatrixXd::Zero(modes.rows(), modes.cols());
  mesh::Points forces(3, model.num_nodes());
  fem::StaticLoads loads;
  loads.external_forces = &forces;
  loads.fixed_nodes = fixed;
  loads.reuse_factorisation = true;
  for (Eigen::Index j = 0; j < modes.cols(); ++j) {
    const double largest = modes.col(j).cwiseAbs().maxCoeff();
    if (!checks::FinitePositive(largest)) continue;  // a zero mode tests nothing
    const double scale = 1e-7 / largest;             // [N per unit of the mode]
    for (const double sign : {1.0, -1.0}) {
      Eigen::Map<Eigen::VectorXd>(forces.data(), forces.size()) = sign * scale * modes.col(j);
      auto state = model.MakeState();
      if (!model.SolveStatic(loads, state.get(), workspace).converged) {
        throw std::invalid_argument("test basis: mode " + std::to_string(j) +
                                    "'s linear response did not converge");
      }
      const mesh::Points u = state->positions - model.rest_positions();
      psi.col(j) += Eigen::Map<const Eigen::VectorXd>(u.data(), u.size()) * (sign / (2.0 * scale));
    }
  }
  return psi;
}

}  // namespace somasim::models::reduced
