// The stiffness followed through a cut (server/cutting/stiffness_update.h): an element's
// small-strain stiffness is symmetric with exactly the six rigid modes in its null space; after
// a real cut of the seed's plate (the cutter's removals and relocations, in the rest shape),
// seed 003's Sherman–Morrison–Woodbury update of the dense inverse and the CHOLMOD factor
// updated and downdated in place both solve K u = f as a from-scratch factorisation of the cut
// mesh does, to 1e-8 relative; a downdate that would leave a node in no element is reported,
// not silently wrong; updates after the first allocate nothing.
#include "server/cutting/stiffness_update.h"

#include <gtest/gtest.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <random>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh_gen/builtin_organs.h"
#include "server/cutting/tet_cutter.h"
#include "tests/support/allocation_counter.h"

namespace somasim::cutting {
namespace {

using Eigen::Vector3d;

TEST(LinearTetStiffness, IsSymmetricWithTheSixRigidModesAsItsNullSpace) {
  Eigen::Matrix<double, 3, 4> x;
  x << 0.0, 0.01, 0.002, 0.001,  //
      0.0, 0.001, 0.012, 0.003,  //
      0.0, 0.0, 0.001, 0.009;
  const Matrix12d k = LinearTetStiffness(x, 2e4, 1e4);
  EXPECT_LT((k - k.transpose()).norm(), 1e-12 * k.norm());
  const Eigen::SelfAdjointEigenSolver<Matrix12d> eig(k);
  const double largest = eig.eigenvalues().maxCoeff();
  int zero = 0;
  for (int i = 0; i < 12; ++i) {
    EXPECT_GT(eig.eigenvalues()[i], -1e-10 * largest);
    zero += eig.eigenvalues()[i] < 1e-10 * largest ? 1 : 0;
  }
  EXPECT_EQ(zero, 6);
  // A translation and a small rotation about z produce no force.
  Eigen::Matrix<double, 12, 1> t, r;
  for (int a = 0; a < 4; ++a) {
    t.segment<3>(3 * a) = Vector3d(1, 2, 3);
    r.segment<3>(3 * a) = Vector3d::UnitZ().cross(Vector3d(x.col(a)));
  }
  EXPECT_LT((k * t).norm(), 1e-10 * k.norm() * t.norm());
  EXPECT_LT((k * r).norm(), 1e-10 * k.norm() * r.norm());
  // Flat: zero.
  Eigen::Matrix<double, 3, 4> flat = x;
  flat.col(3) = 0.5 * (x.col(1) + x.col(2));
  EXPECT_EQ(LinearTetStiffness(flat, 2e4, 1e4).norm(), 0.0);
}

struct CutPlate {
  mesh::TetMesh rest;
  std::vector<uint8_t> fixed;
  mesh::Points cut_rest;  // after the cut
  std::vector<int32_t> removed;
  std::vector<int32_t> moved;
};

// The plate held along its low-x edge, cut from the high-x edge a third of the way in.
CutPlate MakeCut() {
  CutPlate p;
  p.rest = mesh_gen::GenerateBuiltinOrganVolume("plate192");
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(p.rest.vertices);
  p.fixed.assign(static_cast<size_t>(p.rest.vertices.cols()), 0);
  for (Eigen::Index v = 0; v < p.rest.vertices.cols(); ++v) {
    p.fixed[static_cast<size_t>(v)] = p.rest.vertices(0, v) < box.min.x() + 0.01 ? 1 : 0;
  }
  p.cut_rest = p.rest.vertices;
  TetCutter cutter(p.rest.tetrahedra, p.cut_rest);
  const double y = 0.5 * (box.min.y() + box.max.y()) + 0.0017;
  std::vector<uint8_t> moved(static_cast<size_t>(p.rest.vertices.cols()), 0);
  for (double a = box.max.x() + 0.005; a > box.max.x() - 0.07; a -= 0.004) {
    const double below = box.min.z() - 0.002, above = box.max.z() + 0.002;
    cutter.Step({Vector3d(a, y, below), Vector3d(a, y, above), Vector3d(a - 0.004, y, below),
                 Vector3d(a - 0.004, y, above)},
                &p.cut_rest);
    for (const int32_t t : cutter.removed_tets()) p.removed.push_back(t);
    for (const int32_t v : cutter.moved_nodes()) moved[static_cast<size_t>(v)] = 1;
  }
  for (size_t v = 0; v < moved.size(); ++v) {
    if (moved[v] != 0) p.moved.push_back(static_cast<int32_t>(v));
  }
  return p;
}

// The elements with a corner among `nodes` (ascending, each once).
std::vector<int32_t> ElementsTouching(const mesh::Tetrahedra& tets,
                                      const std::vector<int32_t>& nodes) {
  std::vector<uint8_t> mark(static_cast<size_t>(tets.maxCoeff()) + 1, 0);
  for (const int32_t v : nodes) mark[static_cast<size_t>(v)] = 1;
  std::vector<int32_t> out;
  for (Eigen::Index e = 0; e < tets.cols(); ++e) {
    bool touches = false;
    for (int a = 0; a < 4; ++a) touches = touches || mark[static_cast<size_t>(tets(a, e))] != 0;
    if (touches) out.push_back(static_cast<int32_t>(e));
  }
  return out;
}

double RelativeError(const Eigen::VectorXd& a, const Eigen::VectorXd& b) {
  return (a - b).norm() / b.norm();
}

TEST(CutStiffness, SmwAndTheUpdatedFactorSolveTheCutPlateAsAFreshFactorisationDoes) {
  const CutPlate p = MakeCut();
  ASSERT_GT(p.removed.size(), 5u);
  ASSERT_GT(p.moved.size(), 5u);
  CutStiffness problem(p.rest, p.fixed, 1.0e6, 0.4);  // seed 003's plate: 1 MPa, ν 0.4
  DenseInverseStiffness dense(problem);
  SparseFactorStiffness sparse(problem);
  SparseFactorStiffness batched(problem);  // the same changes summed per batch (StepChange)
  StepChange step;
  const auto add = [&](int32_t e, const Matrix12d& change) {
    if (!step.Add(problem, e, change)) {
      step.Split();
      ASSERT_TRUE(batched.Apply(step));
      step.Clear();
      ASSERT_TRUE(step.Add(problem, e, change));
    }
  };
  // The cut as the server applies it: removals, then the elements whose corners moved.
  for (const int32_t e : p.removed) {
    const Matrix12d change = problem.Remove(e);
    const LowRankChange c = SplitChange(problem, e, change);
    EXPECT_LE(c.rank, 6);
    dense.Apply(c);
    ASSERT_TRUE(sparse.Apply(c));
    add(e, change);
  }
  int relocated = 0;
  for (const int32_t e : ElementsTouching(p.rest.tetrahedra, p.moved)) {
    if (!problem.alive(e)) continue;
    const Matrix12d change = problem.Relocate(e, p.cut_rest);
    const LowRankChange c = SplitChange(problem, e, change);
    EXPECT_LE(c.rank, 12);
    dense.Apply(c);
    ASSERT_TRUE(sparse.Apply(c));
    add(e, change);
    ++relocated;
  }
  step.Split();
  ASSERT_TRUE(batched.Apply(step));
  EXPECT_GT(relocated, 5);
  // The reference: the cut mesh assembled and factorised from scratch.
  const Eigen::MatrixXd k = problem.AssembleDense();
  const Eigen::LLT<Eigen::MatrixXd> fresh(k);
  ASSERT_EQ(fresh.info(), Eigen::Success);
  std::mt19937 rng(7);
  std::normal_distribution<double> normal;
  for (int trial = 0; trial < 3; ++trial) {
    Eigen::VectorXd f(problem.num_free());
    for (Eigen::Index i = 0; i < f.size(); ++i) f[i] = normal(rng);
    const Eigen::VectorXd reference = fresh.solve(f);
    Eigen::VectorXd u;
    dense.Solve(f, &u);
    EXPECT_LT(RelativeError(u, reference), 1e-8) << "SMW";
    sparse.Solve(f, &u);
    EXPECT_LT(RelativeError(u, reference), 1e-8) << "CHOLMOD update/downdate";
    batched.Solve(f, &u);
    EXPECT_LT(RelativeError(u, reference), 1e-8) << "CHOLMOD, the changes summed per batch";
  }
}

TEST(CutStiffness, ADowndateThatWouldLeaveANodeInNoElementIsReported) {
  const CutPlate p = MakeCut();
  CutStiffness problem(p.rest, p.fixed, 1.0e6, 0.4);
  SparseFactorStiffness sparse(problem);
  // A free node: remove every element it has. The last removal makes K singular.
  int32_t node = -1;
  for (size_t v = 0; v < p.fixed.size() && node < 0; ++v) {
    if (p.fixed[v] == 0) node = static_cast<int32_t>(v);
  }
  const std::vector<int32_t> elements = ElementsTouching(p.rest.tetrahedra, {node});
  ASSERT_GE(elements.size(), 2u);
  bool ok = true;
  for (size_t i = 0; i < elements.size() && ok; ++i) {
    ok = sparse.Apply(SplitChange(problem, elements[i], problem.Remove(elements[i])));
    if (i + 1 < elements.size()) {
      EXPECT_TRUE(ok) << i;
    }
  }
  EXPECT_FALSE(ok) << "the downdate that orphaned node " << node << " went unnoticed";
}

TEST(CutStiffness, FactorUpdatesAfterTheFirstAllocateNothing) {
  const CutPlate p = MakeCut();
  CutStiffness problem(p.rest, p.fixed, 1.0e6, 0.4);
  SparseFactorStiffness sparse(problem);
  ASSERT_GT(p.removed.size(), 3u);
  std::vector<LowRankChange> changes;
  for (const int32_t e : p.removed) changes.push_back(SplitChange(problem, e, problem.Remove(e)));
  ASSERT_TRUE(sparse.Apply(changes[0]));  // turns the factor into LDL' (allocates)
  StepChange step;
  std::vector<Matrix12d, Eigen::aligned_allocator<Matrix12d>> relocations;
  std::vector<int32_t> relocated;
  for (const int32_t e : ElementsTouching(p.rest.tetrahedra, p.moved)) {
    if (!problem.alive(e)) continue;
    relocations.push_back(problem.Relocate(e, p.cut_rest));
    relocated.push_back(e);
  }
  testing::AllocationCounter counter;
  for (size_t i = 1; i < changes.size(); ++i) ASSERT_TRUE(sparse.Apply(changes[i]));
  // A summed step too: Add, Split, Apply.
  int32_t added = 0;
  for (size_t i = 0; i < relocated.size(); ++i) {
    if (!step.Add(problem, relocated[i], relocations[i])) break;
    ++added;
  }
  step.Split();
  ASSERT_TRUE(sparse.Apply(step));
  EXPECT_EQ(counter.count(), 0);
  EXPECT_GT(added, 3);
}

TEST(CutStiffness, RefusesBadProblems) {
  const mesh::TetMesh plate = mesh_gen::GenerateBuiltinOrganVolume("plate192");
  std::vector<uint8_t> fixed(static_cast<size_t>(plate.vertices.cols()), 0);
  EXPECT_THROW(CutStiffness(plate, std::vector<uint8_t>(3, 0), 1e6, 0.4), std::invalid_argument);
  EXPECT_THROW(CutStiffness(plate, fixed, 0.0, 0.4), std::invalid_argument);
  EXPECT_THROW(CutStiffness(plate, fixed, 1e6, 0.5), std::invalid_argument);
  mesh::TetMesh bad = plate;
  bad.tetrahedra(1, 3) = 500;
  EXPECT_THROW(CutStiffness(bad, fixed, 1e6, 0.4), std::invalid_argument);
}

}  // namespace
}  // namespace somasim::cutting
