// somasim-reduce's engine, the nonlinear reduced model (builder.h): the region nodes' responses
// and static samples, the modes, the ECSW cubature and the static correction's fit (R_p, its
// scale κ and its part in the modes).
#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <set>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/checks/finite.h"
#include "server/models/reduced/reduce_fem.h"
#include "server/reduce/builder.h"
#include "server/reduce/builder_internal.h"

namespace somasim::reduce {

using builder_internal::Require;
using builder_internal::Tangents;
using models::fem::FemModel;
using models::fem::StaticLoads;
using models::fem::StaticWorkspace;

namespace {

// BuildNonlinearModel's stages and what they pass on: the snapshot columns, the training states,
// the region nodes' linear responses and static samples, the model's data in out.data.
class NonlinearBuild {
 public:
  NonlinearBuild(const FemModel& full, const mesh::TetMesh& mesh, const SamplingPlan& plan,
                 const BuildReport& kl, const std::function<void(const BuildProgress&)>& progress)
      : full_(full), plan_(plan), progress_(progress) {
    Require(full.kind() == models::fem::FemKind::kHyperelastic,
            "the nonlinear reduced model needs a hyperelastic organ");
    Require(!kl.training.empty(), "no training state");
    held_.insert(plan.fixed.begin(), plan.fixed.end());
    normals_ = BoundaryNormals(mesh);
    for (const mesh::Points& u : kl.training) Add(u);
    states_ = kl.training;  // the cubature's candidates
    // The magnitudes of the region samples.
    magnitudes_ = plan.nonlinear_forces;
    if (magnitudes_.empty()) {
      magnitudes_ = plan.forces;
      double gamma_sum = 0.0;
      for (const models::fem::PronyTerm& t : full.prony()) gamma_sum += t.gamma;
      const double largest = *std::max_element(plan.forces.begin(), plan.forces.end());
      if (gamma_sum > 0.0 && gamma_sum < 1.0) magnitudes_.push_back(largest / (1.0 - gamma_sum));
    }
    std::sort(magnitudes_.begin(), magnitudes_.end());
    for (const double f : magnitudes_) {
      Require(checks::FinitePositive(f), "a magnitude is not > 0");
    }
    Require(plan.tilts >= 0 && checks::FiniteNonNegative(plan.tilt_deg) && plan.tilt_deg < 90.0,
            "tilts must be >= 0 and tilt_deg in [0, 90)");
  }

  // Every region node: its responses to 1 mN along the normal and two tangents (linear: the
  // tangent at rest, factorised once), then its static samples, each direction's magnitudes in
  // ascending order from the last one's solution (continuation).
  void SampleRegion() {
    size_t done = 0;
    for (const int32_t r : plan_.region_nodes) {
      Require(r >= 0 && r < full_.num_nodes(),
              "region node " + std::to_string(r) + " out of range");
      ++done;
      if (held_.count(r) != 0 || normals_.col(r).squaredNorm() < 0.5) continue;
      SampleRegionNode(r);
      Report("region samples", done, plan_.region_nodes.size());
    }
  }

  // POD of the normalised columns, in the Euclidean inner product (the default) or in the rest
  // tangent's energy (pod.h); with Petrov–Galerkin, the test basis Ψ = K0⁻¹ B (nonlinear_model.h,
  // reduce_fem.h) on the rest factor the region nodes' responses used.
  void Modes() {
    Report("modes", 0, 1);
    Eigen::MatrixXd q(3 * static_cast<Eigen::Index>(full_.num_nodes()),
                      static_cast<Eigen::Index>(columns_.size()));
    for (size_t c = 0; c < columns_.size(); ++c) q.col(static_cast<Eigen::Index>(c)) = columns_[c];
    out.snapshots = columns_.size();
    Eigen::MatrixXd weighted;
    if (plan_.energy_inner_product) {
      models::fem::BlockSparseMatrix tangent;
      full_.AssembleTangent(full_.rest_positions(), &tangent);
      weighted.resize(q.rows(), q.cols());
      for (Eigen::Index c = 0; c < q.cols(); ++c) {
        tangent.Multiply(q.col(c).data(), weighted.col(c).data(), nullptr);
      }
    }
    pod_ = models::reduced::ModesOfSnapshots(q, plan_.nonlinear_pod,
                                             plan_.energy_inner_product ? &weighted : nullptr);
    out.eigenvalues = pod_.eigenvalues;
    out.kept_fraction = pod_.kept_fraction;
    Report("modes", 1, 1);
    if (plan_.petrov_galerkin) {
      Report("test basis", 0, 1);
      try {
        test_modes_ =
            models::reduced::PetrovGalerkinTestBasis(full_, pod_.modes, plan_.fixed, &workspace_);
      } catch (const std::invalid_argument& e) {
        Require(false, e.what());
      }
      Report("test basis", 1, 1);
    }
  }

  // The ECSW cubature, trained on at most max_cubature_states states evenly spread over the
  // list, and the model's data.
  void Cubature() {
    Report("cubature", 0, 1);
    std::vector<mesh::Points> training;
    const size_t take = std::min(states_.size(), std::max<size_t>(plan_.max_cubature_states, 1));
    for (size_t k = 0; k < take; ++k) training.push_back(states_[k * states_.size() / take]);
    out.cubature = models::reduced::TrainCubature(full_, pod_.modes, training, plan_.cubature,
                                                  plan_.petrov_galerkin ? &test_modes_ : nullptr);
    Report("cubature", 1, 1);
    models::reduced::NonlinearModelData& d = out.data;
    d.rest = full_.rest_positions();
    d.masses = full_.masses();
    d.modes = std::move(pod_.modes);
    d.test_modes = std::move(test_modes_);
    d.tets.resize(4, static_cast<Eigen::Index>(out.cubature.elements.size()));
    for (size_t k = 0; k < out.cubature.elements.size(); ++k) {
      d.tets.col(static_cast<Eigen::Index>(k)) =
          full_.elements().tets.col(out.cubature.elements[k]);
    }
    d.weights = out.cubature.weights;
    d.elements = out.cubature.elements;
    d.material = full_.material();
    d.prony = full_.prony();
  }

  // The static correction (nonlinear_model.h) at the region nodes with a linear response: R_p,
  // its scale κ per node and magnitude, and (correction_in_modes) its part in the modes.
  void StaticCorrection() {
    if (!plan_.static_correction || correction_nodes_.empty()) return;
    Report("correction", 0, 1);
    models::reduced::NonlinearModelData& d = out.data;
    const auto model = models::reduced::NonlinearReducedModel::Create(d);
    const auto state = model->MakeState();
    Corrections(*model, *state);
    index_of_.assign(static_cast<size_t>(full_.num_nodes()), -1);
    for (size_t k = 0; k < correction_nodes_.size(); ++k) {
      index_of_[size_t(correction_nodes_[k])] = static_cast<Eigen::Index>(k);
    }
    const Eigen::MatrixXd equilibria = ReducedEquilibria(*model, *state);
    d.correction_magnitudes = magnitudes_;
    FitScales(equilibria);
    if (plan_.correction_in_modes) {
      // κ is fitted again to the dents the fitted part leaves, and the part again to that κ
      // (once: the second pass moves κ by a few per cent).
      const Eigen::LDLT<Eigen::MatrixXd> gram(d.modes.transpose() * d.modes);
      FitCoefficients(equilibria, gram);
      FitScales(equilibria);
      FitCoefficients(equilibria, gram);
    }
    out.correction_scale_mean = d.correction_scales.rowwise().mean();
    Report("correction", 1, 1);
  }

  NonlinearBuildReport out;

 private:
  // A region sample's load and the full model's displacement of the loaded node, for the
  // correction's scale.
  struct Dent {
    int32_t node = 0;
    size_t magnitude = 0;                 // index into magnitudes_
    Eigen::Vector3d force, displacement;  // [N], [m]
    size_t state = 0;                     // index into states_: the full solution
  };

  // A state as a snapshot column, normalised (a 0.1 N state counts as much as a 1 N one).
  void Add(const mesh::Points& u) {
    const double norm = u.norm();
    if (norm > 0.0)
      columns_.emplace_back(Eigen::Map<const Eigen::VectorXd>(u.data(), u.size()) / norm);
  }
  void Report(const char* stage, size_t done, size_t total) const {
    if (progress_) progress_({stage, done, total});
  }
  // The equations' test basis: Ψ, or B for Galerkin.
  const Eigen::MatrixXd& Test() const {
    return out.data.test_modes.size() > 0 ? out.data.test_modes : out.data.modes;
  }

  // Region node r's linear responses (kept for the static correction when all three converge)
  // and its static samples along the normal and `tilts` tilted directions.
  void SampleRegionNode(int32_t r) {
    const int32_t nodes = full_.num_nodes();
    const double tilt = plan_.tilt_deg * 3.14159265358979323846 / 180.0;
    const Eigen::Vector3d inward = -Eigen::Vector3d(normals_.col(r));
    const auto [t1, t2] = Tangents(inward);
    mesh::Points forces = mesh::Points::Zero(3, nodes);
    StaticLoads loads;
    loads.external_forces = &forces;
    loads.fixed_nodes = plan_.fixed;
    loads.reuse_factorisation = true;
    // The responses per newton along x, y, z (from those along the orthonormal d1, d2, d3:
    // Y e_a = Σ_j (d_j · e_a) Y d_j), kept for the static correction.
    Eigen::MatrixXd unit = Eigen::MatrixXd::Zero(3 * static_cast<Eigen::Index>(nodes), 3);
    bool linear_ok = true;
    for (const Eigen::Vector3d& d : {inward, t1, t2}) {
      forces.col(r) = 1e-3 * d;
      auto state = full_.MakeState();
      if (full_.SolveStatic(loads, state.get(), &workspace_).converged) {
        const mesh::Points u = state->positions - full_.rest_positions();
        Add(u);
        const Eigen::Map<const Eigen::VectorXd> y(u.data(), u.size());
        for (int a = 0; a < 3; ++a) unit.col(a) += (d(a) / 1e-3) * y;
      } else {
        linear_ok = false;
      }
    }
    if (linear_ok) {
      correction_nodes_.push_back(r);
      responses_.push_back(std::move(unit));
    }
    std::vector<Eigen::Vector3d> directions{inward};
    for (int k = 0; k < plan_.tilts; ++k) {
      const double azimuth = 2.0 * 3.14159265358979323846 * k / plan_.tilts;
      directions.push_back(std::cos(tilt) * inward +
                           std::sin(tilt) * (std::cos(azimuth) * t1 + std::sin(azimuth) * t2));
    }
    StaticLoads samples = loads;
    samples.reuse_factorisation = false;
    samples.load_steps = plan_.load_steps;
    StaticWorkspace sample_workspace;
    for (const Eigen::Vector3d& d : directions) {
      auto state = full_.MakeState();
      for (size_t m = 0; m < magnitudes_.size(); ++m) {
        const double f = magnitudes_[m];
        forces.col(r) = f * d;
        if (!full_.SolveStatic(samples, state.get(), &sample_workspace).converged) {
          ++out.unconverged;
          break;  // the larger magnitudes would start from an unconverged state
        }
        const mesh::Points u = state->positions - full_.rest_positions();
        Add(u);
        dents_.push_back({r, m, f * d, u.col(r), states_.size()});
        states_.push_back(u);
        ++out.region_solves;
      }
    }
  }

  // R_p = K0⁻¹ E_p − B K̂0⁻¹ Ψᵀ E_p with K̂0 the model's own reduced tangent at rest (its
  // cubature's; Ψ = B for Galerkin).
  void Corrections(const models::reduced::NonlinearReducedModel& model,
                   const models::TissueState& state) {
    models::reduced::NonlinearModelData& d = out.data;
    Eigen::VectorXd force;
    Eigen::MatrixXd tangent;
    model.ReducedForces(state, Eigen::VectorXd::Zero(d.modes.cols()), 0.0, &force, &tangent);
    const Eigen::FullPivLU<Eigen::MatrixXd> rest_lu(tangent);
    Require(rest_lu.isInvertible(), "the reduced tangent at rest is singular");
    const Eigen::MatrixXd& test = Test();
    const auto c = static_cast<Eigen::Index>(correction_nodes_.size());
    d.correction_nodes = correction_nodes_;
    d.corrections.resize(d.modes.rows(), 3 * c);
    for (Eigen::Index k = 0; k < c; ++k) {
      const Eigen::MatrixXd bt =
          test.middleRows(3 * static_cast<Eigen::Index>(correction_nodes_[size_t(k)]), 3)
              .transpose();  // Ψᵀ E_p: n × 3
      d.corrections.middleCols<3>(3 * k) = responses_[size_t(k)] - d.modes * rest_lu.solve(bt);
    }
    out.correction_nodes = c;
  }

  // Each region sample's reduced elastic equilibrium under its force (Newton from the last
  // magnitude's, as the full solves ran): n × samples, NaN where it did not converge.
  Eigen::MatrixXd ReducedEquilibria(const models::reduced::NonlinearReducedModel& model,
                                    const models::TissueState& state) const {
    const Eigen::MatrixXd& test = Test();
    const Eigen::Index n = out.data.modes.cols();
    Eigen::VectorXd xi = Eigen::VectorXd::Zero(n);
    Eigen::VectorXd force;
    Eigen::MatrixXd tangent;
    Eigen::MatrixXd equilibria(n, static_cast<Eigen::Index>(dents_.size()));
    equilibria.setConstant(std::numeric_limits<double>::quiet_NaN());
    for (size_t s_index = 0; s_index < dents_.size(); ++s_index) {
      const Dent& dent = dents_[s_index];
      const Eigen::Index k = index_of_[size_t(dent.node)];
      if (k < 0) continue;
      if (dent.magnitude == 0) xi.setZero();  // a new direction: from rest
      const Eigen::VectorXd load = test.middleRows(3 * dent.node, 3).transpose() * dent.force;
      bool solved = false;
      for (int iteration = 0; iteration < 40; ++iteration) {
        model.ReducedForces(state, xi, 0.0, &force, &tangent);
        if (!force.allFinite()) break;
        const Eigen::VectorXd residual = force + load;
        if (residual.norm() <= 1e-9 * (load.norm() + force.norm())) {
          solved = true;
          break;
        }
        const Eigen::VectorXd step = tangent.partialPivLu().solve(residual);
        double alpha = 1.0;  // halve a step that inverts an element
        Eigen::VectorXd trial = xi + step;
        for (int h = 0; h < 20; ++h) {
          model.ReducedForces(state, trial, 0.0, &force, nullptr);
          if (force.allFinite()) break;
          alpha *= 0.5;
          trial = xi + alpha * step;
        }
        xi = trial;
      }
      if (solved) equilibria.col(static_cast<Eigen::Index>(s_index)) = xi;
    }
    return equilibria;
  }

  // κ per node and magnitude from the dents the reduced equilibria leave (with the part in the
  // modes, once fitted) against the full model's at the loaded node, d = u_full − u_reduced ≈
  // κ R_pp f, fitted over the node's directions by least squares (κ = Σ d·q / Σ q·q,
  // q = R_pp f; clamped to [0, 1.5]).
  void FitScales(const Eigen::MatrixXd& equilibria) {
    models::reduced::NonlinearModelData& d = out.data;
    const auto count = static_cast<Eigen::Index>(magnitudes_.size());
    const auto c = static_cast<Eigen::Index>(correction_nodes_.size());
    Eigen::MatrixXd numerator = Eigen::MatrixXd::Zero(count, c);
    Eigen::MatrixXd denominator = Eigen::MatrixXd::Zero(count, c);
    const bool in_modes = d.correction_coefficients.size() > 0;
    for (size_t s_index = 0; s_index < dents_.size(); ++s_index) {
      const Dent& dent = dents_[s_index];
      const Eigen::Index k = index_of_[size_t(dent.node)];
      const auto column = static_cast<Eigen::Index>(s_index);
      if (k < 0 || !equilibria.col(column).allFinite()) continue;
      Eigen::VectorXd coordinates = equilibria.col(column);
      if (in_modes) {
        coordinates += d.correction_coefficients.middleCols<4>(
                           4 * (k * count + Eigen::Index(dent.magnitude))) *
                       models::reduced::CorrectionFeatures(dent.force);
      }
      const Eigen::Vector3d reduced = d.modes.middleRows(3 * dent.node, 3) * coordinates;
      const Eigen::Vector3d linear =
          d.corrections.block<3, 3>(3 * Eigen::Index(dent.node), 3 * k) * dent.force;
      numerator(Eigen::Index(dent.magnitude), k) += (dent.displacement - reduced).dot(linear);
      denominator(Eigen::Index(dent.magnitude), k) += linear.squaredNorm();
    }
    d.correction_scales = Eigen::MatrixXd::Ones(count, c);
    for (Eigen::Index m = 0; m < count; ++m) {
      for (Eigen::Index k = 0; k < c; ++k) {
        if (denominator(m, k) > 0.0) {
          d.correction_scales(m, k) = std::clamp(numerator(m, k) / denominator(m, k), 0.0, 1.5);
        }
      }
    }
  }

  // The part in the modes: per sample the offset t = (BᵀB)⁻¹ Bᵀ (u_full − κ R_p f) − ξ that
  // B ξ + κ R_p f leaves in span(B), fitted per node and magnitude as G φ(f), φ = (f, |f|), over
  // the node's directions by least squares (G = T Φᵀ (Φ Φᵀ)⁺). Affine in the direction: the
  // offset along the normal (|f|) and its change with the tilt (f); where the directions span
  // only a plane, as with two tilts, G sees the plane's part only. `gram` factors BᵀB.
  void FitCoefficients(const Eigen::MatrixXd& equilibria,
                       const Eigen::LDLT<Eigen::MatrixXd>& gram) {
    models::reduced::NonlinearModelData& d = out.data;
    const Eigen::Index n = d.modes.cols();
    const auto count = static_cast<Eigen::Index>(magnitudes_.size());
    const auto c = static_cast<Eigen::Index>(correction_nodes_.size());
    std::vector<Eigen::MatrixXd> tf(static_cast<size_t>(count * c), Eigen::MatrixXd::Zero(n, 4));
    std::vector<Eigen::Matrix4d> ff(tf.size(), Eigen::Matrix4d::Zero());
    std::vector<Eigen::VectorXd> offsets(dents_.size());
    double field_norm = 0.0, before = 0.0, after = 0.0;
    for (size_t s_index = 0; s_index < dents_.size(); ++s_index) {
      const Dent& dent = dents_[s_index];
      const Eigen::Index k = index_of_[size_t(dent.node)];
      const auto column = static_cast<Eigen::Index>(s_index);
      if (k < 0 || !equilibria.col(column).allFinite()) continue;
      const mesh::Points& u = states_[dent.state];
      const Eigen::Map<const Eigen::VectorXd> flat(u.data(), u.size());
      const double kappa = d.correction_scales(Eigen::Index(dent.magnitude), k);
      const Eigen::VectorXd rest_of =
          flat - kappa * (d.corrections.middleCols<3>(3 * k) * dent.force);
      offsets[s_index] = gram.solve(d.modes.transpose() * rest_of) - equilibria.col(column);
      const size_t block = size_t(k * count) + dent.magnitude;
      const Eigen::Vector4d phi = models::reduced::CorrectionFeatures(dent.force);
      tf[block] += offsets[s_index] * phi.transpose();
      ff[block] += phi * phi.transpose();
      field_norm += flat.squaredNorm();
    }
    d.correction_coefficients = Eigen::MatrixXd::Zero(n, 4 * count * c);
    for (size_t block = 0; block < tf.size(); ++block) {
      const Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> eigen(ff[block]);
      const Eigen::Vector4d& values = eigen.eigenvalues();  // ascending, >= 0
      if (!(values(3) > 0.0)) continue;                     // no sample
      Eigen::Vector4d inverse = Eigen::Vector4d::Zero();
      for (int a = 0; a < 4; ++a) {
        if (values(a) > 1e-9 * values(3)) inverse(a) = 1.0 / values(a);
      }
      d.correction_coefficients.middleCols<4>(4 * static_cast<Eigen::Index>(block)) =
          tf[block] *
          (eigen.eigenvectors() * inverse.asDiagonal() * eigen.eigenvectors().transpose());
    }
    for (size_t s_index = 0; s_index < dents_.size(); ++s_index) {
      if (offsets[s_index].size() == 0) continue;
      const Dent& dent = dents_[s_index];
      const Eigen::Index k = index_of_[size_t(dent.node)];
      const Eigen::Index block = k * count + Eigen::Index(dent.magnitude);
      before += (d.modes * offsets[s_index]).squaredNorm();
      after += (d.modes * (offsets[s_index] - d.correction_coefficients.middleCols<4>(4 * block) *
                                                  models::reduced::CorrectionFeatures(dent.force)))
                   .squaredNorm();
    }
    if (field_norm > 0.0) {
      out.in_span_error_before = std::sqrt(before / field_norm);
      out.in_span_error_after = std::sqrt(after / field_norm);
    }
  }

  const FemModel& full_;
  const SamplingPlan& plan_;
  const std::function<void(const BuildProgress&)>& progress_;
  std::set<int32_t> held_;
  mesh::Points normals_;                  // 3 × N, zero inside
  std::vector<Eigen::VectorXd> columns_;  // the snapshots, normalised
  std::vector<mesh::Points> states_;      // the cubature's candidates
  std::vector<double> magnitudes_;        // of the region samples [N], ascending
  // The region nodes with a linear response and their responses to unit forces along x, y, z
  // (3N × 3 each); the region samples.
  std::vector<int32_t> correction_nodes_;
  std::vector<Eigen::MatrixXd> responses_;
  std::vector<Dent> dents_;
  std::vector<Eigen::Index> index_of_;  // num_nodes: index into correction_nodes_, or -1
  StaticWorkspace workspace_;           // the rest tangent's factor (responses, test basis)
  models::reduced::PodModes pod_;
  Eigen::MatrixXd test_modes_;
};

}  // namespace

NonlinearBuildReport BuildNonlinearModel(
    const FemModel& full, const mesh::TetMesh& mesh, const SamplingPlan& plan,
    const BuildReport& kl, const std::function<void(const BuildProgress&)>& progress) {
  const auto started = std::chrono::steady_clock::now();
  NonlinearBuild build(full, mesh, plan, kl, progress);
  build.SampleRegion();
  build.Modes();
  build.Cubature();
  build.StaticCorrection();
  build.out.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  return std::move(build.out);
}

}  // namespace somasim::reduce
