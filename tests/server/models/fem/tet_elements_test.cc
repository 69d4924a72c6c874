// The polar decomposition without an SVD (PolarRotationFrom, and PolarRotations eight at a time)
// agrees with the SVD one to 1e-12, from cold and warm starts, for large rotations, stretched,
// nearly flat and inverted elements, and returns the same proper rotation as the SVD for an
// inverted element (det F < 0).
#include "server/models/fem/tet_elements.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <random>
#include <vector>

namespace somasim::models::fem {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

Matrix3d RandomRotation(std::mt19937* rng) {
  std::normal_distribution<double> normal;
  Eigen::Quaterniond q(normal(*rng), normal(*rng), normal(*rng), normal(*rng));
  return q.normalized().toRotationMatrix();
}

// F = U diag(s) Vᵀ with random rotations U, V and the given singular values (s2 < 0: inverted).
Matrix3d WithSingularValues(std::mt19937* rng, const Vector3d& s) {
  return RandomRotation(rng) * s.asDiagonal() * RandomRotation(rng).transpose();
}

// Test matrices: general, stretched, nearly flat, inverted (distinct singular values, so the
// proper rotation is unique), and near the identity.
std::vector<Matrix3d> Cases() {
  std::mt19937 rng(21);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  std::vector<Matrix3d> out;
  for (int k = 0; k < 40; ++k) {
    Matrix3d f;
    for (int i = 0; i < 9; ++i) f.data()[i] = unit(rng);
    out.push_back(f);
  }
  for (int k = 0; k < 20; ++k) {
    out.push_back(WithSingularValues(&rng, Vector3d(1.3, 0.9, 0.7)));
    out.push_back(WithSingularValues(&rng, Vector3d(1.0, 0.8, 1e-9)));   // nearly flat
    out.push_back(WithSingularValues(&rng, Vector3d(1.2, 0.9, -0.3)));   // inverted
    out.push_back(WithSingularValues(&rng, Vector3d(1.0, 0.5, -0.49)));  // inverted, near flat
    Matrix3d near = Matrix3d::Identity();
    for (int i = 0; i < 9; ++i) near.data()[i] += 1e-3 * unit(rng);
    out.push_back(RandomRotation(&rng) * near);
  }
  out.push_back(Matrix3d::Identity());
  return out;
}

TEST(PolarRotation, NewtonFromColdAndWarmStartsEqualsTheSvd) {
  std::mt19937 rng(5);
  for (const Matrix3d& f : Cases()) {
    const Matrix3d svd = PolarRotation(f);
    ASSERT_NEAR(svd.determinant(), 1.0, 1e-12);
    double cold[4] = {1.0, 0.0, 0.0, 0.0};
    const Matrix3d r = PolarRotationFrom(f, cold);
    EXPECT_LT((r - svd).norm(), 1e-12) << f;
    EXPECT_LT((r.transpose() * r - Matrix3d::Identity()).norm(), 1e-14);
    // The quaternion returned is R's.
    const Eigen::Quaterniond back(cold[0], cold[1], cold[2], cold[3]);
    EXPECT_LT((back.toRotationMatrix() - svd).norm(), 1e-12);
    // Warm: from a rotation 0.05 rad away (a step's change), and from far away (fallback).
    for (const double angle : {0.05, 2.5}) {
      const Eigen::Quaterniond start(
          Eigen::Quaterniond(svd) *
          Eigen::Quaterniond(Eigen::AngleAxisd(angle, RandomRotation(&rng).col(0))));
      double warm[4] = {start.w(), start.x(), start.y(), start.z()};
      EXPECT_LT((PolarRotationFrom(f, warm) - svd).norm(), 1e-12) << angle << "\n" << f;
    }
  }
}

TEST(PolarRotation, InvertedElementGetsTheProperRotationOfTheSvd) {
  // Reflection through z of a rotated stretch: det F < 0; R = U diag(1, 1, -1) Vᵀ.
  const Matrix3d q = Eigen::AngleAxisd(0.8, Vector3d(1.0, -2.0, 0.5).normalized()).matrix();
  const Matrix3d f = q * Vector3d(1.1, 0.9, -0.4).asDiagonal();
  double start[4] = {1.0, 0.0, 0.0, 0.0};
  const Matrix3d r = PolarRotationFrom(f, start);
  EXPECT_NEAR(r.determinant(), 1.0, 1e-12);
  EXPECT_LT((r - q).norm(), 1e-12);
  EXPECT_LT((r - PolarRotation(f)).norm(), 1e-12);
}

// The batch (AVX-512 where the CPU has it, eight lanes, with a lane left to the scalar path when
// it does not converge) and its portable path give the single-matrix answers; a count that is
// not a multiple of eight exercises the tail.
TEST(PolarRotation, BatchesEqualTheSingleMatrixPath) {
  const std::vector<Matrix3d> cases = Cases();
  const size_t count = cases.size();
  ASSERT_NE(count % 8, 0u);
  std::vector<double> f(9 * count), expected(9 * count);
  std::vector<double> q0(4 * count, 0.0);
  std::mt19937 rng(9);
  for (size_t e = 0; e < count; ++e) {
    Eigen::Map<Matrix3d>(f.data() + 9 * e) = cases[e];
    // Starts: identity, near the answer, or far (some lanes fall back).
    Eigen::Quaterniond start = Eigen::Quaterniond::Identity();
    if (e % 3 == 1) {
      start = Eigen::Quaterniond(PolarRotation(cases[e])) *
              Eigen::Quaterniond(Eigen::AngleAxisd(0.02, RandomRotation(&rng).col(0)));
    } else if (e % 3 == 2) {
      start = Eigen::Quaterniond(RandomRotation(&rng));
    }
    q0[4 * e] = start.w();
    q0[4 * e + 1] = start.x();
    q0[4 * e + 2] = start.y();
    q0[4 * e + 3] = start.z();
    double q[4] = {start.w(), start.x(), start.y(), start.z()};
    Eigen::Map<Matrix3d>(expected.data() + 9 * e) = PolarRotationFrom(cases[e], q);
  }
  for (const bool scalar : {false, true}) {
    std::vector<double> q = q0, r(9 * count, 0.0);
    PolarRotations(f.data(), q.data(), r.data(), count, scalar);
    for (size_t e = 0; e < count; ++e) {
      const Eigen::Map<const Matrix3d> got(r.data() + 9 * e);
      EXPECT_LT((got - Eigen::Map<const Matrix3d>(expected.data() + 9 * e)).norm(), 1e-12)
          << "element " << e << (scalar ? " scalar" : " batch");
      EXPECT_LT((got - PolarRotation(cases[e])).norm(), 1e-12) << e;
    }
    // In place (r = f), as ElasticForces uses it.
    std::vector<double> in_place = f;
    q = q0;
    PolarRotations(in_place.data(), q.data(), in_place.data(), count, scalar);
    EXPECT_EQ(in_place, r);
  }
}

}  // namespace
}  // namespace somasim::models::fem
