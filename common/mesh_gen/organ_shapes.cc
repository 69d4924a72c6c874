#include "common/mesh_gen/organ_shapes.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cassert>
#include <cmath>
#include <numbers>

namespace somasim::mesh_gen {
namespace {

using Eigen::Vector3d;

constexpr double kCm = 0.01;  // [m]

Eigen::Matrix3d RotationDegrees(double about_x, double about_y, double about_z) {
  constexpr double kRad = std::numbers::pi / 180.0;
  return (Eigen::AngleAxisd(about_z * kRad, Vector3d::UnitZ()) *
          Eigen::AngleAxisd(about_y * kRad, Vector3d::UnitY()) *
          Eigen::AngleAxisd(about_x * kRad, Vector3d::UnitX()))
      .toRotationMatrix();
}

mesh::BoundingBox Box(const Vector3d& min, const Vector3d& max) {
  mesh::BoundingBox box;
  box.min = min;
  box.max = max;
  box.empty = false;
  return box;
}

// Liver, in patient coordinates (DICOM LPS: +x towards the patient's left, +y posterior, +z
// cranial). A thick, domed right lobe and a thin left lobe tapering to the left, blended; a
// tilted plane cuts the sharp anterior-inferior border, a large ellipsoid hollows the visceral
// (inferior) surface, and a notch marks the ligamentum teres between the lobes.
class LiverSolid final : public ImplicitSolid {
 public:
  double Value(const Vector3d& p) const override {
    const double right =
        EllipsoidValue(p, Vector3d(-4.0, 0.5, 0.0) * kCm, Vector3d(7.0, 7.0, 7.0) * kCm);
    const double left = EllipsoidValue(p, Vector3d(5.0, 0.5, 2.0) * kCm,
                                       Vector3d(7.5, 5.5, 2.6) * kCm, RotationDegrees(0, 12, 8));
    double value = SmoothMin(right, left, 3.0 * kCm);
    // Anterior-inferior border: the half-space below a plane tilted 40° from horizontal.
    const Vector3d border_normal = Vector3d(0.0, -0.64, -0.77).normalized();
    const double border = border_normal.dot(p - Vector3d(0.0, -2.0, -2.5) * kCm);
    value = SmoothMax(value, border, 2.0 * kCm);
    // Visceral surface: an ellipsoid below and behind carves the concave underside.
    const double visceral =
        EllipsoidValue(p, Vector3d(-1.0, 2.5, -12.0) * kCm, Vector3d(10.0, 8.0, 7.0) * kCm);
    value = SmoothMax(value, -visceral, 2.0 * kCm);
    // Notch on the anterior-inferior border between the lobes.
    const double notch =
        EllipsoidValue(p, Vector3d(1.5, -5.0, -2.5) * kCm, Vector3d(1.0, 2.5, 2.5) * kCm);
    return SmoothMax(value, -notch, 1.0 * kCm);
  }
  mesh::BoundingBox Bounds() const override {
    return Box(Vector3d(-12.0, -8.0, -8.0) * kCm, Vector3d(14.0, 8.5, 8.0) * kCm);
  }
};

// Kidney: an ellipsoid 11.5 × 6 × 4.5 cm bent into a bean (its medial side concave), with the
// renal hilum as a smooth dent in the middle of the medial side (−y).
class KidneySolid final : public ImplicitSolid {
 public:
  double Value(const Vector3d& p) const override {
    // Bend: the ellipsoid is evaluated in coordinates where y is shifted by a parabola in x.
    const double bend = 6.0;  // [1/m]: the poles bend 2 cm towards -y, the hilum side
    const Vector3d q(p.x(), p.y() + bend * p.x() * p.x(), p.z());
    const double body = EllipsoidValue(q, Vector3d(0.0, 0.0, 0.0), Vector3d(5.75, 3.0, 2.25) * kCm);
    const double hilum =
        EllipsoidValue(p, Vector3d(0.0, -3.2, 0.0) * kCm, Vector3d(1.6, 1.2, 1.1) * kCm);
    return SmoothMax(body, -hilum, 0.8 * kCm);
  }
  mesh::BoundingBox Bounds() const override {
    return Box(Vector3d(-6.5, -5.0, -3.0) * kCm, Vector3d(6.5, 4.0, 3.0) * kCm);
  }
};

// Spleen: a flattened ellipsoid 12 × 7 × 3.6 cm curved around the stomach (concave visceral
// side towards −z), with a shallow hilar groove.
class SpleenSolid final : public ImplicitSolid {
 public:
  double Value(const Vector3d& p) const override {
    const double bend = 4.5;  // [1/m]: the poles rise 1.6 cm towards +z
    const Vector3d q(p.x(), p.y(), p.z() - bend * p.x() * p.x());
    const double body = EllipsoidValue(q, Vector3d::Zero(), Vector3d(6.0, 3.5, 1.8) * kCm);
    const double groove =
        EllipsoidValue(q, Vector3d(0.0, 0.0, -2.2) * kCm, Vector3d(3.5, 0.9, 0.9) * kCm);
    return SmoothMax(body, -groove, 0.6 * kCm);
  }
  mesh::BoundingBox Bounds() const override {
    return Box(Vector3d(-6.5, -4.0, -2.5) * kCm, Vector3d(6.5, 4.0, 4.5) * kCm);
  }
};

// Gallbladder: a pear — a full fundus and body (an ellipsoid 7.2 × 3.3 × 3.1 cm) narrowing
// into a neck (a round cone from r 0.75 cm to r 0.5 cm) turned slightly up, ~9.5 cm in all.
class GallbladderSolid final : public ImplicitSolid {
 public:
  double Value(const Vector3d& p) const override {
    const double body =
        EllipsoidValue(p, Vector3d(-1.0, 0.0, 0.0) * kCm, Vector3d(3.6, 1.65, 1.55) * kCm);
    const double neck = RoundConeValue(p, Vector3d(2.0, 0.0, 0.2) * kCm,
                                       Vector3d(4.3, 0.0, 0.9) * kCm, 0.8 * kCm, 0.5 * kCm);
    return SmoothMin(body, neck, 0.8 * kCm);
  }
  mesh::BoundingBox Bounds() const override {
    return Box(Vector3d(-5.5, -2.5, -2.5) * kCm, Vector3d(5.5, 2.5, 2.5) * kCm);
  }
};

}  // namespace

double SmoothMin(double a, double b, double k) {
  const double h = std::max(k - std::abs(a - b), 0.0) / k;
  return std::min(a, b) - h * h * k * 0.25;
}

double SmoothMax(double a, double b, double k) { return -SmoothMin(-a, -b, k); }

double EllipsoidValue(const Vector3d& p, const Vector3d& centre, const Vector3d& semi_axes,
                      const Eigen::Matrix3d& rotation) {
  const Vector3d local = rotation.transpose() * (p - centre);
  return (local.cwiseQuotient(semi_axes).norm() - 1.0) * semi_axes.minCoeff();
}

double RoundConeValue(const Vector3d& p, const Vector3d& a, const Vector3d& b, double ra,
                      double rb) {
  // Inigo Quilez, "distance functions" (round cone, arbitrary endpoints).
  const Vector3d ba = b - a;
  const double l2 = ba.squaredNorm();
  const double rr = ra - rb;
  const double a2 = l2 - rr * rr;
  const double il2 = 1.0 / l2;
  const Vector3d pa = p - a;
  const double y = pa.dot(ba);
  const double z = y - l2;
  const double x2 = (pa * l2 - ba * y).squaredNorm();
  const double y2 = y * y * l2;
  const double z2 = z * z * l2;
  const double k = std::copysign(1.0, rr) * rr * rr * x2;
  if (std::copysign(1.0, z) * a2 * z2 > k) return std::sqrt(x2 + z2) * il2 - rb;
  if (std::copysign(1.0, y) * a2 * y2 < k) return std::sqrt(x2 + y2) * il2 - ra;
  return (std::sqrt(x2 * a2 * il2) + y * rr) * il2 - ra;
}

std::unique_ptr<ImplicitSolid> MakeOrganShape(OrganShape shape) {
  switch (shape) {
    case OrganShape::kLiver:
      return std::make_unique<LiverSolid>();
    case OrganShape::kKidney:
      return std::make_unique<KidneySolid>();
    case OrganShape::kSpleen:
      return std::make_unique<SpleenSolid>();
    case OrganShape::kGallbladder:
      return std::make_unique<GallbladderSolid>();
  }
  assert(false);
  return nullptr;
}

OrganFrame OrganShapeFrame(OrganShape shape) {
  switch (shape) {
    case OrganShape::kLiver:
      return {Vector3d(-2.0, 0.0, 0.5) * kCm, Vector3d::UnitX()};
    case OrganShape::kKidney:
      return {Vector3d(0.0, 0.5, 0.0) * kCm, Vector3d::UnitX()};
    case OrganShape::kSpleen:
      return {Vector3d(0.0, 0.0, 0.3) * kCm, Vector3d::UnitX()};
    case OrganShape::kGallbladder:
      return {Vector3d(1.0, 0.0, 0.25) * kCm, Vector3d::UnitX()};
  }
  assert(false);
  return {};
}

}  // namespace somasim::mesh_gen
