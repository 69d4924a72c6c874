#include "common/mesh_gen/closed_surface_mesher.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_gen/implicit.h"
#include "common/mesh_gen/sphere_layout.h"

namespace somasim::mesh_gen {
namespace {

using Eigen::Vector3d;
constexpr double kPi = std::numbers::pi;

// Polynomial smooth minimum with blend width k (Quilez, "smooth minimum", 2013).
double SmoothMin(double a, double b, double k) {
  const double h = std::clamp(0.5 + 0.5 * (b - a) / k, 0.0, 1.0);
  return b + (a - b) * h - k * h * (1.0 - h);
}

class Sphere final : public ImplicitSolid {
 public:
  Sphere(const Vector3d& centre, double radius) : centre_(centre), radius_(radius) {}
  // Plain scalar arithmetic: Eigen expressions are slow in the unoptimised sanitizer build.
  double Value(const Vector3d& p) const override {
    const double dx = p.x() - centre_.x();
    const double dy = p.y() - centre_.y();
    const double dz = p.z() - centre_.z();
    return std::sqrt(dx * dx + dy * dy + dz * dz) - radius_;
  }
  mesh::BoundingBox Bounds() const override {
    return {centre_ - Vector3d::Constant(radius_), centre_ + Vector3d::Constant(radius_), false};
  }

 private:
  Vector3d centre_;
  double radius_;
};

// An ellipsoid with semi-axes r along the columns of `rotation`, Value as for Ellipsoid, in
// plain scalar arithmetic (Eigen expressions are slow in the unoptimised sanitizer build).
class OrientedEllipsoid final : public ImplicitSolid {
 public:
  OrientedEllipsoid(const Vector3d& centre, const Eigen::Matrix3d& rotation,
                    const Vector3d& semi_axes)
      : centre_(centre), rotation_(rotation), semi_axes_(semi_axes) {}
  double Value(const Vector3d& p) const override {
    const double d[3] = {p.x() - centre_.x(), p.y() - centre_.y(), p.z() - centre_.z()};
    double sum = 0.0;
    for (int i = 0; i < 3; ++i) {
      const double local =
          (d[0] * rotation_(0, i) + d[1] * rotation_(1, i) + d[2] * rotation_(2, i)) /
          semi_axes_[i];
      sum += local * local;
    }
    return (std::sqrt(sum) - 1.0) * semi_axes_.minCoeff();
  }
  mesh::BoundingBox Bounds() const override {
    // Half-extent along world axis j: |row j of rotation · diag(semi_axes)|.
    const Vector3d half = (rotation_ * semi_axes_.asDiagonal()).rowwise().norm();
    return {centre_ - half, centre_ + half, false};
  }

 private:
  Vector3d centre_;
  Eigen::Matrix3d rotation_;
  Vector3d semi_axes_;
};

// A kidney-like bean: an ellipsoid (5.5 × 3 × 2.5 cm semi-axes) with a spherical dent 1 cm deep
// on its +y side (sphere of radius 3 cm centred 5 cm out), blended over 5 mm. Star-shaped from
// the origin: the rays from the origin tangent to the dent sphere touch it outside the ellipsoid.
class Bean final : public ImplicitSolid {
 public:
  double Value(const Vector3d& p) const override {
    return -SmoothMin(-body_.Value(p), dent_.Value(p), 0.005);
  }
  mesh::BoundingBox Bounds() const override { return body_.Bounds(); }

 private:
  OrientedEllipsoid body_{Vector3d::Zero(), Eigen::Matrix3d::Identity(),
                          Vector3d(0.055, 0.03, 0.025)};
  Sphere dent_{Vector3d(0.0, 0.05, 0.0), 0.03};
};

// A gallbladder-like pear along +x: spheres of radius 2.5 cm at the origin and 1.5 cm at
// x = 4 cm, smoothly united over 1.5 cm. Star-shaped from (1.5 cm, 0, 0).
class Pear final : public ImplicitSolid {
 public:
  double Value(const Vector3d& p) const override {
    return SmoothMin(fundus_.Value(p), neck_.Value(p), 0.015);
  }
  mesh::BoundingBox Bounds() const override {
    return {Vector3d(-0.03, -0.03, -0.03), Vector3d(0.06, 0.03, 0.03), false};
  }

 private:
  Sphere fundus_{Vector3d::Zero(), 0.025};
  Sphere neck_{Vector3d(0.04, 0.0, 0.0), 0.015};
};

// Two disjoint balls: not star-shaped from inside either of them.
class TwoBalls final : public ImplicitSolid {
 public:
  double Value(const Vector3d& p) const override { return std::min(a_.Value(p), b_.Value(p)); }
  mesh::BoundingBox Bounds() const override {
    return {Vector3d(-0.02, -0.02, -0.02), Vector3d(0.08, 0.02, 0.02), false};
  }

 private:
  Sphere a_{Vector3d::Zero(), 0.02};
  Sphere b_{Vector3d(0.06, 0.0, 0.0), 0.02};
};

// A solid whose Bounds() lies: it is everything below z = 0.
class HalfSpace final : public ImplicitSolid {
 public:
  double Value(const Vector3d& p) const override { return p.z(); }
  mesh::BoundingBox Bounds() const override {
    return {Vector3d::Constant(-1.0), Vector3d::Constant(1.0), false};
  }
};

// Semi-axes 6 × 3 × 2 cm along x, y, z, off the origin.
const Vector3d kEllipsoidCentre(0.01, -0.02, 0.005);
const Vector3d kEllipsoidSemiAxes(0.06, 0.03, 0.02);

const OrientedEllipsoid& TestEllipsoid() {
  static const OrientedEllipsoid ellipsoid(kEllipsoidCentre, Eigen::Matrix3d::Identity(),
                                           kEllipsoidSemiAxes);
  return ellipsoid;
}

ClosedSurfaceOptions Options(int n, const Vector3d& centre, const Vector3d& axis) {
  ClosedSurfaceOptions options;
  options.num_vertices = n;
  options.centre = centre;
  options.long_axis = axis;
  return options;
}

ClosedSurfaceOptions EllipsoidOptions(int n) {
  return Options(n, kEllipsoidCentre, Vector3d::UnitX());
}

struct Quality {
  double min_angle_deg = 180.0;
  double edge_ratio = 0.0;  // longest / shortest edge
};

Quality MeasureQuality(const mesh::SurfaceMesh& s) {
  Quality q;
  double shortest = std::numeric_limits<double>::infinity();
  double longest = 0.0;
  for (Eigen::Index t = 0; t < s.triangles.cols(); ++t) {
    for (int k = 0; k < 3; ++k) {
      const Vector3d a = s.vertices.col(s.triangles(k, t));
      const Vector3d b = s.vertices.col(s.triangles((k + 1) % 3, t));
      const Vector3d c = s.vertices.col(s.triangles((k + 2) % 3, t));
      const Vector3d u = b - a;
      const Vector3d v = c - a;
      q.min_angle_deg =
          std::min(q.min_angle_deg, std::atan2(u.cross(v).norm(), u.dot(v)) * 180.0 / kPi);
      shortest = std::min(shortest, u.norm());
      longest = std::max(longest, u.norm());
    }
  }
  q.edge_ratio = longest / shortest;
  return q;
}

// Watertight, manifold, one component, sphere topology, every vertex used, right counts.
void ExpectClosedGenusZero(const mesh::SurfaceMesh& s, int n) {
  ASSERT_EQ(s.vertices.cols(), n);
  ASSERT_EQ(s.triangles.cols(), 2 * n - 4);
  const mesh::SurfaceTopology topo = mesh::AnalyseSurfaceTopology(s);
  EXPECT_TRUE(topo.watertight);
  EXPECT_TRUE(topo.manifold);
  EXPECT_EQ(topo.num_components, 1);
  EXPECT_EQ(topo.euler_characteristic, 2);
  EXPECT_EQ(topo.num_edges, 3 * n - 6);
  std::vector<bool> used(static_cast<size_t>(n), false);
  for (Eigen::Index t = 0; t < s.triangles.cols(); ++t) {
    for (int k = 0; k < 3; ++k) used[static_cast<size_t>(s.triangles(k, t))] = true;
  }
  EXPECT_EQ(std::count(used.begin(), used.end(), false), 0);
}

// Every triangle's normal agrees with the solid's gradient at its centroid.
int CountFoldedTriangles(const ImplicitSolid& solid, const mesh::SurfaceMesh& s) {
  int folded = 0;
  for (Eigen::Index t = 0; t < s.triangles.cols(); ++t) {
    const Vector3d a = s.vertices.col(s.triangles(0, t));
    const Vector3d b = s.vertices.col(s.triangles(1, t));
    const Vector3d c = s.vertices.col(s.triangles(2, t));
    const Vector3d normal = (b - a).cross(c - a);
    if (!(normal.dot(ImplicitGradient(solid, (a + b + c) / 3.0)) > 0.0)) ++folded;
  }
  return folded;
}

// Triangles not counter-clockwise seen from `centre` (0 for a mesh star-shaped from it).
int CountTrianglesFacingTheCentre(const mesh::SurfaceMesh& s, const Vector3d& centre) {
  int facing = 0;
  for (Eigen::Index t = 0; t < s.triangles.cols(); ++t) {
    const Vector3d a = s.vertices.col(s.triangles(0, t)) - centre;
    const Vector3d b = s.vertices.col(s.triangles(1, t)) - centre;
    const Vector3d c = s.vertices.col(s.triangles(2, t)) - centre;
    if (!(a.dot(b.cross(c)) > 0.0)) ++facing;
  }
  return facing;
}

double MaxAbsValue(const ImplicitSolid& solid, const mesh::SurfaceMesh& s) {
  double worst = 0.0;
  for (Eigen::Index i = 0; i < s.vertices.cols(); ++i) {
    worst = std::max(worst, std::abs(solid.Value(s.vertices.col(i))));
  }
  return worst;
}

// Meshes shared by several tests (computed once: the mesher is slow under the sanitizers).
const mesh::SurfaceMesh& EllipsoidMesh600() {
  static const mesh::SurfaceMesh mesh = MeshClosedSurface(TestEllipsoid(), EllipsoidOptions(600));
  return mesh;
}

const Pear& ThePear() {
  static const Pear pear;
  return pear;
}

ClosedSurfaceOptions PearOptions(int n) {
  return Options(n, Vector3d(0.015, 0.0, 0.0), Vector3d::UnitX());
}

const mesh::SurfaceMesh& PearMesh300() {
  static const mesh::SurfaceMesh mesh = MeshClosedSurface(ThePear(), PearOptions(300));
  return mesh;
}

const Bean& TheBean() {
  static const Bean bean;
  return bean;
}

const mesh::SurfaceMesh& BeanMesh300() {
  static const mesh::SurfaceMesh mesh =
      MeshClosedSurface(TheBean(), Options(300, Vector3d::Zero(), Vector3d::UnitX()));
  return mesh;
}

TEST(ClosedSurfaceMesher, HasExactlyNVerticesAnd2NMinus4Triangles) {
  const Sphere sphere(Vector3d(0.001, 0.002, -0.003), 0.03);
  for (int n : {4, 5, 6, 7, 8, 10, 11, 33, 100}) {
    SCOPED_TRACE("N = " + std::to_string(n));
    const mesh::SurfaceMesh s =
        MeshClosedSurface(sphere, Options(n, Vector3d(0.001, 0.002, -0.003), Vector3d::UnitZ()));
    ExpectClosedGenusZero(s, n);
    EXPECT_EQ(CountFoldedTriangles(sphere, s), 0);
    EXPECT_GT(mesh::SurfaceEnclosedVolume(s), 0.0);
    EXPECT_LT(MaxAbsValue(sphere, s), 1e-10);
  }
}

TEST(ClosedSurfaceMesher, CoarseElongatedMeshesStayValid) {
  // Few vertices on a 3:1 ellipsoid (implicit.h's class): triangles far coarser than the
  // curvature at the tips.
  const Ellipsoid ellipsoid(kEllipsoidCentre, kEllipsoidSemiAxes);
  for (int n : {4, 5, 7, 10, 16, 30}) {
    SCOPED_TRACE("N = " + std::to_string(n));
    const mesh::SurfaceMesh s = MeshClosedSurface(ellipsoid, EllipsoidOptions(n));
    ExpectClosedGenusZero(s, n);
    EXPECT_EQ(CountFoldedTriangles(ellipsoid, s), 0);
    EXPECT_GT(mesh::SurfaceEnclosedVolume(s), 0.0);
    EXPECT_LT(MaxAbsValue(ellipsoid, s), 1e-10);
  }
}

TEST(ClosedSurfaceMesher, EllipsoidIsClosedOutwardAndOnTheSurface) {
  const mesh::SurfaceMesh& s = EllipsoidMesh600();
  ExpectClosedGenusZero(s, 600);
  EXPECT_EQ(CountFoldedTriangles(TestEllipsoid(), s), 0);
  EXPECT_LT(MaxAbsValue(TestEllipsoid(), s), 1e-10);
}

TEST(ClosedSurfaceMesher, KidneySizedCountIsExact) {
  // The kidney's 2000 vertices, on a sphere with few sweeps to stay quick under the sanitizers.
  const Sphere sphere(Vector3d::Zero(), 0.03);
  ClosedSurfaceOptions options = Options(2000, Vector3d::Zero(), Vector3d::UnitX());
  options.smoothing_iterations = 2;
  const mesh::SurfaceMesh s = MeshClosedSurface(sphere, options);
  ExpectClosedGenusZero(s, 2000);
  EXPECT_EQ(CountFoldedTriangles(sphere, s), 0);
  EXPECT_LT(MaxAbsValue(sphere, s), 1e-10);
  EXPECT_GE(MeasureQuality(s).min_angle_deg, 30.0);
}

TEST(ClosedSurfaceMesher, EnclosedVolumeMatchesAnalyticVolume) {
  // An inscribed polyhedron: a little less than the solid, by about 1.3 % for this 3:1.5:1
  // ellipsoid at 600 vertices (the sharp curvature of its 2 cm axis costs most).
  const double ellipsoid_volume = 4.0 / 3.0 * kPi * 0.06 * 0.03 * 0.02;
  const double ellipsoid_mesh = mesh::SurfaceEnclosedVolume(EllipsoidMesh600());
  EXPECT_NEAR(ellipsoid_mesh / ellipsoid_volume, 1.0, 0.015);
  EXPECT_LT(ellipsoid_mesh, ellipsoid_volume);

  const Sphere sphere(Vector3d::Zero(), 0.03);
  const double sphere_volume = 4.0 / 3.0 * kPi * std::pow(0.03, 3);
  // Few sweeps (quick under the sanitizers): the volume hardly depends on them.
  ClosedSurfaceOptions options = Options(600, Vector3d::Zero(), Vector3d::UnitX());
  options.smoothing_iterations = 5;
  const double sphere_mesh = mesh::SurfaceEnclosedVolume(MeshClosedSurface(sphere, options));
  EXPECT_NEAR(sphere_mesh / sphere_volume, 1.0, 0.01);
  EXPECT_LT(sphere_mesh, sphere_volume);
}

TEST(ClosedSurfaceMesher, EllipsoidTrianglesAreWellShaped) {
  const Quality q = MeasureQuality(EllipsoidMesh600());
  EXPECT_GE(q.min_angle_deg, 30.0);
  EXPECT_LT(q.edge_ratio, 2.5);
}

TEST(ClosedSurfaceMesher, PearIsClosedOutwardAndWellShaped) {
  const mesh::SurfaceMesh& s = PearMesh300();
  ExpectClosedGenusZero(s, 300);
  EXPECT_EQ(CountFoldedTriangles(ThePear(), s), 0);
  EXPECT_LT(MaxAbsValue(ThePear(), s), 1e-10);
  EXPECT_GT(mesh::SurfaceEnclosedVolume(s), 0.0);
  const Quality q = MeasureQuality(s);
  EXPECT_GE(q.min_angle_deg, 30.0);
  EXPECT_LT(q.edge_ratio, 2.5);
}

TEST(ClosedSurfaceMesher, BeanFollowsTheConcaveHilum) {
  const Bean& bean = TheBean();
  const mesh::SurfaceMesh& s = BeanMesh300();
  ExpectClosedGenusZero(s, 300);
  EXPECT_EQ(CountFoldedTriangles(bean, s), 0);
  EXPECT_LT(MaxAbsValue(bean, s), 1e-10);
  EXPECT_GT(mesh::SurfaceEnclosedVolume(s), 0.0);
  const Quality q = MeasureQuality(s);
  EXPECT_GE(q.min_angle_deg, 30.0);
  EXPECT_LT(q.edge_ratio, 2.5);
  // The dent's floor is at y = 2 cm (the ellipsoid alone reaches 3 cm): the vertices above its
  // centre sit in the dent, the highest near its floor.
  double highest_over_dent = -1.0;
  for (Eigen::Index i = 0; i < s.vertices.cols(); ++i) {
    const Vector3d p = s.vertices.col(i);
    if (std::hypot(p.x(), p.z()) < 0.005 && p.y() > 0.0) {
      highest_over_dent = std::max(highest_over_dent, p.y());
    }
  }
  EXPECT_GT(highest_over_dent, 0.019);
  EXPECT_LT(highest_over_dent, 0.022);
}

TEST(ClosedSurfaceMesher, FollowsAnObliqueLongAxis) {
  const Eigen::Matrix3d rotation =
      Eigen::AngleAxisd(0.7, Vector3d(1.0, 2.0, 3.0).normalized()).toRotationMatrix();
  const OrientedEllipsoid oblique(Vector3d::Zero(), rotation, Vector3d(0.06, 0.03, 0.02));
  const Vector3d axis = rotation * Vector3d::UnitX();
  ClosedSurfaceOptions options = Options(300, Vector3d::Zero(), axis);
  options.smoothing_iterations = 8;
  const mesh::SurfaceMesh s = MeshClosedSurface(oblique, options);
  ExpectClosedGenusZero(s, 300);
  EXPECT_EQ(CountFoldedTriangles(oblique, s), 0);
  EXPECT_LT(MaxAbsValue(oblique, s), 1e-10);
  EXPECT_NEAR(mesh::SurfaceEnclosedVolume(s) / (4.0 / 3.0 * kPi * 0.06 * 0.03 * 0.02), 1.0, 0.03);
  EXPECT_GE(MeasureQuality(s).min_angle_deg, 30.0);
}

TEST(ClosedSurfaceMesher, IsDeterministic) {
  const mesh::SurfaceMesh again = MeshClosedSurface(ThePear(), PearOptions(300));
  EXPECT_EQ(again.triangles, PearMesh300().triangles);
  // Bit-identical coordinates, not merely close.
  EXPECT_EQ(again.vertices, PearMesh300().vertices);
}

TEST(ClosedSurfaceMesher, ZeroSmoothingGivesTheMappedLayout) {
  ClosedSurfaceOptions options = EllipsoidOptions(200);
  options.smoothing_iterations = 0;
  const mesh::SurfaceMesh s = MeshClosedSurface(TestEllipsoid(), options);
  ExpectClosedGenusZero(s, 200);
  EXPECT_EQ(CountFoldedTriangles(TestEllipsoid(), s), 0);
  EXPECT_LT(MaxAbsValue(TestEllipsoid(), s), 1e-10);
  // Every vertex lies on the ray from the centre through its layout point, so the mesh is
  // star-shaped from the centre: each triangle is counter-clockwise seen from it.
  EXPECT_EQ(CountTrianglesFacingTheCentre(s, options.centre), 0);
}

TEST(ClosedSurfaceMesher, StaysStarShapedFromTheCentre) {
  // The embedding invariant, after relaxation, on the concave bean and the pear.
  EXPECT_EQ(CountTrianglesFacingTheCentre(BeanMesh300(), Vector3d::Zero()), 0);
  EXPECT_EQ(CountTrianglesFacingTheCentre(PearMesh300(), PearOptions(300).centre), 0);
}

TEST(ClosedSurfaceMesher, SparseMeshSeenObliquelyFromTheCentreStaysValid) {
  // From this off-axis centre the pear's long neck is seen very obliquely: with few vertices
  // the surface-fitted layout would be tangled (a triangle inverted as seen from the centre),
  // and the mesher must fall back to the latitude layout.
  const Vector3d centre(0.008, 0.004, -0.003);
  for (int n : {26, 27, 81}) {
    SCOPED_TRACE("N = " + std::to_string(n));
    const mesh::SurfaceMesh s = MeshClosedSurface(ThePear(), Options(n, centre, Vector3d::UnitX()));
    ExpectClosedGenusZero(s, n);
    EXPECT_EQ(CountTrianglesFacingTheCentre(s, centre), 0);
    EXPECT_LT(MaxAbsValue(ThePear(), s), 1e-10);
  }
}

// The layout as a mesh on the unit sphere (vertices = the layout's points).
mesh::SurfaceMesh LayoutMesh(const sphere_layout::SphereLayout& layout) {
  mesh::SurfaceMesh s;
  s.vertices.resize(3, static_cast<Eigen::Index>(layout.points.size()));
  for (size_t i = 0; i < layout.points.size(); ++i) {
    s.vertices.col(static_cast<Eigen::Index>(i)) = layout.points[i];
  }
  s.triangles.resize(3, static_cast<Eigen::Index>(layout.triangles.size()));
  for (size_t t = 0; t < layout.triangles.size(); ++t) {
    for (size_t k = 0; k < 3; ++k) {
      s.triangles(static_cast<Eigen::Index>(k), static_cast<Eigen::Index>(t)) =
          layout.triangles[t][k];
    }
  }
  return s;
}

TEST(SphereLayout, LatitudeLayoutIsAnEmbeddedSphereWithNPointsAnd2NMinus4Triangles) {
  const sphere_layout::SurfaceProfile profile = sphere_layout::UnitSphereProfile();
  for (int n : {4, 5, 6, 7, 8, 11, 33, 100, 601, 2000}) {
    SCOPED_TRACE("N = " + std::to_string(n));
    const sphere_layout::SphereLayout layout = sphere_layout::MakeSphereLayout(n, profile);
    const mesh::SurfaceMesh s = LayoutMesh(layout);
    ExpectClosedGenusZero(s, n);
    EXPECT_TRUE(sphere_layout::IsRadiallyEmbedded(layout.triangles, layout.points));
    EXPECT_GT(mesh::SurfaceEnclosedVolume(s), 0.0);
    for (const Vector3d& u : layout.points) EXPECT_NEAR(u.norm(), 1.0, 1e-12);
  }
}

TEST(SphereLayout, SurfaceFittedLayoutOfAnEllipsoidIsRadiallyEmbedded) {
  // The layout stage of MeshClosedSurface on the 6 × 3 × 2 cm ellipsoid: rays land on the
  // surface, the measured profile's area is close to the ellipsoid's (an inscribed polyhedron
  // of 32 × 16 rays: a little less), and the fitted layout stays embedded along its rays.
  const OrientedEllipsoid& ellipsoid = TestEllipsoid();
  const sphere_layout::Frame frame = sphere_layout::MakeFrame(Vector3d::UnitX());
  const sphere_layout::RayCaster caster(ellipsoid, kEllipsoidCentre);
  sphere_layout::OctantEllipsoid shape{};
  for (size_t axis = 0; axis < 3; ++axis) {
    const Vector3d direction = frame.ToWorld(Vector3d::Unit(static_cast<Eigen::Index>(axis)));
    const Vector3d plus = caster.Cast(direction);
    const Vector3d minus = caster.Cast(-direction);
    EXPECT_LT(std::abs(ellipsoid.Value(plus)), 1e-10);
    EXPECT_LT(std::abs(ellipsoid.Value(minus)), 1e-10);
    shape.plus[axis] = (plus - kEllipsoidCentre).norm();
    shape.minus[axis] = (minus - kEllipsoidCentre).norm();
    // The frame's axes are the ellipsoid's, so the reach is the semi-axis both ways.
    EXPECT_NEAR(shape.plus[axis], kEllipsoidSemiAxes[static_cast<Eigen::Index>(axis)], 1e-9);
    EXPECT_NEAR(shape.minus[axis], kEllipsoidSemiAxes[static_cast<Eigen::Index>(axis)], 1e-9);
  }
  const sphere_layout::SurfaceProfile profile = sphere_layout::MeasureProfile(caster, frame, shape);
  // Surface area of the ellipsoid by Thomsen's formula (relative error below 1.1 %).
  constexpr double kP = 1.6075;
  const double a = std::pow(0.06, kP);
  const double b = std::pow(0.03, kP);
  const double c = std::pow(0.02, kP);
  const double area = 4.0 * kPi * std::pow((a * b + a * c + b * c) / 3.0, 1.0 / kP);
  EXPECT_NEAR(profile.area / area, 1.0, 0.02);
  for (int n : {20, 200, 600}) {
    SCOPED_TRACE("N = " + std::to_string(n));
    const sphere_layout::SphereLayout layout = sphere_layout::MakeSphereLayout(n, profile);
    ExpectClosedGenusZero(LayoutMesh(layout), n);
    std::vector<Vector3d> directions;
    for (const Vector3d& u : layout.points) {
      directions.push_back(sphere_layout::RayDirection(frame, shape, u));
    }
    EXPECT_TRUE(sphere_layout::IsRadiallyEmbedded(layout.triangles, directions));
  }
}

// The message of the std::invalid_argument that `f` throws ("" and a failure if none).
template <typename F>
std::string InvalidArgumentMessage(F&& f) {
  try {
    f();
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  ADD_FAILURE() << "no std::invalid_argument";
  return "";
}

TEST(ClosedSurfaceMesher, RefusesBadOptionsNamingTheField) {
  const ImplicitSolid& solid = TestEllipsoid();
  auto message = [&](const ClosedSurfaceOptions& options) {
    return InvalidArgumentMessage([&] { MeshClosedSurface(solid, options); });
  };
  ClosedSurfaceOptions options = EllipsoidOptions(3);
  EXPECT_NE(message(options).find("num_vertices"), std::string::npos);
  options = EllipsoidOptions(-5);
  EXPECT_NE(message(options).find("num_vertices"), std::string::npos);

  options = EllipsoidOptions(100);
  options.long_axis = Vector3d::Zero();
  EXPECT_NE(message(options).find("long_axis"), std::string::npos);
  options.long_axis = Vector3d(1.0, 1.0, 0.0);
  EXPECT_NE(message(options).find("long_axis"), std::string::npos);
  options.long_axis = Vector3d(std::nan(""), 0.0, 0.0);
  EXPECT_NE(message(options).find("long_axis"), std::string::npos);

  options = EllipsoidOptions(100);
  options.centre.y() = std::nan("");
  EXPECT_NE(message(options).find("centre"), std::string::npos);
  options.centre = Vector3d(0.1, 0.0, 0.0);  // outside the ellipsoid
  EXPECT_NE(message(options).find("centre"), std::string::npos);

  options = EllipsoidOptions(100);
  options.smoothing_iterations = -1;
  EXPECT_NE(message(options).find("smoothing_iterations"), std::string::npos);
}

TEST(ClosedSurfaceMesher, RefusesSolidsThatAreNotStarShapedFromTheCentre) {
  const TwoBalls two_balls;
  const std::string re_entry = InvalidArgumentMessage(
      [&] { MeshClosedSurface(two_balls, Options(100, Vector3d::Zero(), Vector3d::UnitX())); });
  EXPECT_NE(re_entry.find("star-shaped"), std::string::npos) << re_entry;

  const HalfSpace half_space;
  const std::string no_exit = InvalidArgumentMessage([&] {
    MeshClosedSurface(half_space, Options(100, Vector3d(0.0, 0.0, -0.5), Vector3d::UnitX()));
  });
  EXPECT_NE(no_exit.find("no surface crossing"), std::string::npos) << no_exit;
}

}  // namespace
}  // namespace somasim::mesh_gen
