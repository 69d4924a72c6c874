#include "server/models/fem/fem_model.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cassert>
#include <cmath>
#include <stdexcept>
#include <string>

#include "server/models/cpu_features.h"
#include "server/models/fem/polar_avx512.h"
#include "server/models/particle_mesh.h"

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

[[noreturn]] void Refuse(const std::string& what) { throw std::invalid_argument("fem: " + what); }

// e^{-dt/τ} and β = (τ/dt)(1 - e^{-dt/τ}) of a Prony term (β → 1 as dt/τ → 0).
void CheckParameters(const FemParameters& p) {
  const auto finite_positive = [](double value, const char* what) {
    if (!(value > 0.0) || !std::isfinite(value)) {
      Refuse(std::string(what) + " must be a finite value > 0");
    }
  };
  if (p.kind == FemKind::kHyperelastic) {
    CheckMaterial(p.hyperelastic);
  } else {
    finite_positive(p.youngs_modulus, "youngs_modulus [Pa]");
  }
  finite_positive(p.density, "density [kg/m^3]");
  finite_positive(p.speed_limit, "speed_limit [m/s]");
  finite_positive(p.cg_tolerance, "cg_tolerance");
  if (p.kind != FemKind::kHyperelastic && !(p.poisson_ratio > -1.0 && p.poisson_ratio < 0.5)) {
    Refuse("poisson_ratio must lie in (-1, 0.5)");
  }
  if (!(p.rayleigh_mass >= 0.0) || !std::isfinite(p.rayleigh_mass) ||
      !(p.rayleigh_stiffness >= 0.0) || !std::isfinite(p.rayleigh_stiffness)) {
    Refuse("rayleigh_mass [1/s] and rayleigh_stiffness [s] must be finite and >= 0");
  }
  if (!(p.cg_max_iterations > 0)) Refuse("cg_max_iterations must be > 0");
  if (p.prony.size() > kMaxPronyTerms) {
    Refuse("at most " + std::to_string(kMaxPronyTerms) + " Prony terms");
  }
  double gamma_sum = 0.0;
  for (size_t k = 0; k < p.prony.size(); ++k) {
    const PronyTerm& t = p.prony[k];
    if (!(t.gamma >= 0.0) || !std::isfinite(t.gamma) || !(t.tau > 0.0) || !std::isfinite(t.tau)) {
      Refuse("Prony term " + std::to_string(k + 1) + " needs gamma >= 0 and tau [s] > 0");
    }
    gamma_sum += t.gamma;
  }
  if (!(gamma_sum <= 1.0)) {
    Refuse("the Prony gammas sum to more than 1 (G(0) = 1 needs gamma_inf = 1 - sum >= 0)");
  }
}

// The skew matrix [w]× with [w]× u = w × u.
Matrix3d Skew(const Vector3d& w) {
  Matrix3d m;
  m << 0.0, -w.z(), w.y(), w.z(), 0.0, -w.x(), -w.y(), w.x(), 0.0;
  return m;
}

// The state of a FEM model: positions and velocities plus a step's matrix and scratch, all
// sized by MakeState.
class FemState final : public TissueState {
 public:
  BlockSparseMatrix matrix;  // A = (1 + dt α) M + (dt² + dt β) K
  CgScratch cg;
  std::vector<double> rotations;  // 9 × num_tets, column-major R per element
  // 4 × num_tets: R per element as (w, x, y, z), the next step's warm starts (they change its
  // result by rounding only, but a rollback restores them too, so that replays are bit-exact).
  std::vector<double> quaternions, good_quaternions;
  mesh::Points forces, rhs, dv, temp;  // 3 × num_nodes
  mesh::Points good_dv;  // dv of the last accepted step: CG's warm start, restored on rollback
  std::vector<uint8_t> constrained;  // num_nodes
  double last_cg_residual = 0.0;     // |r| / |b| of the last step's solve
  // QLV internal variables h_k (9 × num_prony × num_tets, element-major), the elastic stress of
  // the last accepted step S^e (9 × num_tets), a step's offset (9 × num_tets), and the copies
  // a rejected step restores.
  std::vector<double> history, elastic_last, offset, good_history, good_elastic_last;
  // The rest geometry the state is computed with (FemModel::ApplyCut): a copy of the model's at
  // first, then cut. rest 3 × num_nodes [m], gradients 3 × 4·num_tets [1/m], volumes num_tets
  // [m³] (0 for an element cut away).
  mesh::Points rest;
  Eigen::Matrix<double, 3, Eigen::Dynamic> gradients;
  std::vector<double> volumes;
  int32_t num_cut = 0;  // elements cut away
  // ApplyCut's scratch: per moved node its rest move (3 × num_nodes), and per element its
  // candidate gradients and volume while a move is tried.
  mesh::Points rest_move;

 protected:
  void SaveGood() override {
    good_dv = dv;  // same size: no allocation
    std::copy(quaternions.begin(), quaternions.end(), good_quaternions.begin());
    std::copy(history.begin(), history.end(), good_history.begin());
    std::copy(elastic_last.begin(), elastic_last.end(), good_elastic_last.begin());
  }
  void RestoreGood() override {
    dv = good_dv;
    std::copy(good_quaternions.begin(), good_quaternions.end(), quaternions.begin());
    std::copy(good_history.begin(), good_history.end(), history.begin());
    std::copy(good_elastic_last.begin(), good_elastic_last.end(), elastic_last.begin());
  }
};

}  // namespace

std::vector<PronyTerm> LiverNava2008Prony() { return {{0.5054, 0.5784}, {0.1485, 6.8863}}; }

void PronyFactors(const PronyTerm& term, double dt, double* decay, double* beta) {
  const double x = dt / term.tau;
  *decay = std::exp(-x);
  *beta = x > 1e-8 ? -std::expm1(-x) / x : 1.0 - 0.5 * x;
}

std::unique_ptr<FemModel> FemModel::FromTetMesh(const mesh::TetMesh& mesh,
                                                const FemParameters& parameters) {
  CheckParameters(parameters);
  std::unique_ptr<FemModel> model(new FemModel());
  model->elements_ = BuildTetElements(mesh, "fem");
  model->rest_ = mesh.vertices;
  model->pattern_ = BlockSparseMatrix::FromTets(mesh.tetrahedra, model->num_nodes());
  if (parameters.kind != FemKind::kHyperelastic) {
    model->upper_pattern_ = BlockSparseMatrix::FromTets(mesh.tetrahedra, model->num_nodes(), true);
  }
  model->mass_.resize(model->elements_.node_volume.size());
  for (size_t i = 0; i < model->mass_.size(); ++i) {
    model->mass_[i] = parameters.density * model->elements_.node_volume[i];
  }
  const double e = parameters.youngs_modulus, nu = parameters.poisson_ratio;
  model->lambda_ = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
  model->mu_ = e / (2.0 * (1.0 + nu));
  model->kind_ = parameters.kind;
  model->material_ = parameters.hyperelastic;
  model->prony_ = parameters.prony;
  if (parameters.kind == FemKind::kHyperelastic) {  // λ, μ at rest (the rest stiffness)
    const double k0 = parameters.hyperelastic.InitialBulkModulus();
    model->mu_ = parameters.hyperelastic.InitialShearModulus();
    model->lambda_ = k0 - 2.0 * model->mu_ / 3.0;
  }
  model->rayleigh_mass_ = parameters.rayleigh_mass;
  model->rayleigh_stiffness_ = parameters.rayleigh_stiffness;
  model->cg_tolerance_ = parameters.cg_tolerance;
  model->cg_max_iterations_ = parameters.cg_max_iterations;
  model->cg_fixed_iterations_ = parameters.cg_fixed_iterations;
  model->set_speed_limit(parameters.speed_limit);
  return model;
}

std::unique_ptr<TissueState> FemModel::MakeState() const {
  auto state = std::make_unique<FemState>();
  InitialiseState(rest_, state.get());
  state->matrix = kind_ == FemKind::kHyperelastic ? pattern_ : upper_pattern_;
  state->rest = rest_;
  state->gradients = elements_.gradients;
  state->volumes = elements_.volumes;
  state->rest_move = mesh::Points::Zero(3, num_nodes());
  state->cg = CgScratch(num_nodes());
  state->rotations.assign(9 * static_cast<size_t>(num_tets()), 0.0);
  for (size_t e = 0; e < static_cast<size_t>(num_tets()); ++e) {
    Eigen::Map<Matrix3d>(state->rotations.data() + 9 * e).setIdentity();
  }
  // Warm starts for the corotational model's rotations (the others have none).
  const size_t rotated = kind_ == FemKind::kCorotational ? static_cast<size_t>(num_tets()) : 0;
  state->quaternions.assign(4 * rotated, 0.0);
  for (size_t e = 0; e < rotated; ++e) state->quaternions[4 * e] = 1.0;
  state->good_quaternions = state->quaternions;
  for (mesh::Points* p : {&state->forces, &state->rhs, &state->dv, &state->temp, &state->good_dv}) {
    *p = mesh::Points::Zero(3, num_nodes());
  }
  state->constrained.assign(static_cast<size_t>(num_nodes()), 0);
  const size_t m = static_cast<size_t>(num_tets());
  for (std::vector<double>* v : {&state->history, &state->good_history}) {
    v->assign(9 * prony_.size() * m, 0.0);
  }
  for (std::vector<double>* v : {&state->elastic_last, &state->offset, &state->good_elastic_last}) {
    v->assign(prony_.empty() ? 0 : 9 * m, 0.0);
  }
  return state;
}

Matrix3d FemModel::RestBlock(const Shape& sh, int32_t e, int a, int b) const {
  const Vector3d ga = sh.gradients.col(4 * e + a);
  const Vector3d gb = sh.gradients.col(4 * e + b);
  const double v = sh.volumes[static_cast<size_t>(e)];
  return v * (lambda_ * ga * gb.transpose() + mu_ * gb * ga.transpose() +
              mu_ * ga.dot(gb) * Matrix3d::Identity());
}

void FemModel::ElementStress(const Shape& sh, const mesh::Points& x, int32_t e, Matrix3d* rotation,
                             Matrix3d* strain, Matrix3d* stress, const ViscousStep* viscous) const {
  const Matrix3d h = DisplacementGradientOf(sh, x, e);  // F - I
  const bool has_offset = viscous != nullptr && viscous->offset != nullptr;
  if (kind_ == FemKind::kHyperelastic) {
    rotation->setIdentity();
    strain->setZero();  // no caller reads it for this model (ElasticEnergy has its own E)
    const Matrix3d f = Matrix3d::Identity() + h;
    *stress = FirstPiolaStress(material_, f);
    if (viscous != nullptr) {  // P = F (g S^e + offset) = g P^e + F offset
      *stress *= viscous->g;
      if (has_offset) {
        *stress += f * Eigen::Map<const Matrix3d>(viscous->offset + 9 * static_cast<size_t>(e));
      }
    }
    return;
  }
  if (kind_ == FemKind::kLinear) {
    rotation->setIdentity();
    *strain = 0.5 * (h + h.transpose());
  } else {
    double identity[4] = {1.0, 0.0, 0.0, 0.0};  // a cold start (PolarRotationFrom)
    *rotation = PolarRotationFrom(Matrix3d::Identity() + h, identity);
    // S - I = Rᵀ (I + H) - I = (Rᵀ - I) + Rᵀ H, symmetric up to rounding.
    const Matrix3d s_minus_i =
        (rotation->transpose() - Matrix3d::Identity()) + rotation->transpose() * h;
    *strain = 0.5 * (s_minus_i + s_minus_i.transpose());
  }
  Matrix3d sigma = lambda_ * strain->trace() * Matrix3d::Identity() + 2.0 * mu_ * *strain;
  if (viscous != nullptr) {  // rotated frame: S = g σ^e + offset
    sigma *= viscous->g;
    if (has_offset) {
      sigma += Eigen::Map<const Matrix3d>(viscous->offset + 9 * static_cast<size_t>(e));
    }
  }
  *stress = *rotation * sigma;
}

Matrix3d FemModel::ElasticStress(const Shape& sh, const mesh::Points& x, int32_t e) const {
  Matrix3d r, strain, p;
  ElementStress(sh, x, e, &r, &strain, &p);
  if (kind_ == FemKind::kHyperelastic) {  // S^e = F⁻¹ P^e
    return (Matrix3d::Identity() + DisplacementGradientOf(sh, x, e)).inverse() * p;
  }
  return r.transpose() * p;  // σ^e in the rotated frame
}

double FemModel::ElasticEnergy(const Shape& sh, const mesh::Points& x,
                               const ViscousStep* viscous) const {
  double energy = 0.0;
  const double g = viscous != nullptr ? viscous->g : 1.0;
  const bool has_offset = viscous != nullptr && viscous->offset != nullptr;
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const double v = sh.volumes[static_cast<size_t>(e)];
    Matrix3d r, strain, p;
    double w = 0.0;
    if (kind_ == FemKind::kHyperelastic) {
      const Matrix3d h = DisplacementGradientOf(sh, x, e);
      w = StrainEnergy(material_, Matrix3d::Identity() + h);
      strain = 0.5 * (h + h.transpose() + h.transpose() * h);  // Green's E
    } else {
      ElementStress(sh, x, e, &r, &strain, &p);
      const double tr = strain.trace();
      w = mu_ * strain.squaredNorm() + 0.5 * lambda_ * tr * tr;
    }
    energy += v * g * w;
    if (has_offset) {  // + offset : strain (its gradient is the offset's stress)
      const Eigen::Map<const Matrix3d> c(viscous->offset + 9 * static_cast<size_t>(e));
      energy += v * (c.array() * strain.array()).sum();
    }
  }
  return energy;
}

ViscousStep FemModel::BeginViscousStep(const TissueState& base, double dt, double* offset) const {
  const auto& state = static_cast<const FemState&>(base);
  ViscousStep step;
  double gamma_sum = 0.0;
  step.g = 0.0;
  for (const PronyTerm& t : prony_) {
    double decay = 0.0, beta = 0.0;
    PronyFactors(t, dt, &decay, &beta);
    step.g += t.gamma * beta;
    gamma_sum += t.gamma;
  }
  step.g += 1.0 - gamma_sum;  // γ∞
  const size_t m = static_cast<size_t>(num_tets()), terms = prony_.size();
  // e^{-dt/τ_k} and γ_k β_k, the same for every element (at most kMaxPronyTerms).
  double decay[kMaxPronyTerms] = {}, weight[kMaxPronyTerms] = {};
  for (size_t k = 0; k < terms; ++k) {
    double beta = 0.0;
    PronyFactors(prony_[k], dt, &decay[k], &beta);
    weight[k] = prony_[k].gamma * beta;
  }
  for (size_t e = 0; e < m; ++e) {
    Eigen::Map<Matrix3d> out(offset + 9 * e);
    out.setZero();
    const Eigen::Map<const Matrix3d> last(state.elastic_last.data() + 9 * e);
    for (size_t k = 0; k < terms; ++k) {
      out += decay[k] * Eigen::Map<const Matrix3d>(state.history.data() + 9 * (e * terms + k)) -
             weight[k] * last;
    }
  }
  step.offset = offset;
  return step;
}

void FemModel::EndViscousStep(double dt, TissueState* base) const {
  auto* state = static_cast<FemState*>(base);
  const Shape sh = ShapeOf(*state);
  const size_t m = static_cast<size_t>(num_tets()), terms = prony_.size();
  double decay[kMaxPronyTerms] = {}, weight[kMaxPronyTerms] = {};
  for (size_t k = 0; k < terms; ++k) {
    double beta = 0.0;
    PronyFactors(prony_[k], dt, &decay[k], &beta);
    weight[k] = prony_[k].gamma * beta;
  }
  for (size_t e = 0; e < m; ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const Matrix3d now = ElasticStress(sh, state->positions, static_cast<int32_t>(e));
    Eigen::Map<Matrix3d> last(state->elastic_last.data() + 9 * e);
    for (size_t k = 0; k < terms; ++k) {
      Eigen::Map<Matrix3d> h(state->history.data() + 9 * (e * terms + k));
      h = decay[k] * h + weight[k] * (now - last);  // exact for linear S^e over dt
    }
    last = now;
  }
}

void FemModel::ElasticForces(const Shape& sh, const mesh::Points& x, double* forces,
                             double* rotations, const ViscousStep* viscous) const {
  std::fill(forces, forces + 3 * static_cast<size_t>(num_nodes()), 0.0);
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    Matrix3d r, strain, p;
    ElementStress(sh, x, e, &r, &strain, &p, viscous);
    if (rotations != nullptr) Eigen::Map<Matrix3d>(rotations + 9 * static_cast<size_t>(e)) = r;
    const double v = sh.volumes[static_cast<size_t>(e)];
    for (int a = 0; a < 4; ++a) {
      const Vector3d fa = -v * (p * sh.gradients.col(4 * e + a));
      double* out = forces + 3 * static_cast<size_t>(elements_.tets(a, e));
      out[0] += fa.x();
      out[1] += fa.y();
      out[2] += fa.z();
    }
  }
}

namespace {

// ForcesAndWarpedMatrix's pass over the elements, on raw arrays: the portable ElementPass, and
// with AVX-512 ElementPassAvx512 (the linear kind) or CorotationalPassAvx512.
struct WarpedPass {
  const double* x;                // 3 × num_nodes
  const double* rest;             // 3 × num_nodes
  const int32_t* tets;            // 4 × num_tets
  const double* gradients;        // 12 × num_tets
  const double* volumes;          // num_tets
  const double* rotations;        // 9 × num_tets
  const double* offset;           // 9 × num_tets, or null
  const int32_t* element_blocks;  // 16 × num_tets
  double* forces;                 // 3 × num_nodes, accumulated
  double* values;                 // the matrix's blocks, accumulated
  size_t num_tets;
  double g, lambda, mu, k_scale;
  bool linear;
};

// H = F - I = Σ_a (x_a - X_a) ∇N_aᵀ of element e (TetElements::DisplacementGradient), h[i][j] =
// H(i, j).
__attribute__((always_inline)) inline void DisplacementGradient(const WarpedPass& a, size_t e,
                                                                double h[3][3]) {
  const double* grad = a.gradients + 12 * e;
  const int32_t* node = a.tets + 4 * e;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) h[i][j] = 0.0;
  }
  for (int c0 = 0; c0 < 4; ++c0) {
    const auto k = 3 * static_cast<size_t>(node[c0]);
    for (int i = 0; i < 3; ++i) {
      const double u = a.x[k + static_cast<size_t>(i)] - a.rest[k + static_cast<size_t>(i)];
      for (int j = 0; j < 3; ++j) h[i][j] += u * grad[3 * c0 + j];
    }
  }
}

// F = I + H of every element into f (9 × num_tets, column-major), for PolarRotations (the
// portable path; CorotationalPassAvx512 keeps F in registers).
void DeformationGradients(const WarpedPass& a, double* f) {
  for (size_t e = 0; e < a.num_tets; ++e) {
    double h[3][3];
    DisplacementGradient(a, e, h);
    double* out = f + 9 * e;
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 3; ++i) out[3 * j + i] = h[i][j] + (i == j ? 1.0 : 0.0);
    }
  }
}

// Element e's part before its blocks: its nodal forces into a.forces, its rotated gradients
// r_a = R ∇N_a (r[4][3]) and the blocks' factors V k λ, V k μ (k = k_scale g).
// Always inlined, so that the AVX-512 pass compiles it for its target too (FMA).
__attribute__((always_inline)) inline void ElementForcesAndGradients(const WarpedPass& a, size_t e,
                                                                     double r[4][3], double* cl_out,
                                                                     double* cm_out) {
  const double g = a.g, lambda = a.lambda, mu = a.mu;
  const double* grad = a.gradients + 12 * e;  // ∇N_a at grad + 3a
  const double* rot = a.rotations + 9 * e;    // column-major R
  const int32_t* node = a.tets + 4 * e;
  double h[3][3];
  DisplacementGradient(a, e, h);
  // ε: linear sym(H); corotational sym((Rᵀ - I) + Rᵀ H) (ElementStress).
  double eps[3][3];
  if (a.linear) {
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) eps[i][j] = 0.5 * (h[i][j] + h[j][i]);
    }
  } else {
    double s[3][3];  // S - I = Rᵀ - I + Rᵀ H
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        double v = rot[3 * i + j] - (i == j ? 1.0 : 0.0);  // Rᵀ(i, j) = R(j, i)
        for (int k = 0; k < 3; ++k) v += rot[3 * i + k] * h[k][j];
        s[i][j] = v;
      }
    }
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) eps[i][j] = 0.5 * (s[i][j] + s[j][i]);
    }
  }
  // σ = g (λ tr ε I + 2 μ ε) + offset, P = R σ.
  const double tr = eps[0][0] + eps[1][1] + eps[2][2];
  double sigma[3][3];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      sigma[i][j] = g * (2.0 * mu * eps[i][j] + (i == j ? lambda * tr : 0.0));
    }
  }
  if (a.offset != nullptr) {
    const double* c = a.offset + 9 * e;  // column-major
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) sigma[i][j] += c[3 * j + i];
    }
  }
  double p[3][3];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      p[i][j] = rot[i] * sigma[0][j] + rot[3 + i] * sigma[1][j] + rot[6 + i] * sigma[2][j];
    }
  }
  const double volume = a.volumes[e];
  // f_a = -V P ∇N_a; r_a = R ∇N_a for the blocks.
  for (int c0 = 0; c0 < 4; ++c0) {
    const double* ga = grad + 3 * c0;
    double* out = a.forces + 3 * static_cast<size_t>(node[c0]);
    for (int i = 0; i < 3; ++i) {
      out[i] -= volume * (p[i][0] * ga[0] + p[i][1] * ga[1] + p[i][2] * ga[2]);
      r[c0][i] = rot[i] * ga[0] + rot[3 + i] * ga[1] + rot[6 + i] * ga[2];
    }
  }
  const double v = a.k_scale * g * volume;  // a viscous step's stiffness is g times the elastic
  *cl_out = v * lambda;
  *cm_out = v * mu;
}

void ElementPass(const WarpedPass& a) {
  for (size_t e = 0; e < a.num_tets; ++e) {
    double r[4][3], cl, cm;
    ElementForcesAndGradients(a, e, r, &cl, &cm);
    const double* grad = a.gradients + 12 * e;
    // The warped blocks as AssembleWarped: R K_ab Rᵀ = V (λ r_a r_bᵀ + μ r_b r_aᵀ + μ (∇N_a·∇N_b)
    // I).
    for (int c0 = 0; c0 < 4; ++c0) {
      for (int b = 0; b < 4; ++b) {
        const int32_t block = a.element_blocks[16 * e + static_cast<size_t>(4 * c0 + b)];
        if (block < 0) continue;  // upper storage: the transpose of (b, a)
        const double* ga = grad + 3 * c0;
        const double* gb = grad + 3 * b;
        const double diagonal = cm * (ga[0] * gb[0] + ga[1] * gb[1] + ga[2] * gb[2]);
        double* out = a.values + 9 * static_cast<size_t>(block);
        for (int c = 0; c < 3; ++c) {
          for (int i = 0; i < 3; ++i) {
            out[3 * c + i] += cl * r[c0][i] * r[b][c] + cm * r[b][i] * r[c0][c];
          }
          out[4 * c] += diagonal;
        }
      }
    }
  }
}

#ifdef SOMASIM_FEM_HAS_AVX512_PATH
// ElementPass's blocks of element e, each block's first eight values (column-major) in one
// AVX-512 register: value 3c + i is cl r_a[i] r_b[c] + cm r_b[i] r_a[c] (+ the diagonal term
// where c = i), so with each corner's r in the lane patterns I_a = (r0 r1 r2 r0 r1 r2 r0 r1)
// (lane k: r[k mod 3]) and C_a = (r0 r0 r0 r1 r1 r1 r2 r2) (lane k: r[k / 3]) the eight are
// cl I_a C_b + cm I_b C_a, two FMAs; value 8 (c = i = 2) is (cl + cm) r_a[2] r_b[2] + diagonal.
// Equal to ElementPass up to rounding (the order of the additions).
SOMASIM_FEM_AVX512 __attribute__((always_inline)) inline void AddWarpedBlocks(
    const WarpedPass& a, size_t e, const double r[4][3], double cl, double cm) {
  const __m512i i_pattern = _mm512_set_epi64(1, 0, 2, 1, 0, 2, 1, 0);
  const __m512i c_pattern = _mm512_set_epi64(2, 2, 1, 1, 1, 0, 0, 0);
  __m512d lanes_i[4], lanes_c[4];
  for (int c0 = 0; c0 < 4; ++c0) {
    // From registers (a vector load of the three just-stored scalars would stall on store
    // forwarding).
    const __m512d ra = _mm512_castpd256_pd512(_mm256_set_pd(0.0, r[c0][2], r[c0][1], r[c0][0]));
    lanes_i[c0] = _mm512_maskz_permutexvar_pd(0xFF, i_pattern, ra);
    lanes_c[c0] = _mm512_maskz_permutexvar_pd(0xFF, c_pattern, ra);
  }
  const __m512d cl8 = _mm512_set1_pd(cl), cm8 = _mm512_set1_pd(cm);
  const double* grad = a.gradients + 12 * e;
  const int32_t* blocks = a.element_blocks + 16 * e;
  for (int c0 = 0; c0 < 4; ++c0) {
    const __m512d cl_ia = _mm512_mul_pd(cl8, lanes_i[c0]);
    for (int b = 0; b < 4; ++b) {
      const int32_t block = blocks[4 * c0 + b];
      if (block < 0) continue;  // upper storage: the transpose of (b, a)
      const double* ga = grad + 3 * c0;
      const double* gb = grad + 3 * b;
      const double diagonal = cm * (ga[0] * gb[0] + ga[1] * gb[1] + ga[2] * gb[2]);
      double* out = a.values + 9 * static_cast<size_t>(block);
      __m512d v = _mm512_maskz_mov_pd(0x11, _mm512_set1_pd(diagonal));
      v = _mm512_fmadd_pd(_mm512_mul_pd(cm8, lanes_i[b]), lanes_c[c0], v);
      v = _mm512_fmadd_pd(cl_ia, lanes_c[b], v);
      _mm512_storeu_pd(out, _mm512_add_pd(_mm512_loadu_pd(out), v));
      out[8] += (cl + cm) * r[c0][2] * r[b][2] + diagonal;
    }
  }
}

// ElementPass with the blocks written by AddWarpedBlocks (the linear kind: R = I).
SOMASIM_FEM_AVX512 void ElementPassAvx512(const WarpedPass& a) {
  for (size_t e = 0; e < a.num_tets; ++e) {
    double r[4][3], cl, cm;
    ElementForcesAndGradients(a, e, r, &cl, &cm);
    AddWarpedBlocks(a, e, r, cl, cm);
  }
}

// The corotational kind's DeformationGradients, PolarRotations and ElementPass in one pass,
// eight elements in the eight lanes of AVX-512 registers (lane l: element e0 + l): H and F from
// gathered x - X and ∇N, R by PolarIterate8 warm-started from `quaternions` (4 × num_tets,
// updated; a lane it leaves goes to PolarRotationFrom, as in PolarRotations), the stress and
// forces as ElementForcesAndGradients, then per element its forces into a.forces and its blocks
// by AddWarpedBlocks. Writes R into `rotations` (9 × num_tets, column-major), which is
// a.rotations. The last num_tets mod 8 elements go one at a time. Equal to the three passes up
// to rounding; F is not stored (a pass over memory less) and the rotations never wait for a
// separate pass to write them.
SOMASIM_FEM_AVX512 void CorotationalPassAvx512(const WarpedPass& a, double* rotations,
                                               double* quaternions) {
  const __m512i twelve = _mm512_set_epi64(84, 72, 60, 48, 36, 24, 12, 0);
  const __m512i nine = _mm512_set_epi64(63, 54, 45, 36, 27, 18, 9, 0);
  const __m512i four = _mm512_set_epi64(28, 24, 20, 16, 12, 8, 4, 0);
  // Corner c of element l of 8 is tets value 4 l + c of the 32 in two registers.
  const __m512i corner_index =
      _mm512_set_epi32(0, 0, 0, 0, 0, 0, 0, 0, 28, 24, 20, 16, 12, 8, 4, 0);
  const __m512d zero = _mm512_setzero_pd();
  const __m512d g = _mm512_set1_pd(a.g), two_mu = _mm512_set1_pd(2.0 * a.mu);
  const __m512d lambda = _mm512_set1_pd(a.lambda), mu = _mm512_set1_pd(a.mu);
  const __m512d k_scale = _mm512_set1_pd(a.k_scale), half = _mm512_set1_pd(0.5);
  alignas(64) double rbuf[12][8];  // r_c[i] of lane l at [3 c + i][l]
  alignas(64) double fbuf[12][8];  // the forces on corner c, f_c[i], likewise [N]
  alignas(64) double cbuf[2][8];   // cl, cm
  alignas(64) double mbuf[9][8];   // F, then R, of lanes left to PolarRotationFrom
  const size_t groups = a.num_tets / 8;
  for (size_t group = 0; group < groups; ++group) {
    const size_t e0 = 8 * group;
    const __m512i t0 = _mm512_loadu_si512(a.tets + 4 * e0);
    const __m512i t1 = _mm512_loadu_si512(a.tets + 4 * e0 + 16);
    const double* gradients = a.gradients + 12 * e0;
    __m512d grad[4][3];  // ∇N_c[j]
    __m512d h[3][3];     // H(i, j) = Σ_c (x_c - X_c)[i] ∇N_c[j]
    for (int c = 0; c < 4; ++c) {
      const __m256i node = _mm512_maskz_extracti64x4_epi64(
          0xF,
          _mm512_permutex2var_epi32(t0, _mm512_add_epi32(corner_index, _mm512_set1_epi32(c)), t1),
          0);
      const __m256i node3 = _mm256_add_epi32(node, _mm256_add_epi32(node, node));
      for (int j = 0; j < 3; ++j) {
        grad[c][j] = _mm512_mask_i64gather_pd(zero, 0xFF, twelve, gradients + 3 * c + j, 8);
      }
      for (int i = 0; i < 3; ++i) {
        const __m512d u = _mm512_sub_pd(_mm512_mask_i32gather_pd(zero, 0xFF, node3, a.x + i, 8),
                                        _mm512_mask_i32gather_pd(zero, 0xFF, node3, a.rest + i, 8));
        for (int j = 0; j < 3; ++j) {
          h[i][j] = c == 0 ? _mm512_mul_pd(u, grad[c][j]) : _mm512_fmadd_pd(u, grad[c][j], h[i][j]);
        }
      }
    }
    __m512d fm[9];  // F column-major
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 3; ++i) {
        fm[3 * j + i] = i == j ? _mm512_add_pd(h[i][j], _mm512_set1_pd(1.0)) : h[i][j];
      }
    }
    double* const qb = quaternions + 4 * e0;
    __m512d q[4];
    for (int k = 0; k < 4; ++k) q[k] = _mm512_mask_i64gather_pd(zero, 0xFF, four, qb + k, 8);
    __m512d rm[9];  // R column-major: R(i, k) = rm[3 k + i]
    const __mmask8 left = PolarIterate8(fm, q, rm);
    for (int k = 0; k < 4; ++k) {
      _mm512_mask_i64scatter_pd(qb + k, static_cast<__mmask8>(~left), four, q[k], 8);
    }
    if (left != 0) {
      for (int k = 0; k < 9; ++k) _mm512_store_pd(mbuf[k], fm[k]);
      Matrix3d f[8];
      for (int l = 0; l < 8; ++l) {
        for (int k = 0; k < 9; ++k) f[l](k) = mbuf[k][l];
      }
      for (int k = 0; k < 9; ++k) _mm512_store_pd(mbuf[k], rm[k]);
      for (int l = 0; l < 8; ++l) {
        if (((left >> l) & 1U) == 0) continue;
        const Matrix3d r = PolarRotationFrom(f[l], qb + 4 * l);
        for (int k = 0; k < 9; ++k) mbuf[k][l] = r(k);
      }
      for (int k = 0; k < 9; ++k) rm[k] = _mm512_load_pd(mbuf[k]);
    }
    for (int k = 0; k < 9; ++k) {
      _mm512_mask_i64scatter_pd(rotations + 9 * e0 + k, 0xFF, nine, rm[k], 8);
    }
    // ε = sym((Rᵀ - I) + Rᵀ H) (ElementStress), σ = g (λ tr ε I + 2 μ ε) + offset, P = R σ.
    __m512d st[3][3];  // (Rᵀ - I) + Rᵀ H
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        __m512d v = i == j ? _mm512_sub_pd(rm[3 * i + j], _mm512_set1_pd(1.0)) : rm[3 * i + j];
        for (int k = 0; k < 3; ++k) v = _mm512_fmadd_pd(rm[3 * i + k], h[k][j], v);
        st[i][j] = v;
      }
    }
    const __m512d tr = _mm512_add_pd(st[0][0], _mm512_add_pd(st[1][1], st[2][2]));
    const __m512d lambda_tr = _mm512_mul_pd(lambda, tr);
    __m512d sigma[3][3];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        const __m512d eps = _mm512_mul_pd(half, _mm512_add_pd(st[i][j], st[j][i]));
        __m512d v = i == j ? _mm512_fmadd_pd(two_mu, eps, lambda_tr) : _mm512_mul_pd(two_mu, eps);
        v = _mm512_mul_pd(g, v);
        if (a.offset != nullptr) {  // column-major 9 per element
          v = _mm512_add_pd(
              v, _mm512_mask_i64gather_pd(zero, 0xFF, nine, a.offset + 9 * e0 + 3 * j + i, 8));
        }
        sigma[i][j] = v;
      }
    }
    __m512d p[3][3];
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        p[i][j] = _mm512_fmadd_pd(
            rm[6 + i], sigma[2][j],
            _mm512_fmadd_pd(rm[3 + i], sigma[1][j], _mm512_mul_pd(rm[i], sigma[0][j])));
      }
    }
    const __m512d volume = _mm512_loadu_pd(a.volumes + e0);
    const __m512d minus_volume = _mm512_sub_pd(zero, volume);
    // f_c = -V P ∇N_c; r_c = R ∇N_c.
    for (int c = 0; c < 4; ++c) {
      for (int i = 0; i < 3; ++i) {
        const __m512d pg = _mm512_fmadd_pd(
            p[i][2], grad[c][2],
            _mm512_fmadd_pd(p[i][1], grad[c][1], _mm512_mul_pd(p[i][0], grad[c][0])));
        _mm512_store_pd(fbuf[3 * c + i], _mm512_mul_pd(minus_volume, pg));
        const __m512d rg = _mm512_fmadd_pd(
            rm[6 + i], grad[c][2],
            _mm512_fmadd_pd(rm[3 + i], grad[c][1], _mm512_mul_pd(rm[i], grad[c][0])));
        _mm512_store_pd(rbuf[3 * c + i], rg);
      }
    }
    const __m512d v = _mm512_mul_pd(_mm512_mul_pd(k_scale, g), volume);
    _mm512_store_pd(cbuf[0], _mm512_mul_pd(v, lambda));
    _mm512_store_pd(cbuf[1], _mm512_mul_pd(v, mu));
    for (size_t l = 0; l < 8; ++l) {
      const size_t e = e0 + l;
      const int32_t* node = a.tets + 4 * e;
      double r[4][3];
      for (int c = 0; c < 4; ++c) {
        double* out = a.forces + 3 * static_cast<size_t>(node[c]);
        for (int i = 0; i < 3; ++i) {
          out[i] += fbuf[3 * c + i][l];
          r[c][i] = rbuf[3 * c + i][l];
        }
      }
      AddWarpedBlocks(a, e, r, cbuf[0][l], cbuf[1][l]);
    }
  }
  for (size_t e = 8 * groups; e < a.num_tets; ++e) {
    double h[3][3];
    DisplacementGradient(a, e, h);
    Matrix3d f;
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) f(i, j) = h[i][j] + (i == j ? 1.0 : 0.0);
    }
    Eigen::Map<Matrix3d>(rotations + 9 * e) = PolarRotationFrom(f, quaternions + 4 * e);
    double r[4][3], cl, cm;
    ElementForcesAndGradients(a, e, r, &cl, &cm);
    AddWarpedBlocks(a, e, r, cl, cm);
  }
}
#endif

}  // namespace

void FemModel::ForcesAndWarpedMatrix(const Shape& sh, const mesh::Points& x, double* forces,
                                     double* rotations, double* quaternions,
                                     const ViscousStep* viscous, double k_scale, double m_scale,
                                     BlockSparseMatrix* matrix) const {
  assert(kind_ != FemKind::kHyperelastic);
  const auto m = static_cast<size_t>(num_tets());
  std::fill(forces, forces + 3 * static_cast<size_t>(num_nodes()), 0.0);
  matrix->SetZero();
  WarpedPass pass{};
  pass.x = x.data();
  pass.rest = sh.rest.data();
  pass.tets = elements_.tets.data();
  pass.gradients = sh.gradients.data();
  pass.volumes = sh.volumes.data();
  pass.rotations = rotations;
  pass.offset = viscous != nullptr ? viscous->offset : nullptr;
  pass.element_blocks = matrix->element_blocks();
  pass.forces = forces;
  pass.values = matrix->values();
  pass.num_tets = m;
  pass.g = viscous != nullptr ? viscous->g : 1.0;
  pass.lambda = lambda_;
  pass.mu = mu_;
  pass.k_scale = k_scale;
  pass.linear = kind_ == FemKind::kLinear;
  const bool vector = CpuHasAvx512() && !force_scalar_element_pass_;
#ifdef SOMASIM_FEM_HAS_AVX512_PATH
  if (vector && kind_ != FemKind::kLinear) {
    CorotationalPassAvx512(pass, rotations, quaternions);
  } else
#endif
  {
    // The rotations first, in batches (PolarRotations): F of each element into `rotations`,
    // turned into R in place.
    if (kind_ == FemKind::kLinear) {
      for (size_t e = 0; e < m; ++e) Eigen::Map<Matrix3d>(rotations + 9 * e).setIdentity();
    } else {
      DeformationGradients(pass, rotations);
      PolarRotations(rotations, quaternions, rotations, m);
    }
#ifdef SOMASIM_FEM_HAS_AVX512_PATH
    if (vector) {
      ElementPassAvx512(pass);
    } else {
      ElementPass(pass);
    }
#else
    ElementPass(pass);
#endif
  }
  for (int32_t i = 0; i < num_nodes(); ++i) {
    matrix->block(matrix->diagonal_block(i)).diagonal().array() +=
        m_scale * mass_[static_cast<size_t>(i)];
  }
}

void FemModel::AssembleWarped(const Shape& sh, const mesh::Points& x, const double* rotations,
                              double scale, double mass_scale, BlockSparseMatrix* matrix,
                              const ViscousStep* viscous) const {
  matrix->SetZero();
  // A viscous step's effective stiffness is g times the elastic one (hyperelastic: plus the
  // offset's geometric term, inside ElementTangent).
  if (viscous != nullptr && kind_ != FemKind::kHyperelastic) scale *= viscous->g;
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    if (kind_ == FemKind::kHyperelastic) {  // the exact tangent: there is no rotated one
      const Eigen::Matrix<double, 12, 12> k = ElementTangentOf(sh, x, e, true, viscous);
      for (int a = 0; a < 4; ++a) {
        for (int b = 0; b < 4; ++b) {
          if (matrix->element_block(e, a, b) < 0) continue;
          matrix->block(matrix->element_block(e, a, b)).noalias() +=
              scale * k.block<3, 3>(3 * a, 3 * b);
        }
      }
      continue;
    }
    // R K_ab Rᵀ = V (λ r_a r_bᵀ + μ r_b r_aᵀ + μ (r_a·r_b) I) with the rotated gradients
    // r_a = R ∇N_a (RestBlock's formula in the rotated frame; r_a·r_b = ∇N_a·∇N_b): 16 outer
    // products instead of 32 3×3 matrix products.
    const double* rot = rotations + 9 * static_cast<size_t>(e);  // column-major
    const double* grad = sh.gradients.data() + 12 * static_cast<size_t>(e);
    double r[4][3];
    for (int a = 0; a < 4; ++a) {
      const double* g = grad + 3 * a;
      for (int i = 0; i < 3; ++i) r[a][i] = rot[i] * g[0] + rot[3 + i] * g[1] + rot[6 + i] * g[2];
    }
    const double v = scale * sh.volumes[static_cast<size_t>(e)];
    const double cl = v * lambda_, cm = v * mu_;
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        const double* ga = grad + 3 * a;
        const double* gb = grad + 3 * b;
        const int32_t block = matrix->element_block(e, a, b);
        if (block < 0) continue;  // upper storage: the transpose of (b, a)
        const double diagonal = cm * (ga[0] * gb[0] + ga[1] * gb[1] + ga[2] * gb[2]);
        double* out = matrix->block(block).data();
        for (int c = 0; c < 3; ++c) {
          for (int i = 0; i < 3; ++i) {
            out[3 * c + i] += cl * r[a][i] * r[b][c] + cm * r[b][i] * r[a][c];
          }
          out[4 * c] += diagonal;
        }
      }
    }
  }
  for (int32_t i = 0; i < num_nodes(); ++i) {
    matrix->block(matrix->diagonal_block(i)).diagonal().array() +=
        mass_scale * mass_[static_cast<size_t>(i)];
  }
}

Eigen::Matrix<double, 12, 12> FemModel::ElementTangent(const mesh::Points& x, int32_t e, bool exact,
                                                       const ViscousStep* viscous) const {
  return ElementTangentOf(ModelShape(), x, e, exact, viscous);
}

Eigen::Matrix<double, 12, 12> FemModel::ElementTangentOf(const Shape& sh, const mesh::Points& x,
                                                         int32_t e, bool exact,
                                                         const ViscousStep* viscous) const {
  Eigen::Matrix<double, 12, 12> k;
  Matrix3d r = Matrix3d::Identity(), strain = Matrix3d::Zero(), p = Matrix3d::Zero();
  // The stress enters the linear and corotational tangents only (the hyperelastic one is dP).
  if (kind_ != FemKind::kHyperelastic) ElementStress(sh, x, e, &r, &strain, &p, viscous);
  // A viscous step scales the elastic response by g and adds a constant offset stress:
  // hyperelastic dP = g dP^e + dF offset; rotated frame d(R (g σ + offset)).
  const double g = viscous != nullptr ? viscous->g : 1.0;
  const bool has_offset = viscous != nullptr && viscous->offset != nullptr;
  if (kind_ == FemKind::kHyperelastic) {
    const Matrix3d f = Matrix3d::Identity() + DisplacementGradientOf(sh, x, e);
    const double v = sh.volumes[static_cast<size_t>(e)];
    const StressPoint point = PrepareStressDifferential(material_, f);  // once for 12 dF
    if (material_.law == HyperelasticLaw::kReducedPolynomial) {
      // dF = e_c ∇N_bᵀ is rank one, so StressDifferential's terms applied to ∇N_a reduce to
      // vectors of the element: with A_a = a ∇N_a, Q_a = F⁻ᵀ ∇N_a, P_a = F ∇N_a,
      //   F⁻ᵀ : dF = Q_b[c],  dI1 = 2 P_b[c],  dF⁻ᵀ ∇N_a = -Q_b Q_a[c],
      //   da ∇N_a = 2 (∇N_a·∇N_b) e_c - (2/3) (dI1 Q_a - I1 Q_b Q_a[c]),
      // and column (b, c) of the block (a, b) is V (g dP + dF offset) ∇N_a (~20 flops each instead
      // of a 3 × 3 differential).
      Vector3d ga[4], aa[4], qa[4], pa[4];
      for (int a = 0; a < 4; ++a) {
        ga[a] = sh.gradients.col(4 * e + a);
        aa[a] = point.a * ga[a];
        qa[a] = point.f_inv_t * ga[a];
        pa[a] = f * ga[a];
      }
      Vector3d offset_ga[4];  // offset ∇N_a
      if (has_offset) {
        const Eigen::Map<const Matrix3d> offset(viscous->offset + 9 * static_cast<size_t>(e));
        for (int a = 0; a < 4; ++a) offset_ga[a] = offset * ga[a];
      }
      const double jj = point.j;
      for (int b = 0; b < 4; ++b) {
        for (int c = 0; c < 3; ++c) {
          const double tr = qa[b][c];
          const double d_i1 = 2.0 * pa[b][c];
          const double dg = -(2.0 / 3.0) * point.g * tr;
          const double d_i1_bar = dg * point.i1 + point.g * d_i1;
          const double s_a = point.w2 * d_i1_bar * point.g + point.w1 * dg;
          const double s_q = point.u2 * jj * tr * jj + point.u1 * jj * tr;
          for (int a = 0; a < 4; ++a) {
            Vector3d da = -(2.0 / 3.0) * (d_i1 * qa[a] - point.i1 * qa[a][c] * qa[b]);
            da[c] += 2.0 * ga[a].dot(ga[b]);
            Vector3d column = s_a * aa[a] + point.w1 * point.g * da + s_q * qa[a] -
                              point.u1 * jj * qa[a][c] * qa[b];
            column *= g;
            if (has_offset) column[c] += ga[b].dot(offset_ga[a]);
            k.block<3, 1>(3 * a, 3 * b + c) = v * column;
          }
        }
      }
      return k;
    }
    for (int b = 0; b < 4; ++b) {
      const Vector3d gb = sh.gradients.col(4 * e + b);
      for (int c = 0; c < 3; ++c) {
        const Matrix3d df = Vector3d::Unit(c) * gb.transpose();
        Matrix3d dp = g * StressDifferential(point, df);
        if (has_offset) {
          dp += df * Eigen::Map<const Matrix3d>(viscous->offset + 9 * static_cast<size_t>(e));
        }
        for (int a = 0; a < 4; ++a) {
          k.block<3, 1>(3 * a, 3 * b + c) = v * (dp * sh.gradients.col(4 * e + a));
        }
      }
    }
    return k;
  }
  if (!exact) {
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        k.block<3, 3>(3 * a, 3 * b) = g * (r * RestBlock(sh, e, a, b) * r.transpose());
      }
    }
    return k;
  }
  const double v = sh.volumes[static_cast<size_t>(e)];
  const Matrix3d sigma = r.transpose() * p;          // g σ(ε) + offset
  const Matrix3d s = strain + Matrix3d::Identity();  // Rᵀ F, symmetrised
  // dP for dF: linear, dP = σ(sym dF); corotational, P = R σ(S - I) with dR = R [ω]×, where
  // (tr S I - S) ω = axial(Rᵀ dF - dFᵀ R) and dS = Rᵀ dF - [ω]× S.
  const Matrix3d t = s.trace() * Matrix3d::Identity() - s;
  const Eigen::FullPivLU<Matrix3d> t_lu(t);
  for (int b = 0; b < 4; ++b) {
    const Vector3d gb = sh.gradients.col(4 * e + b);
    for (int c = 0; c < 3; ++c) {
      const Matrix3d df = Vector3d::Unit(c) * gb.transpose();
      Matrix3d dp;
      if (kind_ == FemKind::kLinear) {
        const Matrix3d de = 0.5 * (df + df.transpose());
        dp = g * (lambda_ * de.trace() * Matrix3d::Identity() + 2.0 * mu_ * de);
      } else {
        const Matrix3d w = r.transpose() * df;
        const Vector3d axial(w(2, 1) - w(1, 2), w(0, 2) - w(2, 0), w(1, 0) - w(0, 1));
        const Vector3d omega = t_lu.isInvertible() ? Vector3d(t_lu.solve(axial)) : Vector3d::Zero();
        const Matrix3d ds = w - Skew(omega) * s;
        const Matrix3d de = 0.5 * (ds + ds.transpose());
        const Matrix3d dsigma = lambda_ * de.trace() * Matrix3d::Identity() + 2.0 * mu_ * de;
        dp = r * (Skew(omega) * sigma + g * dsigma);
      }
      for (int a = 0; a < 4; ++a) {
        k.block<3, 1>(3 * a, 3 * b + c) = v * (dp * sh.gradients.col(4 * e + a));
      }
    }
  }
  return k;
}

void FemModel::InternalForces(const TissueState& state, mesh::Points* forces) const {
  forces->resize(3, num_nodes());
  const Shape sh = ShapeOf(state);
  ElasticForces(sh, state.positions, forces->data(), nullptr);
  if (rayleigh_mass_ > 0.0 || rayleigh_stiffness_ > 0.0) {
    // -C v = -α M v - β K v, K the warped stiffness at the state.
    for (int32_t i = 0; i < num_nodes(); ++i) {
      forces->col(i) -= rayleigh_mass_ * mass_[static_cast<size_t>(i)] * state.velocities.col(i);
    }
    if (rayleigh_stiffness_ > 0.0) {
      for (int32_t e = 0; e < num_tets(); ++e) {
        if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
        const Eigen::Matrix<double, 12, 12> k = ElementTangentOf(sh, state.positions, e, false);
        for (int a = 0; a < 4; ++a) {
          Vector3d kv = Vector3d::Zero();
          for (int b = 0; b < 4; ++b) {
            kv += k.block<3, 3>(3 * a, 3 * b) * state.velocities.col(elements_.tets(b, e));
          }
          forces->col(elements_.tets(a, e)) -= rayleigh_stiffness_ * kv;
        }
      }
    }
  }
}

EnergyReport FemModel::Energy(const TissueState& state, const Eigen::Vector3d& gravity) const {
  EnergyReport report;
  report.elastic = ElasticEnergy(ShapeOf(state), state.positions, nullptr);
  AddKineticAndGravity(mass_, state, gravity, &report);
  return report;
}

Eigen::Matrix3d FemModel::LocalStiffness(const TissueState& state, int32_t node) const {
  assert(node >= 0 && node < num_nodes());
  const Shape sh = ShapeOf(state);
  Matrix3d k = Matrix3d::Zero();
  for (int32_t k_index = elements_.node_start[static_cast<size_t>(node)];
       k_index < elements_.node_start[static_cast<size_t>(node) + 1]; ++k_index) {
    const int32_t packed = elements_.element_of_node[static_cast<size_t>(k_index)];
    const int32_t e = packed / 4;
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const int a = packed % 4;
    if (kind_ == FemKind::kHyperelastic) {
      k += ElementTangentOf(sh, state.positions, e, true).block<3, 3>(3 * a, 3 * a);
      continue;
    }
    Matrix3d r = Matrix3d::Identity();
    if (kind_ == FemKind::kCorotational) {  // from the element's rotation in the last step
      const double* last = static_cast<const FemState&>(state).quaternions.data() + 4 * e;
      double q[4] = {last[0], last[1], last[2], last[3]};
      r = PolarRotationFrom(Matrix3d::Identity() + DisplacementGradientOf(sh, state.positions, e),
                            q);
    }
    k += r * RestBlock(sh, e, a, a) * r.transpose();
  }
  return k;
}

FemModel::Shape FemModel::ShapeOf(const TissueState& base) const {
  const auto& state = static_cast<const FemState&>(base);
  return {state.rest, state.gradients, state.volumes, elements_.tets};
}

Matrix3d FemModel::DisplacementGradientOf(const Shape& sh, const mesh::Points& x, int32_t e) {
  Matrix3d h = Matrix3d::Zero();
  for (int a = 0; a < 4; ++a) {
    const int32_t node = sh.tets(a, e);
    h.noalias() += (x.col(node) - sh.rest.col(node)) * sh.gradients.col(4 * e + a).transpose();
  }
  return h;
}

bool FemModel::ElementAlive(const TissueState& state, int32_t e) const {
  assert(e >= 0 && e < num_tets());
  return static_cast<const FemState&>(state).volumes[static_cast<size_t>(e)] > 0.0;
}

const mesh::Points& FemModel::RestPositions(const TissueState& state) const {
  return static_cast<const FemState&>(state).rest;
}

namespace {

// Element e's rest gradients (3 × 4, column a = ∇N_a) and volume from the rest positions:
// with D = [X1 - X0, X2 - X0, X3 - X0], ∇N_1..3 are the columns of D⁻ᵀ and ∇N_0 = -Σ; V =
// det D / 6. False (nothing written) when det D <= 0.
bool RestGeometry(const mesh::Points& rest, const mesh::Tetrahedra& tets, int32_t e,
                  Eigen::Matrix<double, 3, 4>* gradients, double* volume) {
  Matrix3d d;
  for (int c = 0; c < 3; ++c) d.col(c) = rest.col(tets(c + 1, e)) - rest.col(tets(0, e));
  const double det = d.determinant();
  if (!(det > 0.0)) return false;
  const Matrix3d inv_t = d.inverse().transpose();
  gradients->rightCols<3>() = inv_t;
  gradients->col(0) = -inv_t.rowwise().sum();
  *volume = det / 6.0;
  return true;
}

}  // namespace

void FemModel::ApplyCut(std::span<const int32_t> removed, std::span<const int32_t> moved,
                        const mesh::Points& positions_before, TissueState* base) const {
  auto* state = static_cast<FemState*>(base);
  const int32_t n = num_nodes(), m = num_tets();
  for (const int32_t e : removed) {
    if (e < 0 || e >= m) Refuse("cut: element " + std::to_string(e) + " out of range");
    if (!(state->volumes[static_cast<size_t>(e)] > 0.0)) {
      Refuse("cut: element " + std::to_string(e) + " was already cut away");
    }
  }
  for (const int32_t node : moved) {
    if (node < 0 || node >= n) Refuse("cut: node " + std::to_string(node) + " out of range");
  }
  if (positions_before.cols() != n || !positions_before.allFinite()) {
    Refuse("cut: positions before the cut must be 3 x num_nodes and finite");
  }
  for (const int32_t e : removed) {
    state->volumes[static_cast<size_t>(e)] = 0.0;
    ++state->num_cut;
  }
  // The rest moves, all from the geometry before any of them (F̄ at positions_before).
  for (const int32_t node : moved) {
    Matrix3d f_sum = Matrix3d::Zero();
    int count = 0;
    const Shape sh = ShapeOf(*state);
    for (int32_t k = elements_.node_start[static_cast<size_t>(node)];
         k < elements_.node_start[static_cast<size_t>(node) + 1]; ++k) {
      const int32_t e = elements_.element_of_node[static_cast<size_t>(k)] / 4;
      if (!(state->volumes[static_cast<size_t>(e)] > 0.0)) continue;
      f_sum += Matrix3d::Identity() + DisplacementGradientOf(sh, positions_before, e);
      ++count;
    }
    const Vector3d dx = state->positions.col(node) - positions_before.col(node);
    Vector3d dr = dx;
    if (count > 0) {
      const Matrix3d f = f_sum / count;
      const double det = f.determinant();
      if (det > 0.1 && std::isfinite(det)) dr = f.inverse() * dx;
    }
    state->rest_move.col(node) = dr.allFinite() ? dr : dx;
  }
  // Apply each node's rest move, shortened until its alive elements keep 5 % of their
  // original volume; then their gradients and volumes follow.
  for (const int32_t node : moved) {
    const Vector3d from = state->rest.col(node);
    Vector3d step = state->rest_move.col(node);
    bool accepted = false;
    for (int attempt = 0; attempt <= 8 && !accepted; ++attempt, step *= 0.5) {
      state->rest.col(node) = from + step;
      accepted = true;
      for (int32_t k = elements_.node_start[static_cast<size_t>(node)];
           accepted && k < elements_.node_start[static_cast<size_t>(node) + 1]; ++k) {
        const int32_t e = elements_.element_of_node[static_cast<size_t>(k)] / 4;
        if (!(state->volumes[static_cast<size_t>(e)] > 0.0)) continue;
        Eigen::Matrix<double, 3, 4> g;
        double v = 0.0;
        accepted = RestGeometry(state->rest, elements_.tets, e, &g, &v) &&
                   v >= 0.05 * elements_.volumes[static_cast<size_t>(e)];
      }
    }
    if (!accepted) state->rest.col(node) = from;
    for (int32_t k = elements_.node_start[static_cast<size_t>(node)];
         k < elements_.node_start[static_cast<size_t>(node) + 1]; ++k) {
      const int32_t e = elements_.element_of_node[static_cast<size_t>(k)] / 4;
      if (!(state->volumes[static_cast<size_t>(e)] > 0.0)) continue;
      Eigen::Matrix<double, 3, 4> g;
      double v = 0.0;
      if (RestGeometry(state->rest, elements_.tets, e, &g, &v)) {
        state->gradients.middleCols<4>(4 * static_cast<Eigen::Index>(e)) = g;
        state->volumes[static_cast<size_t>(e)] = v;
      }
    }
    double* good = LastGoodPositions(state);
    for (int c = 0; c < 3; ++c) good[3 * static_cast<size_t>(node) + c] = state->positions(c, node);
  }
}

double FemModel::LastSolverResidual(const TissueState& state) const {
  return static_cast<const FemState&>(state).last_cg_residual;
}

void FemModel::Advance(const StepInputs& inputs, TissueState* base) const {
  auto* state = static_cast<FemState*>(base);
  const Shape sh = ShapeOf(*state);
  const double dt = inputs.dt;
  const auto n = static_cast<size_t>(num_nodes());
  const double alpha = rayleigh_mass_, beta = rayleigh_stiffness_;
  // QLV: this step's stress is g S^e + offset (ViscousStep); elastic models skip it.
  ViscousStep viscous;
  const ViscousStep* const visc = prony_.empty() ? nullptr : &viscous;
  if (visc != nullptr) viscous = BeginViscousStep(*state, dt, state->offset.data());
  // f(x) and the rotations, then A = (1 + dt α) M + (dt² + dt β) K.
  const double k_scale = dt * dt + dt * beta;
  const double m_scale = 1.0 + dt * alpha;
  if (kind_ == FemKind::kHyperelastic) {
    ElasticForces(sh, state->positions, state->forces.data(), state->rotations.data(), visc);
    AssembleWarped(sh, state->positions, state->rotations.data(), k_scale, m_scale, &state->matrix,
                   visc);
  } else {  // one pass over the elements for both
    ForcesAndWarpedMatrix(sh, state->positions, state->forces.data(), state->rotations.data(),
                          state->quaternions.data(), visc, k_scale, m_scale, &state->matrix);
  }
  // K v = (A v - m_scale M v) / k_scale (before the grasps join A: they have no damping).
  double* const kv = state->temp.data();
  const double* const v = state->velocities.data();
  state->matrix.Multiply(v, kv, nullptr);
  for (size_t i = 0; i < n; ++i) {
    for (size_t c = 0; c < 3; ++c) {
      kv[3 * i + c] = (kv[3 * i + c] - m_scale * mass_[i] * v[3 * i + c]) / k_scale;
    }
  }
  // b = dt (f(x) + f_ext + M g - α M v - (β + dt) K v).
  double* const b = state->rhs.data();
  const double* const f = state->forces.data();
  const double* const external =
      inputs.external_forces != nullptr ? inputs.external_forces->data() : nullptr;
  for (size_t i = 0; i < n; ++i) {
    for (size_t c = 0; c < 3; ++c) {
      const size_t k = 3 * i + c;
      const double ext = external != nullptr ? external[k] : 0.0;
      b[k] = dt * (f[k] + ext +
                   mass_[i] * (inputs.gravity[static_cast<Eigen::Index>(c)] - alpha * v[k]) -
                   (beta + dt) * kv[k]);
    }
  }
  // Grasps: f = k (target - x), stiffness k I (implicit in x: dt² k on A, -dt² k v in b).
  for (const Attachment& grasp : inputs.attachments) {
    const auto i = static_cast<size_t>(grasp.node);
    state->matrix.block(state->matrix.diagonal_block(grasp.node)).diagonal().array() +=
        dt * dt * grasp.stiffness;
    for (size_t c = 0; c < 3; ++c) {
      const auto ci = static_cast<Eigen::Index>(c);
      b[3 * i + c] += dt * grasp.stiffness *
                      (grasp.target[ci] - state->positions(ci, grasp.node) - dt * v[3 * i + c]);
    }
  }
  // Dirichlet nodes: Δv known (fixed: -v; prescribed: reach the target in dt); their columns
  // move to the right-hand side.
  std::fill(state->constrained.begin(), state->constrained.end(), uint8_t{0});
  double* const known = state->temp.data();  // K v is no longer needed
  std::fill(known, known + 3 * n, 0.0);
  for (const int32_t node : inputs.fixed_nodes) {
    const auto i = static_cast<size_t>(node);
    state->constrained[i] = 1;
    for (size_t c = 0; c < 3; ++c) known[3 * i + c] = -v[3 * i + c];
  }
  for (size_t k = 0; k < inputs.prescribed_nodes.size(); ++k) {
    const auto i = static_cast<size_t>(inputs.prescribed_nodes[k]);
    state->constrained[i] = 1;
    for (size_t c = 0; c < 3; ++c) {
      const auto ci = static_cast<Eigen::Index>(c);
      known[3 * i + c] = (inputs.prescribed_positions->coeff(ci, static_cast<Eigen::Index>(k)) -
                          state->positions(ci, static_cast<Eigen::Index>(i))) /
                             dt -
                         v[3 * i + c];
    }
  }
  // Held nodes at rest (a fixed node after its first step, a prescribed one whose target stays)
  // know Δv = 0 and move nothing: no product then.
  const bool any_known = std::any_of(known, known + 3 * n, [](double k) { return k != 0.0; });
  if (any_known) {
    double* const moved = state->cg.product.data();  // free before the solve
    state->matrix.Multiply(known, moved, nullptr);
    for (size_t i = 0; i < n; ++i) {
      for (size_t c = 0; c < 3; ++c) {
        b[3 * i + c] =
            state->constrained[i] != 0 ? known[3 * i + c] : b[3 * i + c] - moved[3 * i + c];
      }
    }
  } else {
    for (size_t i = 0; i < n; ++i) {
      if (state->constrained[i] != 0) std::fill(b + 3 * i, b + 3 * i + 3, 0.0);
    }
  }
  const CgResult cg =
      ConjugateGradients(state->matrix, state->constrained.data(), b, state->dv.data(),
                         cg_tolerance_, cg_max_iterations_, &state->cg, cg_fixed_iterations_);
  state->counters.solver_iterations += cg.iterations;
  if (!cg.converged) ++state->counters.solver_unconverged;
  state->last_cg_residual = cg.relative_residual;
  state->velocities += state->dv;
  state->positions += dt * state->velocities;
  ApplyFixedAndPrescribed(inputs, state);
  if (visc != nullptr) EndViscousStep(dt, state);  // a rejected step restores h (RestoreGood)
}

struct StaticWorkspace::Impl {
  const FemModel* owner = nullptr;  // the model the pattern below belongs to
  std::vector<int32_t> dof;         // 3 × num_nodes: free DOF number, or -1 where held
  std::vector<int32_t> lower_dof;   // the numbering k_free (and the analysis) is for
  BlockSparseMatrix tangent;        // the model's pattern
  LowerCsc k_free;                  // the tangent on the free DOFs, scalar lower triangle
  std::vector<int32_t> k_source;    // k_free.values[k] = tangent value k_source[k]
  SparseCholesky cholesky;
  bool analysed = false;       // cholesky holds the analysis of k_free's pattern
  bool factorised = false;     // and a factor of a tangent on these free DOFs
  std::vector<double> offset;  // a QLV step's offset stress, 9 × num_tets
  // The last converged call's result and its change from where it started (time-history mode,
  // StaticLoads::reuse_factorisation), 3 × num_nodes.
  bool has_history = false;
  mesh::Points last_solution, last_change;
};

StaticWorkspace::StaticWorkspace() : impl_(std::make_unique<Impl>()) {}
StaticWorkspace::~StaticWorkspace() = default;

StaticResult FemModel::SolveStatic(const StaticLoads& loads, TissueState* state,
                                   StaticWorkspace* workspace) const {
  return SolveStaticImpl(loads, state, nullptr, workspace, false);
}

StaticResult FemModel::NewtonIteration(const StaticLoads& loads, TissueState* state,
                                       StaticWorkspace* workspace) const {
  return SolveStaticImpl(loads, state, nullptr, workspace, true);
}

StaticResult FemModel::SolveQuasiStatic(const StaticLoads& loads, double dt, TissueState* state,
                                        StaticWorkspace* workspace) const {
  if (!(dt > 0.0) || !std::isfinite(dt)) Refuse("quasi-static dt [s] must be > 0");
  if (prony_.empty()) return SolveStaticImpl(loads, state, nullptr, workspace, false);
  StaticWorkspace local;
  if (workspace == nullptr) workspace = &local;
  std::vector<double>& offset = workspace->impl_->offset;
  offset.resize(9 * static_cast<size_t>(num_tets()));
  const ViscousStep viscous = BeginViscousStep(*state, dt, offset.data());
  StaticResult result = SolveStaticImpl(loads, state, &viscous, workspace, false);
  if (result.converged) {
    EndViscousStep(dt, state);
    state->time += dt;
  }
  return result;
}

void FemModel::AssembleTangent(const mesh::Points& x, BlockSparseMatrix* matrix) const {
  if (matrix->num_blocks() != pattern_.num_blocks()) *matrix = pattern_;
  AssembleExact(ModelShape(), x, matrix, nullptr);
}

void FemModel::AssembleExact(const Shape& sh, const mesh::Points& x, BlockSparseMatrix* matrix,
                             const ViscousStep* viscous) const {
  matrix->SetZero();
  for (int32_t e = 0; e < num_tets(); ++e) {
    if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
    const Eigen::Matrix<double, 12, 12> ke = ElementTangentOf(sh, x, e, true, viscous);
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        matrix->block(matrix->element_block(e, a, b)) += ke.block<3, 3>(3 * a, 3 * b);
      }
    }
  }
}

StaticResult FemModel::SolveStaticImpl(const StaticLoads& loads, TissueState* state,
                                       const ViscousStep* viscous, StaticWorkspace* workspace,
                                       bool single_iteration) const {
  const Shape sh = ShapeOf(*state);
  const auto n = static_cast<size_t>(num_nodes());
  StaticWorkspace local;
  if (workspace == nullptr) workspace = &local;
  StaticWorkspace::Impl& ws = *workspace->impl_;
  if (ws.owner != this) {  // a fresh workspace, or one another model used: start over
    ws.owner = this;
    ws.tangent = pattern_;
    ws.lower_dof.clear();
    ws.analysed = false;
    ws.factorised = false;
    ws.has_history = false;
  }
  if (loads.external_forces != nullptr &&
      (loads.external_forces->cols() != num_nodes() || !loads.external_forces->allFinite())) {
    Refuse("static external forces must be 3 x num_nodes and finite");
  }
  if (!loads.gravity.allFinite()) Refuse("static gravity must be finite");
  if (!(loads.load_steps > 0) || !(loads.tolerance > 0.0) || !(loads.step_tolerance >= 0.0) ||
      !(loads.max_newton_iterations > 0)) {
    Refuse("load_steps, tolerance, step_tolerance and max_newton_iterations must be > 0");
  }
  if (loads.reuse_factorisation && !(loads.reuse_ratio > 0.0 && loads.reuse_ratio < 1.0)) {
    Refuse("reuse_ratio must lie in (0, 1)");
  }
  std::vector<int32_t>& dof = ws.dof;
  dof.assign(3 * n, 0);
  for (const int32_t node : loads.fixed_nodes) {
    if (node < 0 || node >= num_nodes())
      Refuse("fixed node " + std::to_string(node) + " out of range");
    for (size_t c = 0; c < 3; ++c) dof[3 * static_cast<size_t>(node) + c] = -1;
  }
  if (!loads.prescribed_nodes.empty() &&
      (loads.prescribed_positions == nullptr ||
       loads.prescribed_positions->cols() !=
           static_cast<Eigen::Index>(loads.prescribed_nodes.size()) ||
       !loads.prescribed_positions->allFinite())) {
    Refuse("prescribed positions must be 3 x prescribed_nodes and finite");
  }
  for (const int32_t node : loads.prescribed_nodes) {
    if (node < 0 || node >= num_nodes()) {
      Refuse("prescribed node " + std::to_string(node) + " out of range");
    }
    for (size_t c = 0; c < 3; ++c) dof[3 * static_cast<size_t>(node) + c] = -1;
  }
  for (const ComponentConstraint& c : loads.components) {
    if (c.node < 0 || c.node >= num_nodes() || c.axis < 0 || c.axis > 2 ||
        !std::isfinite(c.value)) {
      Refuse("component constraint on node " + std::to_string(c.node) + " axis " +
             std::to_string(c.axis) + " is out of range or not finite");
    }
    dof[3 * static_cast<size_t>(c.node) + static_cast<size_t>(c.axis)] = -1;
  }
  int32_t num_dofs = 0;
  for (int32_t& d : dof) {
    if (d == 0) d = num_dofs++;
  }
  if (dof != ws.lower_dof) {  // new held DOFs: a new reduced pattern and a new analysis
    ws.k_free = ws.tangent.ScalarLowerPattern(dof, num_dofs, &ws.k_source);
    ws.lower_dof = dof;
    ws.analysed = false;
    ws.factorised = false;
  }
  BlockSparseMatrix& tangent = ws.tangent;
  SparseCholesky& cholesky = ws.cholesky;
  // Total load at full scale: external forces and gravity.
  mesh::Points load = mesh::Points::Zero(3, num_nodes());
  if (loads.external_forces != nullptr) load = *loads.external_forces;
  for (size_t i = 0; i < n; ++i) {
    load.col(static_cast<Eigen::Index>(i)) += mass_[i] * loads.gravity;
  }
  const mesh::Points start = state->positions;
  StaticResult result;
  mesh::Points forces(3, num_nodes());
  // Free-DOF norm of r = f(x) + scale · load.
  const auto residual = [&](double scale, Eigen::VectorXd* r) {
    ElasticForces(sh, state->positions, forces.data(), nullptr, viscous);
    r->setZero(num_dofs);
    double load_norm2 = 0.0;
    for (size_t k = 0; k < 3 * n; ++k) {
      if (dof[k] < 0) continue;
      const double l = scale * load.data()[k];
      (*r)[dof[k]] = forces.data()[k] + l;
      load_norm2 += l * l;
    }
    return std::sqrt(load_norm2);
  };
  const auto potential = [&](double scale) {
    double value = ElasticEnergy(sh, state->positions, viscous);
    for (Eigen::Index k = 0; k < load.size(); ++k) {
      value -= scale * load.data()[k] * (state->positions.data()[k] - sh.rest.data()[k]);
    }
    return value;
  };
  // Factorises the tangent at the state's positions: the exact one when it is positive definite
  // on the free DOFs, else the rotated one (corotational), else the rest stiffness (always
  // positive definite: a quasi-Newton step). The linear model's K is constant: factorised once.
  bool linear_factorised = false;
  const auto factorise_tangent = [&]() {
    if (kind_ == FemKind::kLinear && linear_factorised) return true;
    for (int attempt = 0; attempt < 3; ++attempt) {
      if (attempt == 1 && kind_ != FemKind::kCorotational) continue;
      if (attempt == 1) {  // the rotated (warped) tangent, positive semi-definite
        tangent.SetZero();
        for (int32_t e = 0; e < num_tets(); ++e) {
          if (sh.volumes[static_cast<size_t>(e)] == 0.0) continue;  // cut away
          const Eigen::Matrix<double, 12, 12> ke =
              ElementTangentOf(sh, state->positions, e, false, viscous);
          for (int a = 0; a < 4; ++a) {
            for (int b = 0; b < 4; ++b) {
              tangent.block(tangent.element_block(e, a, b)) += ke.block<3, 3>(3 * a, 3 * b);
            }
          }
        }
      } else {
        AssembleExact(sh, attempt == 2 ? sh.rest : state->positions, &tangent, viscous);
      }
      tangent.FillScalarLower(ws.k_source, &ws.k_free);
      if (!ws.analysed) {
        cholesky.Analyse(ws.k_free);
        ws.analysed = true;
      }
      ++result.factorisations;
      if (cholesky.Factorise(ws.k_free)) {
        linear_factorised = true;
        ws.factorised = true;
        return true;
      }
    }
    ws.factorised = false;
    return false;
  };
  // A single iteration (NewtonIteration) is at full load, with the held DOFs put in place.
  const int load_steps = single_iteration ? 1 : loads.load_steps;
  for (int step = 1; step <= load_steps; ++step) {
    const double scale = static_cast<double>(step) / load_steps;
    // This step's Dirichlet values (they move in increments too), as an increment d.
    mesh::Points target = state->positions;
    for (const int32_t node : loads.fixed_nodes) target.col(node) = sh.rest.col(node);
    for (size_t k = 0; k < loads.prescribed_nodes.size(); ++k) {
      const int32_t node = loads.prescribed_nodes[k];
      const Eigen::Index kk = static_cast<Eigen::Index>(k);
      target.col(node) =
          start.col(node) + scale * (loads.prescribed_positions->col(kk) - start.col(node));
    }
    for (const ComponentConstraint& c : loads.components) {
      const double from = start(c.axis, c.node);
      target(c.axis, c.node) = from + scale * (c.value - from);
    }
    const mesh::Points increment = target - state->positions;  // zero on free DOFs
    // Predictor: the free DOFs follow the held ones through the tangent at the last equilibrium,
    // K_ff Δu_f = r_f - K_fc d_c (moving only the held nodes would crush the elements next to
    // them, and a hyperelastic tangent there may not be positive definite).
    Eigen::VectorXd r;
    if (!single_iteration && num_dofs > 0 && increment.cwiseAbs().maxCoeff() > 0.0 &&
        factorise_tangent()) {
      residual(scale, &r);
      mesh::Points moved(3, num_nodes());
      tangent.Multiply(increment.data(), moved.data(), nullptr);
      for (size_t k = 0; k < 3 * n; ++k) {
        if (dof[k] >= 0) r[dof[k]] -= moved.data()[k];
      }
      Eigen::VectorXd du(num_dofs);
      cholesky.Solve(r.data(), du.data());
      const mesh::Points before = state->positions;
      state->positions = target;
      for (size_t k = 0; k < 3 * n; ++k) {
        if (dof[k] >= 0) state->positions.data()[k] += du[dof[k]];
      }
      if (!std::isfinite(residual(scale, &r)) || !r.allFinite()) {  // overshot: no predictor
        state->positions = before + increment;
      }
    } else {
      state->positions = target;
    }
    // Time-history mode: a state that is the one the last call left starts from its positions
    // extrapolated along that call's change (the next step of a creep or relaxation is close to
    // it), cutting the first residual and so the iterations; not where that is not finite.
    if (loads.reuse_factorisation && loads.load_steps == 1 && !single_iteration && ws.has_history &&
        ws.last_solution.cols() == num_nodes() && state->positions == ws.last_solution) {
      const mesh::Points here = state->positions;
      for (size_t k = 0; k < 3 * n; ++k) {
        if (dof[k] >= 0) state->positions.data()[k] += ws.last_change.data()[k];
      }
      if (!std::isfinite(residual(scale, &r)) || !r.allFinite() ||
          !std::isfinite(potential(scale))) {
        state->positions = here;
      }
    }
    result.residual_history.clear();
    const double load_norm = residual(scale, &r);
    // A scale for "zero" when nothing is loaded (pure Dirichlet): the forces at the start.
    double reference = load_norm;
    if (!(reference > 0.0)) {
      reference = 0.0;
      for (Eigen::Index k = 0; k < forces.size(); ++k) {
        reference += forces.data()[k] * forces.data()[k];
      }
      reference = std::max(std::sqrt(reference), 1e-300);
    }
    double r_norm = r.norm();
    bool small_step = false;
    const int max_iterations = single_iteration ? 1 : loads.max_newton_iterations;
    bool refactorise = false;
    for (int it = 0; num_dofs > 0 && it < max_iterations &&
                     (single_iteration || r_norm > loads.tolerance * reference) && !small_step;
         ++it) {
      const bool reuse = loads.reuse_factorisation && ws.factorised && !refactorise;
      if (!reuse && !factorise_tangent()) break;
      Eigen::VectorXd du(num_dofs);
      cholesky.Solve(r.data(), du.data());
      // Backtracking on the potential (Armijo), accepting a full step that lowers the residual
      // (tested first: the potential is evaluated only when needed).
      double pi0 = 0.0;
      bool have_pi0 = false;
      const double slope = -r.dot(du);  // dΠ/dt along du at t = 0 (r = -∇Π)
      const mesh::Points before = state->positions;
      double t = 1.0;
      Eigen::VectorXd r_new;
      double r_new_norm = 0.0;
      for (int ls = 0; ls < 20; ++ls) {
        state->positions = before;
        for (size_t k = 0; k < 3 * n; ++k) {
          if (dof[k] >= 0) state->positions.data()[k] += t * du[dof[k]];
        }
        residual(scale, &r_new);
        r_new_norm = r_new.norm();
        if (r_new_norm < r_norm) break;
        if (!have_pi0) {
          const mesh::Points trial = state->positions;
          state->positions = before;
          pi0 = potential(scale);
          have_pi0 = true;
          state->positions = trial;
        }
        if (potential(scale) <= pi0 + 1e-4 * t * slope) break;
        t *= 0.5;
      }
      // A step of the old factor that no longer shrinks the residual enough: refactorise.
      refactorise = r_new_norm > loads.reuse_ratio * r_norm;
      r = r_new;
      r_norm = r_new_norm;
      double u_norm2 = 0.0;
      for (size_t k = 0; k < 3 * n; ++k) {
        const double u = state->positions.data()[k] - sh.rest.data()[k];
        u_norm2 += u * u;
      }
      small_step = t * du.norm() <= loads.step_tolerance * std::sqrt(u_norm2);
      ++result.newton_iterations;
      result.residual_history.push_back(r_norm / reference);
    }
    result.final_residual = r_norm / reference;
    result.converged = r_norm <= loads.tolerance * reference || small_step || num_dofs == 0;
    if (!result.converged) break;
  }
  if (single_iteration) {
    result.converged = result.final_residual <= loads.tolerance;
    state->velocities.setZero();
    return result;
  }
  ws.has_history = result.converged;
  if (result.converged) {
    ws.last_change = state->positions - start;
    ws.last_solution = state->positions;
  }
  // Reactions: what the supports must supply, -(f(x) + load) on the held DOFs. `forces` is f at
  // the final positions already: every path above ends on a residual evaluation there.
  result.reactions = mesh::Points::Zero(3, num_nodes());
  for (size_t k = 0; k < 3 * n; ++k) {
    if (dof[k] < 0) result.reactions.data()[k] = -(forces.data()[k] + load.data()[k]);
  }
  state->velocities.setZero();
  return result;
}

}  // namespace somasim::models::fem
