#include "server/contact/tissue_compliance.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <numeric>
#include <stdexcept>
#include <string>

#include "server/models/fem/block_sparse.h"
#include "server/models/fem/fem_model.h"
#include "server/models/fem/sparse_cholesky.h"
#include "server/models/fem/tet_elements.h"

namespace somasim::contact {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using models::fem::FemKind;
using models::fem::FemModel;

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("FemCompliance: " + what);
}

// LocalCompliance's pseudo-inverse: a direction whose stiffness is below kMinStiffness [N/m] or
// below kRelativeMinStiffness of the node's largest (rounding), or negative (an unstable,
// compressed spring's geometric term), counts as free and gets the compliance 1/kMinStiffness
// [m/N]: practically no force along it, yet finite. Real soft directions are much stiffer: a
// membrane's bending stiffness at a node is ~0.1-5 N/m on a 5 kPa spleen.
constexpr double kMinStiffness = 1e-3;
constexpr double kRelativeMinStiffness = 1e-9;

// Union-find root with path halving.
int32_t Root(std::vector<int32_t>* parent, int32_t i) {
  while ((*parent)[static_cast<size_t>(i)] != i) {
    (*parent)[static_cast<size_t>(i)] =
        (*parent)[static_cast<size_t>((*parent)[static_cast<size_t>(i)])];
    i = (*parent)[static_cast<size_t>(i)];
  }
  return i;
}

// Throws unless every connected part of the mesh (tetrahedra sharing a node) holds at least
// three non-collinear nodes: anything less leaves a rigid motion of that part free (a
// translation, or a rotation about the held line), and K singular. A factorisation would not
// reliably say so: rounding can leave a tiny positive pivot on a singular matrix.
void CheckHeldSetFixesRigidMotions(const FemModel& model, const std::vector<uint8_t>& held) {
  const int32_t n = model.num_nodes();
  const mesh::Tetrahedra& tets = model.elements().tets;
  const mesh::Points& rest = model.rest_positions();
  std::vector<int32_t> parent(static_cast<size_t>(n));
  std::iota(parent.begin(), parent.end(), 0);
  for (Eigen::Index e = 0; e < tets.cols(); ++e) {
    for (int a = 1; a < 4; ++a) {
      const int32_t r0 = Root(&parent, tets(0, e));
      const int32_t r1 = Root(&parent, tets(a, e));
      parent[static_cast<size_t>(r1)] = r0;
    }
  }
  // Per part: its size (bounding-box diagonal) for a relative tolerance, a first held node p0,
  // the held node p1 farthest from it, and the largest distance of a held node from line p0 p1.
  std::vector<int32_t> first(static_cast<size_t>(n), -1), farthest(static_cast<size_t>(n), -1);
  std::vector<Vector3d> low(static_cast<size_t>(n), Vector3d::Constant(HUGE_VAL));
  std::vector<Vector3d> high(static_cast<size_t>(n), Vector3d::Constant(-HUGE_VAL));
  for (int32_t i = 0; i < n; ++i) {
    const auto r = static_cast<size_t>(Root(&parent, i));
    low[r] = low[r].cwiseMin(rest.col(i));
    high[r] = high[r].cwiseMax(rest.col(i));
    if (held[static_cast<size_t>(i)] == 0) continue;
    if (first[r] < 0) first[r] = i;
    const Vector3d p0 = rest.col(first[r]);
    if (farthest[r] < 0 || (rest.col(i) - p0).norm() > (rest.col(farthest[r]) - p0).norm()) {
      farthest[r] = i;
    }
  }
  std::vector<double> off_line(static_cast<size_t>(n), 0.0);
  for (int32_t i = 0; i < n; ++i) {
    if (held[static_cast<size_t>(i)] == 0) continue;
    const auto r = static_cast<size_t>(Root(&parent, i));
    const Vector3d p0 = rest.col(first[r]);
    const Vector3d axis = rest.col(farthest[r]) - p0;
    if (axis.norm() == 0.0) continue;
    off_line[r] = std::max(off_line[r], axis.normalized().cross(rest.col(i) - p0).norm());
  }
  for (int32_t i = 0; i < n; ++i) {
    const auto r = static_cast<size_t>(Root(&parent, i));
    if (r != static_cast<size_t>(i)) continue;
    const double size = (high[r] - low[r]).norm();
    if (first[r] < 0) {
      Refuse("the part of the mesh with node " + std::to_string(i) +
             " holds no node: a rigid motion of it is free");
    }
    const double span = (rest.col(farthest[r]) - rest.col(first[r])).norm();
    if (!(span > 1e-9 * size) || !(off_line[r] > 1e-9 * size)) {
      Refuse("the held nodes of the part with node " + std::to_string(i) +
             " are one point or on one line: a rigid rotation of it is free");
    }
  }
}

}  // namespace

struct FemCompliance::Impl {
  const FemModel* model = nullptr;
  std::vector<int32_t> dof;  // 3 × num_nodes: free DOF number, or -1 where held
  int32_t num_dofs = 0;
  models::fem::SparseCholesky cholesky;   // of K0 on the free DOFs
  std::vector<Matrix3d> rest_compliance;  // C0 per node [m/N] (valid where cached)
  std::vector<uint8_t> cached;            // num_nodes
  bool held(int32_t node) const { return dof[3 * static_cast<size_t>(node)] < 0; }

  void CheckNode(int32_t node) const {
    if (node < 0 || node >= model->num_nodes()) {
      Refuse("node " + std::to_string(node) + " out of range");
    }
  }

  // C0 = [K0⁻¹]_ii, node i's 3 × 3 diagonal block of the inverse, by CHOLMOD's factor: a sparse
  // forward substitution along the elimination tree above the node's rows (InverseBlocks,
  // which groups neighbouring nodes so the dense top of the tree is streamed once per group).
  void Compute(std::span<const int32_t> nodes) {
    for (const int32_t node : nodes) CheckNode(node);
    std::vector<int32_t> todo;
    for (const int32_t node : nodes) {
      const auto i = static_cast<size_t>(node);
      if (cached[i] != 0) continue;
      if (held(node)) {
        rest_compliance[i].setZero();
        cached[i] = 1;
      } else {
        todo.push_back(node);
      }
    }
    std::sort(todo.begin(), todo.end());
    todo.erase(std::unique(todo.begin(), todo.end()), todo.end());
    if (todo.empty()) return;
    std::vector<int32_t> dofs(3 * todo.size());
    std::vector<double> blocks(9 * todo.size());
    for (size_t k = 0; k < todo.size(); ++k) {
      for (size_t c = 0; c < 3; ++c) dofs[3 * k + c] = dof[3 * static_cast<size_t>(todo[k]) + c];
    }
    cholesky.InverseBlocks(dofs.data(), 3, static_cast<int32_t>(todo.size()), blocks.data());
    for (size_t k = 0; k < todo.size(); ++k) {
      const auto i = static_cast<size_t>(todo[k]);
      rest_compliance[i] = Eigen::Map<const Matrix3d>(blocks.data() + 9 * k);
      cached[i] = 1;
    }
  }

  const Matrix3d& Rest(int32_t node) {
    CheckNode(node);
    if (cached[static_cast<size_t>(node)] == 0) {
      const int32_t one[1] = {node};
      Compute(one);
    }
    return rest_compliance[static_cast<size_t>(node)];
  }
};

FemCompliance::FemCompliance(const models::fem::FemModel& model,
                             std::span<const int32_t> fixed_nodes)
    : impl_(std::make_unique<Impl>()) {
  Impl& s = *impl_;
  s.model = &model;
  const int32_t n = model.num_nodes();
  if (!model.rest_positions().allFinite()) Refuse("the model's rest positions are not finite");
  if (fixed_nodes.empty()) Refuse("nothing held: the organ can move rigidly");
  std::vector<uint8_t> held(static_cast<size_t>(n), 0);
  for (const int32_t node : fixed_nodes) {
    if (node < 0 || node >= n) Refuse("fixed node " + std::to_string(node) + " out of range");
    held[static_cast<size_t>(node)] = 1;
  }
  CheckHeldSetFixesRigidMotions(model, held);
  s.dof.assign(3 * static_cast<size_t>(n), -1);
  for (int32_t i = 0; i < n; ++i) {
    if (held[static_cast<size_t>(i)] != 0) continue;
    for (size_t c = 0; c < 3; ++c) s.dof[3 * static_cast<size_t>(i) + c] = s.num_dofs++;
  }
  s.rest_compliance.assign(static_cast<size_t>(n), Matrix3d::Zero());
  s.cached.assign(static_cast<size_t>(n), 0);
  if (s.num_dofs == 0) return;  // everything held: C = 0 everywhere
  // K0: the exact tangent at rest, the same for every kind (at zero stress the corotational
  // dR terms vanish and the hyperelastic tangent is the small-strain Hooke stiffness with μ0,
  // κ0). With QLV (Prony terms) it is the instantaneous stiffness, G(0) = 1: what a hand feels.
  models::fem::BlockSparseMatrix k0;
  model.AssembleTangent(model.rest_positions(), &k0);
  const models::fem::LowerCsc lower = k0.ScalarLower(s.dof, s.num_dofs);
  s.cholesky.Analyse(lower);
  if (!s.cholesky.Factorise(lower)) {
    Refuse("the rest stiffness with the held nodes removed is not positive definite");
  }
  // A singular K can factorise with a pivot at rounding level (e.g. parts joined at one node).
  if (!(s.cholesky.ReciprocalConditionEstimate() > 1e-14)) {
    Refuse(
        "the rest stiffness with the held nodes removed is singular to rounding: a motion "
        "without strain is free");
  }
}

FemCompliance::~FemCompliance() = default;

void FemCompliance::Precompute(std::span<const int32_t> nodes) { impl_->Compute(nodes); }

Eigen::Matrix3d FemCompliance::RestAtNode(int32_t node) { return impl_->Rest(node); }

const models::fem::FemModel& FemCompliance::model() const { return *impl_->model; }

Eigen::Matrix3d FemCompliance::AtNode(const models::TissueState& state, int32_t node) {
  Impl& s = *impl_;
  const FemModel& model = *s.model;
  s.CheckNode(node);
  if (state.positions.cols() != model.num_nodes()) {
    Refuse("the state's positions are not 3 x num_nodes");
  }
  const Matrix3d& c0 = s.Rest(node);
  if (model.kind() == FemKind::kLinear || s.held(node)) return c0;
  // R: the polar rotation of the node's elements' volume-weighted mean deformation gradient
  // (from displacements, H = F - I, so a small strain keeps its digits).
  const models::fem::TetElements& elements = model.elements();
  Matrix3d h = Matrix3d::Zero();
  double volume = 0.0;
  for (int32_t k = elements.node_start[static_cast<size_t>(node)];
       k < elements.node_start[static_cast<size_t>(node) + 1]; ++k) {
    const int32_t e = elements.element_of_node[static_cast<size_t>(k)] / 4;
    const double v = elements.volumes[static_cast<size_t>(e)];
    h += v * elements.DisplacementGradient(state.positions, model.rest_positions(), e);
    volume += v;
  }
  if (!(volume > 0.0)) return c0;  // a node of no element: nothing rotates it
  const Matrix3d f = Matrix3d::Identity() + h / volume;
  if (!f.allFinite()) {
    Refuse("the state's positions around node " + std::to_string(node) + " are not finite");
  }
  const Matrix3d r = models::fem::PolarRotation(f);
  return r * c0 * r.transpose();
}

Eigen::Matrix3d LocalCompliance(const models::TissueModel& model, const models::TissueState& state,
                                int32_t node, FemCompliance* fem) {
  if (node < 0 || node >= model.num_nodes()) {
    throw std::invalid_argument("LocalCompliance: node " + std::to_string(node) + " out of range");
  }
  if (state.positions.cols() != model.num_nodes()) {
    throw std::invalid_argument("LocalCompliance: the state's positions are not 3 x num_nodes");
  }
  if (fem != nullptr) {
    if (&fem->model() != &model) {
      throw std::invalid_argument("LocalCompliance: the FemCompliance belongs to another model");
    }
    return fem->AtNode(state, node);
  }
  // The model's own stiffness at the node, inverted in its eigenbasis; free directions (see
  // kMinStiffness) get the cap 1000 m/N, so C stays symmetric positive definite and finite.
  const Matrix3d k = model.LocalStiffness(state, node);
  if (!k.allFinite()) {
    throw std::invalid_argument("LocalCompliance: the stiffness at node " + std::to_string(node) +
                                " is not finite");
  }
  const Eigen::SelfAdjointEigenSolver<Matrix3d> eigen(0.5 * (k + k.transpose()));
  const Vector3d& values = eigen.eigenvalues();  // ascending
  const double floor = std::max(kMinStiffness, kRelativeMinStiffness * values[2]);
  Vector3d c;
  for (int i = 0; i < 3; ++i) c[i] = values[i] >= floor ? 1.0 / values[i] : 1.0 / kMinStiffness;
  return eigen.eigenvectors() * c.asDiagonal() * eigen.eigenvectors().transpose();
}

}  // namespace somasim::contact
