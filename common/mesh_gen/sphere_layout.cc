#include "common/mesh_gen/sphere_layout.h"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <cstddef>
#include <limits>
#include <numbers>
#include <sstream>
#include <stdexcept>

namespace somasim::mesh_gen::sphere_layout {

using Eigen::Vector3d;

namespace {

// Ring sizes proportional to `weights`, each >= 3, summing to `total` (largest remainder).
std::vector<int> RingSizes(const std::vector<double>& weights, int total) {
  double weight_sum = 0.0;
  for (double w : weights) weight_sum += w;
  const size_t rings = weights.size();
  std::vector<double> ideal(rings);
  std::vector<int> sizes(rings);
  int assigned = 0;
  for (size_t k = 0; k < rings; ++k) {
    ideal[k] = total * weights[k] / weight_sum;
    sizes[k] = std::max(3, static_cast<int>(std::floor(ideal[k])));
    assigned += sizes[k];
  }
  // The first ring with the largest (or smallest) remainder ideal − size wins ties.
  while (assigned < total) {
    size_t best = 0;
    for (size_t k = 1; k < rings; ++k) {
      if (ideal[k] - sizes[k] > ideal[best] - sizes[best]) best = k;
    }
    ++sizes[best];
    ++assigned;
  }
  while (assigned > total) {
    size_t best = rings;
    for (size_t k = 0; k < rings; ++k) {
      if (sizes[k] > 3 && (best == rings || ideal[k] - sizes[k] < ideal[best] - sizes[best])) {
        best = k;
      }
    }
    assert(best < rings);
    --sizes[best];
    --assigned;
  }
  return sizes;
}

// A point of the unit sphere in frame coordinates: polar angle θ from e1, azimuth φ from e2.
Vector3d SpherePoint(double theta, double phi) {
  return {std::cos(theta), std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi)};
}

}  // namespace

[[noreturn]] void Fail(const std::string& message) {
  throw std::invalid_argument("MeshClosedSurface: " + message);
}

std::string Format(const Vector3d& v) {
  std::ostringstream text;
  text.precision(6);
  text << '(' << v.x() << ", " << v.y() << ", " << v.z() << ')';
  return text.str();
}

Frame MakeFrame(const Vector3d& long_axis) {
  Frame frame;
  frame.e1 = long_axis.normalized();
  // The coordinate axis least aligned with e1 (first one on ties) gives a well-conditioned e2.
  int least = 0;
  for (int axis = 1; axis < 3; ++axis) {
    if (std::abs(frame.e1[axis]) < std::abs(frame.e1[least])) least = axis;
  }
  const Vector3d helper = Vector3d::Unit(least);
  frame.e2 = (helper - helper.dot(frame.e1) * frame.e1).normalized();
  frame.e3 = frame.e1.cross(frame.e2);
  return frame;
}

RayCaster::RayCaster(const ImplicitSolid& solid, const Vector3d& centre)
    : solid_(solid), centre_(centre) {
  const mesh::BoundingBox bounds = solid.Bounds();
  if (bounds.empty || !bounds.min.allFinite() || !bounds.max.allFinite() ||
      !(bounds.min.array() < bounds.max.array()).all()) {
    Fail("solid.Bounds() is empty or not finite");
  }
  if (!((centre.array() > bounds.min.array()).all() &&
        (centre.array() < bounds.max.array()).all())) {
    Fail("options.centre " + Format(centre) + " lies outside solid.Bounds()");
  }
  // Slightly enlarged so the last sample of a ray is strictly outside the solid.
  const Vector3d margin = Vector3d::Constant(0.01 * (bounds.max - bounds.min).norm());
  box_min_ = bounds.min - margin;
  box_max_ = bounds.max + margin;
  min_step_ = (box_max_ - box_min_).norm() / kRaySamples;
  centre_value_ = solid.Value(centre);
}

Vector3d RayCaster::Cast(const Vector3d& direction) const {
  double exit = std::numeric_limits<double>::infinity();
  for (int axis = 0; axis < 3; ++axis) {
    if (direction[axis] > 0.0) {
      exit = std::min(exit, (box_max_[axis] - centre_[axis]) / direction[axis]);
    } else if (direction[axis] < 0.0) {
      exit = std::min(exit, (box_min_[axis] - centre_[axis]) / direction[axis]);
    }
  }
  bool found = false;
  Vector3d hit = centre_;
  double t = 0.0;
  double value = centre_value_;
  while (t < exit) {
    const double t_next = std::min(t + std::max(0.5 * std::abs(value), min_step_), exit);
    const Vector3d point = centre_ + t_next * direction;
    value = solid_.Value(point);
    if (std::isnan(value)) Fail("solid.Value is NaN at " + Format(point));
    if (!found) {
      if (!(value < 0.0)) {
        hit = FindSegmentRoot(solid_, centre_ + t * direction, point);
        found = true;
      }
    } else if (value < 0.0) {
      Fail("the solid is not star-shaped from options.centre " + Format(centre_) +
           ": the ray towards " + Format(direction) + " re-enters the solid at " + Format(point));
    }
    t = t_next;
  }
  if (!found) {
    Fail("the ray from options.centre " + Format(centre_) + " towards " + Format(direction) +
         " finds no surface crossing inside solid.Bounds()");
  }
  return hit;
}

Vector3d RayDirection(const Frame& frame, const OctantEllipsoid& shape, const Vector3d& u) {
  return frame.ToWorld(shape.Map(u)).normalized();
}

SurfaceProfile MeasureProfile(const RayCaster& caster, const Frame& frame,
                              const OctantEllipsoid& shape) {
  constexpr double kPi = std::numbers::pi;
  SurfaceProfile profile;
  profile.arc.assign(kProfileRows + 1, 0.0);
  profile.perimeter.assign(kProfileRows + 1, 0.0);
  profile.fraction.assign((kProfileRows + 1) * (kProfileColumns + 1), 0.0);
  for (size_t j = 0; j <= kProfileColumns; ++j) {
    profile.fraction[j] = static_cast<double>(j) / kProfileColumns;
  }
  std::vector<Vector3d> previous(kProfileColumns,
                                 caster.Cast(RayDirection(frame, shape, SpherePoint(0.0, 0.0))));
  std::vector<Vector3d> current(kProfileColumns);
  for (int i = 1; i <= kProfileRows; ++i) {
    const double theta = kPi * i / kProfileRows;
    for (size_t j = 0; j < kProfileColumns; ++j) {
      const double phi = 2.0 * kPi * static_cast<double>(j) / kProfileColumns;
      // The last row is the other pole: one point.
      current[j] = (i == kProfileRows && j > 0)
                       ? current[0]
                       : caster.Cast(RayDirection(frame, shape, SpherePoint(theta, phi)));
    }
    double ds = 0.0;
    double perimeter = 0.0;
    for (size_t j = 0; j < kProfileColumns; ++j) {
      ds += (current[j] - previous[j]).norm() / kProfileColumns;
      perimeter += (current[(j + 1) % kProfileColumns] - current[j]).norm();
    }
    const auto row = static_cast<size_t>(i);
    profile.arc[row] = profile.arc[row - 1] + ds;
    profile.perimeter[row] = perimeter;
    double* fraction = &profile.fraction[row * (kProfileColumns + 1)];
    double walked = 0.0;
    for (size_t j = 0; j <= kProfileColumns; ++j) {
      fraction[j] = perimeter > 0.0 ? walked / perimeter : static_cast<double>(j) / kProfileColumns;
      walked += (current[(j + 1) % kProfileColumns] - current[j % kProfileColumns]).norm();
    }
    fraction[kProfileColumns] = 1.0;
    profile.area += 0.5 * (profile.perimeter[row - 1] + perimeter) * ds;
    std::swap(previous, current);
  }
  return profile;
}

SurfaceProfile UnitSphereProfile() {
  constexpr double kPi = std::numbers::pi;
  SurfaceProfile profile;
  profile.arc.resize(kProfileRows + 1);
  profile.perimeter.resize(kProfileRows + 1);
  profile.fraction.resize((kProfileRows + 1) * (kProfileColumns + 1));
  for (size_t i = 0; i <= kProfileRows; ++i) {
    const double theta = kPi * static_cast<double>(i) / kProfileRows;
    profile.arc[i] = theta;
    profile.perimeter[i] = 2.0 * kPi * std::sin(theta);
    for (size_t j = 0; j <= kProfileColumns; ++j) {
      profile.fraction[i * (kProfileColumns + 1) + j] = static_cast<double>(j) / kProfileColumns;
    }
  }
  profile.area = 4.0 * kPi;
  return profile;
}

SphereLayout MakeSphereLayout(int n, const SurfaceProfile& profile) {
  constexpr double kPi = std::numbers::pi;
  const std::vector<double>& arc = profile.arc;
  const double length = arc.back();
  // The polar angle at arc length s, and the row perimeter at a polar angle, by linear
  // interpolation in the profile's table.
  auto theta_at = [&](double s) {
    const auto it = std::lower_bound(arc.begin() + 1, arc.end(), s);
    const auto k = static_cast<size_t>(std::min<std::ptrdiff_t>(it - arc.begin(), kProfileRows));
    const double span = arc[k] - arc[k - 1];
    const double f = span > 0.0 ? std::clamp((s - arc[k - 1]) / span, 0.0, 1.0) : 0.0;
    return kPi * (static_cast<double>(k - 1) + f) / kProfileRows;
  };
  auto perimeter_at = [&](double theta) {
    const double x = std::clamp(theta / kPi * kProfileRows, 0.0, double{kProfileRows});
    const auto k = std::min(static_cast<size_t>(x), size_t{kProfileRows - 1});
    const double f = x - static_cast<double>(k);
    return (1.0 - f) * profile.perimeter[k] + f * profile.perimeter[k + 1];
  };
  // The azimuth φ ∈ [0, 2π) that splits the ring at θ so that a fraction t ∈ [0, 1) of its
  // perimeter lies between φ = 0 and φ: rows' fraction tables interpolated in θ, then inverted.
  auto azimuth_at = [&](double theta, double t) {
    const double x = std::clamp(theta / kPi * kProfileRows, 0.0, double{kProfileRows});
    const auto k = std::min(static_cast<size_t>(x), size_t{kProfileRows - 1});
    const double f = x - static_cast<double>(k);
    const double* lower = &profile.fraction[k * (kProfileColumns + 1)];
    const double* upper = lower + (kProfileColumns + 1);
    auto fraction = [&](size_t j) { return (1.0 - f) * lower[j] + f * upper[j]; };
    size_t j = 0;
    while (j + 1 < kProfileColumns && fraction(j + 1) <= t) ++j;
    const double span = fraction(j + 1) - fraction(j);
    const double within = span > 0.0 ? std::clamp((t - fraction(j)) / span, 0.0, 1.0) : 0.0;
    return 2.0 * kPi * (static_cast<double>(j) + within) / kProfileColumns;
  };

  // Equilateral triangles of equal area: edge h, ring spacing h·√3/2 (the triangle's height).
  const double triangle_area = profile.area / (2.0 * n - 4.0);
  const double edge = std::sqrt(4.0 * triangle_area / std::sqrt(3.0));
  const bool single_pole = (n == 4);
  const int ring_points = single_pole ? n - 1 : n - 2;
  int rings = static_cast<int>(std::lround(length / (edge * std::sqrt(3.0) / 2.0))) - 1;
  rings = std::clamp(rings, 1, ring_points / 3);
  if (single_pole) rings = 1;

  std::vector<double> thetas(static_cast<size_t>(rings));
  std::vector<double> weights(static_cast<size_t>(rings));
  for (int k = 0; k < rings; ++k) {
    // A tetrahedron's ring sits at θ = arccos(−1/3).
    thetas[static_cast<size_t>(k)] =
        single_pole ? std::acos(-1.0 / 3.0) : theta_at(length * (k + 1) / (rings + 1));
    // Tiny floor: a ring never gets a zero share.
    weights[static_cast<size_t>(k)] =
        std::max(perimeter_at(thetas[static_cast<size_t>(k)]), 1e-9 * length);
  }
  const std::vector<int> sizes = RingSizes(weights, ring_points);

  SphereLayout layout;
  layout.points.reserve(static_cast<size_t>(n));
  layout.points.emplace_back(1.0, 0.0, 0.0);
  // first[k]: index of ring k's first point; phis[k]: its points' azimuths, increasing,
  // unwrapped to [phis[k][0], phis[k][0] + 2π). Points split each ring's perimeter evenly, and
  // consecutive rings start a golden-ratio fraction further round so that no seam lines up
  // along the meridians.
  std::vector<int32_t> first(static_cast<size_t>(rings));
  std::vector<std::vector<double>> phis(static_cast<size_t>(rings));
  const double golden_fraction = (3.0 - std::sqrt(5.0)) / 2.0;
  for (int k = 0; k < rings; ++k) {
    const size_t kk = static_cast<size_t>(k);
    first[kk] = static_cast<int32_t>(layout.points.size());
    const double start = std::fmod(golden_fraction * k, 1.0);
    for (int i = 0; i < sizes[kk]; ++i) {
      const double t = start + static_cast<double>(i) / sizes[kk];
      const double turns = std::floor(t);
      phis[kk].push_back(azimuth_at(thetas[kk], t - turns) + 2.0 * kPi * turns);
      layout.points.push_back(SpherePoint(thetas[kk], phis[kk].back()));
    }
  }
  auto ring_vertex = [&](int k, int i) {
    const int size = sizes[static_cast<size_t>(k)];
    return first[static_cast<size_t>(k)] + static_cast<int32_t>(((i % size) + size) % size);
  };

  // Cap at the first pole, strips zipped between consecutive rings by increasing azimuth (each
  // strip of rings of m and p points gives m + p triangles), and the cap or the last pole at
  // the other end. Azimuth grows counter-clockwise seen from outside above the first pole
  // (e1 × e2 = e3), which fixes the corner order of each kind of triangle.
  for (int i = 0; i < sizes[0]; ++i) {
    layout.triangles.push_back({0, ring_vertex(0, i), ring_vertex(0, i + 1)});
  }
  for (int k = 0; k + 1 < rings; ++k) {
    const std::vector<double>& ring_a = phis[static_cast<size_t>(k)];
    const std::vector<double>& ring_b = phis[static_cast<size_t>(k) + 1];
    const int m = static_cast<int>(ring_a.size());
    const int p = static_cast<int>(ring_b.size());
    // Ring b's azimuths unwrapped to [ring_a[0], ring_a[0] + 2π); the zip starts at the
    // smallest, point j0.
    std::vector<double> unwrapped(ring_b.size());
    int j0 = 0;
    for (size_t j = 0; j < ring_b.size(); ++j) {
      unwrapped[j] =
          ring_a[0] + std::fmod(std::fmod(ring_b[j] - ring_a[0], 2.0 * kPi) + 2.0 * kPi, 2.0 * kPi);
      if (unwrapped[j] < unwrapped[static_cast<size_t>(j0)]) j0 = static_cast<int>(j);
    }
    auto angle_a = [&](int i) {
      return i < m ? ring_a[static_cast<size_t>(i)] : ring_a[0] + 2.0 * kPi;
    };
    auto angle_b = [&](int i) {
      const double angle = unwrapped[static_cast<size_t>((j0 + i) % p)];
      return i < p ? angle : angle + 2.0 * kPi;
    };
    int ia = 0;
    int ib = 0;
    while (ia < m || ib < p) {
      const bool advance_a = ib == p || (ia < m && angle_a(ia + 1) <= angle_b(ib + 1));
      if (advance_a) {
        layout.triangles.push_back(
            {ring_vertex(k, ia), ring_vertex(k + 1, j0 + ib), ring_vertex(k, ia + 1)});
        ++ia;
      } else {
        layout.triangles.push_back(
            {ring_vertex(k, ia), ring_vertex(k + 1, j0 + ib), ring_vertex(k + 1, j0 + ib + 1)});
        ++ib;
      }
    }
  }
  const int last_ring = rings - 1;
  if (single_pole) {
    layout.triangles.push_back(
        {ring_vertex(last_ring, 0), ring_vertex(last_ring, 2), ring_vertex(last_ring, 1)});
  } else {
    const auto pole = static_cast<int32_t>(layout.points.size());
    layout.points.emplace_back(-1.0, 0.0, 0.0);
    for (int i = 0; i < sizes[static_cast<size_t>(last_ring)]; ++i) {
      layout.triangles.push_back({pole, ring_vertex(last_ring, i + 1), ring_vertex(last_ring, i)});
    }
  }
  assert(layout.points.size() == static_cast<size_t>(n));
  assert(layout.triangles.size() == static_cast<size_t>(2 * n - 4));
  return layout;
}

bool IsRadiallyEmbedded(const std::vector<Triangle>& triangles,
                        const std::vector<Vector3d>& directions) {
  for (const Triangle& t : triangles) {
    const Vector3d& a = directions[static_cast<size_t>(t[0])];
    const Vector3d& b = directions[static_cast<size_t>(t[1])];
    const Vector3d& c = directions[static_cast<size_t>(t[2])];
    if (!(a.dot(b.cross(c)) > 0.0)) return false;
  }
  return true;
}

}  // namespace somasim::mesh_gen::sphere_layout
