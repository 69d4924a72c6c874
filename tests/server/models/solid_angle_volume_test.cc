// Solid-angle volume reaction (seed 004, SPEC §4.3): the solid angle matches known geometry (flat
// patch, cube corner, regular pyramids and their circular-cone limit, Gram's relation on closed
// surfaces) and is continuous through flat; the force is the exact negative energy gradient on
// both branches, conserves momentum and angular momentum, vanishes at rest, restores dents and
// bulges along the normal of the neighbours' plane; the local stiffness is the energy Hessian
// block; evaluation allocates nothing; bad input is refused by name. Small meshes keep the
// tests fast in sanitizer builds.
#include "server/models/solid_angle_volume.h"

#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <cmath>
#include <functional>
#include <limits>
#include <map>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_gen/closed_surface_mesher.h"
#include "common/mesh_gen/implicit.h"
#include "tests/support/allocation_counter.h"

namespace somasim::models {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
constexpr double kPi = std::numbers::pi;

SolidAngleVolumeParameters Params(double gamma_plus, double sigma_plus, double gamma_minus,
                                  double sigma_minus) {
  SolidAngleVolumeParameters p;
  p.gamma_plus = gamma_plus;
  p.sigma_plus = sigma_plus;
  p.gamma_minus = gamma_minus;
  p.sigma_minus = sigma_minus;
  return p;
}

const SolidAngleVolumeParameters kMixed = Params(3.0, 2.0, 5.0, 0.7);

// A sphere of radius 2 cm centred at the origin with `n` vertices (meshed once per n).
const mesh::SurfaceMesh& Sphere(int n) {
  static std::map<int, mesh::SurfaceMesh> cache;
  auto it = cache.find(n);
  if (it == cache.end()) {
    const mesh_gen::Ellipsoid sphere(Vector3d::Zero(), Vector3d::Constant(0.02));
    mesh_gen::ClosedSurfaceOptions options;
    options.num_vertices = n;
    it = cache.emplace(n, mesh_gen::MeshClosedSurface(sphere, options)).first;
  }
  return it->second;
}

// The unit cube [0,1]³ with a vertex at each face centre: 14 vertices (0..7 the corners, index
// x + 2y + 4z; 8..13 the face centres), 24 triangles counter-clockwise seen from outside.
// The built-in spleen (600 vertices), generated once.
const mesh::SurfaceMesh& Spleen() {
  static const mesh::SurfaceMesh spleen = mesh_gen::GenerateBuiltinOrgan("spleen600").surface;
  return spleen;
}

mesh::SurfaceMesh CubeWithFaceCentres() {
  mesh::SurfaceMesh cube;
  cube.vertices.resize(3, 14);
  for (int v = 0; v < 8; ++v) cube.vertices.col(v) = Vector3d(v & 1, (v >> 1) & 1, (v >> 2) & 1);
  cube.triangles.resize(3, 24);
  int face = 0;
  for (int axis = 0; axis < 3; ++axis) {
    const int u = (axis + 1) % 3;
    const int w = (axis + 2) % 3;
    for (int side = 0; side < 2; ++side, ++face) {
      // Corners counter-clockwise about +axis in the (u, w) plane; reversed on the − side.
      int corners[4];
      const int uv[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
      for (int k = 0; k < 4; ++k) {
        const int q = side == 1 ? k : 3 - k;
        corners[k] = (side << axis) | (uv[q][0] << u) | (uv[q][1] << w);
      }
      const int centre = 8 + face;
      Vector3d c = Vector3d::Constant(0.5);
      c[axis] = side;
      cube.vertices.col(centre) = c;
      for (int k = 0; k < 4; ++k) {
        cube.triangles.col(4 * face + k) << centre, corners[k], corners[(k + 1) % 4];
      }
    }
  }
  return cube;
}

// A closed pyramid: apex 0 at the origin, base ring 1..n on the circle at polar angle θ from −z
// (unit distance from the apex), base centre n + 1; counter-clockwise seen from outside
// (inside out when θ > π/2).
mesh::SurfaceMesh Pyramid(int n, double theta) {
  mesh::SurfaceMesh pyramid;
  pyramid.vertices = mesh::Points::Zero(3, n + 2);  // apex 0 at the origin
  for (int k = 0; k < n; ++k) {
    const double phi = 2.0 * kPi * k / n;
    pyramid.vertices.col(1 + k) = Vector3d(std::sin(theta) * std::cos(phi),
                                           std::sin(theta) * std::sin(phi), -std::cos(theta));
  }
  pyramid.vertices.col(n + 1) = Vector3d(0.0, 0.0, -std::cos(theta));
  pyramid.triangles.resize(3, 2 * n);
  for (int k = 0; k < n; ++k) {
    pyramid.triangles.col(k) << 0, 1 + k, 1 + (k + 1) % n;
    pyramid.triangles.col(n + k) << n + 1, 1 + (k + 1) % n, 1 + k;
  }
  return pyramid;
}

// Solid angle at the apex of a regular n-gon pyramid whose edges make angle θ with the axis.
double RegularPyramidAngle(int n, double theta) {
  return 2.0 * kPi - 2.0 * n * std::atan(std::tan(kPi / n) * std::cos(theta));
}

// A tetrahedron's surface, counter-clockwise seen from outside.
mesh::SurfaceMesh Tetrahedron() {
  mesh::SurfaceMesh tet;
  tet.vertices.resize(3, 4);
  tet.vertices << 0, 1, 0, 0,  //
      0, 0, 1, 0,              //
      0, 0, 0, 1;
  tet.triangles.resize(3, 4);
  tet.triangles << 0, 0, 0, 1,  //
      2, 1, 3, 2,               //
      1, 3, 2, 3;
  return tet;
}

void Perturb(mesh::Points* x, double amplitude, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> offset(-amplitude, amplitude);
  for (Eigen::Index i = 0; i < x->size(); ++i) x->data()[i] += offset(rng);
}

double MeanEdge(const mesh::SurfaceMesh& surface) {
  double sum = 0.0;
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    for (int k = 0; k < 3; ++k) {
      sum += (surface.vertices.col(surface.triangles(k, t)) -
              surface.vertices.col(surface.triangles((k + 1) % 3, t)))
                 .norm();
    }
  }
  return sum / (3.0 * static_cast<double>(surface.triangles.cols()));
}

mesh::Points Forces(const SolidAngleVolumeTerm& term, const mesh::Points& x) {
  mesh::Points forces = mesh::Points::Zero(3, x.cols());
  term.AddForces(x, &forces);
  return forces;
}

// Σ_v Ω_v − 2 Σ_e φ_e + 2π F − 4π for a closed triangle surface, φ_e the interior dihedral
// angle: zero by Gram's relation (the normalised angle sums of vertices, edges, faces and the
// solid alternate to zero).
double GramDefect(const SolidAngleVolumeTerm& term, const mesh::SurfaceMesh& surface) {
  double sum = 0.0;
  for (int32_t v = 0; v < term.num_points(); ++v) {
    if (term.HasTerm(v)) sum += term.SolidAngle(surface.vertices, v);
  }
  std::map<std::pair<int32_t, int32_t>, int32_t> opposite;  // directed edge → third vertex
  const auto& tri = surface.triangles;
  const auto& x = surface.vertices;
  for (Eigen::Index t = 0; t < tri.cols(); ++t) {
    for (int k = 0; k < 3; ++k) opposite[{tri(k, t), tri((k + 1) % 3, t)}] = tri((k + 2) % 3, t);
  }
  for (const auto& [edge, c] : opposite) {
    const auto [a, b] = edge;
    if (a > b) continue;
    const int32_t d = opposite.at({b, a});
    const Vector3d n1 = (x.col(b) - x.col(a)).cross(x.col(c) - x.col(a));
    const Vector3d n2 = (x.col(a) - x.col(b)).cross(x.col(d) - x.col(b));
    const double turn = std::atan2(n1.cross(n2).norm(), n1.dot(n2));  // in [0, π]
    const bool convex = (x.col(d) - x.col(a)).dot(n1) <= 0.0;
    sum -= 2.0 * (convex ? kPi - turn : kPi + turn);
  }
  return sum + 2.0 * kPi * static_cast<double>(tri.cols()) - 4.0 * kPi;
}

TEST(SolidAngleVolume, CubeCornersAreQuarterPiAndFlatNodesTwoPi) {
  mesh::SurfaceMesh cube = CubeWithFaceCentres();
  const auto term = SolidAngleVolumeTerm::Build(cube, kMixed);
  EXPECT_EQ(term.num_terms(), 14);
  for (int32_t v = 0; v < 8; ++v) EXPECT_NEAR(term.SolidAngle(cube.vertices, v), kPi / 2, 1e-14);
  for (int32_t v = 8; v < 14; ++v) EXPECT_NEAR(term.SolidAngle(cube.vertices, v), 2 * kPi, 1e-14);
  EXPECT_NEAR(GramDefect(term, cube), 0.0, 1e-12);
  // Moving the face centres within their faces keeps them flat: irregular flat rings.
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> offset(-0.3, 0.3);
  for (int face = 0; face < 6; ++face) {
    for (int axis = 0; axis < 3; ++axis) {
      if (axis != face / 2) cube.vertices(axis, 8 + face) += offset(rng);
    }
  }
  for (int32_t v = 8; v < 14; ++v) EXPECT_NEAR(term.SolidAngle(cube.vertices, v), 2 * kPi, 1e-13);
  // A tetrahedron's right-angled corner is an octant as well.
  const mesh::SurfaceMesh tet = Tetrahedron();
  EXPECT_NEAR(SolidAngleVolumeTerm::Build(tet, kMixed).SolidAngle(tet.vertices, 0), kPi / 2, 1e-14);
}

TEST(SolidAngleVolume, PyramidApexIsTheInteriorSolidAngle) {
  for (const int n : {3, 4, 6, 11}) {
    for (const double theta : {0.3, 0.7, 1.2, 2.0}) {  // 2.0: inside out, a reflex apex
      const mesh::SurfaceMesh pyramid = Pyramid(n, theta);
      const auto term = SolidAngleVolumeTerm::Build(pyramid, kMixed);
      EXPECT_NEAR(term.SolidAngle(pyramid.vertices, 0), RegularPyramidAngle(n, theta), 1e-13)
          << n << " " << theta;
      EXPECT_NEAR(term.RestSolidAngle(0), RegularPyramidAngle(n, theta), 1e-13);
      EXPECT_NEAR(GramDefect(term, pyramid), 0.0, 1e-12);
    }
  }
  // Square pyramid with base a × a at depth h: Ω = 4 arcsin(a² / (a² + 4h²)).
  const double theta = 0.9;
  const double a = std::sqrt(2.0) * std::sin(theta);
  const double h = std::cos(theta);
  const mesh::SurfaceMesh square = Pyramid(4, theta);
  EXPECT_NEAR(SolidAngleVolumeTerm::Build(square, kMixed).SolidAngle(square.vertices, 0),
              4.0 * std::asin(a * a / (a * a + 4 * h * h)), 1e-13);
  // Many sides: the circular cone of half-angle θ, 2π(1 − cos θ).
  for (const double cone : {0.4, 1.0, 2.2}) {
    const mesh::SurfaceMesh pyramid = Pyramid(400, cone);
    EXPECT_NEAR(SolidAngleVolumeTerm::Build(pyramid, kMixed).SolidAngle(pyramid.vertices, 0),
                2 * kPi * (1 - std::cos(cone)), 2e-4);
  }
}

TEST(SolidAngleVolume, GramRelationHoldsOnOrganAndSphere) {
  const mesh::SurfaceMesh& spleen = Spleen();
  const auto term = SolidAngleVolumeTerm::Build(spleen, kMixed);
  EXPECT_EQ(term.num_terms(), 600);
  EXPECT_NEAR(GramDefect(term, spleen), 0.0, 1e-9);
  const mesh::SurfaceMesh sphere = Sphere(80);
  const auto sphere_term = SolidAngleVolumeTerm::Build(sphere, kMixed);
  EXPECT_NEAR(GramDefect(sphere_term, sphere), 0.0, 1e-10);
  for (int32_t v = 0; v < 80; ++v) {  // convex everywhere: just under 2π
    EXPECT_LT(sphere_term.RestSolidAngle(v), 2 * kPi);
    EXPECT_GT(sphere_term.RestSolidAngle(v), 1.4 * kPi);
  }
}

TEST(SolidAngleVolume, SolidAngleIsContinuousThroughFlatAndIntoADent) {
  const mesh::SurfaceMesh sphere = Sphere(80);
  const auto term = SolidAngleVolumeTerm::Build(sphere, kMixed);
  const double edge = MeanEdge(sphere);
  const int32_t node = 17;
  const Vector3d radial = sphere.vertices.col(node).normalized();
  mesh::Points x = sphere.vertices;
  double previous = 0.0;
  // From well outside (a spike) to well inside (a deep dent): Ω rises monotonically through 2π
  // without a jump of the argument's branch.
  const int steps = 400;
  for (int k = 0; k <= steps; ++k) {
    const double depth = edge * (-1.0 + 2.0 * k / steps);
    x.col(node) = sphere.vertices.col(node) - depth * radial;
    const double omega = term.SolidAngle(x, node);
    EXPECT_GT(omega, 0.0);
    EXPECT_LT(omega, 4 * kPi);
    if (k > 0) {
      EXPECT_GT(omega, previous) << k;
      EXPECT_LT(omega - previous, 0.05) << k;
    }
    previous = omega;
  }
  EXPECT_GT(previous, 2 * kPi);  // a dent's interior angle exceeds 2π
}

TEST(SolidAngleVolume, ForcesAreNegativeEnergyGradient) {
  const mesh::SurfaceMesh sphere = Sphere(50);
  const double edge = MeanEdge(sphere);
  mesh::Points x = sphere.vertices;
  Perturb(&x, 0.15 * edge, 7);
  // Plus side only, minus side only, all four different (σ only and γ only: the dent test).
  for (const auto& p : {Params(4.0, 1.5, 0.0, 0.0), Params(0.0, 0.0, 2.0, 3.0), kMixed}) {
    const auto term = SolidAngleVolumeTerm::Build(sphere, p);
    int plus = 0;
    int minus = 0;
    for (int32_t v = 0; v < term.num_terms(); ++v) {
      (term.SolidAngle(x, v) > term.RestSolidAngle(v) ? plus : minus) += 1;
    }
    ASSERT_GT(plus, 5);  // both branches are exercised
    ASSERT_GT(minus, 5);
    EXPECT_GT(term.Energy(x), 0.0);
    const mesh::Points forces = Forces(term, x);
    const double h = 1e-6 * edge;
    double worst = 0.0;
    for (Eigen::Index i = 0; i < x.size(); ++i) {
      mesh::Points y = x;
      y.data()[i] = x.data()[i] + h;
      const double e_plus = term.Energy(y);
      y.data()[i] = x.data()[i] - h;
      const double e_minus = term.Energy(y);
      worst = std::max(worst, std::abs(forces.data()[i] + (e_plus - e_minus) / (2 * h)));
    }
    EXPECT_LT(worst, 1e-6 * forces.cwiseAbs().maxCoeff())
        << p.gamma_plus << " " << p.sigma_plus << " " << p.gamma_minus << " " << p.sigma_minus;
  }
}

TEST(SolidAngleVolume, EnergyUsesTheSideOfEachDeviation) {
  const mesh::SurfaceMesh sphere = Sphere(50);
  mesh::Points x = sphere.vertices;
  Perturb(&x, 0.15 * MeanEdge(sphere), 8);
  const auto term = SolidAngleVolumeTerm::Build(sphere, kMixed);
  double expected = 0.0;
  for (int32_t v = 0; v < term.num_terms(); ++v) {
    const double d = term.SolidAngle(x, v) - term.RestSolidAngle(v);
    const double a = std::abs(d);
    expected += d > 0 ? kMixed.sigma_plus * d * d / 2 + kMixed.gamma_plus * a * a * a / 3
                      : kMixed.sigma_minus * d * d / 2 + kMixed.gamma_minus * a * a * a / 3;
  }
  EXPECT_NEAR(term.Energy(x), expected, 1e-13 * expected);
}

TEST(SolidAngleVolume, ForcesConserveMomentumAndAngularMomentum) {
  const mesh::SurfaceMesh& spleen = Spleen();
  const auto term = SolidAngleVolumeTerm::Build(spleen, kMixed);
  mesh::Points x = spleen.vertices;
  Perturb(&x, 0.1 * MeanEdge(spleen), 9);
  const mesh::Points forces = Forces(term, x);
  const double scale = forces.cwiseAbs().maxCoeff();
  ASSERT_GT(scale, 0.0);
  Vector3d total = Vector3d::Zero();
  Vector3d torque = Vector3d::Zero();
  const Vector3d centre = x.rowwise().mean();
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    total += forces.col(i);
    torque += (x.col(i) - centre).cross(forces.col(i));
  }
  const double size = (x.colwise() - centre).colwise().norm().maxCoeff();
  EXPECT_LT(total.norm(), 1e-12 * scale * static_cast<double>(x.cols()));
  EXPECT_LT(torque.norm(), 1e-12 * scale * size * static_cast<double>(x.cols()));
}

TEST(SolidAngleVolume, RestAndRigidMotionsAreForceFree) {
  const mesh::SurfaceMesh& spleen = Spleen();
  const auto term = SolidAngleVolumeTerm::Build(spleen, kMixed);
  EXPECT_EQ(term.Energy(spleen.vertices), 0.0);
  EXPECT_EQ(Forces(term, spleen.vertices).cwiseAbs().maxCoeff(), 0.0);
  // Rotated and translated: the solid angles do not change (to rounding).
  const Matrix3d rotation = Eigen::AngleAxisd(0.8, Vector3d(1, 2, 3).normalized()).matrix();
  const mesh::Points moved = (rotation * spleen.vertices).colwise() + Vector3d(0.1, -0.2, 0.3);
  for (int32_t v = 0; v < term.num_terms(); ++v) {
    EXPECT_NEAR(term.SolidAngle(moved, v), term.RestSolidAngle(v), 1e-11);
  }
  mesh::Points dented = spleen.vertices;
  dented.col(5) -= 0.1 * MeanEdge(spleen) * Vector3d::UnitX();
  EXPECT_LT(Forces(term, moved).cwiseAbs().maxCoeff(),
            1e-8 * Forces(term, dented).cwiseAbs().maxCoeff());
}

// Pushes node `node` of a sphere along its radius by `inward` [m] (negative: outward) and
// returns the reaction on it.
Vector3d ReactionOnDisplacedNode(const SolidAngleVolumeParameters& p, int32_t node, double inward) {
  const mesh::SurfaceMesh sphere = Sphere(80);
  const auto term = SolidAngleVolumeTerm::Build(sphere, p);
  mesh::Points x = sphere.vertices;
  x.col(node) -= inward * x.col(node).normalized();
  return Forces(term, x).col(node);
}

TEST(SolidAngleVolume, DentsArePushedOutAndBulgesPulledIn) {
  const double edge = MeanEdge(Sphere(80));
  for (const int32_t node : {3, 40, 77}) {
    const Vector3d outward = Sphere(80).vertices.col(node).normalized();
    for (const auto& p : {Params(0.0, 1.0, 0.0, 0.0), Params(1.0, 0.0, 0.0, 0.0), kMixed}) {
      const Vector3d f = ReactionOnDisplacedNode(p, node, 0.2 * edge);
      EXPECT_GT(f.dot(outward), 0.95 * f.norm()) << node;  // outwards, along the normal
    }
    // A bulge opens the node's own angle (d < 0); its neighbours' angles close (d > 0), so
    // minus-side parameters alone test the own term's sign on that side.
    for (const auto& p : {Params(0.0, 0.0, 0.0, 1.0), Params(0.0, 0.0, 1.0, 0.0), kMixed}) {
      const Vector3d f = ReactionOnDisplacedNode(p, node, -0.2 * edge);
      EXPECT_LT(f.dot(outward), -0.95 * f.norm()) << node;  // inwards
    }
    // The γ term grows like d², the σ term like d: doubling the dent ~ ×4 and ×2.
    const double sigma1 = ReactionOnDisplacedNode(Params(0, 1, 0, 0), node, 0.05 * edge).norm();
    const double sigma2 = ReactionOnDisplacedNode(Params(0, 1, 0, 0), node, 0.1 * edge).norm();
    const double gamma1 = ReactionOnDisplacedNode(Params(1, 0, 0, 0), node, 0.05 * edge).norm();
    const double gamma2 = ReactionOnDisplacedNode(Params(1, 0, 0, 0), node, 0.1 * edge).norm();
    EXPECT_NEAR(sigma2 / sigma1, 2.0, 0.2);
    EXPECT_NEAR(gamma2 / gamma1, 4.0, 0.6);
  }
}

TEST(SolidAngleVolume, OwnGradientFollowsTheNormalOfTheNeighboursPlane) {
  // ∂Ω_i/∂x_i (by differences of SolidAngle) against the inward normal of the ring's plane
  // (the ring polygon's area vector: the ring is clockwise seen from outside).
  const mesh::SurfaceMesh sphere = Sphere(80);
  const auto term = SolidAngleVolumeTerm::Build(sphere, kMixed);
  const double h = 1e-7 * MeanEdge(sphere);
  double worst_cos = 1.0;
  for (int32_t v = 0; v < term.num_terms(); ++v) {
    mesh::Points x = sphere.vertices;
    Vector3d gradient;
    for (int axis = 0; axis < 3; ++axis) {
      x(axis, v) += h;
      const double plus = term.SolidAngle(x, v);
      x(axis, v) -= 2 * h;
      const double minus = term.SolidAngle(x, v);
      x(axis, v) += h;
      gradient[axis] = (plus - minus) / (2 * h);
    }
    const std::vector<int32_t> ring = term.Ring(v);
    Vector3d area = Vector3d::Zero();
    for (size_t j = 0; j < ring.size(); ++j) {
      area += x.col(ring[j]).cross(x.col(ring[(j + 1) % ring.size()]));
    }
    worst_cos = std::min(worst_cos, gradient.normalized().dot(area.normalized()));
    EXPECT_LT(area.dot(x.col(v)), 0.0);  // inward
  }
  EXPECT_GT(worst_cos, 0.9999);  // measured 0.999991 (0.24°)
  // Exactly along the axis for a regular ring.
  const mesh::SurfaceMesh pyramid = Pyramid(7, 1.1);
  const auto pyramid_term = SolidAngleVolumeTerm::Build(pyramid, kMixed);
  mesh::Points x = pyramid.vertices;
  x(2, 0) = 0.05;  // apex pulled out along the axis: a regular ring still
  const Vector3d f = Forces(pyramid_term, x).col(0);
  EXPECT_GT(f.norm(), 0.0);
  EXPECT_LT(f.head<2>().norm(), 1e-12 * f.norm());
  EXPECT_LT(f.z(), 0.0);
}

TEST(SolidAngleVolume, LocalStiffnessIsTheEnergyHessianBlock) {
  const mesh::SurfaceMesh sphere = Sphere(50);
  const double edge = MeanEdge(sphere);
  mesh::Points x = sphere.vertices;
  Perturb(&x, 0.15 * edge, 11);
  const auto term = SolidAngleVolumeTerm::Build(sphere, kMixed);
  for (const int32_t node : {0, 13, 31}) {
    const Matrix3d k = term.LocalStiffness(x, node);
    EXPECT_LT((k - k.transpose()).norm(), 1e-14 * k.norm());
    const double h = 1e-4 * edge;
    Matrix3d hessian;
    for (int a = 0; a < 3; ++a) {
      for (int b = 0; b < 3; ++b) {
        double sum = 0.0;
        for (const int sa : {-1, 1}) {
          for (const int sb : {-1, 1}) {
            mesh::Points y = x;
            y(a, node) += sa * h;
            y(b, node) += sb * h;
            sum += sa * sb * term.Energy(y);
          }
        }
        hessian(a, b) = sum / (4 * h * h);
      }
    }
    EXPECT_LT((k - hessian).norm(), 1e-5 * k.norm()) << node << "\n" << k << "\n" << hessian;
  }
  // Near rest: positive semi-definite, and zero off the surface.
  const auto rest = SolidAngleVolumeTerm::Build(sphere, Params(0.0, 1.0, 0.0, 1.0));
  const Matrix3d k0 = rest.LocalStiffness(sphere.vertices, 4);
  const Eigen::SelfAdjointEigenSolver<Matrix3d> eigen(k0);
  EXPECT_GT(eigen.eigenvalues().maxCoeff(), 0.0);
  EXPECT_GT(eigen.eigenvalues().minCoeff(), -1e-7 * eigen.eigenvalues().maxCoeff());
}

TEST(SolidAngleVolume, SubsetOfALargerModelsNodes) {
  const mesh::SurfaceMesh sphere = Sphere(50);
  const int extra = 5;
  mesh::Points points = mesh::Points::Zero(3, sphere.vertices.cols() + 2 * extra);
  points.middleCols(extra, sphere.vertices.cols()) = sphere.vertices;
  const mesh::Triangles triangles = sphere.triangles.array() + extra;
  const auto subset = SolidAngleVolumeTerm::Build(points, triangles, kMixed);
  const auto plain = SolidAngleVolumeTerm::Build(sphere, kMixed);
  EXPECT_EQ(subset.num_points(), 60);
  EXPECT_EQ(subset.num_terms(), 50);
  EXPECT_FALSE(subset.HasTerm(0));
  EXPECT_FALSE(subset.HasTerm(59));
  EXPECT_TRUE(subset.HasTerm(extra));
  EXPECT_THROW(subset.SolidAngle(points, 2), std::out_of_range);
  EXPECT_EQ(subset.LocalStiffness(points, 2), Matrix3d::Zero());
  mesh::Points x = points;
  Perturb(&x, 0.001, 12);
  const mesh::Points plain_x = x.middleCols(extra, sphere.vertices.cols());
  EXPECT_EQ(subset.Energy(x), plain.Energy(plain_x));
  const mesh::Points forces = Forces(subset, x);
  EXPECT_EQ(forces.leftCols(extra).cwiseAbs().maxCoeff(), 0.0);
  EXPECT_EQ(forces.rightCols(extra).cwiseAbs().maxCoeff(), 0.0);
  EXPECT_EQ(forces.middleCols(extra, 50), Forces(plain, plain_x));
}

TEST(SolidAngleVolume, EvaluationAllocatesNothing) {
  const mesh::SurfaceMesh sphere = Sphere(50);
  const auto term = SolidAngleVolumeTerm::Build(sphere, kMixed);
  mesh::Points x = sphere.vertices;
  Perturb(&x, 0.001, 13);
  mesh::Points forces = mesh::Points::Zero(3, x.cols());
  double energy = 0.0;
  Matrix3d k;
  {
    const testing::AllocationCounter counter;
    energy = term.Energy(x);
    term.AddForces(x, &forces);
    k = term.LocalStiffness(x, 7);
    EXPECT_EQ(counter.count(), 0);
  }
  EXPECT_GT(energy, 0.0);
  EXPECT_GT(forces.norm(), 0.0);
  EXPECT_GT(k.norm(), 0.0);
}

void ExpectRefused(const std::function<void()>& build, const std::string& fragment) {
  try {
    build();
    ADD_FAILURE() << "accepted; expected a refusal naming \"" << fragment << "\"";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find(fragment), std::string::npos) << e.what();
    EXPECT_EQ(std::string(e.what()).rfind("solid-angle volume: ", 0), 0u) << e.what();
  }
}

TEST(SolidAngleVolume, RefusesBadParametersByName) {
  const mesh::SurfaceMesh tet = Tetrahedron();
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  ExpectRefused([&] { SolidAngleVolumeTerm::Build(tet, Params(-1, 0, 0, 0)); }, "gamma_plus");
  ExpectRefused([&] { SolidAngleVolumeTerm::Build(tet, Params(0, nan, 0, 0)); }, "sigma_plus");
  ExpectRefused([&] { SolidAngleVolumeTerm::Build(tet, Params(0, 0, inf, 0)); }, "gamma_minus");
  ExpectRefused([&] { SolidAngleVolumeTerm::Build(tet, Params(0, 0, 0, -0.1)); }, "sigma_minus");
  EXPECT_NO_THROW(SolidAngleVolumeTerm::Build(tet, Params(0, 0, 0, 0)));
}

TEST(SolidAngleVolume, RefusesBadSurfacesNamingTheFault) {
  const mesh::SurfaceMesh cube = CubeWithFaceCentres();
  const auto with = [](mesh::SurfaceMesh s, const std::function<void(mesh::SurfaceMesh*)>& edit) {
    edit(&s);
    return s;
  };
  const auto refuse = [](const mesh::SurfaceMesh& s, const std::string& fragment) {
    ExpectRefused([&] { SolidAngleVolumeTerm::Build(s, kMixed); }, fragment);
  };
  refuse(with(cube, [](mesh::SurfaceMesh* s) { s->triangles.resize(3, 0); }), "no triangles");
  refuse(with(cube, [](mesh::SurfaceMesh* s) { s->triangles.conservativeResize(3, 23); }),
         "one side only");
  refuse(
      with(cube, [](mesh::SurfaceMesh* s) { std::swap(s->triangles(1, 5), s->triangles(2, 5)); }),
      "twice in the same direction");
  refuse(with(cube,
              [](mesh::SurfaceMesh* s) {
                s->triangles.conservativeResize(3, 25);
                s->triangles.col(24) = s->triangles.col(0);
              }),
         "twice in the same direction");
  refuse(with(cube, [](mesh::SurfaceMesh* s) { s->triangles(0, 3) = 14; }), "out of range");
  refuse(with(cube, [](mesh::SurfaceMesh* s) { s->triangles(0, 3) = -1; }), "out of range");
  refuse(with(cube, [](mesh::SurfaceMesh* s) { s->triangles(1, 3) = s->triangles(0, 3); }),
         "repeats node");
  refuse(with(cube, [](mesh::SurfaceMesh* s) { s->vertices(1, 2) = std::nan(""); }),
         "vertex 2 is not finite");
  // Two tetrahedra touching at one vertex: a non-manifold vertex.
  const mesh::SurfaceMesh tet = Tetrahedron();
  mesh::SurfaceMesh bowtie;
  bowtie.vertices.resize(3, 7);
  bowtie.vertices << tet.vertices, -tet.vertices.rightCols(3);
  bowtie.triangles.resize(3, 8);
  mesh::Triangles second = tet.triangles.array() + 3;
  for (Eigen::Index t = 0; t < 4; ++t) {
    for (int k = 0; k < 3; ++k) {
      if (second(k, t) == 3) second(k, t) = 0;
    }
  }
  bowtie.triangles << tet.triangles, second;
  refuse(bowtie, "more than one fan");
  // Two triangles back to back.
  mesh::SurfaceMesh pillow;
  pillow.vertices = tet.vertices.leftCols(3);
  pillow.triangles.resize(3, 2);
  pillow.triangles << 0, 0, 1, 2, 2, 1;
  refuse(pillow, "only 2 neighbours");
  // Degenerate geometry at rest.
  refuse(with(tet, [](mesh::SurfaceMesh* s) { s->vertices.col(3) = s->vertices.col(0); }),
         "at the node's position");
  refuse(with(tet, [](mesh::SurfaceMesh* s) { s->vertices.col(3) = Vector3d(2, 0, 0); }),
         "in line with it");
}

}  // namespace
}  // namespace somasim::models
