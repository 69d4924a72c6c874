// The block-sparse matrix and its solvers: the product matches a dense matrix, CG with
// Dirichlet nodes and CHOLMOD on the reduced system give the same solution, CHOLMOD refuses a
// matrix that is not positive definite, and CG allocates nothing.
#include "server/models/fem/block_sparse.h"

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <initializer_list>
#include <random>
#include <vector>

#include "common/mesh_gen/structured_meshes.h"
#include "server/models/fem/sparse_cholesky.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models::fem {
namespace {

// A random symmetric positive definite matrix on a box's node graph: Σ_e G_eᵀ G_e over
// elements (12 × 12 random G_e) plus `shift` I, also returned dense.
BlockSparseMatrix RandomSpd(const mesh::TetMesh& mesh, double shift, Eigen::MatrixXd* dense,
                            bool upper = false) {
  BlockSparseMatrix a = BlockSparseMatrix::FromTets(
      mesh.tetrahedra, static_cast<int32_t>(mesh.vertices.cols()), upper);
  const Eigen::Index n = 3 * mesh.vertices.cols();
  *dense = shift * Eigen::MatrixXd::Identity(n, n);
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  for (Eigen::Index e = 0; e < mesh.tetrahedra.cols(); ++e) {
    Eigen::Matrix<double, 12, 12> g;
    for (Eigen::Index k = 0; k < g.size(); ++k) g.data()[k] = value(rng);
    const Eigen::Matrix<double, 12, 12> ke = g.transpose() * g;
    for (int p = 0; p < 4; ++p) {
      for (int q = 0; q < 4; ++q) {
        const auto ep = static_cast<int32_t>(e);
        if (a.element_block(ep, p, q) >= 0) {  // upper storage leaves the lower blocks out
          a.block(a.element_block(ep, p, q)) += ke.block<3, 3>(3 * p, 3 * q);
        }
        dense->block<3, 3>(3 * mesh.tetrahedra(p, e), 3 * mesh.tetrahedra(q, e)) +=
            ke.block<3, 3>(3 * p, 3 * q);
      }
    }
  }
  for (int32_t i = 0; i < a.num_nodes(); ++i) {
    a.block(a.diagonal_block(i)).diagonal().array() += shift;
  }
  return a;
}

// 1 for the nodes in `held`, 0 for the others (num_nodes entries).
std::vector<uint8_t> HeldNodes(int32_t num_nodes, std::initializer_list<int32_t> held) {
  std::vector<uint8_t> out(static_cast<size_t>(num_nodes), 0);
  for (const int32_t i : held) out[static_cast<size_t>(i)] = 1;
  return out;
}

TEST(BlockSparseMatrix, ProductMatchesTheDenseMatrix) {
  const mesh::TetMesh box =
      mesh_gen::BoxGridTets(3, 3, 3, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones());
  Eigen::MatrixXd dense;
  const BlockSparseMatrix a = RandomSpd(box, 0.5, &dense);
  const Eigen::VectorXd x = Eigen::VectorXd::LinSpaced(dense.rows(), -1.0, 2.0);
  Eigen::VectorXd y(dense.rows());
  a.Multiply(x.data(), y.data(), nullptr);
  EXPECT_LT((y - dense * x).norm(), 1e-12 * (dense * x).norm());
}

// The scalar and AVX-512 products, full and upper storage, with and without held nodes, all
// equal the dense product (held rows and columns replaced by the identity).
TEST(BlockSparseMatrix, EveryProductPathMatchesTheDenseMatrix) {
  const mesh::TetMesh box =
      mesh_gen::BoxGridTets(4, 3, 3, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones());
  Eigen::MatrixXd dense, dense_upper;
  BlockSparseMatrix full = RandomSpd(box, 0.5, &dense);
  BlockSparseMatrix upper = RandomSpd(box, 0.5, &dense_upper, true);
  ASSERT_TRUE(upper.upper());
  EXPECT_LT(2 * upper.num_blocks(), full.num_blocks() + full.num_nodes() + 1);
  EXPECT_EQ(dense, dense_upper);
  const int32_t n = full.num_nodes();
  const std::vector<uint8_t> held = HeldNodes(n, {0, 7, 20, n - 1});
  Eigen::MatrixXd masked = dense;  // held rows and columns replaced by the identity
  for (int32_t i = 0; i < n; ++i) {
    if (held[static_cast<size_t>(i)] == 0) continue;
    masked.middleRows(3 * i, 3).setZero();
    masked.middleCols(3 * i, 3).setZero();
    masked.block<3, 3>(3 * i, 3 * i).setIdentity();
  }
  const Eigen::VectorXd x = Eigen::VectorXd::LinSpaced(dense.rows(), -1.0, 2.0);
  for (BlockSparseMatrix* a : {&full, &upper}) {
    for (const bool scalar : {false, true}) {
      a->set_force_scalar(scalar);
      // Twice each, alternated: the upper vector path's scratch (the transposed blocks' sums)
      // must be left clear by every product.
      for (int round = 0; round < 2; ++round) {
        Eigen::VectorXd y = Eigen::VectorXd::Constant(dense.rows(), 7.0);  // overwritten
        a->Multiply(x.data(), y.data(), nullptr);
        EXPECT_LT((y - dense * x).norm(), 1e-13 * (dense * x).norm()) << a->upper() << scalar;
        a->Multiply(x.data(), y.data(), held.data());
        EXPECT_LT((y - masked * x).norm(), 1e-13 * (masked * x).norm()) << a->upper() << scalar;
      }
    }
  }
}

TEST(BlockSparseMatrix, ScalarLowerInTwoPartsEqualsTheSortedOne) {
  const mesh::TetMesh box =
      mesh_gen::BoxGridTets(3, 3, 4, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones());
  Eigen::MatrixXd dense;
  BlockSparseMatrix a = RandomSpd(box, 0.5, &dense);
  std::vector<int32_t> dof(3 * static_cast<size_t>(a.num_nodes()), 0);
  dof[3] = dof[4] = dof[5] = dof[10] = -1;  // node 1 held, and the y of node 3
  int32_t num_dofs = 0;
  for (int32_t& d : dof) {
    if (d == 0) d = num_dofs++;
  }
  const LowerCsc sorted = a.ScalarLower(dof, num_dofs);
  std::vector<int32_t> source;
  LowerCsc pattern = a.ScalarLowerPattern(dof, num_dofs, &source);
  a.block(0) *= 2.0;  // new values, same pattern: Fill must see them
  a.FillScalarLower(source, &pattern);
  EXPECT_EQ(pattern.col_start, sorted.col_start);
  EXPECT_EQ(pattern.rows, sorted.rows);
  const LowerCsc again = a.ScalarLower(dof, num_dofs);
  EXPECT_EQ(pattern.values, again.values);
  EXPECT_NE(pattern.values, sorted.values);
}

TEST(BlockSparseMatrix, ConjugateGradientsWithDirichletNodesMatchesCholmod) {
  const mesh::TetMesh box =
      mesh_gen::BoxGridTets(4, 3, 3, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones());
  Eigen::MatrixXd dense;
  const BlockSparseMatrix a = RandomSpd(box, 1e-3, &dense);
  const int32_t n = a.num_nodes();
  const std::vector<uint8_t> constrained = HeldNodes(n, {0, 5, 17});
  Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(3 * n, 1.0, -1.0);
  // Known values on the held nodes; the free rows carry the held columns to the right-hand side.
  Eigen::VectorXd known = Eigen::VectorXd::Zero(3 * n);
  for (int32_t i = 0; i < n; ++i) {
    if (constrained[static_cast<size_t>(i)] != 0) known.segment<3>(3 * i) << 0.1, -0.2, 0.3;
  }
  const Eigen::VectorXd moved = dense * known;
  std::vector<int32_t> dof(static_cast<size_t>(3 * n), -1);
  int32_t free_dofs = 0;
  for (int32_t i = 0; i < n; ++i) {
    for (int c = 0; c < 3; ++c) {
      if (constrained[static_cast<size_t>(i)] != 0) {
        b[3 * i + c] = known[3 * i + c];
      } else {
        b[3 * i + c] -= moved[3 * i + c];
        dof[3 * static_cast<size_t>(i) + static_cast<size_t>(c)] = free_dofs++;
      }
    }
  }
  Eigen::VectorXd x = Eigen::VectorXd::Zero(3 * n);
  CgScratch scratch(n);
  CgResult result;
  {
    somasim::testing::AllocationCounter counter;
    result = ConjugateGradients(a, constrained.data(), b.data(), x.data(), 1e-12, 1000, &scratch);
    EXPECT_EQ(counter.count(), 0);
  }
  ASSERT_TRUE(result.converged);
  EXPECT_LE(result.relative_residual, 1e-12);
  // CHOLMOD on the free DOFs only.
  const LowerCsc reduced = a.ScalarLower(dof, free_dofs);
  SparseCholesky cholesky;
  cholesky.Analyse(reduced);
  ASSERT_TRUE(cholesky.Factorise(reduced));
  Eigen::VectorXd rhs(free_dofs), solution(free_dofs);
  for (Eigen::Index k = 0; k < 3 * n; ++k) {
    if (dof[static_cast<size_t>(k)] >= 0) rhs[dof[static_cast<size_t>(k)]] = b[k];
  }
  cholesky.Solve(rhs.data(), solution.data());
  for (Eigen::Index k = 0; k < 3 * n; ++k) {
    const int32_t d = dof[static_cast<size_t>(k)];
    EXPECT_NEAR(x[k], d >= 0 ? solution[d] : known[k], 1e-8 * solution.cwiseAbs().maxCoeff())
        << "dof " << k;
  }
}

TEST(SparseCholesky, RefusesAMatrixThatIsNotPositiveDefinite) {
  LowerCsc m;
  m.size = 2;
  m.col_start = {0, 2, 3};
  m.rows = {0, 1, 1};
  m.values = {1.0, 2.0, 1.0};  // [[1, 2], [2, 1]]: eigenvalues 3 and -1
  SparseCholesky cholesky;
  cholesky.Analyse(m);
  EXPECT_FALSE(cholesky.Factorise(m));
  m.values = {2.0, 1.0, 2.0};  // eigenvalues 3 and 1
  ASSERT_TRUE(cholesky.Factorise(m));
  const double b[2] = {3.0, 3.0};
  double x[2] = {0.0, 0.0};
  cholesky.Solve(b, x);
  EXPECT_NEAR(x[0], 1.0, 1e-14);
  EXPECT_NEAR(x[1], 1.0, 1e-14);
}

}  // namespace
}  // namespace somasim::models::fem

namespace somasim::models::fem {
namespace {

// Selected inversion: diagonal blocks of A⁻¹ by sparse forward substitution along the
// elimination tree equal the columns of full solves, for single blocks and for many at once
// (grouped internally), and a repeated call allocates nothing.
TEST(SparseCholesky, InverseBlocksEqualFullSolves) {
  // A random sparse SPD matrix: a banded Laplacian-like pattern plus a few long couplings.
  const int32_t n = 300;
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  std::vector<std::vector<std::pair<int32_t, double>>> columns(static_cast<size_t>(n));
  std::vector<double> row_sum(static_cast<size_t>(n), 0.0);
  const auto couple = [&](int32_t i, int32_t j) {  // i > j
    const double v = value(rng);
    columns[static_cast<size_t>(j)].push_back({i, v});
    row_sum[static_cast<size_t>(i)] += std::abs(v);
    row_sum[static_cast<size_t>(j)] += std::abs(v);
  };
  for (int32_t j = 0; j < n; ++j) {
    for (int32_t d = 1; d <= 4 && j + d < n; ++d) couple(j + d, j);
    if (j + 97 < n) couple(j + 97, j);
  }
  LowerCsc m;
  m.size = n;
  m.col_start.push_back(0);
  for (int32_t j = 0; j < n; ++j) {
    auto& column = columns[static_cast<size_t>(j)];
    std::sort(column.begin(), column.end());
    m.rows.push_back(j);
    m.values.push_back(row_sum[static_cast<size_t>(j)] + 0.5);  // diagonally dominant
    for (const auto& [i, v] : column) {
      m.rows.push_back(i);
      m.values.push_back(v);
    }
    m.col_start.push_back(static_cast<int32_t>(m.rows.size()));
  }
  SparseCholesky cholesky;
  cholesky.Analyse(m);
  ASSERT_TRUE(cholesky.Factorise(m));
  EXPECT_GT(cholesky.ReciprocalConditionEstimate(), 1e-6);
  // The inverse's columns by full solves.
  std::vector<std::vector<double>> inverse(static_cast<size_t>(n),
                                           std::vector<double>(static_cast<size_t>(n)));
  std::vector<double> e(static_cast<size_t>(n), 0.0);
  for (int32_t j = 0; j < n; ++j) {
    e[static_cast<size_t>(j)] = 1.0;
    cholesky.Solve(e.data(), inverse[static_cast<size_t>(j)].data());
    e[static_cast<size_t>(j)] = 0.0;
  }
  const auto want = [&](int32_t i, int32_t j) {
    return inverse[static_cast<size_t>(j)][static_cast<size_t>(i)];
  };
  // SolveMany: 150 right-hand sides at once (three CHOLMOD calls of up to 64) equal Solve's.
  {
    const int32_t rhs_count = 150;
    std::vector<double> many(static_cast<size_t>(n * rhs_count), 0.0);
    for (int32_t j = 0; j < rhs_count; ++j)
      many[static_cast<size_t>(j) * static_cast<size_t>(n) + static_cast<size_t>(2 * j)] = 1.0;
    cholesky.SolveMany(many.data(), many.data(), rhs_count);  // in place: b and x may alias
    double worst = 0.0;
    for (int32_t j = 0; j < rhs_count; ++j) {
      for (int32_t i = 0; i < n; ++i) {
        worst = std::max(
            worst,
            std::abs(
                many[static_cast<size_t>(j) * static_cast<size_t>(n) + static_cast<size_t>(i)] -
                want(i, 2 * j)));
      }
    }
    EXPECT_LT(worst, 1e-13);
  }
  // One 3 × 3 block of scattered indices.
  const int32_t one[3] = {5, 150, 299};
  double block[9];
  cholesky.InverseBlock(one, 3, block);
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) EXPECT_NEAR(block[3 * b + a], want(one[a], one[b]), 1e-13);
  }
  // Every node-like triple at once (100 blocks, grouped internally), twice: the second call
  // reuses the workspace and allocates nothing.
  std::vector<int32_t> all(static_cast<size_t>(n));
  for (int32_t i = 0; i < n; ++i) all[static_cast<size_t>(i)] = (i * 7) % n;  // a permutation
  std::vector<double> blocks(3 * static_cast<size_t>(n));
  cholesky.InverseBlocks(all.data(), 3, n / 3, blocks.data());
  {
    somasim::testing::AllocationCounter counter;
    cholesky.InverseBlocks(all.data(), 3, n / 3, blocks.data());
    EXPECT_EQ(counter.count(), 0);
  }
  for (int32_t k = 0; k < n / 3; ++k) {
    for (int a = 0; a < 3; ++a) {
      for (int b = 0; b < 3; ++b) {
        EXPECT_NEAR(blocks[9 * static_cast<size_t>(k) + 3 * static_cast<size_t>(b) +
                           static_cast<size_t>(a)],
                    want(all[3 * static_cast<size_t>(k) + static_cast<size_t>(a)],
                         all[3 * static_cast<size_t>(k) + static_cast<size_t>(b)]),
                    1e-13)
            << "block " << k;
      }
    }
  }
  const int32_t bad[1] = {n};
  EXPECT_THROW(cholesky.InverseBlock(bad, 1, block), std::out_of_range);
  // A new factorisation of other values: the blocks follow it (no stale copy of the factor).
  for (size_t k = 0; k < m.values.size(); ++k) m.values[k] *= 2.0;
  ASSERT_TRUE(cholesky.Factorise(m));
  cholesky.InverseBlock(one, 3, block);
  EXPECT_NEAR(block[0], 0.5 * want(one[0], one[0]), 1e-13);
}

}  // namespace
}  // namespace somasim::models::fem
